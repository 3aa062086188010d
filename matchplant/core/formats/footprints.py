"""Image footprints on the ground: where an undistorted image's border rays meet the DSM.

A footprint follows the relief (slope, plants) and the camera's tilt, which the bounding box of an
orthorectified image hides, and it needs no orthorectification: only the image border is traced, through
:func:`~matchplant.core.geometry.ground.pixels_to_ground`. The reverse, a ground outline drawn in an image's pixels
(:func:`polygon_to_pixels`), is how a ground area chosen on the map is shown to the annotator. Kept in core
because any step that reasons about "which part of the field does this photo see" needs the same answer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from affine import Affine

from matchplant.core.formats.odm import ODMProject
from matchplant.core.geometry.frames import Frame
from matchplant.core.geometry.ground import ground_to_pixels, pixels_to_ground
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.surface import HIT, Surface
from matchplant.core.runtime.errors import GeometryError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress

if TYPE_CHECKING:  # GIS libraries only where footprints are made: module 7 imports this without them
    from shapely.geometry import Polygon

log = get_logger("footprints")


@dataclass
class Footprint:
    """An image's ground footprint, with the border samples that made it (to check it against the DSM)."""

    name: str  # shot id (original image name)
    file: Path  # undistorted image
    shot: Shot  # with the camera sized to the undistorted image
    polygon: Polygon  # ground footprint in the map CRS
    border: np.ndarray  # (N, 3) map points where the border rays meet the DSM (or the fallback plane)
    border_uv: np.ndarray  # (N, 2) the border pixels
    hit: np.ndarray  # (N,) True where the ray met the DSM
    frame: Frame | None = None  # the shot's frame (a split project's submodels have one each)

    @property
    def centroid(self) -> tuple[float, float]:
        """Centroid (x, y) of the footprint on the map."""
        c = self.polygon.centroid
        return float(c.x), float(c.y)


def border_pixels(width: int, height: int, per_side: int) -> np.ndarray:
    """Points along the image's outer edge (pixel-edge coordinates, corners exactly), counter-clockwise
    on the ground for a nadir camera; the first point is the top-left corner."""
    u0, v0, u1, v1 = -0.5, -0.5, width - 0.5, height - 0.5
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)
    top = np.stack([u0 + t * (u1 - u0), np.full_like(t, v0)], 1)
    right = np.stack([np.full_like(t, u1), v0 + t * (v1 - v0)], 1)
    bottom = np.stack([u1 - t * (u1 - u0), np.full_like(t, v1)], 1)
    left = np.stack([np.full_like(t, u0), v1 - t * (v1 - v0)], 1)
    return np.concatenate([top, right, bottom, left])


def image_footprint(
    shot: Shot, frame: Frame, surface: Surface, per_side: int = 16
) -> tuple[Polygon, np.ndarray, np.ndarray, np.ndarray]:
    """The ground polygon seen by ``shot``: its border rays intersected with the DSM.

    Rays that miss the DSM (they leave it, or meet a nodata hole) end on the horizontal plane at the median
    height of the rays that hit, so an image at the field's edge still gets a sensible outline.
    Returns ``(polygon, border points (N, 3), border pixels (N, 2), hit mask (N,))``.
    """
    import shapely  # lazy: GIS, only where footprints are made (module 7 runs without it)
    from shapely.geometry import Polygon

    uv = border_pixels(shot.camera.width, shot.camera.height, per_side)
    pts, status = pixels_to_ground(shot, uv, frame, surface)
    hit = status == HIT
    if not hit.all():
        z = float(np.median(pts[hit, 2])) if hit.any() else float(np.nanmedian(surface.data))
        origin = frame.to_map(shot.center[None, :])[0]
        dirs = shot.ray_directions(uv[~hit])
        reach = max(origin[2] - z, 1.0)
        far = frame.to_map(shot.center[None, :] + reach * dirs / np.maximum(-dirs[:, 2:3], 1e-6))
        d = far - origin
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (z - origin[2]) / d[:, 2]
        ok = np.isfinite(s) & (s > 0)
        pts[~hit] = np.where(ok[:, None], origin + s[:, None] * d, np.nan)
    good = np.isfinite(pts).all(axis=1)
    if good.sum() < 3:
        raise GeometryError(
            f"image '{shot.id}' does not look at the ground (its border rays miss the DSM)",
            fix="exclude it, or check that the DSM and the reconstruction are of the same field",
        )
    poly = shapely.make_valid(Polygon(pts[good, :2]))
    if not isinstance(poly, Polygon):  # a self-crossing outline (extreme tilt): keep its largest piece
        parts = [g for g in getattr(poly, "geoms", []) if isinstance(g, Polygon)]
        poly = max(parts, key=lambda g: g.area) if parts else Polygon(pts[good, :2]).convex_hull
    return poly, pts, uv, hit


def open_dsm(path: Path, resolution: float = 0.0) -> Surface:
    """The DSM as a :class:`Surface`, averaged down to ``resolution`` metres when that is coarser.

    Footprints only need the relief at the scale of an image border's sampling, so a coarser DSM makes
    them much faster on large flights at no visible cost.
    """
    import rasterio  # lazy: GIS, only where footprints are made (module 7 runs without it)
    from rasterio.enums import Resampling

    if not Path(path).is_file():
        raise InputError("DSM not found", path=path, fix="run ODM with --dsm (module 2 does)")
    with rasterio.open(path) as src:
        factor = resolution / abs(src.transform.a) if resolution > 0 else 1.0
        if factor <= 1.5:
            return Surface.open(path)
        h, w = max(2, math.ceil(src.height / factor)), max(2, math.ceil(src.width / factor))
        arr = src.read(1, out_shape=(h, w), masked=True, resampling=Resampling.average)
        transform = src.transform @ Affine.scale(src.width / w, src.height / h)
        crs = src.crs
    data = arr.astype(float).filled(np.nan)
    data[data <= -9999] = np.nan
    return Surface(data=data, transform=transform, crs=crs, path=Path(path))


def compute_footprints(
    project: ODMProject, frame: Frame | None, surface: Surface, per_side: int = 16, names: Sequence[str] | None = None
) -> list[Footprint]:
    """Footprints of every undistorted image in the reconstruction (sorted by name), over every submodel of a
    split project (each image once, each shot in its own frame; ``frame``, if given, only sets the map CRS).

    An image whose border misses the DSM is skipped with a warning rather than failing the flight.
    """
    originals = not project.shot_ids(undistorted=True) and bool(project.shot_ids(undistorted=False))
    originals = originals and hasattr(project, "image_paths")  # Metashape, Pix4D: they pose the original photos
    ids = project.shot_ids(undistorted=not originals)
    if not ids:
        project.require("undistorted_reconstruction")
    files = project.image_paths() if originals else project.undistorted_images()
    todo = sorted(n for n in (names or ids) if n in files and n in ids)
    if not todo:
        raise InputError(
            "no undistorted image matches the undistorted reconstruction",
            path=project.path("undistorted_images"),
            fix="re-run ODM without --optimize-disk-space (module 2)",
        )
    out = []
    for name in progress(todo, desc="footprints", unit="image"):
        shot = project.shot(name, undistorted=not originals)
        shot_frame = project.frame_of(name)
        try:
            poly, pts, uv, hit = image_footprint(shot, shot_frame, surface, per_side)
        except GeometryError as exc:
            log.warning("skipping %s: %s", name, exc.problem)
            continue
        out.append(
            Footprint(
                name=name,
                file=files[name],
                shot=shot,
                polygon=poly,
                border=pts,
                border_uv=uv,
                hit=hit,
                frame=shot_frame,
            )
        )
    if not out:
        raise InputError(
            "no image footprint could be placed on the DSM",
            path=project.path("dsm"),
            fix="check that the DSM and the reconstruction are of the same field",
        )
    return out


def polygon_to_pixels(poly: Polygon, shot: Shot, frame: Frame, surface: Surface, step: float) -> np.ndarray:
    """A ground polygon's outline in an image's pixels: densified, lifted onto the DSM, projected, clipped.

    Densified every ``step`` metres because a straight edge on the ground is curved in the image wherever
    the relief under it changes.
    """
    import shapely  # lazy: GIS, only where footprints are made (module 7 runs without it)

    if poly.is_empty:
        return np.zeros((0, 2))
    ring = shapely.segmentize(poly.exterior, max(step, 1e-3))
    xy = np.asarray(ring.coords)[:-1, :2]
    z = surface.sample(xy[:, 0], xy[:, 1])
    if np.isnan(z).any():
        z = np.where(np.isnan(z), np.nanmedian(z) if np.isfinite(z).any() else np.nanmedian(surface.data), z)
    uv = ground_to_pixels(shot, np.column_stack([xy, z]), frame)
    w, h = shot.camera.width, shot.camera.height
    uv[:, 0] = np.clip(uv[:, 0], -0.5, w - 0.5)
    uv[:, 1] = np.clip(uv[:, 1], -0.5, h - 0.5)
    return uv[np.isfinite(uv).all(axis=1)]
