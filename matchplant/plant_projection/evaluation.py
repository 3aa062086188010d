"""Projected plants against boxes drawn on the orthophoto: the paper's share matched and IoU, and a figure.

Reference boxes may come as a COCO JSON over the orthophoto (placed on the map through its transform),
a vector file or a CSV in the map CRS. Matching is one to one, best IoU first (:mod:`matchplant.core.geometry.boxes`).
"""

from __future__ import annotations

from pathlib import Path

import geopandas as gpd
import numpy as np
import rasterio
from matplotlib.collections import PolyCollection

from matchplant.core.formats.coco import read_dataset, source_name, to_source_pixels
from matchplant.core.geometry.boxes import match_boxes
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_path
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import read_csv
from matchplant.core.runtime.validate_gis import check_vector

log = get_logger("plant_projection")

# the figure's colours, named once: the figure draws with them and its caption (``evaluation_caption``, which the
# demo's report prints) is written from them, so the two cannot disagree again
REFERENCE_GOOD, REFERENCE_BAD, PROJECTED = "yellow", "red", "cyan"


def evaluation_caption(iou_threshold: float = 0.5) -> str:
    """What ``evaluation.png`` shows, in the colours it is drawn with."""
    return (
        f"left: projected plants (dashed {PROJECTED}) over the reference plant boxes ({REFERENCE_GOOD}: matched with "
        f"IoU > {iou_threshold:g}; {REFERENCE_BAD}: IoU <= {iou_threshold:g} or unmatched) on the orthophoto; "
        "right: the IoU of the matched boxes"
    )


def read_boxes(path: Path, *, orthophoto: Path | None = None, crs=None) -> np.ndarray:
    """Map boxes (N, 4) from a COCO JSON over the orthophoto, a vector file or a CSV (xmin,ymin,xmax,ymax)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return _coco_map_boxes(path, orthophoto)
    if suffix in (".csv", ".txt"):
        need = ("xmin", "ymin", "xmax", "ymax")
        table = read_csv(path, required=need, numeric=need, what="box CSV")
        boxes = np.column_stack([table.numbers[c] for c in need])
        flat = np.flatnonzero((boxes[:, 2] <= boxes[:, 0]) | (boxes[:, 3] <= boxes[:, 1]))
        if flat.size:
            raise InputError(
                f"box CSV, line {table.lines[flat[0]]}: xmax <= xmin or ymax <= ymin ({flat.size} of "
                f"{len(boxes)} boxes)",
                path=path,
                fix="give each box as xmin,ymin,xmax,ymax with xmin < xmax and ymin < ymax (map CRS)",
            )
        return boxes
    check_vector(path, what="box file", require_crs=crs is not None)
    try:
        gdf = gpd.read_file(path)
    except Exception as exc:  # noqa: BLE001 - GDAL's many formats; say which file failed
        raise InputError(
            f"cannot read the vector file: {exc}",
            path=path,
            fix="give a GeoPackage, shapefile or GeoJSON (or a CSV / COCO JSON)",
        ) from exc
    if crs is not None and gdf.crs is not None and not gdf.crs.equals(crs):
        log.info("boxes of %s are in %s: reprojected to %s", path.name, gdf.crs.name, getattr(crs, "name", crs))
        gdf = gdf.to_crs(crs)
    return np.asarray(gdf.geometry.bounds[["minx", "miny", "maxx", "maxy"]], dtype=float).reshape(-1, 4)


def _coco_map_boxes(path: Path, orthophoto: Path | None) -> np.ndarray:
    if orthophoto is None or not Path(orthophoto).is_file():
        raise InputError(
            "boxes drawn on the orthophoto need the orthophoto to be placed on the map",
            path=path,
            fix="set evaluate.orthophoto (or project) so odm_orthophoto.tif can be found",
        )
    ds = read_dataset(path, validate=False)
    images = {im["id"]: im for im in ds["images"]}
    with rasterio.open(orthophoto) as src:
        t = src.transform
    names = {Path(source_name(im)).name for im in images.values()}
    if names - {Path(orthophoto).name}:
        log.warning("reference boxes are on %s; placing them on %s", ", ".join(sorted(names)), Path(orthophoto).name)
    boxes = []
    for a in ds["annotations"]:
        x, y, w, h = to_source_pixels(a["bbox"], images[a["image_id"]])
        xs, ys = t @ (np.array([x, x + w]), np.array([y, y + h]))
        boxes.append([min(xs), min(ys), max(xs), max(ys)])
    return np.array(boxes, dtype=float).reshape(-1, 4)


def evaluate_boxes(reference: np.ndarray, predicted: np.ndarray, iou_threshold: float = 0.5) -> dict:
    """The paper's two numbers and more: share of reference boxes matched (any overlap), the IoU
    distribution of the matches, and the share with IoU above the threshold."""
    match, iou = match_boxes(reference, predicted)
    matched = match >= 0
    n_ref, n_pred = len(reference), len(predicted)
    m_iou = iou[matched]

    def q(p: float) -> float:
        return float(np.quantile(m_iou, p)) if m_iou.size else 0.0

    return {
        "reference_boxes": int(n_ref),
        "projected_boxes": int(n_pred),
        "matched": int(matched.sum()),
        "share_matched": float(matched.mean()) if n_ref else 0.0,
        f"share_iou_above_{iou_threshold:g}": float((iou > iou_threshold).mean()) if n_ref else 0.0,
        f"share_of_matched_iou_above_{iou_threshold:g}": float((m_iou > iou_threshold).mean()) if m_iou.size else 0.0,
        "iou_mean": float(m_iou.mean()) if m_iou.size else 0.0,
        "iou_median": q(0.5),
        "iou_p10": q(0.1),
        "iou_p90": q(0.9),
        "unmatched_projected": int(n_pred - matched.sum()),
        "iou_threshold": iou_threshold,
        "_match": match,
        "_iou": iou,
    }


def read_plants_boxes(path: Path) -> tuple[np.ndarray, object]:
    """Boxes and CRS of projected plants (our GeoPackage/shapefile/CSV)."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return read_boxes(path), None
    check_vector(path, what="plants file")
    gdf = gpd.read_file(path)
    if {"xmin", "ymin", "xmax", "ymax"} <= set(gdf.columns):
        return gdf[["xmin", "ymin", "xmax", "ymax"]].to_numpy(float), gdf.crs
    return np.asarray(gdf.geometry.bounds, dtype=float).reshape(-1, 4), gdf.crs


def evaluation_figure(
    path: Path,
    reference: np.ndarray,
    predicted: np.ndarray,
    metrics: dict,
    orthophoto: Path | None = None,
    max_pixels: int = 1600,
) -> Path:
    """Both box sets over the orthophoto (read at reduced resolution) and the IoU histogram."""
    fig = figure(headless=True, figsize=(14, 7))
    ax, axh = fig.subplots(1, 2, gridspec_kw={"width_ratios": [2.2, 1]})
    if orthophoto is not None and Path(orthophoto).is_file():
        _draw_orthophoto(ax, orthophoto, max_pixels)

    def rects(b):
        return np.stack([b[:, [0, 1]], b[:, [2, 1]], b[:, [2, 3]], b[:, [0, 3]]], axis=1)

    match, iou = metrics["_match"], metrics["_iou"]
    thr = metrics["iou_threshold"]
    good = iou > thr
    ax.add_collection(
        PolyCollection(
            rects(reference[good]),
            facecolors="none",
            edgecolors=REFERENCE_GOOD,
            linewidths=0.8,
            label=f"reference, IoU > {thr:g}",
        )
    )
    ax.add_collection(
        PolyCollection(
            rects(reference[~good]),
            facecolors="none",
            edgecolors=REFERENCE_BAD,
            linewidths=1.2,
            label=f"reference, IoU <= {thr:g} or unmatched",
        )
    )
    ax.add_collection(
        PolyCollection(
            rects(predicted),
            facecolors="none",
            edgecolors=PROJECTED,
            linewidths=0.6,
            linestyles="--",
            label="projected",
        )
    )
    allb = np.concatenate([reference, predicted]) if len(predicted) else reference
    if len(allb):
        pad = 0.02 * max(allb[:, 2].max() - allb[:, 0].min(), allb[:, 3].max() - allb[:, 1].min())
        ax.set_xlim(allb[:, 0].min() - pad, allb[:, 2].max() + pad)
        ax.set_ylim(allb[:, 1].min() - pad, allb[:, 3].max() + pad)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"projected plants ({PROJECTED}) and reference boxes")
    ax.ticklabel_format(useOffset=False, style="plain")
    matched_iou = iou[match >= 0]
    axh.hist(matched_iou, bins=np.linspace(0, 1, 21), color="tab:green", edgecolor="black")
    axh.axvline(thr, color="red", linestyle="--")
    axh.set_xlabel("IoU of matched boxes")
    axh.set_ylabel("reference boxes")
    axh.set_title(
        f"{metrics['share_matched']:.1%} matched, "
        f"{metrics[f'share_iou_above_{thr:g}']:.1%} with IoU > {thr:g}\nmedian IoU {metrics['iou_median']:.3f}"
    )
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fmt = Path(path).suffix.lstrip(".") or "png"
        # the caption travels in the PNG (its Description), for the demo's report to print as it is
        fig.savefig(
            tmp, dpi=120, format=fmt, metadata={"Description": evaluation_caption(thr)} if fmt == "png" else None
        )
    return Path(path)


def _draw_orthophoto(ax, path: Path, max_pixels: int) -> None:
    with rasterio.open(path) as src:
        f = max(1.0, max(src.width, src.height) / max_pixels)
        shape = (max(1, int(src.height / f)), max(1, int(src.width / f)))
        bands = min(src.count, 4)
        arr = src.read(list(range(1, bands + 1)), out_shape=(bands,) + shape)
        b = src.bounds
    img = np.moveaxis(arr, 0, -1)
    if img.dtype != np.uint8:
        hi = np.nanpercentile(img[..., :3], 99) or 1.0
        img = np.clip(img / hi * 255, 0, 255).astype(np.uint8)
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    ax.imshow(img, extent=(b.left, b.right, b.bottom, b.top), origin="upper", interpolation="nearest")
