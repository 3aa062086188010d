"""Module 9's plots and field books (issue 27): broken field books and plot layouts a breeder gives, from
the tiny field (its plot grid and field book in ``truth/``, module 8's plants from the true boxes), and the
ones that must work, checked against the field's plot truth."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
import shapely
from cases_spatial_stat_extractor import args, gpkg
from harness import Case, Work
from pyproj import Transformer

from matchplant.cli import run_module

try:
    import openpyxl
except ImportError:  # (requirements.txt lists it; without it an .xlsx field book is a clear error)
    openpyxl = None


def grid(w: Work) -> dict:
    return json.loads((w.artifacts / "field/truth/plots.json").read_text())


def grid_args(w: Work, corners=None, *extra: str) -> list[str]:
    g = grid(w)
    return args(
        w,
        gpkg(w),
        f"plots.corners={json.dumps(corners or g['corners'])}",
        f"plots.columns={g['columns']}",
        f"plots.ranges={g['ranges']}",
        f"plots.plant_spacing={g['plant_spacing']}",
        *extra,
    )


def book_rows(w: Work) -> list[list[str]]:
    with open(w.artifacts / "field/truth/field_book.csv", newline="") as fh:
        return list(csv.reader(fh))


def excel_book(w: Work, rows: list[list[str]], name: str = "field book.csv") -> Path:
    """As Excel saves a CSV: BOM, CRLF, a quoted note with a comma, empty rows at the end."""
    lines = [",".join([*rows[0], "note"])]
    lines += [",".join([*r, '"re-sown, late"' if i == 1 else "ok"]) for i, r in enumerate(rows[1:])]
    path = w.inputs / name
    path.write_bytes(b"\xef\xbb\xbf" + "\r\n".join([*lines, ",,,", ",,,", ""]).encode("utf-8"))
    return path


def with_book(path_of):
    def prepare(w: Work) -> list[str]:
        return grid_args(w, None, f"plots.field_book={path_of(w)}")

    return prepare


def truth_plots(w: Work) -> pd.DataFrame:
    return pd.read_csv(w.artifacts / "field/truth/plots.csv")


def plots_file(w: Work, geoms, ids, name: str) -> Path:
    crs = gpd.read_file(w.artifacts / "plants/plants.gpkg").crs
    path = w.inputs / name
    gpd.GeoDataFrame({"plot_id": ids}, geometry=list(geoms), crs=crs).to_file(path, driver="GPKG")
    return path


def truth_geoms(w: Work):
    return shapely.from_wkt(truth_plots(w)["geometry"].to_numpy())


def stand_counts_right(w: Work) -> None:
    got, truth = pd.read_csv(w.out / "plots.csv"), truth_plots(w)
    assert list(got["plot_id"]) == list(truth["plot_id"])
    assert (got["stand_count"].to_numpy() == truth["stand_count"].to_numpy()).all()
    assert (got["expected"].to_numpy() == truth["expected"].to_numpy()).all()


def book_joined(w: Work) -> None:
    stand_counts_right(w)
    got = pd.read_csv(w.out / "plots.csv")
    want = {int(r[0]): r[1] for r in book_rows(w)[1:]}
    assert list(got["genotype"]) == [want[int(p)] for p in got["plot_id"]]


def excel_csv_book(w: Work) -> Path:
    return excel_book(w, book_rows(w))


def prefixed_book(w: Work) -> Path:
    rows = book_rows(w)
    return excel_book(w, [["Plot", *rows[0][1:]], *[[f"P{r[0]}", *r[1:]] for r in rows[1:]]], "book P.csv")


def other_trial_book(w: Work) -> Path:
    rows = book_rows(w)
    return excel_book(w, [rows[0], *[[str(1000 + int(r[0]) * 7), *r[1:]] for r in rows[1:]]], "trial 2025.csv")


def xlsx_book(w: Work) -> Path:
    wb = openpyxl.Workbook()
    ws = wb.active
    rows = book_rows(w)
    ws.append(["Plot ID", *rows[0][1:]])
    for r in rows[1:]:
        ws.append([int(r[0]), r[1], int(r[2])])
    ws.append([None, None, None])
    path = w.inputs / "field book.xlsx"
    wb.save(path)
    return path


def xls_book(w: Work) -> Path:
    path = w.inputs / "field book.xls"
    path.write_bytes(b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1" + b"\0" * 504)
    return path


def no_id_book(w: Work) -> Path:
    rows = book_rows(w)
    return excel_book(w, [["parcel", *rows[0][1:]], *rows[1:]], "book.csv")


def header_only_book(w: Work) -> Path:
    path = w.inputs / "book.csv"
    path.write_text("plot_id,genotype,rep\r\n,,\r\n")
    return path


def book_without_plots(w: Work) -> list[str]:
    return args(w, gpkg(w), f"plots.field_book={excel_csv_book(w)}")


def corners_in_degrees(swap: bool):
    def prepare(w: Work) -> list[str]:
        g = grid(w)
        to_ll = Transformer.from_crs(g["crs"], "EPSG:4326", always_xy=True)
        ll = [list(to_ll.transform(*c)) for c in g["corners"]]
        return grid_args(w, [[b, a] for a, b in ll] if swap else ll)

    return prepare


def last_years_corners(w: Work) -> list[str]:
    return grid_args(w, [[x + 150.0, y - 20.0] for x, y in grid(w)["corners"]])


def identical_plots(w: Work) -> list[str]:
    geoms = truth_geoms(w)
    ids = truth_plots(w)["plot_id"].tolist()
    path = plots_file(w, [*geoms, geoms[1]], [*ids, max(ids) + 1], "plots drawn.gpkg")
    return args(w, gpkg(w), f"plots.polygons={path}", f"plots.plant_spacing={grid(w)['plant_spacing']}")


def hand_drawn_overlapping(w: Work) -> list[str]:
    geoms = shapely.buffer(truth_geoms(w), 0.08, join_style="mitre")
    path = plots_file(w, geoms, truth_plots(w)["plot_id"].tolist(), "plots drawn.gpkg")
    return args(w, gpkg(w), f"plots.polygons={path}", f"plots.plant_spacing={grid(w)['plant_spacing']}")


def zero_row_directions(w: Work) -> list[str]:
    """A plot file whose row_dir_x/row_dir_y columns are all 0 (a template filled with zeros): ignored without a
    word before."""
    path = plots_file(w, truth_geoms(w), truth_plots(w)["plot_id"].tolist(), "plots zero dirs.gpkg")
    g = gpd.read_file(path).assign(row_dir_x=0.0, row_dir_y=0.0)
    g.to_file(path, driver="GPKG")
    return args(w, gpkg(w), f"plots.polygons={path}", f"plots.plant_spacing={grid(w)['plant_spacing']}")


def own_plots_read_back(w: Work) -> list[str]:
    first = w.root / "first run"
    a = grid_args(w)
    a[a.index(f"output_dir={w.out}")] = f"output_dir={first}"
    assert run_module("spatial_stat_extractor", [*a, "--quiet"]) == 0
    path = w.inputs / "plots from last run.gpkg"
    path.write_bytes((first / "plots.gpkg").read_bytes())
    return args(w, gpkg(w), f"plots.polygons={path}", f"plots.plant_spacing={grid(w)['plant_spacing']}")


def same_as_first_run(w: Work) -> None:
    stand_counts_right(w)
    first = pd.read_csv(w.root / "first run" / "plots.csv")
    got = pd.read_csv(w.out / "plots.csv")
    assert np.allclose(got["expected"], first["expected"], rtol=0.02)
    assert abs(got["gaps"].sum() - first["gaps"].sum()) <= 0.02 * first["expected"].sum()


def overlap_counted_once(w: Work) -> None:
    stand_counts_right(w)
    got = pd.read_csv(w.out / "plots.csv")
    assert got["stand_count"].sum() == truth_plots(w)["stand_count"].sum()


need_openpyxl = (pytest.mark.skipif(openpyxl is None, reason="openpyxl is not installed"),)

CASES = [
    Case(
        "m9-plots-field-book-excel-csv",
        "spatial_stat_extractor",
        with_book(excel_csv_book),
        expect="ok",
        check=book_joined,
    ),
    Case(
        "m9-plots-field-book-xlsx",
        "spatial_stat_extractor",
        with_book(xlsx_book),
        expect="ok",
        check=book_joined,
        marks=need_openpyxl,
    ),
    Case(
        "m9-plots-field-book-ids-prefixed",
        "spatial_stat_extractor",
        with_book(prefixed_book),
        expect="ok",
        check=book_joined,
    ),
    Case(
        "m9-plots-field-book-joins-nothing",
        "spatial_stat_extractor",
        with_book(other_trial_book),
        mentions=("trial 2025.csv", "none of the", "plot ids"),
    ),
    Case(
        "m9-plots-field-book-old-xls",
        "spatial_stat_extractor",
        with_book(xls_book),
        mentions=("field book.xls", ".xlsx"),
    ),
    Case(
        "m9-plots-field-book-no-id-column",
        "spatial_stat_extractor",
        with_book(no_id_book),
        mentions=("book.csv", "plot_id", "plots.field_book_id_column"),
    ),
    Case(
        "m9-plots-field-book-header-only",
        "spatial_stat_extractor",
        with_book(header_only_book),
        mentions=("book.csv", "no data rows"),
    ),
    Case(
        "m9-plots-field-book-without-plots",
        "spatial_stat_extractor",
        book_without_plots,
        mentions=("plots.field_book", "plots.corners"),
    ),
    Case(
        "m9-plots-corners-lon-lat",
        "spatial_stat_extractor",
        corners_in_degrees(False),
        expect="ok",
        check=stand_counts_right,
    ),
    Case(
        "m9-plots-corners-lat-lon",
        "spatial_stat_extractor",
        corners_in_degrees(True),
        expect="ok",
        check=stand_counts_right,
    ),
    Case(
        "m9-plots-corners-last-year",
        "spatial_stat_extractor",
        last_years_corners,
        mentions=("plots.corners", "hold no plant"),
    ),
    Case(
        "m9-plots-identical-polygons",
        "spatial_stat_extractor",
        identical_plots,
        mentions=("plots drawn.gpkg", "same plot", "counted twice"),
    ),
    Case(
        "m9-plots-hand-drawn-overlapping",
        "spatial_stat_extractor",
        hand_drawn_overlapping,
        expect="ok",
        check=overlap_counted_once,
    ),
    Case(
        "m9-plots-own-file-read-back",
        "spatial_stat_extractor",
        own_plots_read_back,
        expect="ok",
        check=same_as_first_run,
    ),
    Case(
        "m9-plots-row-direction-out-of-range",
        "spatial_stat_extractor",
        lambda w: grid_args(w, None, "plots.row_direction=400"),
        mentions=("plots.row_direction",),
    ),
    Case(
        "m9-plots-polygons-and-corners",
        "spatial_stat_extractor",
        lambda w: grid_args(
            w, None, f"plots.polygons={plots_file(w, truth_geoms(w), truth_plots(w)['plot_id'].tolist(), 'p.gpkg')}"
        ),
        mentions=("plots.polygons", "plots.corners"),
    ),
    Case(
        "m9-plots-zero-row-directions",
        "spatial_stat_extractor",
        zero_row_directions,
        mentions=("plots zero dirs.gpkg", "row_dir_x/row_dir_y", "zero vector", "plots.row_direction"),
    ),
]
