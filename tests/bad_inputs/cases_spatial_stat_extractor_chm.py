"""Module 9's CHM sanity (issue 27): DSM and DTM swapped, a CHM in centimetres, a DSM given as the CHM,
``canopy.min_top: 5`` meant as 5 cm, a later flight georeferenced 1.5 m off (no GCPs) - and the inputs that
must work: the same flight registered with ``canopy.register``, a noisy CHM with the default thresholds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyproj
import rasterio
import rasterio.crs
from affine import Affine
from cases_odm_runner import DSM
from cases_spatial_stat_extractor import DTM, args, gpkg, heights_right, rows
from harness import Case, Work
from scipy import ndimage as ndi

MAX_SHIFT = 0.1  # canopy.max_shift's default


def write_like(src_path: Path, dst: Path, data: np.ndarray | None = None, transform: Affine | None = None) -> Path:
    """A copy of a raster with its values and/or its transform replaced."""
    with rasterio.open(src_path) as src:
        profile, arr = src.profile, src.read(1)
    if data is not None:
        arr = data.astype(arr.dtype)
    if transform is not None:
        profile["transform"] = transform
    dst.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(dst, "w", **profile) as out:
        out.write(arr, 1)
    return dst


def chm_of(w: Work) -> tuple[np.ndarray, dict]:
    with rasterio.open(w.artifacts / "field" / DSM) as a, rasterio.open(w.artifacts / "field" / DTM) as b:
        dsm, dtm, profile = a.read(1).astype(float), b.read(1).astype(float), a.profile
        bad = (dsm == a.nodata) | (dtm == b.nodata)
    chm = dsm - dtm
    chm[bad] = -9999
    return chm, profile


def swapped(w: Work) -> list[str]:
    dsm, dtm = w.copy("field/" + DSM), w.copy("field/" + DTM)
    return args(w, gpkg(w), dsm=dtm, dtm=dsm)


def chm_file(w: Work, name: str, scale: float = 1.0, offset: float = 0.0) -> Path:
    chm, _ = chm_of(w)
    data = np.where(chm == -9999, -9999, chm * scale + offset)
    return write_like(w.artifacts / "field" / DSM, w.inputs / name, data)


def chm_args(w: Work, chm: Path, *extra: str) -> list[str]:
    a = ["--set", f"polygons={gpkg(w)}", "--set", f"rasters.chm={chm}", "--set", f"output_dir={w.out}"]
    for e in extra:
        a += ["--set", e]
    return a


def later_flight(w: Work, dx: float, *extra: str) -> list[str]:
    """A second flight: the same field, its DSM and DTM georeferenced ``dx`` m east (GNSS only, no GCPs)."""
    out = []
    for rel in (DSM, DTM):
        with rasterio.open(w.artifacts / "field" / rel) as src:
            t = src.transform
        out.append(
            write_like(
                w.artifacts / "field" / rel,
                w.inputs / "flight 2" / Path(rel).name,
                transform=Affine.translation(dx, 0) @ t,
            )
        )
    second = json.dumps([{"date": "d2", "dsm": str(out[0]), "dtm": str(out[1])}])
    return args(w, gpkg(w), "rasters.date=d1", f"more_dates={second}", *extra)


def registered_right(w: Work) -> None:
    """Registered: the offset found is the one put in; on the moved boxes every plant of the second flight is
    outlined, as tall as on the first (the same flight), its top 1.5 m east."""
    report = json.loads((w.out / "stats_report.json").read_text())
    got = report["canopy"]["dates"][1]["registered"]
    assert abs(got["dx"] - 1.5) < 0.01 and abs(got["dy"]) < 0.01, got
    table = rows(w.out / "stats.csv")
    ok = [r for r in table if r["outline_flag_d1"] == ""]
    assert len(ok) >= 0.9 * len(table)
    assert all(r["outline_flag_d2"] == "" for r in ok)
    for r in ok:
        assert abs(float(r["top_height_d2"]) - float(r["top_height_d1"])) < 1e-6
        assert abs(float(r["top_x_d2"]) - float(r["top_x_d1"]) - 1.5) < 0.01


def noisy(w: Work) -> list[str]:
    """The tiny field's DSM with a photogrammetric ground noise (correlated, SD 2.5 cm, median +1.5 cm)."""
    with rasterio.open(w.artifacts / "field" / DSM) as src:
        dsm, nodata = src.read(1).astype(float), src.nodata
    rng = np.random.default_rng(3)
    n = ndi.gaussian_filter(rng.normal(0, 1, dsm.shape), 2.0)
    data = np.where(dsm == nodata, nodata, dsm + 0.015 + 0.025 * n / n.std())
    dsm_path = write_like(w.artifacts / "field" / DSM, w.inputs / "dsm_noisy.tif", data)
    return args(w, gpkg(w), dsm=dsm_path)


def noisy_right(w: Work) -> None:
    """The noise measured (SD within 20 % of 2.5 cm), min_height and min_top derived from it, no outline fills
    its box, no ground bump listed as a plant the detector missed."""
    report = json.loads((w.out / "stats_report.json").read_text())["canopy"]["dates"][0]
    assert abs(report["ground_noise"]["sd"] - 0.025) < 0.005, report["ground_noise"]
    assert report["min_height"] > 0.07 and report["thresholds_from"]["min_height"].startswith("auto")
    assert report["fills_box"] == 0 and report["unclaimed_canopies"] == 0
    heights_right(w, tol=0.2)  # box maxima of the noisy CHM, recomputed from the clean one within the noise


def chm_in_feet(w: Work, vertical: bool) -> list[str]:
    """The CHM in US survey feet as its CRS says: heights in a NAVD88 (ftUS) vertical CRS, or the whole grid in a
    UTM projection in ftUS (coordinates and heights)."""
    chm, profile = chm_of(w)
    ft = 0.3048006096012192
    data = np.where(chm == -9999, -9999, chm / ft)
    epsg = rasterio.crs.CRS(profile["crs"]).to_epsg()
    if vertical:
        crs, transform, name = rasterio.crs.CRS.from_user_input(f"EPSG:{epsg}+6360"), profile["transform"], "v"
    else:
        proj4 = pyproj.CRS.from_epsg(epsg).to_proj4().replace("+units=m", "+units=us-ft")
        crs, transform, name = rasterio.crs.CRS.from_proj4(proj4), Affine.scale(1 / ft) @ profile["transform"], "h"
    path = w.inputs / f"chm_ftUS_{name}.tif"
    path.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(path, "w", **dict(profile, crs=crs, transform=transform)) as out:
        out.write(data.astype(profile["dtype"]), 1)
    return chm_args(w, path)


def dsm_as_dtm(w: Work) -> list[str]:
    """The DSM given as the DTM too (a copy): a CHM of zeros everywhere."""
    dsm = w.copy("field/" + DSM)
    return args(w, gpkg(w), dsm=dsm, dtm=w.copy("field/" + DSM, "dtm.tif"))


CASES = [
    Case(
        "m9-dsm-dtm-swapped",
        "spatial_stat_extractor",
        swapped,
        mentions=("rasters.dsm", "rasters.dtm", "swapped", "negative"),
    ),
    Case(
        "m9-chm-in-centimetres",
        "spatial_stat_extractor",
        lambda w: chm_args(w, chm_file(w, "chm_cm.tif", scale=100.0)),
        mentions=("chm_cm.tif", "centimetres", "canopy.max_height"),
    ),
    Case(
        "m9-dsm-given-as-chm",
        "spatial_stat_extractor",
        lambda w: chm_args(w, w.copy("field/" + DSM, "chm.tif")),
        mentions=("chm.tif", "rasters.chm", "bare ground"),
    ),
    Case(
        "m9-canopy-min-top-in-cm",
        "spatial_stat_extractor",
        lambda w: args(w, gpkg(w), "canopy.min_top=5"),
        mentions=("canopy.min_top", "0.05", "5 cm"),
    ),
    Case(
        "m9-later-flight-1.5m-off",
        "spatial_stat_extractor",
        lambda w: later_flight(w, 1.5),
        mentions=("d2", "shifted 1.5", "canopy.max_shift", "canopy.register"),
    ),
    Case(
        "m9-later-flight-registered",
        "spatial_stat_extractor",
        lambda w: later_flight(w, 1.5, "canopy.register=true"),
        expect="ok",
        check=registered_right,
    ),
    Case("m9-noisy-chm-default-thresholds", "spatial_stat_extractor", noisy, expect="ok", check=noisy_right),
    Case(
        "m9-chm-all-zeros",
        "spatial_stat_extractor",
        lambda w: chm_args(w, chm_file(w, "chm_zero.tif", scale=0.0)),
        mentions=("chm_zero.tif", "0 everywhere", "rasters.chm", "'low'"),
    ),
    Case(
        "m9-dsm-given-as-dtm",
        "spatial_stat_extractor",
        dsm_as_dtm,
        mentions=("dtm.tif", "everywhere", "rasters.dsm", "rasters.dtm", "same surface"),
    ),
    Case(
        "m9-chm-vertical-us-feet",
        "spatial_stat_extractor",
        lambda w: chm_in_feet(w, vertical=True),
        mentions=("chm_ftUS_v.tif", "rasters.chm", "US survey foot", "0.3048"),
    ),
    Case(
        "m9-chm-grid-in-us-feet",
        "spatial_stat_extractor",
        lambda w: chm_in_feet(w, vertical=False),
        mentions=("chm_ftUS_h.tif", "rasters.chm", "US survey foot", "gdalwarp"),
    ),
]
