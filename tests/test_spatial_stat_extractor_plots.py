"""Module 9's plots (issue 19): plot grids, plants joined to plots, stand counts, gaps, spacing, traits per
plot, the field book - against a sown layout with known missing plants, and against the synthetic field's
plot truth."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import rasterio
import rasterio.features
import rasterio.warp
import shapely
import yaml

from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.simfield.scoring import plot_scores
from matchplant.spatial_stat_extractor.config import (
    BandFile,
    RasterSet,
    SpatialStatExtractorConfig,
)
from matchplant.spatial_stat_extractor.plots import (
    PlotsConfig,
    join_field_book,
    plot_grid,
    plot_table,
    read_plots,
    run_plots,
)
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
    corners = [
        origin,
        origin + cols * width * u,
        origin + cols * width * u + ranges * length * v,
        origin + ranges * length * v,
    ]
    cfg = PlotsConfig(
        corners=[list(c) for c in corners], columns=cols, ranges=ranges, rows_per_plot=rows_per_plot, plant_spacing=sp
    )
    xy = np.array(xs)
    table = pd.DataFrame(
        {
            "plant_id": np.arange(1, len(xy) + 1),
            "x": xy[:, 0],
            "y": xy[:, 1],
            "chm_max": rng.uniform(0.2, 0.6, len(xy)),
            "_plot": [r[0] for r in rows],
            "_row": [r[1] for r in rows],
            "_along": xy @ v,
        }
    )
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
        assert row["spacing_mean_m"] == pytest.approx(d.mean()) and row["spacing_cv"] == pytest.approx(
            d.std() / d.mean()
        )
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
    # a file without row columns: the direction is left to the plants (see test_plot_file_read_back...)
    assert from_file[["row_dir_x", "row_dir_y"]].isna().all().all()
    book = pd.DataFrame(
        {"plot_id": range(1, 13), "genotype": [f"G{i % 4}" for i in range(12)], "rep": [i // 4 + 1 for i in range(12)]}
    )
    book.to_csv(tmp_path / "book.csv", index=False)
    file_cfg = PlotsConfig(
        polygons=tmp_path / "plots.gpkg", plant_spacing=0.25, field_book=tmp_path / "book.csv", figure_trait="chm_max"
    )
    polys = gpd.GeoDataFrame(
        table[["plant_id"]],
        geometry=shapely.buffer(shapely.points(table[["x", "y"]].to_numpy()), 0.05),
        crs="EPSG:32615",
    )
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
    cfg = PlotsConfig(
        corners=[[0, 0], [6, 0], [6, 8], [0, 8]], columns=3, ranges=2, plot_width=1.5, plot_length=3.0, serpentine=True
    )
    g = plot_grid(cfg)
    assert np.allclose(g.area, 4.5)
    assert list(g["column"]) == [1, 2, 3, 3, 2, 1]
    c = shapely.centroid(g.geometry.values)
    assert np.allclose(shapely.get_x(c), [1, 3, 5, 5, 3, 1]) and np.allclose(shapely.get_y(c), [2, 2, 2, 6, 6, 6])


def test_module_9_plots_on_the_synthetic_field(tiny_field, tmp_path):
    """Module 9 from the true plant boxes, with the plot grid of the field's truth: stand counts and gaps
    as the truth has them, the field book joined."""
    grid = json.loads(tiny_field.plots_json.read_text())
    cfg = load_config(
        SpatialStatExtractorConfig,
        None,
        [
            f"polygons={tiny_field.map_boxes}",
            f"polygons_crs={grid['crs']}",
            f"output_dir={tmp_path}",
            f"rasters.dsm={tiny_field.dsm}",
            f"rasters.dtm={tiny_field.dtm}",
            f"plots.corners={json.dumps(grid['corners'])}",
            f"plots.columns={grid['columns']}",
            f"plots.ranges={grid['ranges']}",
            f"plots.plant_spacing={grid['plant_spacing']}",
            f"plots.field_book={tiny_field.field_book}",
        ],
    )
    _, _, _, written = extract_and_write(cfg)
    plots = pd.read_csv(written["plots_csv"])
    s = plot_scores(plots, pd.read_csv(written["plot_gaps_csv"]), tiny_field, grid["plant_spacing"])
    assert s["plots"] == grid["columns"] * grid["ranges"] and s["stand_count_exact_share"] == 1.0
    assert s["gaps_found_share"] == 1.0 and s["false_gap_share"] == 0.0
    assert plots["genotype"].notna().all()
    truth = pd.read_csv(tiny_field.plots_csv)
    assert (plots["expected"].to_numpy() == truth["expected"].to_numpy()).all()
    assert (plots["canopy_cover"] > 0).all() and (plots["canopy_cover"] < 1).all()


# --------------------------------------------------------------------------------------------------
# issue 26/27: rows from the grid, the file, the key or the plants; skewed grids; overlaps; degrees;
# field books; plot statistics over the plot polygons; the figure


def sown(
    rng,
    *,
    cols=3,
    ranges=4,
    nrow=2,
    seeds=12,
    sp=0.25,
    rs=0.75,
    angle=0.0,
    skew=0.0,
    miss=0.12,
    origin=(500000.0, 4000000.0),
):
    """A field sown row by row: rows along v (bearing ``angle`` from the x axis rotated), plots side by side
    along the across axis, which leans ``skew`` degrees off the perpendicular (a parallelogram); each row's
    seeds start 0.3 spacing after the plot's (slanted) edge. Returns the grid config, the plant table, the
    true counts per plot and the true gaps (plot id, x, y)."""
    a, k = np.radians(angle), np.radians(skew)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])
    ua = np.cos(k) * u + np.sin(k) * v  # the grid's across axis; its component across the rows is cos(skew)
    step = rs / np.cos(k)  # one row further along ua
    o = np.asarray(origin)
    xs, plot_of, truth, gaps = [], [], {}, []
    length = seeds * sp
    for j in range(ranges):
        for i in range(cols):
            pid = j * cols + i + 1
            truth[pid] = 0
            for r in range(nrow):
                for s in range(seeds):
                    p = o + (i * nrow + r + 0.5) * step * ua + (j * length + (s + 0.3) * sp) * v
                    if rng.random() < miss:
                        gaps.append((pid, *p))
                        continue
                    jit = rng.normal(0, 0.015, 2)
                    xs.append(p + jit[0] * u + np.clip(jit[1], -0.04, 0.04) * v)
                    plot_of.append(pid)
                    truth[pid] += 1
    across = cols * nrow * step * ua
    corners = [o, o + across, o + across + ranges * length * v, o + ranges * length * v]
    cfg = PlotsConfig(
        corners=[list(c) for c in corners], columns=cols, ranges=ranges, rows_per_plot=nrow, plant_spacing=sp
    )
    xy = np.array(xs)
    table = pd.DataFrame(
        {
            "plant_id": np.arange(1, len(xy) + 1),
            "x": xy[:, 0],
            "y": xy[:, 1],
            "chm_max": rng.uniform(0.2, 0.6, len(xy)),
            "_plot": plot_of,
        }
    )
    return cfg, table, truth, pd.DataFrame(gaps, columns=["plot_id", "x", "y"])


def boxes(table, crs="EPSG:32615"):
    return gpd.GeoDataFrame(
        table[["plant_id"]], crs=crs, geometry=shapely.buffer(shapely.points(table[["x", "y"]].to_numpy()), 0.05)
    )


def test_plot_file_read_back_gives_the_grids_rows(tmp_path):
    """Wide plots (6 rows of 3 m, 4.5 m across: the long side runs across the rows). The module's own
    plots.gpkg read back, the same file without its row columns (rows from the plants), and the file with
    plots.row_direction give the grid's expected plants and gaps; the long side would not."""
    rng = np.random.default_rng(11)
    cfg, table, truth, true_gaps = sown(rng, cols=3, ranges=2, nrow=6, seeds=10, sp=0.3, angle=20.0)
    polys = boxes(table)
    ref = pd.read_csv(run_plots(cfg, table, None, polys, tmp_path / "grid")["plots_csv"])
    assert dict(zip(ref["plot_id"], ref["stand_count"])) == truth and (ref["expected"] == 60).all()
    assert ref["gaps"].sum() == len(true_gaps)
    own = gpd.read_file(tmp_path / "grid" / "plots.gpkg")
    assert {"row_dir_x", "row_dir_y"} <= set(own.columns)
    own.drop(columns=["row_dir_x", "row_dir_y"]).to_file(tmp_path / "bare.gpkg", driver="GPKG")
    bearing = float(np.degrees(np.arctan2(*own[["row_dir_x", "row_dir_y"]].to_numpy()[0])))
    runs = {
        "own file": PlotsConfig(polygons=tmp_path / "grid" / "plots.gpkg", rows_per_plot=6, plant_spacing=0.3),
        "from plants": PlotsConfig(polygons=tmp_path / "bare.gpkg", rows_per_plot=6, plant_spacing=0.3),
        "row_direction": PlotsConfig(
            polygons=tmp_path / "bare.gpkg", rows_per_plot=6, plant_spacing=0.3, row_direction=bearing
        ),
    }
    for name, c in runs.items():
        got, gaps, _ = plot_table(read_plots(c, polys.crs), table, c)  # (what run_plots writes, without the figure)
        assert np.allclose(got["expected"], ref["expected"], rtol=0.02), name
        assert abs(got["gaps"].sum() - ref["gaps"].sum()) <= 0.02 * ref["expected"].sum(), name
        d = np.hypot(
            *(gaps[["x", "y"]].to_numpy()[:, None] - true_gaps[["x", "y"]].to_numpy()[None]).transpose(2, 0, 1)
        )
        assert (d.min(axis=1) < 0.06).mean() >= 0.98, name
    wrong = plot_table(
        read_plots(replace(runs["row_direction"], row_direction=bearing + 90)),
        table,
        replace(runs["row_direction"], row_direction=bearing + 90),
    )[0]
    assert abs(wrong["expected"].sum() / ref["expected"].sum() - 1) > 0.1  # the long side: not the rows


def test_unusable_row_direction_columns_are_named(tmp_path, caplog):
    """Issue 39: zero or text row_dir_x/row_dir_y values in a plot file were ignored without a word. Some
    unusable: a warning naming the file, the columns and the plots, their direction from the plants (the same
    counts as the file read whole); all unusable, or one column of the two: an error naming them."""
    rng = np.random.default_rng(11)
    cfg, table, truth, _ = sown(rng, cols=3, ranges=2, nrow=6, seeds=10, sp=0.3, angle=20.0)
    polys = boxes(table)
    run_plots(cfg, table, None, polys, tmp_path / "grid")
    own = gpd.read_file(tmp_path / "grid" / "plots.gpkg")

    def variant(name, change):
        g = own.copy()
        change(g)
        g.to_file(tmp_path / name, driver="GPKG")
        return PlotsConfig(polygons=tmp_path / name, rows_per_plot=6, plant_spacing=0.3)

    def zero_first_two(g):
        g.loc[:1, ["row_dir_x", "row_dir_y"]] = 0.0

    some = variant("some_zero.gpkg", zero_first_two)
    with caplog.at_level("WARNING", logger="matchplant"):
        plots = read_plots(some, polys.crs)
    assert "some_zero.gpkg" in caplog.text and "row_dir_x/row_dir_y of 2 of 6 plots" in caplog.text
    assert "zero vector" in caplog.text and str(list(own["plot_id"][:2])) in caplog.text
    assert plots[["row_dir_x", "row_dir_y"]].isna().sum().tolist() == [2, 2]
    got, _, _ = plot_table(plots, table, some)
    assert dict(zip(got["plot_id"], got["stand_count"])) == truth and (got["expected"] == 60).all()

    def all_zero(g):
        g["row_dir_x"], g["row_dir_y"] = 0.0, 0.0

    def text(g):
        g["row_dir_x"] = "north"

    def one_column(g):
        del g["row_dir_y"]

    for name, change, why in (
        ("all_zero.gpkg", all_zero, "zero vector"),
        ("text.gpkg", text, "text where a number belongs"),
        ("one.gpkg", one_column, "only row_dir_x is in the file"),
    ):
        with pytest.raises(InputError) as e:
            read_plots(variant(name, change), polys.crs)
        text = str(e.value)
        assert name in text and "row_dir_x" in text and why in text and "plots.row_direction" in text, text
    # plots.row_direction set: it overrides the columns, nothing to refuse
    read_plots(replace(variant("all_zero2.gpkg", all_zero), row_direction=20.0), polys.crs)


def test_row_direction_from_the_plants_is_accurate():
    rng = np.random.default_rng(3)
    cfg, table, _, _ = sown(rng, angle=-33.0, cols=2, ranges=2)
    plots = plot_grid(cfg).drop(columns=["row_dir_x", "row_dir_y"])
    pts = table[["x", "y"]].to_numpy()

    from matchplant.spatial_stat_extractor.plots import join_plants, row_directions

    plant_i, plot_i = join_plants(plots, pts)
    v = row_directions(plots, pts, plant_i, plot_i, cfg)
    truth = np.array([-np.sin(np.radians(-33.0)), np.cos(np.radians(-33.0))])
    assert np.degrees(np.arccos(np.minimum(np.abs(v @ truth), 1))).max() < 0.6  # 1.5 cm jitter over 3 m rows


@pytest.mark.parametrize("skew", [0.0, 25.0])
def test_skewed_grid_seeds_follow_the_rows_and_stay_in_their_plot(skew):
    rng = np.random.default_rng(8)
    cfg, table, truth, true_gaps = sown(rng, skew=skew, angle=10.0)
    plots = plot_grid(cfg)
    per_plot, gaps, _ = plot_table(plots, table, cfg)
    assert dict(zip(per_plot["plot_id"], per_plot["stand_count"])) == truth
    assert (per_plot["expected"] == 24).all()
    geom = plots.set_index("plot_id").geometry
    inside = shapely.contains(geom.reindex(gaps["plot_id"]).values, shapely.points(gaps[["x", "y"]].to_numpy()))
    assert inside.mean() >= 0.99
    d = np.hypot(*(gaps[["x", "y"]].to_numpy()[:, None] - true_gaps[["x", "y"]].to_numpy()[None]).transpose(2, 0, 1))
    assert len(gaps) == len(true_gaps) and (d.min(axis=1) < 0.06).all()


def test_identical_plots_refused_and_overlapping_plots_count_each_plant_once(tmp_path):
    rng = np.random.default_rng(2)
    cfg, table, truth, _ = sown(rng)
    grid = plot_grid(cfg).set_crs("EPSG:32615")
    twice = pd.concat([grid, grid.iloc[[4]].assign(plot_id=99)], ignore_index=True)
    twice[["plot_id", "geometry"]].to_file(tmp_path / "twice.gpkg", driver="GPKG")
    c = PlotsConfig(polygons=tmp_path / "twice.gpkg", plant_spacing=0.25)
    with pytest.raises(InputError, match=r"plots 5 and 99 \(100%\)"):
        plot_table(read_plots(c, grid.crs), table, c)
    # hand-drawn: every plot 0.2 m larger on each side, so that neighbours overlap
    drawn = grid.assign(geometry=shapely.buffer(grid.geometry.values, 0.2, join_style="mitre"))
    drawn[["plot_id", "geometry"]].to_file(tmp_path / "drawn.gpkg", driver="GPKG")
    c = PlotsConfig(polygons=tmp_path / "drawn.gpkg", plant_spacing=0.25)
    per_plot, _, _ = plot_table(read_plots(c, grid.crs), table, c)
    assert per_plot["stand_count"].sum() == len(table)  # each plant in one plot
    assert dict(zip(per_plot["plot_id"], per_plot["stand_count"])) == truth  # ... the nearest one


def test_corners_in_degrees_and_last_years_corners():
    from pyproj import Transformer

    rng = np.random.default_rng(6)
    cfg, table, truth, _ = sown(rng, angle=15.0, origin=(566000.0, 5705000.0))
    to_ll = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    lonlat = [list(to_ll.transform(*c)) for c in cfg.corners]
    pts = table[["x", "y"]].to_numpy()
    utm = plot_grid(cfg, "EPSG:32632")
    for corners in (lonlat, [[b, a] for a, b in lonlat]):  # longitude, latitude or latitude, longitude
        g = plot_grid(replace(cfg, corners=corners), "EPSG:32632", pts)
        assert shapely.hausdorff_distance(g.geometry.values, utm.geometry.values).max() < 0.01
        per_plot = plot_table(g, table, cfg)[0]
        assert dict(zip(per_plot["plot_id"], per_plot["stand_count"])) == truth
    moved = replace(cfg, corners=[[x + 150.0, y] for x, y in cfg.corners])
    with pytest.raises(InputError, match="plots.corners") as e:
        plot_table(plot_grid(moved, "EPSG:32632", pts), table, moved)
    assert "hold no plant" in str(e.value) and "150.0 m" in str(e.value)


def excel_csv(path, rows, header="plot_id,genotype,note"):
    text = "\r\n".join([header, *rows, ",,", ",,", ""])
    path.write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    return path


def test_field_books_as_breeders_keep_them(tmp_path):
    rng = np.random.default_rng(5)
    cfg, table, _, _ = sown(rng)
    per_plot = plot_table(plot_grid(cfg), table, cfg)[0]
    rows = [f'{i},G{i % 4},"sown late, re-sown"' if i == 3 else f"{i},G{i % 4},ok" for i in range(1, 13)]
    got = join_field_book(per_plot, excel_csv(tmp_path / "book.csv", rows), "plot_id")
    assert len(got) == 12 and list(got["genotype"]) == [f"G{i % 4}" for i in range(1, 13)]
    assert got.loc[got["plot_id"] == 3, "note"].item() == "sown late, re-sown"
    # P1, P2 ... against a grid numbered 1, 2 ...: matched by the numbers
    prefixed = excel_csv(
        tmp_path / "p.csv", [f"P{i},G{i % 4},ok" for i in range(1, 11)] + ["X99,G0,ok"], "Plot,genotype,note"
    )
    got = join_field_book(per_plot, prefixed, "plot_id")
    assert list(got["genotype"][:10]) == [f"G{i % 4}" for i in range(1, 11)] and got["genotype"][10:].isna().all()
    with pytest.raises(InputError, match="none of the 3 field-book rows"):
        join_field_book(per_plot, excel_csv(tmp_path / "other.csv", ["A,G1,x", "B,G2,x", "C,G3,x"]), "plot_id")
    with pytest.raises(InputError, match="did you mean 'genotype'"):
        join_field_book(per_plot, excel_csv(tmp_path / "b.csv", ["1,G1,x"], "parcel,genotype,note"), "genotyp")
    with pytest.raises(InputError, match="repeat"):
        join_field_book(per_plot, excel_csv(tmp_path / "d.csv", ["1,G1,x", "01,G2,y"]), "plot_id")
    with pytest.raises(ConfigError, match="plots.field_book"):
        PlotsConfig(field_book=tmp_path / "book.csv").check()
    openpyxl = pytest.importorskip("openpyxl")
    wb = openpyxl.Workbook()
    ws = wb.active
    ws.append(["Plot ID", "genotype", "rep"])
    for i in range(1, 13):
        ws.append([i, f"G{i % 4}", (i - 1) // 4 + 1])
    ws.append([None, None, None])
    wb.save(tmp_path / "book.xlsx")
    got = join_field_book(per_plot, tmp_path / "book.xlsx", "plot_id")
    assert (
        list(got["genotype"]) == [f"G{i % 4}" for i in range(1, 13)] and list(got["rep"]) == [1] * 4 + [2] * 4 + [3] * 4
    )


LAI = Path(__file__).parent / "data" / "cercospora-lai-plots"


def lai_plots():
    """A 4 x 3 grid of 8 m x 6 m plots in UTM 32N over the LAI rasters (which are in EPSG:4326)."""
    with rasterio.open(LAI / "lai_2022_06_14.tif") as ds:
        b = rasterio.warp.transform_bounds(ds.crs, "EPSG:32632", *ds.bounds)
    x0, y0 = b[0] + 5.0, b[1] + 5.0
    return PlotsConfig(
        corners=[[x0, y0], [x0 + 32, y0], [x0 + 32, y0 + 18], [x0, y0 + 18]],
        columns=4,
        ranges=3,
        plant_spacing=0.5,
        rows_per_plot=8,
    )


def numpy_plot_means(plots, path):
    with rasterio.open(path) as ds:
        a = ds.read(1)
        valid = a != ds.nodata
        out = []
        for g in plots.to_crs(ds.crs).geometry.values:
            inside = rasterio.features.geometry_mask([g], out_shape=a.shape, transform=ds.transform, invert=True)
            out.append((a[inside & valid].astype(float).mean(), int((inside & valid).sum())))
    return np.array(out)


def test_plot_statistics_over_plot_polygons_on_real_lai_in_another_crs(tmp_path):
    from matchplant.spatial_stat_extractor.plots import plot_raster_stats

    cfg = lai_plots()
    plots = plot_grid(cfg, "EPSG:32632")
    sets = [
        RasterSet(date=d, bands=[BandFile(name="lai", path=LAI / f"lai_{d}.tif")]) for d in ("2022_06_14", "2022_06_28")
    ]
    got = plot_raster_stats(plots, sets, ["mean", "count"])
    for d in ("2022_06_14", "2022_06_28"):
        want = numpy_plot_means(plots, LAI / f"lai_{d}.tif")
        assert np.allclose(got[f"plot_lai_mean_{d}"], want[:, 0], rtol=1e-6)
        assert (got[f"plot_lai_count_{d}"] == want[:, 1]).all() and (want[:, 1] > 500).all()
    # the whole step without a CHM: plants on the LAI field, plots.csv with plant-trait and plot columns
    x0, y0 = cfg.corners[0]
    gx, gy = np.meshgrid(x0 + 0.5 + 1.0 * np.arange(32), y0 + 0.25 + 0.5 * np.arange(36))
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    plants = gpd.GeoDataFrame(
        {"plant_id": np.arange(1, len(pts) + 1)}, crs="EPSG:32632", geometry=shapely.buffer(shapely.points(pts), 0.15)
    )
    plants.to_file(tmp_path / "plants.gpkg", driver="GPKG")
    (tmp_path / "c.yaml").write_text(
        yaml.safe_dump(
            {
                "polygons": str(tmp_path / "plants.gpkg"),
                "output_dir": str(tmp_path / "out"),
                "rasters": {"date": "d1", "bands": [{"name": "lai", "path": str(LAI / "lai_2022_06_14.tif")}]},
                "more_dates": [{"date": "d2", "bands": [{"name": "lai", "path": str(LAI / "lai_2022_06_28.tif")}]}],
                "plots": {
                    "corners": cfg.corners,
                    "columns": 4,
                    "ranges": 3,
                    "rows_per_plot": 8,
                    "plant_spacing": 0.5,
                    "row_direction": 0,
                },
            }
        )
    )
    _, table, _, written = extract_and_write(load_config(SpatialStatExtractorConfig, tmp_path / "c.yaml"))
    out = pd.read_csv(written["plots_csv"])
    assert (out["expected"] == 8 * 12).all() and (out["stand_count"] == 96).all() and (out["gaps"] == 0).all()
    assert np.allclose(out["plot_lai_mean_d2"], numpy_plot_means(plots, LAI / "lai_2022_06_28.tif")[:, 0], rtol=1e-6)
    inside = shapely.contains(plots.geometry.values[0], shapely.points(pts))
    assert out["lai_mean_d1_mean"][0] == pytest.approx(np.nanmean(table["lai_mean_d1"].to_numpy()[inside]))


def overlapping(boxes_):
    n = len(boxes_)
    return any(boxes_[i].overlaps(boxes_[j]) for i in range(n) for j in range(i + 1, n))


def test_field_figure_readable_on_one_small_plot(tmp_path):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from matchplant.spatial_stat_extractor.plots import (
        colour_norm,
        draw_field,
        unit_of,
    )

    plot = gpd.GeoDataFrame(
        {"plot_id": [1], "chm_max_mean": [0.42]},
        crs="EPSG:32632",
        geometry=[shapely.box(566001.0, 5705001.0, 566002.5, 5705004.0)],
    )
    norm = colour_norm(plot["chm_max_mean"])
    assert 0.4 < norm(0.42) < 0.6  # a single plot in the middle of the scale, not at its minimum
    gaps = pd.DataFrame({"x": [566001.4, 566001.4], "y": [5705001.5, 5705002.0]})
    fig = Figure(figsize=(8, 7), constrained_layout=True)
    FigureCanvasAgg(fig)
    ax = draw_field(fig, plot, np.array([[566001.4, 5705002.5]]), gaps, "chm_max_mean", 0.25)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    for labels in (ax.get_xticklabels(), ax.get_yticklabels()):
        extents = [t.get_window_extent(r) for t in labels if t.get_visible() and t.get_text()]
        assert len(extents) >= 2 and not overlapping(extents)
    cbar_label = fig.axes[1].get_ylabel()
    assert cbar_label == "chm_max_mean (m)"
    # the gap crosses are smaller than the seed spacing on the page: they do not hide the plot
    x0, x1 = ax.get_xlim()
    points_per_m = ax.get_window_extent(r).width * 72 / fig.dpi / (x1 - x0)
    crosses = [ln for ln in ax.get_lines() if ln.get_label() == "gaps"]
    assert crosses and crosses[0].get_markersize() <= 0.25 * points_per_m
    assert unit_of("plot_ndvi_mean") == "index, no unit" and unit_of("canopy_area_m2_mean") == "m²"
    assert unit_of("stand_count") == "plants"


def test_unclaimed_canopies_count_only_at_empty_seed_positions():
    """Canopies no box claims (plots.count_unclaimed) count where a plant is expected and none was counted:
    the plants the detector missed count (once each, though one is in two pieces), while weeds between the
    rows and a counted plant's leaf cut off beside it do not; the stand counts are the field's truth."""
    rng = np.random.default_rng(5)
    cfg, table, truth, true_gaps = sown_field(27.0, rng)
    a = np.radians(27.0)
    u, v = np.array([np.cos(a), np.sin(a)]), np.array([-np.sin(a), np.cos(a)])  # across, along the rows
    missed = table.sample(15, random_state=1)
    boxes = table.drop(missed.index).reset_index(drop=True)
    miss = missed[["x", "y"]].to_numpy()
    piece = miss[:3] + 0.03 * v  # a second piece of three missed plants, at the same seed
    leaves = boxes[["x", "y"]].to_numpy()[::10] + 0.06 * u  # a leaf beside a counted plant
    # weeds anywhere between the rows (beyond 0.2 m of a row line; rows 0.75 m apart)
    across = rng.integers(0, 6, 40) * 0.75 + rng.uniform(-0.17, 0.17, 40)
    weeds = np.array([500000.0, 4000000.0]) + across[:, None] * u + rng.uniform(0, 12.0, 40)[:, None] * v
    xy = np.concatenate([miss, piece, leaves, weeds])
    unclaimed = pd.DataFrame({"x": xy[:, 0], "y": xy[:, 1], "height": 0.2, "pixels": 100, "faint": False})
    per_plot, gaps, _ = plot_table(plot_grid(cfg), boxes, cfg, unclaimed)
    assert dict(zip(per_plot["plot_id"], per_plot["stand_count"])) == truth
    assert per_plot["unclaimed"].sum() == len(missed) and len(gaps) == len(true_gaps)
    per_plot, _, _ = plot_table(plot_grid(cfg), boxes, replace(cfg, count_unclaimed=False), unclaimed)
    assert per_plot["stand_count"].sum() == len(boxes)
