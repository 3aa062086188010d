"""Module 9 (spatial_stat_extractor): the output folder on the polygons' folder, rasters that are all nodata,
truncated or of another field, polygons without a CRS anywhere, in another CRS or far from the rasters, band
numbers beyond the raster, an unknown GeoPackage layer, an empty polygon file, and inputs that must work
(a DTM on another grid, CSV polygons with BOM/CRLF, non-ASCII paths, CSV polygons whose CRS comes from the
raster or from the 'crs' column of module 8's plants.csv)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import geopandas as gpd
import numpy as np
import rasterio
from affine import Affine
from cases_odm_runner import DSM, rewrite_raster, truncate
from harness import Case, Work
from rasterio.enums import Resampling

DTM = "odm_dem/dtm.tif"
ORTHO = "odm_orthophoto/odm_orthophoto.tif"


def args(w: Work, polygons: Path, *extra: str, dsm: Path | None = None, dtm: Path | None = None) -> list[str]:
    dsm = dsm or w.copy("field/" + DSM)
    dtm = dtm or w.copy("field/" + DTM)
    a = [
        "--set",
        f"polygons={polygons}",
        "--set",
        f"rasters.dsm={dsm}",
        "--set",
        f"rasters.dtm={dtm}",
        "--set",
        f"output_dir={w.out}",
    ]
    for e in extra:
        a += ["--set", e]
    return a


def gpkg(w: Work) -> Path:
    return w.copy("plants/plants.gpkg")


def broken_raster(which: str, change):
    def prepare(w: Work) -> list[str]:
        path = w.copy("field/" + which)
        change(path)
        return args(w, gpkg(w), **{Path(which).stem: path})

    return prepare


def output_on_polygons_folder(w: Work) -> list[str]:
    folder = w.copy("plants")
    a = args(w, folder / "plants.gpkg")
    a[a.index(f"output_dir={w.out}")] = f"output_dir={folder}"
    return a


def chm_all_nan(w: Work) -> list[str]:
    path = w.copy("field/" + DSM, "chm week 3.tif")
    rewrite_raster(path, data=np.nan, nodata=None)
    return ["--set", f"polygons={gpkg(w)}", "--set", f"rasters.chm={path}", "--set", f"output_dir={w.out}"]


def csv_alone(w: Work, name: str = "plants.csv") -> Path:
    """A hand-made CSV: module 8's plants.csv without its 'crs' column."""
    path = w.copy("plants/plants.csv", name)
    table = rows(path)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        out = csv.DictWriter(fh, fieldnames=[k for k in table[0] if k != "crs"], extrasaction="ignore")
        out.writeheader()
        out.writerows(table)
    return path


def csv_no_crs_anywhere(w: Work) -> list[str]:
    dsm, dtm = w.copy("field/" + DSM), w.copy("field/" + DTM)
    rewrite_raster(dsm, crs=None)
    rewrite_raster(dtm, crs=None)
    return args(w, csv_alone(w), dsm=dsm, dtm=dtm)


def moved(w: Work, dx: float) -> Path:
    gdf = gpd.read_file(w.artifacts / "plants" / "plants.gpkg")
    gdf["geometry"] = gdf.translate(dx, 0)
    path = w.inputs / "plants elsewhere.gpkg"
    gdf.to_file(path, driver="GPKG")
    return path


def in_crs(w: Work, crs: str) -> list[str]:
    gdf = gpd.read_file(w.artifacts / "plants" / "plants.gpkg").to_crs(crs)
    path = w.inputs / "plants_wgs84.gpkg"
    gdf.to_file(path, driver="GPKG")
    return args(w, path)


def empty_gpkg(w: Work) -> list[str]:
    gdf = gpd.read_file(w.artifacts / "plants" / "plants.gpkg").iloc[:0]
    path = w.inputs / "plants_empty.gpkg"
    gdf.to_file(path, driver="GPKG")
    return args(w, path)


def header_only_csv(w: Work) -> list[str]:
    path = w.inputs / "plants.csv"
    path.write_text((w.artifacts / "plants" / "plants.csv").read_text().splitlines()[0] + "\n")
    return args(w, path, f"polygons_crs={plant_crs(w).to_string()}")


def nir_beyond(w: Work) -> list[str]:
    return args(
        w, gpkg(w), f"rasters.multispectral={w.copy('field/' + ORTHO)}", "rasters.red_band=1", "rasters.nir_band=7"
    )


def dtm_other_grid(w: Work) -> list[str]:
    """The DTM at half the resolution (another grid, same area), as a GIS export may give it."""
    path = w.inputs / "dtm_coarse.tif"
    with rasterio.open(w.artifacts / "field" / DTM) as src:
        profile = src.profile
        h, wd = src.height // 2, src.width // 2
        data = src.read(out_shape=(src.count, h, wd), resampling=Resampling.average)
        profile.update(height=h, width=wd, transform=src.transform @ Affine.scale(src.width / wd, src.height / h))
    profile.pop("blockxsize", None), profile.pop("blockysize", None), profile.pop("tiled", None)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    return args(w, gpkg(w), dtm=path)


def dtm_other_field(w: Work) -> list[str]:
    path = w.copy("field/" + DTM, "dtm_other.tif")
    with rasterio.open(path) as src:
        profile, data = src.profile, src.read()
    profile["transform"] = Affine.translation(3000, 0) @ profile["transform"]
    path.unlink()
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    return args(w, gpkg(w), dtm=path)


def unicode_paths(w: Work) -> list[str]:
    folder = w.inputs / "parcela ñ 3 (año 2024)"
    folder.mkdir()
    poly = w.copy("plants/plants.gpkg", "parcela ñ 3 (año 2024)/plantas é.gpkg")
    dsm = w.copy("field/" + DSM, "parcela ñ 3 (año 2024)/dsm día 1.tif")
    a = args(w, poly, dsm=dsm)
    out = w.root / "salida ü 9"
    a[a.index(f"output_dir={w.out}")] = f"output_dir={out}"
    return a


def bom_crlf_csv(w: Work) -> list[str]:
    text = (w.artifacts / "plants" / "plants.csv").read_text()
    path = w.inputs / "plants.csv"
    path.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    return args(w, path, f"polygons_crs={plant_crs(w).to_string()}")


def excel_csv(w: Work) -> list[str]:
    """Semicolons, decimal commas, BOM and CRLF, as a European spreadsheet saves plants.csv."""
    lines = (w.artifacts / "plants" / "plants.csv").read_text().splitlines()
    rows_ = [ln.replace(",", ";").replace(".", ",") for ln in lines]
    path = w.inputs / "plantas (excel).csv"
    path.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(rows_).encode() + b"\r\n")
    return args(w, path, f"polygons_crs={plant_crs(w).to_string()}")


def csv_box_blank(w: Work) -> list[str]:
    lines = (w.artifacts / "plants" / "plants.csv").read_text().splitlines()
    head = lines[0].split(",")
    third = lines[3].split(",")
    third[head.index("ymax")] = "n/a"
    lines[3] = ",".join(third)
    path = w.inputs / "plants.csv"
    path.write_text("\n".join(lines) + "\n")
    return args(w, path, f"polygons_crs={plant_crs(w).to_string()}")


def csv_with_crs(w: Work) -> list[str]:
    """Module 8's plants.csv alone (no projection_summary.json beside it): its 'crs' column places it."""
    return args(w, w.copy("plants/plants.csv"))


# -- checks --------------------------------------------------------------------------------------------------


def rows(path: Path) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def plant_crs(w: Work):
    with rasterio.open(w.artifacts / "field" / DSM) as src:
        return src.crs


def heights_right(w: Work, out: Path | None = None, tol: float = 1e-6, crs=None) -> None:
    """Every plant has a height; the CHM maximum (DSM - DTM) of each plant, recomputed here from the
    session's rasters with pixel centres in the box, matches; the GIS files carry ``crs`` (default: the
    rasters' CRS, which is also module 8's)."""
    out = out or w.out
    got = rows(out / "stats.csv")
    plants = rows(w.artifacts / "plants" / "plants.csv")
    assert len(got) == len(plants) > 0
    with rasterio.open(w.artifacts / "field" / DSM) as a, rasterio.open(w.artifacts / "field" / DTM) as b:
        chm = a.read(1).astype(float) - b.read(1).astype(float)
        bad = (a.read(1) == a.nodata) | (b.read(1) == b.nodata)
        chm[bad] = np.nan
        t = a.transform
    cols, rws = np.meshgrid(np.arange(chm.shape[1]) + 0.5, np.arange(chm.shape[0]) + 0.5)
    xs, ys = t @ (cols, rws)
    by_id = {r["plant_id"]: r for r in got}
    checked = 0
    for p in plants[:10]:
        inside = (
            (xs >= float(p["xmin"])) & (xs <= float(p["xmax"])) & (ys >= float(p["ymin"])) & (ys <= float(p["ymax"]))
        )
        if not inside.any() or np.isnan(chm[inside]).all():
            continue
        want = np.nanmax(chm[inside])
        have = float(by_id[p["plant_id"]]["chm_max"])
        assert math.isclose(have, want, abs_tol=tol), (p["plant_id"], have, want)
        checked += 1
    assert checked >= 5
    for name in ("polygons.gpkg", "stats.gpkg"):
        assert gpd.read_file(out / name).crs == (crs or plant_crs(w)), name


def heights_close(w: Work) -> None:
    """Another DTM grid: the heights are resampled, so they agree within 5 cm."""
    heights_right(w, tol=0.05)


def crs_from(source: str):
    """The heights are right, and stats_report.json says where the polygons' CRS came from."""

    def check(w: Work) -> None:
        heights_right(w)
        said = json.loads((w.out / "stats_report.json").read_text())["polygons_crs"]
        assert source in (said["from"] or ""), said

    return check


def unicode_ok(w: Work) -> None:
    heights_right(w, w.root / "salida ü 9")


CASES = [
    Case(
        "m9-output-dir-is-polygons-folder",
        "spatial_stat_extractor",
        output_on_polygons_folder,
        mentions=("output_dir", "polygons"),
    ),
    Case(
        "m9-dsm-all-nodata",
        "spatial_stat_extractor",
        broken_raster(DSM, lambda p: rewrite_raster(p, data=-9999, nodata=-9999)),
        mentions=("dsm.tif", "no valid"),
    ),
    Case("m9-chm-all-nan", "spatial_stat_extractor", chm_all_nan, mentions=("chm week 3.tif", "no valid")),
    Case(
        "m9-dtm-truncated",
        "spatial_stat_extractor",
        broken_raster(DTM, lambda p: truncate(p, 0.4)),
        mentions=("dtm.tif",),
    ),
    Case(
        "m9-dtm-not-a-raster",
        "spatial_stat_extractor",
        broken_raster(DTM, lambda p: p.write_text("ENVI header\n")),
        mentions=("dtm.tif",),
    ),
    Case(
        "m9-csv-polygons-no-crs-anywhere",
        "spatial_stat_extractor",
        csv_no_crs_anywhere,
        mentions=("plants.csv", "polygons_crs"),
    ),
    Case(
        "m9-polygons-miss-the-raster",
        "spatial_stat_extractor",
        lambda w: args(w, moved(w, 2500.0)),
        mentions=("plants elsewhere.gpkg", "none of"),
    ),
    Case(
        "m9-nir-beyond-band-count",
        "spatial_stat_extractor",
        nir_beyond,
        mentions=("odm_orthophoto.tif", "nir_band = 7", "4 band"),
    ),
    Case(
        "m9-rgb-band-beyond-band-count",
        "spatial_stat_extractor",
        lambda w: args(w, gpkg(w), f"rasters.rgb={w.copy('field/' + ORTHO, 'ortho.tif')}", "rasters.rgb_bands=[1,2,5]"),
        mentions=("ortho.tif", "rgb_bands[2] = 5"),
    ),
    Case(
        "m9-red-band-zero",
        "spatial_stat_extractor",
        lambda w: args(w, gpkg(w), f"rasters.multispectral={w.copy('field/' + ORTHO)}", "rasters.red_band=0"),
        mentions=("red_band",),
    ),
    Case(
        "m9-gpkg-layer-misspelt",
        "spatial_stat_extractor",
        lambda w: args(w, gpkg(w), "layer=plant"),
        mentions=("plants.gpkg", "did you mean 'plants'"),
    ),
    Case("m9-polygons-gpkg-empty", "spatial_stat_extractor", empty_gpkg, mentions=("plants_empty.gpkg", "no features")),
    Case(
        "m9-polygons-csv-header-only",
        "spatial_stat_extractor",
        header_only_csv,
        mentions=("plants.csv", "no data rows"),
    ),
    Case(
        "m9-polygons-missing",
        "spatial_stat_extractor",
        lambda w: args(w, w.inputs / "plantas.gpkg"),
        mentions=("plantas.gpkg",),
    ),
    Case("m9-dtm-of-another-field", "spatial_stat_extractor", dtm_other_field, mentions=("dtm_other.tif",)),
    Case(
        "m9-polygons-crs-not-a-crs",
        "spatial_stat_extractor",
        lambda w: args(w, csv_alone(w), "polygons_crs=UTM zone 15"),
        mentions=("polygons_crs", "EPSG"),
    ),
    Case(
        "m9-polygons-csv-box-not-a-number",
        "spatial_stat_extractor",
        csv_box_blank,
        mentions=("plants.csv", "ymax", "line 4"),
    ),
    Case(
        "m9-id-column-misspelt",
        "spatial_stat_extractor",
        lambda w: args(w, gpkg(w), "id_column=plantid"),
        mentions=("plants.gpkg", "did you mean 'plant_id'"),
    ),
    Case("m9-polygons-csv-excel-export", "spatial_stat_extractor", excel_csv, expect="ok", check=heights_right),
    Case(
        "m9-polygons-gpkg-truncated",
        "spatial_stat_extractor",
        lambda w: args(w, (lambda p: (truncate(p, 0.3), p)[1])(gpkg(w))),
        mentions=("plants.gpkg",),
    ),
    Case(
        "m9-polygons-in-wgs84",
        "spatial_stat_extractor",
        lambda w: in_crs(w, "EPSG:4326"),
        expect="ok",
        check=lambda w: heights_right(w, tol=1e-6, crs="EPSG:4326"),
    ),
    Case(
        "m9-csv-polygons-crs-from-raster",
        "spatial_stat_extractor",
        lambda w: args(w, csv_alone(w)),
        expect="ok",
        check=crs_from("dsm.tif"),
    ),
    Case(
        "m9-csv-polygons-crs-from-column",
        "spatial_stat_extractor",
        csv_with_crs,
        expect="ok",
        check=crs_from("'crs' column of"),
    ),
    Case(
        "m9-csv-polygons-bom-crlf", "spatial_stat_extractor", bom_crlf_csv, expect="ok", check=crs_from("polygons_crs")
    ),
    Case("m9-unicode-space-paths", "spatial_stat_extractor", unicode_paths, expect="ok", check=unicode_ok),
    Case("m9-dtm-on-another-grid", "spatial_stat_extractor", dtm_other_grid, expect="ok", check=heights_close),
]
