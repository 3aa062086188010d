"""Every figure the project saves, drawn on small inputs and checked as a reader looks at it: no text runs out
of the figure (a clipped label), captions name the colours the artists are drawn with, whole-number axes
(epochs) ticked at whole numbers.

Figures are captured where they are made (each module's ``figure`` is wrapped) and checked after saving.
"""

from __future__ import annotations

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
from figure_checks import colour_names, outside_figure, same_colour
from matplotlib.collections import PolyCollection
from PIL import Image
from shapely.geometry import box

import matchplant.core.runtime.gui as gui
import matchplant.detection.evaluate as detection_evaluate
import matchplant.model_train.report as train_report
import matchplant.plant_projection.evaluation as evaluation
import matchplant.spatial_stat_extractor.compare as compare
import matchplant.spatial_stat_extractor.plots.figure as plots_figure
from matchplant.demo_report import figure_caption
from matchplant.plant_projection.evaluation import evaluate_boxes, evaluation_caption, evaluation_figure

# UTM coordinates as on a real field: long tick labels are what ran out of the figure
X0, Y0 = 702309.0, 4524878.0


@pytest.fixture
def made(monkeypatch):
    """The figures made while a test runs, by any module whose ``figure`` is wrapped here."""
    figs = []

    def capture(*args, **kwargs):
        fig = gui.figure(*args, **kwargs)
        figs.append(fig)
        return fig

    for module in (train_report, evaluation, compare, plots_figure, detection_evaluate):
        monkeypatch.setattr(module, "figure", capture)
    return figs


def _boxes(n, rng, size=0.3):
    xy = np.c_[rng.uniform(X0, X0 + 14, n), rng.uniform(Y0, Y0 + 14, n)]
    return np.c_[xy, xy + size]


def _evaluation(tmp_path, made):
    rng = np.random.default_rng(0)
    ref = _boxes(60, rng)
    pred = ref + rng.normal(0, 0.08, ref.shape)
    pred = np.c_[np.minimum(pred[:, :2], pred[:, 2:]), np.maximum(pred[:, :2], pred[:, 2:])]
    metrics = evaluate_boxes(ref, pred)
    path = evaluation_figure(tmp_path / "evaluation.png", ref, pred, metrics)
    return path, made[-1]


def _field(tmp_path, made, column="ndvi_canopy_mean_mean"):
    rng = np.random.default_rng(1)
    polys = [box(X0 + i * 1.5, Y0 + j * 2, X0 + i * 1.5 + 1.4, Y0 + j * 2 + 1.9) for j in range(7) for i in range(9)]
    plots = gpd.GeoDataFrame(
        {"plot_id": range(1, 64), column: rng.uniform(0.65, 0.75, 63)}, geometry=polys, crs="EPSG:32614"
    )
    pts = np.c_[rng.uniform(X0, X0 + 14, 400), rng.uniform(Y0, Y0 + 14, 400)]
    gaps = pd.DataFrame({"x": rng.uniform(X0, X0 + 14, 20), "y": rng.uniform(Y0, Y0 + 14, 20)})
    path = plots_figure.field_figure(plots, pts, gaps, column, tmp_path / "plots.png", 0.2)
    return path, made[-1]


def test_evaluation_figure_fits_and_its_caption_names_its_colours(tmp_path, made):
    path, fig = _evaluation(tmp_path, made)
    assert outside_figure(fig) == []
    caption = figure_caption(path)
    assert caption == evaluation_caption(0.5)  # the report prints what the figure carries
    drawn = [c.get_edgecolor()[0] for c in fig.axes[0].collections if isinstance(c, PolyCollection)]
    named = colour_names(caption)
    assert len(drawn) == 3 and len(named) == 3
    # each colour the caption names is a colour the boxes are drawn with, and each box colour is named
    assert all(any(same_colour(w, c) for c in drawn) for w in named)
    assert all(any(same_colour(w, c) for w in named) for c in drawn)


def test_plots_figure_fits_has_a_readable_title_and_its_caption_names_its_colours(tmp_path, made):
    path, fig = _field(tmp_path, made)
    assert outside_figure(fig) == []
    title = fig.axes[0].get_title()
    assert "ndvi_canopy_mean_mean" not in title and "NDVI" in title and "index, no unit" in title
    caption = figure_caption(path)
    lines = {ln.get_label(): ln.get_color() for ln in fig.axes[0].get_lines()}
    for word, mark in zip(("dots", "crosses"), ("plants", "gaps")):
        colour = caption.split(f" {word}: {mark}")[0].split()[-1]  # "black dots: plants"
        assert same_colour(colour, lines[mark]), (caption, lines)


def test_plots_figure_fits_with_a_raster_column(tmp_path, made):
    _, fig = _field(tmp_path, made, column="exg_min")
    assert outside_figure(fig) == []
    assert "ExG min" in fig.axes[0].get_title()


def test_training_curves_tick_whole_epochs_and_fit(tmp_path, made):
    history = [
        {"epoch": e, "losses": {"loss": 1.0 / e, "loss_box_reg": 0.5 / e}, "val": {"AP50": 0.2 * e, "AP": 0.1 * e}}
        for e in (1, 2)
    ]
    train_report.plot_curves(history, tmp_path / "curves.png")
    fig = made[-1]
    assert outside_figure(fig) == []
    for ax in fig.axes:
        ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
        assert ticks and all(float(t).is_integer() for t in ticks), ticks


def test_comparison_figure_fits(tmp_path, made):
    rng = np.random.default_rng(2)
    a = pd.DataFrame({"plant_id": range(30), "chm_max": rng.uniform(0.2, 0.6, 30)})
    b = a.assign(chm_max=a["chm_max"] + rng.normal(0, 0.02, 30))
    matches = pd.DataFrame({"index_a": range(30), "index_b": range(30), "iou": np.full(30, 0.9)})
    summary, pairs = compare.compare_tables(a, b, matches, ["chm_max"], "d1", "d2")
    compare.comparison_figure(a, b, pairs, summary, ["chm_max"], tmp_path / "compare.png", "d1", "d2")
    assert outside_figure(made[-1]) == []


def test_caption_read_from_a_png_without_one_is_empty(tmp_path):
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "x.png")
    assert figure_caption(tmp_path / "x.png") == ""


def test_demo_trait_figure_and_report_line_describe_the_same_statistic(tmp_path, monkeypatch):
    """The report's trait table and the figure beside it score the same columns: the canopy height panel's r
    is the report's canopy height r (a figure of CHM P95 beside a line of CHM max was seen)."""
    import matchplant.demo as demo
    from matchplant.simfield.layout import FieldPaths
    from matchplant.simfield.scoring import trait_scores

    figs = []
    monkeypatch.setattr(demo, "figure", lambda *a, **k: figs.append(gui.figure(*a, **k)) or figs[-1])
    rng = np.random.default_rng(3)
    n = 40
    truth = pd.DataFrame({"id": range(n), "x": np.arange(n) * 1.0, "y": np.zeros(n)})
    truth["height"], truth["ndvi"] = rng.uniform(0.2, 0.6, n), rng.uniform(0.5, 0.8, n)
    paths = FieldPaths(tmp_path)
    paths.traits_csv.parent.mkdir(parents=True)
    truth.to_csv(paths.traits_csv, index=False)
    table = truth[["x", "y"]].assign(plant_id=range(n))
    # every candidate statistic differs from the others, so that a panel of another one shows another r
    for col, noise in (("chm_max", 0.05), ("chm_canopy_max", 0.01), ("chm_canopy_p95", 0.1)):
        table[col] = truth["height"] + rng.normal(0, noise, n)
    for col, noise in (("ndvi_mean", 0.1), ("ndvi_canopy_mean", 0.01)):
        table[col] = truth["ndvi"] + rng.normal(0, noise, n)
    demo._scatter(tmp_path / "traits.png", table, paths)
    scores = trait_scores(table, paths)
    titles = [ax.get_title() for ax in figs[-1].axes]
    for key in ("height_box_r", "height_r", "ndvi_box_r", "ndvi_r"):
        assert sum(f"r = {scores[key]:.3f}," in t for t in titles) == 1, (key, scores[key], titles)
    assert outside_figure(figs[-1]) == []


def test_score_histogram_fits(tmp_path, made):
    rng = np.random.default_rng(4)
    scores = rng.uniform(0, 1, 200)
    detection_evaluate.plot_score_histogram(scores, scores > 0.4, tmp_path / "scores.png", threshold=0.5)
    assert outside_figure(made[-1]) == []
