"""Cutting one photo: decoded once, every crop it owes cut from it, written as one folder.

A photo's crops and its rows of the index are written into a hidden folder that is renamed into place when
complete, so a photo is done exactly when its folder exists: an interrupted run resumes at the next photo.
"""

from __future__ import annotations

import csv
import io
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from matchplant.core.geometry.ground import ground_to_pixels
from matchplant.core.runtime.errors import InputError
from matchplant.views.cameras import CameraView
from matchplant.views.outlines import Outlines

SUPERSAMPLE = 4  # the outline is traced on a mask this many times finer than the crop's pixels
COLUMNS = (
    "plant_id",
    "photo",
    "crop",
    "rank",
    "x0",
    "y0",
    "width",
    "height",
    "off_nadir_deg",
    "distance_m",
    "gsd_cm",
    "outline_px",
)
ROWS_FILE = "views.csv"
PARTIAL = ".partial-"


def crop_box(box: np.ndarray, width: int, height: int, margin: float, margin_px: int) -> np.ndarray:
    """Integer crop windows (x0, y0, x1, y1; x1, y1 exclusive) around pixel boxes (n, 4), with a margin of
    ``margin`` times the box's larger side (at least ``margin_px``), clipped to the photo."""
    side = np.maximum(box[:, 2] - box[:, 0], box[:, 3] - box[:, 1])
    m = np.maximum(margin * side, margin_px)[:, None]
    lo = np.floor(box[:, :2] + 0.5 - m)
    hi = np.ceil(box[:, 2:] + 0.5 + m)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [width, height])
    return np.concatenate([lo, hi], axis=1).astype(int)


def silhouette(rings: list[np.ndarray], size: tuple[int, int]) -> np.ndarray:
    """The outline (K, 2) of the union of prisms ``rings`` (each (n, 2, 2): every point's top and bottom, pixel
    coordinates, centres at integers) within an image of ``size`` (width, height); its largest part when it
    falls apart. Every edge is drawn as a line (filling overlapping polygons at once would cancel their
    overlaps) and what the lines enclose is filled, on a mask finer than the pixels."""
    s, shift = SUPERSAMPLE, 4
    mask = np.zeros((size[1] * s, size[0] * s), np.uint8)
    lines = []
    for ring in rings:
        pts = np.round(((ring + 0.5) * s - 0.5) * (1 << shift)).astype(np.int32)
        lines += [np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]), *pts]
    cv2.polylines(mask, lines, True, 1, shift=shift)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(mask, contours, -1, 1, cv2.FILLED)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return np.zeros((0, 2))
    c = cv2.approxPolyDP(max(contours, key=cv2.contourArea), s / 8, True)[:, 0, :].astype(float)  # 1/8 px
    return (c + 0.5) / s - 0.5


def outline_wkt(xy: np.ndarray) -> str:
    """A polygon's WKT to a tenth of a pixel (an empty polygon for fewer than three points)."""
    if len(xy) < 3:
        return "POLYGON EMPTY"
    ring = np.round(np.vstack([xy, xy[:1]]), 1)
    return "POLYGON ((" + ", ".join(f"{x:g} {y:g}" for x, y in ring.tolist()) + "))"


def decode(cam: CameraView) -> np.ndarray:
    """The photo's pixels as stored (BGR, no EXIF rotation: the camera model is of the sensor's grid)."""
    img = cv2.imread(str(cam.photo), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise InputError("cannot decode the photo", path=cam.photo, fix="replace the file with a complete copy")
    if img.shape[1] != cam.shot.camera.width or img.shape[0] != cam.shot.camera.height:
        raise InputError(
            f"the photo is {img.shape[1]}x{img.shape[0]} px, its camera {cam.shot.camera.width}x"
            f"{cam.shot.camera.height}",
            path=cam.photo,
            fix="use the original photos the reconstruction was made from",
        )
    return img


def cut_photo(
    cam: CameraView,
    img: np.ndarray,
    plants: np.ndarray,
    boxes: np.ndarray,
    rows: list[dict],
    outlines: Outlines,
    names: list[str],
    folder: Path,
    quality: int,
) -> Path:
    """Write the crops of ``plants`` from ``cam``'s decoded photo ``img`` (windows ``boxes``: x0, y0, x1, y1),
    named ``names`` (``<name>.jpg``), with ``rows`` (the index's view columns) completed and written as
    ``views.csv``, into ``folder``, which appears whole."""
    partial = folder.with_name(PARTIAL + folder.name)
    shutil.rmtree(partial, ignore_errors=True)
    pts, offsets = outlines.plant_points(plants)
    uv = ground_to_pixels(cam.shot, pts, cam.frame)
    encode = [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    # plain writes: the folder's rename below is what makes the photo's crops appear, all at once
    partial.mkdir(parents=True)
    for j, p in enumerate(plants):
        x0, y0, x1, y1 = (int(v) for v in boxes[j])
        ok, jpg = cv2.imencode(".jpg", img[y0:y1, x0:x1], encode)
        (partial / f"{names[j]}.jpg").write_bytes(jpg.tobytes())
        ring_uv = (uv[2 * offsets[j] : 2 * offsets[j + 1]] - [x0, y0]).reshape(-1, 2, 2)
        rings = np.split(ring_uv, outlines.ring_cuts(p))
        row = dict(rows[j], x0=x0, y0=y0, width=x1 - x0, height=y1 - y0)
        row["outline_px"] = outline_wkt(silhouette(rings, (x1 - x0, y1 - y0)))
        writer.writerow(row)
    (partial / ROWS_FILE).write_text(table.getvalue(), encoding="utf-8")
    os.replace(partial, folder)
    return folder
