"""The area of interest (AOI) that step 3 must cover, and its coverage grid.

The AOI is the orthophoto's valid-data area (read at reduced resolution and polygonised), or a polygon file
from the user. It is then cut into square cells weighted by area, and each footprint is rasterised onto
them: the set-cover solver (:mod:`matchplant.min_img_finder.setcover`) works on that grid alone.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path

import geopandas as gpd
import numpy as np
import pyogrio
import rasterio
import shapely
from affine import Affine
from rasterio.features import shapes
from scipy import sparse
from shapely.geometry import MultiPolygon, Polygon

from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.min_img_finder.setcover import CoverageGrid

log = get_logger("min_img_finder")


def orthophoto_preview(path: Path, max_size: int = 1500) -> tuple[np.ndarray, np.ndarray, object, object]:
    """The orthophoto read at reduced resolution: ``(rgb (h, w, 3) uint8, valid mask (h, w), transform, crs)``."""
    if not Path(path).is_file():
        raise InputError("orthophoto not found", path=path, fix="run ODM without --skip-orthophoto (module 2)")
    with rasterio.open(path) as src:
        scale = max(1.0, max(src.width, src.height) / max_size)
        h, w = max(1, round(src.height / scale)), max(1, round(src.width / scale))
        bands = [1, 2, 3] if src.count >= 3 else [1, 1, 1]
        rgb = src.read(bands, out_shape=(3, h, w))
        with warnings.catch_warnings():  # RGBA with a nodata value: either mask is fine for "valid data"
            warnings.simplefilter("ignore")
            mask = src.dataset_mask(out_shape=(h, w)) > 0
        transform = src.transform @ Affine.scale(src.width / w, src.height / h)
        crs = src.crs
    rgb = np.moveaxis(rgb, 0, -1)
    if rgb.dtype != np.uint8:  # scale other types to 0..255 for display
        valid = rgb[mask] if mask.any() else rgb.reshape(-1, 3)
        lo, hi = np.percentile(valid, [1, 99]) if valid.size else (0, 1)
        rgb = np.clip((rgb.astype(float) - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    return rgb, mask, transform, crs


def aoi_from_mask(mask: np.ndarray, transform, path: Path | None = None) -> Polygon | MultiPolygon:
    """Polygonise a valid-data mask (``rasterio.features.shapes``) into one (multi)polygon."""
    geoms = [
        shapely.geometry.shape(g) for g, v in shapes(mask.astype(np.uint8), mask=mask, transform=transform) if v == 1
    ]
    if not geoms:
        raise InputError(
            "the orthophoto has no valid pixels, so it gives no area of interest",
            path=path,
            fix="set aoi_file to a polygon file of the field, or re-run ODM (module 2)",
        )
    aoi = shapely.union_all(geoms)
    return aoi.simplify(abs(transform.a) * 0.5)


def read_aoi_file(path: Path, crs) -> Polygon | MultiPolygon:
    """The union of the polygons in a vector file, in ``crs`` (reprojected from the file's own CRS, said in
    the log). A file without a CRS, or whose coordinates do not fit its CRS (a GeoJSON is WGS84 by
    definition), is an error: guessing would put the area somewhere else."""
    path = Path(path)
    try:
        layers = [(str(name), str(kind)) for name, kind in pyogrio.list_layers(path)]
        polygonal = [name for name, kind in layers if "polygon" in kind.lower()]
        if len(polygonal) > 1:
            raise InputError(
                f"the area-of-interest file (aoi_file) has {len(polygonal)} polygon layers "
                f"({', '.join(polygonal)}); which one is the area?",
                path=path,
                fix="save the field boundary alone in its own file (e.g. QGIS: Export > Save Features As)",
            )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # odd fields: what matters is checked below
            gdf = gpd.read_file(path, layer=polygonal[0] if polygonal else None)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any driver error means the file cannot be used
        raise InputError(
            f"cannot read the area-of-interest file (aoi_file): {exc}",
            path=path,
            fix="use a GeoPackage, Shapefile or GeoJSON with polygons (a truncated copy must be copied again)",
        ) from exc
    kinds = sorted(set(gdf.geometry.dropna().geom_type)) if len(gdf) else []
    gdf = gdf[gdf.geometry.notna() & gdf.geometry.geom_type.isin(["Polygon", "MultiPolygon"])]
    gdf = gdf[~gdf.geometry.is_empty]
    if gdf.empty:
        holds = f"only {', '.join(kinds)}" if kinds else "no features"
        raise InputError(
            f"the area-of-interest file (aoi_file) holds no polygon ({holds})",
            path=path,
            fix="draw the field boundary as a polygon (e.g. in QGIS) and save it",
        )
    x0, y0, x1, y1 = (float(v) for v in gdf.total_bounds)
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise InputError(
            "the area-of-interest file (aoi_file) has coordinates that are not numbers",
            path=path,
            fix="redraw the polygon",
        )
    target = parse_crs(crs) if crs is not None else None
    if gdf.crs is None:
        guess = (
            f" (its coordinates look like {target.name})"
            if target is not None and not target.is_geographic and max(abs(x0), abs(x1)) > 180
            else ""
        )
        raise InputError(
            f"the area-of-interest file (aoi_file) has no coordinate system{guess}",
            path=path,
            fix="set its CRS (in QGIS: Layer > Set CRS, or ogr2ogr -a_srs EPSG:xxxx) and save it again",
        )
    if gdf.crs.is_geographic and (max(abs(x0), abs(x1)) > 180 or max(abs(y0), abs(y1)) > 90):
        said = (
            "GeoJSON means WGS84 lat/lon"
            if path.suffix.lower() in (".geojson", ".json")
            else f"the file says {gdf.crs.name}"
        )
        raise InputError(
            f"the area-of-interest file (aoi_file) holds coordinates like ({x0:.0f}, {y0:.0f}), "
            f"which are not degrees, but {said}",
            path=path,
            fix="save it with its true (projected) CRS, e.g. as a GeoPackage, or convert it to WGS84 lat/lon",
        )
    if target is not None and not parse_crs(gdf.crs).equals(target):
        log.info("area of interest %s is in %s: reprojected to the project's %s", path.name, gdf.crs.name, target.name)
        gdf = gdf.to_crs(target)
    aoi = shapely.make_valid(shapely.union_all(gdf.geometry.values))
    if aoi.is_empty or aoi.area <= 0:
        raise InputError(
            "the area-of-interest file (aoi_file) holds only empty or zero-area polygons",
            path=path,
            fix="redraw the field boundary as a polygon",
        )
    return aoi


def build_grid(aoi, polygons: Sequence[Polygon], cell: float = 0.0, target_cells: int = 40_000) -> CoverageGrid:
    """Cut the AOI into square cells and record which footprint covers each (vectorised point-in-polygon)."""
    if aoi.is_empty or aoi.area <= 0:
        raise InputError("the area of interest is empty", fix="check the AOI file or the orthophoto")
    if cell <= 0:
        cell = math.sqrt(aoi.area / target_cells)
    xmin, ymin, xmax, ymax = aoi.bounds
    nx, ny = max(1, math.ceil((xmax - xmin) / cell)), max(1, math.ceil((ymax - ymin) / cell))
    if nx * ny > 50_000_000:
        raise ConfigError(f"cell_size {cell:g} m makes {nx * ny:,} cells", fix="set cell_size larger (or 0)")
    gx = xmin + (np.arange(nx) + 0.5) * cell
    gy = ymin + (np.arange(ny) + 0.5) * cell
    X, Y = np.meshgrid(gx, gy)
    shapely.prepare(aoi)
    inside = shapely.contains_xy(aoi, X, Y)
    index = np.full(inside.shape, -1, dtype=np.int64)  # grid (row, col) -> cell number
    index[inside] = np.arange(int(inside.sum()))
    rows, cols = [], []
    for i, poly in enumerate(polygons):
        bx0, by0, bx1, by1 = poly.bounds
        c0, c1 = np.clip([math.floor((bx0 - xmin) / cell), math.ceil((bx1 - xmin) / cell)], 0, nx)
        r0, r1 = np.clip([math.floor((by0 - ymin) / cell), math.ceil((by1 - ymin) / cell)], 0, ny)
        if c1 <= c0 or r1 <= r0:
            continue
        sub = index[r0:r1, c0:c1]
        shapely.prepare(poly)
        hit = shapely.contains_xy(poly, X[r0:r1, c0:c1], Y[r0:r1, c0:c1]) & (sub >= 0)
        cells = sub[hit]
        rows.append(np.full(cells.size, i))
        cols.append(cells)
    m = int(inside.sum())
    r = np.concatenate(rows) if rows else np.zeros(0, int)
    c = np.concatenate(cols) if cols else np.zeros(0, int)
    A = sparse.csr_matrix((np.ones(r.size, dtype=bool), (r, c)), shape=(len(polygons), m))
    return CoverageGrid(x=X[inside], y=Y[inside], cell=cell, A=A, weights=np.full(m, cell * cell))
