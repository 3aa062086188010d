"""The DSM around the rays: read once when it fits in memory, else one window per image.

A large field's DSM (a 1 cm grid over hectares) does not fit in memory; each image's rays only need
the part under its boxes, bounded by where its corner rays cross the lowest and highest heights.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio

from matchplant.core.geometry.frames import Frame, parse_crs
from matchplant.core.geometry.raycast import ODM_NODATA
from matchplant.core.geometry.shot import Shot
from matchplant.core.geometry.surface import Surface
from matchplant.core.geometry.units import height_unit, metric_heights
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.plant_projection.dsm_noise import Holes, SoilSurface, ground_noise, soil_surface
from matchplant.plant_projection.geometry import box_outline

log = get_logger("plant_projection")

MAX_SURFACE_CELLS = 64_000_000  # 256 MB of float32 (a 1 cm DSM of 0.64 ha): above this, read per image
DECIMATED = 512  # cells along the longer side of the decimated read that bounds the heights of a large DSM
PAD = 1.0  # metres, plus PAD_SHARE of the height range: the margin of the rays' height bounds
PAD_SHARE = 0.2
RAY_PROBE = 100.0  # ray parameter of the second point that turns a reconstruction-frame ray into a map ray
UPWARD = -1e-6  # a map ray whose downward component is not below this never comes down to the DSM
EDGE_CELLS = 4  # DSM cells read beyond the rays' bounds (bilinear neighbours, the ground's blocks)


def _padded(lo: float, hi: float) -> tuple[float, float]:
    """A height range widened by the margin the rays' bounds need."""
    pad = PAD + PAD_SHARE * (hi - lo)
    return lo - pad, hi + pad


def approx_heights(path: Path) -> tuple[float, float]:
    """DSM height range (metres) from a decimated read (for the window of the rays)."""
    with rasterio.open(path) as src:
        f = max(1, int(max(src.width, src.height) // DECIMATED))
        arr = src.read(1, out_shape=(max(1, src.height // f), max(1, src.width // f)), masked=True)
        factor, _ = height_unit(src.crs, src.units[0], path)
    data = arr.astype(float).filled(np.nan)
    data[data <= ODM_NODATA] = np.nan
    data *= factor  # metres, as the surfaces read (Surface.open)
    if not np.isfinite(data).any():
        raise InputError("the DSM holds no valid heights", path=path, fix="check the DSM (re-run ODM with --dsm)")
    return float(np.nanmin(data)), float(np.nanmax(data))


def ray_bounds(shot: Shot, frame: Frame, boxes: np.ndarray, z_lo: float, z_hi: float) -> np.ndarray | None:
    """Map bounds where the boxes' corner rays cross the heights z_lo and z_hi (None if a ray looks up)."""
    uv = box_outline(boxes, 0).reshape(-1, 2)
    d = shot.ray_directions(uv)
    c = shot.center
    c_map = frame.to_map(c[None, :])[0]
    far = frame.to_map(c[None, :] + RAY_PROBE * d)
    dm = (far - c_map) / RAY_PROBE
    if (dm[:, 2] > UPWARD).any():
        return None
    x, y = np.ascontiguousarray(dm[:, 0]), np.ascontiguousarray(dm[:, 1])  # 1-D reductions: fast
    out = np.array([np.inf, np.inf, -np.inf, -np.inf])
    for z in (z_lo, z_hi):
        s = (z - c_map[2]) / dm[:, 2]
        px, py = c_map[0] + s * x, c_map[1] + s * y
        out = np.r_[np.minimum(out[:2], [px.min(), py.min()]), np.maximum(out[2:], [px.max(), py.max()])]
    return out


class DsmSurfaces:
    """The DSM read once over every image's rays when that fits in memory, else per image; small holes filled
    and the ground lifted to the soil (:mod:`~matchplant.plant_projection.dsm_noise`)."""

    def __init__(self, path: Path, crs, ground_window: float, fill_holes: float = 0.0):
        self.path, self.crs, self.ground_window, self.fill_holes = path, crs, ground_window, fill_holes
        self._whole: SoilSurface | None = None
        self._read: list[tuple[SoilSurface, int]] = []  # every surface read, with its cells filled
        with rasterio.open(path) as src:
            small = src.width * src.height <= MAX_SURFACE_CELLS
            self.unit = height_unit(src.crs, src.units[0], path)[1]  # "": the file names none (metres assumed)
        if small:  # the whole DSM fits: read it once, its heights bound the rays
            self._whole = self._surface()
            self.z_min, z_max = self._whole.zmin, self._whole.zmax
        else:
            self.z_min, z_max = approx_heights(path)
        self.z_lo, self.z_hi = _padded(self.z_min, z_max)

    def check_below(self, cameras: np.ndarray) -> None:
        """A DSM whose lowest height lies above every camera (map heights ``cameras``) is refused: no ray meets it.
        With no unit in the file, that is a DSM in feet read as metres (heights 3.28 times too high)."""
        if not self.z_min > np.max(cameras):
            return
        feet = "" if self.unit else " (the file names no height unit: heights in feet, read as metres?)"
        raise InputError(
            f"the DSM's lowest height ({self.z_min:.1f} m) lies above every camera (highest {np.max(cameras):.1f} m), "
            f"so no ray can meet it{feet}",
            path=self.path,
            fix="give heights in metres: set the DSM's unit (gdal_edit.py -units ft, or a CRS with its vertical unit) "
            'and it is converted, or convert it (gdal_calc.py --calc="A*0.3048"); else give this field\'s DSM',
        )

    def prepare(self, all_bounds: list[np.ndarray | None]) -> None:
        """Once every image's ray bounds are known: refuse a DSM in another CRS, and read the union of
        the bounds at once when it fits (one read instead of one per image)."""
        with rasterio.open(self.path) as src:
            res = min(abs(src.transform.a), abs(src.transform.e))
            dsm_crs = src.crs
        if dsm_crs is not None and self.crs is not None and not metric_heights(parse_crs(dsm_crs)).equals(self.crs):
            raise InputError(
                f"the DSM is in {dsm_crs} but the reconstruction in {self.crs.name}",
                path=self.path,
                fix="use the DSM of this ODM project (or reproject it to the project's CRS)",
            )
        if self._whole is not None:
            return
        if any(b is None for b in all_bounds):
            self._whole = self._surface()
            return
        b = np.array(all_bounds)
        union = (b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max())
        cells = (union[2] - union[0]) * (union[3] - union[1]) / res**2
        if cells <= MAX_SURFACE_CELLS:
            self._whole = self._open(union, res)

    def _surface(self, bounds: tuple | None = None) -> SoilSurface:
        surface, filled = soil_surface(Surface.open(self.path, bounds=bounds), self.fill_holes)
        self._read.append((surface, filled))
        return surface

    def _open(self, bounds, res) -> SoilSurface:
        pad = EDGE_CELLS * res + self.ground_window  # the ground estimate needs terrain around the rays
        return self._surface((bounds[0] - pad, bounds[1] - pad, bounds[2] + pad, bounds[3] + pad))

    def report(self) -> float:
        """Say in the log what was filled and measured on the surfaces read; returns the largest soil spread."""
        if not self._read:
            return 0.0
        noise = [ground_noise(s, self.ground_window) for s, _ in self._read]
        filled = sum(f for _, f in self._read)
        lift, spread = max(n.lift for n in noise), max(n.spread for n in noise)
        if filled:
            log.info(
                "%s: %d DSM cells in holes up to fill_holes=%g m filled from their rims",
                self.path,
                filled,
                self.fill_holes,
            )
        if lift:
            log.info(
                "%s: bare soil lies %.1f cm above the DSM's lowest envelope (noise, spread %.1f cm): the ground "
                "estimate is lifted to it%s",
                self.path,
                100 * lift,
                100 * spread,
                "" if len(noise) == 1 else f" (largest of {len(noise)} windows)",
            )
        return spread

    def holes(self) -> Holes:
        """The holes left unfilled on the surfaces read (the most in one read, the largest)."""
        kept = [s.holes for s, _ in self._read]
        return Holes(max((h.count for h in kept), default=0), max((h.largest for h in kept), default=0.0))

    def get(self, bounds: np.ndarray) -> SoilSurface:
        """The surface under one image's rays (``bounds`` from :func:`ray_bounds`)."""
        if self._whole is not None:
            return self._whole
        with rasterio.open(self.path) as src:
            res = min(abs(src.transform.a), abs(src.transform.e))
        return self._open(bounds, res)
