"""The interactive field map: one self-contained HTML file that opens with no network.

Leaflet (bundled in ``assets/``, inlined) shows the orthophoto, downsampled into the file, the plants on one
canvas (``assets/fieldmap.js``: one canvas for every plant, not one element each, so 100,000 plants stay
usable), coloured by the trait the user picks with a legend and a histogram, the plots with their statistics, and
a popup per plant with its traits and its crops from the raw photos (:mod:`.crops`; files beside the map,
referenced by relative paths). The map's units are metres from a corner of the field, in a projected CRS.
"""

from __future__ import annotations

import base64
import json
import math
import os
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import shapely

from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import write_text
from matchplant.core.runtime.log import get_logger

log = get_logger("views")

ORTHO_PX = 2048  # the orthophoto's longer side in the file, pixels
SIMPLIFY = 0.005  # metres: plant and plot outlines are simplified this much (the map shows centimetres)
CROPS_SHOWN = 8  # thumbnails per plant popup, best first
SKIPPED = {"plant_id", "plot_id", "crs", "geometry"}
COORDINATES = {"x", "y", "z", "xmin", "ymin", "xmax", "ymax", "lon", "lat", "longitude", "latitude"}

PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>{leaflet_css}</style><style>{css}</style></head>
<body><div id="map"></div>
<div id="panel"><h1>{title}</h1>
<label for="trait">Colour plants by</label><select id="trait"></select>
<div id="ramp"></div><div id="legend"><span id="legend-lo"></span><span id="legend-hi"></span></div>
<canvas id="histogram" width="228" height="80"></canvas>
<label for="search">Find a plant or plot id</label><input id="search" type="search" placeholder="id, then Enter">
<div id="search-msg"></div>
<p>{summary}</p></div>
<script>{leaflet_js}</script>
<script>const DATA = {data};</script>
<script>{js}</script>
</body></html>
"""


def _asset(name: str) -> str:
    return resources.files("matchplant.views").joinpath("assets", name).read_text(encoding="utf-8")


def _numbers(values) -> list:
    """A column as JSON numbers (None for missing), or as text when it is not numeric."""
    s = pd.Series(values)
    if pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s):
        a = s.to_numpy(dtype=float)
        return [None if not math.isfinite(v) else (int(v) if float(v).is_integer() else float(f"{v:.6g}")) for v in a]
    return [None if pd.isna(v) else str(v) for v in s]


def _rings(geoms, origin: np.ndarray) -> tuple[list[int], list[int]]:
    """Each geometry's outer ring (its largest part's) in centimetres from ``origin``, flat, with offsets."""
    coords, offsets = [], [0]
    for g in shapely.simplify(np.asarray(geoms, dtype=object), SIMPLIFY):
        parts = [p for p in shapely.get_parts(g) if not p.is_empty] if g is not None else []
        if parts:
            ring = np.asarray(max(parts, key=lambda p: p.area).exterior.coords)[:-1, :2]
            coords.append(np.round((ring - origin) * 100).astype(np.int64).ravel())
            offsets.append(offsets[-1] + len(ring))
        else:
            offsets.append(offsets[-1])
    flat = np.concatenate(coords).tolist() if coords else []
    return flat, offsets


def _orthophoto(path: Path, crs, bounds: np.ndarray, origin: np.ndarray) -> dict:
    """The orthophoto over ``bounds`` (xmin, ymin, xmax, ymax in ``crs``), downsampled, as a WebP data URL."""
    import rasterio  # lazy: GIS
    from rasterio.enums import ColorInterp, Resampling
    from rasterio.warp import transform_bounds
    from rasterio.windows import Window, from_bounds
    from rasterio.windows import bounds as window_bounds

    if not Path(path).is_file():
        raise InputError(
            "orthophoto not found", path=path, fix="check 'orthophoto' (ODM: odm_orthophoto/odm_orthophoto.tif)"
        )
    with rasterio.open(path) as src:
        if src.crs is None:
            raise InputError("the orthophoto has no CRS", path=path, fix="give a georeferenced GeoTIFF")
        same = parse_crs(src.crs).equals(crs)
        b = tuple(bounds) if same else transform_bounds(crs.to_wkt(), src.crs, *bounds)
        win = from_bounds(*b, transform=src.transform).intersection(Window(0, 0, src.width, src.height))
        scale = max(max(win.width, win.height) / ORTHO_PX, 1.0)
        shape = (max(1, round(win.height / scale)), max(1, round(win.width / scale)))
        bands = [1, 2, 3] if src.count >= 3 else [1, 1, 1]
        rgb = src.read(bands, window=win, out_shape=(3, *shape), resampling=Resampling.average)
        if src.count >= 4 and src.colorinterp[3] == ColorInterp.alpha:  # ODM's RGBA orthophoto
            alpha = src.read(4, window=win, out_shape=shape, resampling=Resampling.nearest)
        else:
            alpha = src.dataset_mask(window=win, out_shape=shape, resampling=Resampling.nearest)
        wb = window_bounds(win, src.transform)
        if not same:  # shown on the plants' grid by its box: fine for the CRSs of one field
            wb = transform_bounds(src.crs, crs.to_wkt(), *wb)
    if rgb.dtype != np.uint8:
        hi = float(np.nanpercentile(rgb, 99.5)) or 1.0
        rgb = np.clip(rgb.astype(float) / hi * 255, 0, 255).astype(np.uint8)
    bgra = np.dstack([rgb[2], rgb[1], rgb[0], alpha])
    ok, buf = cv2.imencode(".webp", bgra, [cv2.IMWRITE_WEBP_QUALITY, 80])
    local = np.array(wb) - np.concatenate([origin, origin])
    return {
        "src": "data:image/webp;base64," + base64.b64encode(buf.tobytes()).decode(),
        "bounds": local.round(3).tolist(),
    }


def _crops(index_csv: Path, html: Path) -> dict:
    """plant id -> up to CROPS_SHOWN [path relative to the map, off-nadir, outline points, width, height]."""
    t = pd.read_csv(index_csv, dtype={"plant_id": str})
    t = t.sort_values(["plant_id", "rank"]).groupby("plant_id").head(CROPS_SHOWN)
    rel = os.path.relpath(index_csv.parent.resolve(), html.parent.resolve())
    if rel.startswith(".."):
        log.warning(
            "the crops (%s) are outside the map's folder: the map shows them only beside them", index_csv.parent
        )
    out: dict[str, list] = {}
    for r in t.itertuples(index=False):
        geom = shapely.from_wkt(r.outline_px)
        pts = "" if geom.is_empty else " ".join(f"{x:.1f},{y:.1f}" for x, y in np.asarray(geom.exterior.coords)[:-1])
        src = Path(rel, r.crop).as_posix()
        out.setdefault(r.plant_id, []).append([src, round(float(r.off_nadir_deg), 2), pts, int(r.width), int(r.height)])
    return out


def _default_trait(asked: str | None, numeric: list[str]) -> str | None:
    """The trait the map opens with: the one asked for, else the first about height, else the first that is not
    a coordinate."""
    if asked in numeric:
        return asked
    traits = [c for c in numeric if c.lower() not in COORDINATES]
    return next((c for c in traits if "height" in c.lower()), traits[0] if traits else None)


def write_field_map(
    path: str | Path,
    plants,
    *,
    plots=None,
    orthophoto: str | Path | None = None,
    crops: str | Path | None = None,
    title: str = "MatchPlant field map",
    trait: str | None = None,
) -> Path:
    """Write the map of ``plants`` (GeoDataFrame: ``plant_id``, traits, polygons) to ``path``.

    Parameters
    ----------
    plots : GeoDataFrame with ``plot_id`` and statistics, optional
    orthophoto : GeoTIFF shown under the plants, downsampled into the file
    crops : the crops' ``index.csv`` (:func:`~matchplant.views.crops.cut_crops`); best keep the crops inside the
        map's folder, which the page may read
    trait : the trait the map opens with (default: the first numeric one)
    """
    path = Path(path)
    if plants.crs is None:
        raise InputError("the plant polygons have no CRS", path=plants.attrs.get("source"), fix="give polygons_crs")
    crs = plants.crs if plants.crs.is_projected else plants.estimate_utm_crs()
    plants = plants.to_crs(crs)
    plots = plots.to_crs(crs) if plots is not None else None
    bounds = np.array(plants.total_bounds)
    if plots is not None and len(plots):
        pb = plots.total_bounds
        bounds = np.array([min(bounds[0], pb[0]), min(bounds[1], pb[1]), max(bounds[2], pb[2]), max(bounds[3], pb[3])])
    origin = np.floor(bounds[:2])
    columns = [c for c in plants.columns if c not in SKIPPED and c != plants.geometry.name]
    traits = {c: _numbers(plants[c]) for c in columns}
    numeric = [c for c in columns if pd.api.types.is_numeric_dtype(plants[c])]
    coords, offsets = _rings(plants.geometry.values, origin)
    size = np.median(np.diff(plants.geometry.bounds.to_numpy()[:, [0, 2]], axis=1)) if len(plants) else 1.0
    data = {
        "origin": origin.tolist(),
        "crs": crs.to_string(),
        "extent": [0, 0, float(bounds[2] - origin[0]), float(bounds[3] - origin[1])],
        "cell": float(max(2 * size, 0.5)),
        "default_trait": _default_trait(trait, numeric),
        "plants": {
            "ids": [str(i) for i in plants["plant_id"]],
            "offsets": offsets,
            "coords": coords,
            "traits": {c: v for c, v in traits.items() if c in numeric},
        },
        "plots": None,
        "ortho": _orthophoto(Path(orthophoto), crs, bounds, origin) if orthophoto else None,
        "crops": _crops(Path(crops), path) if crops else None,
    }
    if plots is not None and len(plots):
        pcoords, poffsets = _rings(plots.geometry.values, origin)
        stats = [c for c in plots.columns if c not in SKIPPED and c != plots.geometry.name]
        data["plots"] = {
            "ids": [str(i) for i in plots["plot_id"]],
            "offsets": poffsets,
            "coords": pcoords,
            "stats": {c: _numbers(plots[c]) for c in stats},
        }
    text = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    summary = f"{len(plants):,} plants" + (f", {len(plots):,} plots" if data["plots"] else "") + f"; {crs.name}"
    page = PAGE.format(
        title=title,
        summary=summary,
        leaflet_css=_asset("leaflet.css"),
        css=_asset("fieldmap.css"),
        leaflet_js=_asset("leaflet.js"),
        js=_asset("fieldmap.js"),
        data=text,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text(path, page)


def read_plots(path: str | Path, id_column: str = "plot_id"):
    """Plot polygons with their statistics from a vector file, the id column renamed ``plot_id``."""
    import geopandas as gpd  # lazy: GIS

    path = Path(path)
    try:
        plots = gpd.read_file(path)
    except Exception as exc:  # pyogrio raises several kinds; all mean the file can't be used
        raise InputError(
            f"cannot read the plots: {exc}", path=path, fix="give a GeoPackage, a shapefile or a GeoJSON file"
        ) from exc
    if id_column not in plots.columns:
        raise InputError(
            f"the plots have no column '{id_column}' (columns: {', '.join(map(str, plots.columns))})",
            path=path,
            fix="set plot_id_column to the column holding the plot id",
        )
    if plots.crs is None:
        raise InputError("the plots have no CRS", path=path, fix="give a plot file with a CRS (module 9 writes one)")
    return plots.rename(columns={id_column: "plot_id"})
