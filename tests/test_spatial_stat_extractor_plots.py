"""Module 9's plots (issue 19): plot grids, plants joined to plots, stand counts, gaps, spacing, traits per
plot, the field book - against a sown layout with known missing plants, and against the synthetic field's
plot truth."""

from __future__ import annotations

import json

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import shapely

from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError
from matchplant.simfield.scoring import plot_scores
from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.plots import plot_grid, plot_table, read_plots, run_plots
from matchplant.spatial_stat_extractor.plots_config import PlotsConfig
from matchplant.spatial_stat_extractor.run import extract_and_write


def sown_field(angle_deg: float, rng):
    """A rotated field of 3 x 4 plots, 2 rows of 12 seeds per plot (0.25 m apart, 0.75 m rows), some seeds
    missing; returns the plots config, the plant table and the true per-plot counts and gaps."""
    a = np.radians(angle_deg)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])  # across, along the rows
    origin = np.array([500000.0, 4000000.0])
    cols, ranges, rows_per_plot, seeds, sp, rs = 3, 4, 2, 12, 0.25, 0.75
    width, length = rows_per_plot * rs, seeds * sp
    xs, truth, gaps, rows = [], {}, [], []
    for j in range(ranges):
        for i in range(cols):
            pid = j * cols + i + 1
            n = 0
            for r in range(rows_per_plot):
                for k in range(seeds):
                    across = i * width + (r + 0.5) * rs
                    along = j * length + (k + 0.3) * sp  # sown 0.3 spacing after the plot's start
                    p = origin + across * u + along * v
                    if rng.random() < 0.12:
                        gaps.append(p)
                        continue
                    jitter = rng.normal(0, 0.02, 2)
                    xs.append(p + jitter[0] * u + np.clip(jitter[1], -0.05, 0.05) * v)
                    rows.append((pid, r))
                    n += 1
            truth[pid] = n
    corners = [origin, origin + cols * width * u, origin + cols * width * u + ranges * length * v,
               origin + ranges * length * v]
    cfg = PlotsConfig(corners=[list(c) for c in corners], columns=cols, ranges=ranges, rows_per_plot=rows_per_plot,
                      plant_spacing=sp)
    xy = np.array(xs)
    table = pd.DataFrame({"plant_id": np.arange(1, len(xy) + 1), "x": xy[:, 0], "y": xy[:, 1],
                          "chm_max": rng.uniform(0.2, 0.6, len(xy)), "_plot": [r[0] for r in rows],
                          "_row": [r[1] for r in rows], "_along": xy @ v})
    return cfg, table, truth, np.array(gaps)


@pytest.mark.parametrize("angle", [0.0, 27.0])
def test_stand_counts_gaps_and_spacing(angle):
    rng = np.random.default_rng(4)
    cfg, table, truth, true_gaps = sown_field(angle, rng)
    plots = plot_grid(cfg)
    assert len(plots) == 12 and np.allclose(plots.area, 1.5 * 3.0)
    per_plot, gaps, traits = plot_table(plots, table, cfg)
    assert dict(zip(per_plot["plot_id"], per_plot["stand_count"])) == truth
    assert (per_plot["expected"] == 24).all()
    assert (per_plot["stand_count"] + per_plot["gaps"] == per_plot["expected"]).all()
    # every gap where a seed is missing, and nowhere else
    d = np.hypot(*(gaps[["x", "y"]].to_numpy()[:, None, :] - true_gaps[None, :, :]).transpose(2, 0, 1))
    assert len(gaps) == len(true_gaps) and (d.min(axis=1) < 0.06).all() and (d.min(axis=0) < 0.06).all()
    # in-row spacing (gaps included): mean and CV of the distances between neighbours in each row
    for _, row in per_plot.iterrows():
        mine = table[table["_plot"] == row["plot_id"]]
        d = np.concatenate([np.diff(np.sort(g["_along"].to_numpy())) for _, g in mine.groupby("_row")])
        assert row["spacing_mean_m"] == pytest.approx(d.mean()) and row["spacing_cv"] == pytest.approx(d.std() / d.mean())
    # traits: mean, sd and cv per plot, as numpy computes them
    pts = shapely.points(table[["x", "y"]].to_numpy())
    for _, row in per_plot.iterrows():
        inside = shapely.contains(plots.geometry.values[int(row["plot_id"]) - 1], pts)
        vals = table["chm_max"].to_numpy()[inside]
        assert row["chm_max_mean"] == pytest.approx(vals.mean())
        assert row["chm_max_sd"] == pytest.approx(vals.std(ddof=1))
        assert row["chm_max_cv"] == pytest.approx(vals.std(ddof=1) / vals.mean())
    assert traits == ["chm_max"]  # the default traits that the table has


def test_plot_polygons_from_a_file_and_a_field_book(tmp_path):
    rng = np.random.default_rng(5)
    cfg, table, truth, _ = sown_field(27.0, rng)
    grid = plot_grid(cfg).set_crs("EPSG:32615")
    grid[["plot_id", "geometry"]].to_file(tmp_path / "plots.gpkg", driver="GPKG")
    from_file = read_plots(PlotsConfig(polygons=tmp_path / "plots.gpkg", plant_spacing=0.25), grid.crs)
    # the row direction of each plot comes from its long side
    assert np.allclose(np.abs(from_file[["row_dir_x", "row_dir_y"]].to_numpy()),
                       np.abs(grid[["row_dir_x", "row_dir_y"]].to_numpy()), atol=1e-3)
    book = pd.DataFrame({"plot_id": range(1, 13), "genotype": [f"G{i % 4}" for i in range(12)],
                         "rep": [i // 4 + 1 for i in range(12)]})
    book.to_csv(tmp_path / "book.csv", index=False)
    file_cfg = PlotsConfig(polygons=tmp_path / "plots.gpkg", plant_spacing=0.25, field_book=tmp_path / "book.csv",
                           figure_trait="chm_max")
    polys = gpd.GeoDataFrame(table[["plant_id"]], geometry=shapely.buffer(shapely.points(table[["x", "y"]].to_numpy()), 0.05),
                             crs="EPSG:32615")
    written = run_plots(file_cfg, table, None, polys, tmp_path / "out")
    out = pd.read_csv(written["plots_csv"])
    assert dict(zip(out["plot_id"], out["stand_count"])) == truth
    assert list(out["genotype"]) == list(book["genotype"]) and list(out["rep"]) == list(book["rep"])
    assert gpd.read_file(written["plots_gpkg"]).crs.to_epsg() == 32615
    assert written["plots_figure"].stat().st_size > 10_000
    with pytest.raises(ConfigError, match="corners"):
        plot_grid(PlotsConfig(corners=[[0, 0], [1, 0]], columns=2, ranges=2))
    with pytest.raises(ConfigError, match="nope"):
        plot_table(grid, table, PlotsConfig(traits=["nope"], plant_spacing=0.25))


def test_serpentine_numbering_and_alleys():
    cfg = PlotsConfig(corners=[[0, 0], [6, 0], [6, 8], [0, 8]], columns=3, ranges=2, plot_width=1.5,
                      plot_length=3.0, serpentine=True)
    g = plot_grid(cfg)
    assert np.allclose(g.area, 4.5)
    assert list(g["column"]) == [1, 2, 3, 3, 2, 1]
    c = shapely.centroid(g.geometry.values)
    assert np.allclose(shapely.get_x(c), [1, 3, 5, 5, 3, 1]) and np.allclose(shapely.get_y(c), [2, 2, 2, 6, 6, 6])


def test_module_9_plots_on_the_synthetic_field(tiny_field, tmp_path):
    """Module 9 from the true plant boxes, with the plot grid of the field's truth: stand counts and gaps
    as the truth has them, the field book joined."""
    grid = json.loads(tiny_field.plots_json.read_text())
    cfg = load_config(SpatialStatExtractorConfig, None, [
        f"polygons={tiny_field.map_boxes}", f"polygons_crs={grid['crs']}", f"output_dir={tmp_path}",
        f"rasters.dsm={tiny_field.dsm}", f"rasters.dtm={tiny_field.dtm}",
        f"plots.corners={json.dumps(grid['corners'])}", f"plots.columns={grid['columns']}",
        f"plots.ranges={grid['ranges']}", f"plots.plant_spacing={grid['plant_spacing']}",
        f"plots.field_book={tiny_field.field_book}"])
    _, table, _, written = extract_and_write(cfg)
    plots = pd.read_csv(written["plots_csv"])
    s = plot_scores(plots, pd.read_csv(written["plot_gaps_csv"]), tiny_field, grid["plant_spacing"])
    assert s["plots"] == grid["columns"] * grid["ranges"] and s["stand_count_exact_share"] == 1.0
    assert s["gaps_found_share"] == 1.0 and s["false_gap_share"] == 0.0
    assert plots["genotype"].notna().all()
    truth = pd.read_csv(tiny_field.plots_csv)
    assert (plots["expected"].to_numpy() == truth["expected"].to_numpy()).all()
    assert (plots["canopy_cover"] > 0).all() and (plots["canopy_cover"] < 1).all()
