"""A DSM (or any elevation raster) in memory: bilinear sampling with holes masked, and ray intersection.

Only the window that is needed is read from the file. Nodata (ODM writes -9999) and NaN are holes:
bilinear interpolation renormalises over the valid neighbours, so hole edges stay usable, and a ray that
meets the surface inside a hole is reported, not placed on an invented height.

The compiled per-ray work (sampling, the walk to a ray's first crossing) is in
:mod:`matchplant.core.geometry.raycast`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from affine import Affine

from matchplant.core.geometry.raycast import (
    HIT,
    NO_HIT,
    NODATA,
    NOT_DOWNWARD,
    OUTSIDE,
    Hits,
    Raster,
    Rays,
    block_stats,
    holes_to_nan,
    intersect_gentle,
    intersect_many,
    max_tangent,
    patch_block_max,
    ray_points,
    sample_many,
)
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("surface")

STATUS_TEXT = {
    HIT: "ok",
    NOT_DOWNWARD: "ray does not point towards the ground",
    OUTSIDE: "ray leaves the DSM before reaching the ground",
    NODATA: "ray meets the ground in a DSM nodata area",
    NO_HIT: "no intersection with the DSM (camera below the surface?)",
}
_BLOCK = 4  # patches per side of the blocks whose highest points let rays skip empty space
GROUND_CELL = 0.02  # metres: cell size (at least the DSM's) of the ground estimated from the DSM
ROTATION = 1e-12  # affine rotation terms above this: a rotated raster
WINDOW_RAISED = 1.5  # the ground's window, raised above ground_window by more than this factor, is said in the log
GENTLE = 0.8  # max_slope x the rays' steepest tangent below this: each ray crosses the surface once (fixed point)
MAX_STEPS = 200_000  # patches a ray walks at most


@dataclass
class Surface:
    """An elevation raster in memory (NaN for holes) with its north-up transform and CRS."""

    data: np.ndarray  # float32 (as ODM writes it), NaN for holes
    transform: object  # affine.Affine, north-up
    crs: object = None
    path: Path | None = None

    def __post_init__(self):
        t = self.transform
        if abs(t.b) > ROTATION or abs(t.d) > ROTATION:
            raise InputError(
                "rotated rasters are not supported", path=self.path, fix="warp the raster to a north-up grid (gdalwarp)"
            )
        self.data = np.ascontiguousarray(self.data, dtype=np.float32)  # as ODM writes it: half the memory traffic
        i = ~t
        self._inv = np.array([i.a, i.b, i.c, i.d, i.e, i.f], dtype=np.float64)
        self.zmin, self.zmax = float(np.nanmin(self.data, initial=np.inf)), float(np.nanmax(self.data, initial=-np.inf))
        if not self.zmax >= self.zmin:
            raise InputError(
                "the elevation raster holds no valid data in the area of interest",
                path=self.path,
                fix="check that the DSM covers the images (same CRS, same field)",
            )
        self.raster = Raster(self.data, self._inv, patch_block_max(self.data, _BLOCK), _BLOCK, self.zmin, self.zmax)
        self._grounds: dict[float, Surface] = {}
        self._canopy: dict[float, float] = {}
        self._max_slope: float | None = None

    def ground(self, window: float) -> Surface:
        """The bare ground under the plants, estimated from this surface: a morphological opening (the
        highest flat square of side ``window`` metres that fits under the surface, at each point) removes
        every bump narrower than the window and keeps the soil between them exactly, slopes included.
        Computed on a grid of about :data:`GROUND_CELL` (lowest cell of each block); blocks holding a DSM
        hole are holes. Cached per window."""
        if window not in self._grounds:
            block = max(1, int(round(GROUND_CELL / self.pixel_size)))
            low, high, hole = block_stats(self.data, block)
            size = max(3, int(math.ceil(window / (block * self.pixel_size))) | 1)
            used = size * block * self.pixel_size
            if used > window * WINDOW_RAISED:
                log.info(
                    "ground estimate: window raised from ground_window=%.3g m to %.3g m (%d cells of %.3g m, "
                    "the least the opening needs)",
                    window,
                    used,
                    size,
                    block * self.pixel_size,
                )
            # OpenCV's separable min / max filters: the same values as scipy.ndimage's, in a third of the time
            square = cv2.getStructuringElement(cv2.MORPH_RECT, (size, size))
            eroded = cv2.erode(low, square, borderType=cv2.BORDER_REPLICATE)
            opened = cv2.dilate(
                np.where(np.isinf(eroded), -np.inf, eroded).astype(np.float32, copy=False),
                square,
                borderType=cv2.BORDER_REPLICATE,
            )
            opened[~np.isfinite(opened) | hole] = np.nan  # DSM holes stay holes: rays meeting them are reported
            with np.errstate(invalid="ignore"):
                self._canopy[window] = float(np.nanmax(high - opened, initial=0.0))
            self._grounds[window] = Surface(opened, self.transform @ Affine.scale(block), self.crs, self.path)
        return self._grounds[window]

    def canopy_height(self, window: float) -> float:
        """The greatest height of this surface above its :meth:`ground` (the tallest plant), metres."""
        self.ground(window)
        return self._canopy[window]

    @classmethod
    def open(cls, path: str | Path, bounds: tuple[float, float, float, float] | None = None, band: int = 1) -> Surface:
        """Read ``path`` (only the window covering ``bounds = (xmin, ymin, xmax, ymax)``, if given)."""
        import rasterio  # lazy: GIS, only where a DSM is read (module 7 imports this module without it)
        from rasterio.enums import MaskFlags
        from rasterio.windows import Window, from_bounds

        path = Path(path)
        if not path.is_file():
            raise InputError(
                "elevation raster not found",
                path=path,
                fix="run ODM with --dsm, or point the config at the DSM GeoTIFF",
            )
        try:
            with rasterio.open(path) as src:
                if bounds is not None:
                    win = from_bounds(*bounds, transform=src.transform)
                    # whole pixels, one extra on each side so bilinear sampling at the edge has neighbours
                    col0, row0 = int(np.floor(win.col_off)) - 1, int(np.floor(win.row_off)) - 1
                    col1 = int(np.ceil(win.col_off + win.width)) + 1
                    row1 = int(np.ceil(win.row_off + win.height)) + 1
                    win = Window(col0, row0, col1 - col0, row1 - row0).intersection(Window(0, 0, src.width, src.height))
                    transform = src.window_transform(win)
                else:
                    win, transform = None, src.transform
                data = src.read(band, window=win).astype(np.float32, copy=False)
                flags = src.mask_flag_enums[band - 1]
                if MaskFlags.per_dataset in flags or MaskFlags.alpha in flags:  # a mask band: read it
                    data[src.read_masks(band, window=win) == 0] = np.nan
                # the nodata value alone marks holes: no mask to read (GDAL would build one, at 3x the cost)
                nodata = src.nodata if MaskFlags.nodata in flags and src.nodata is not None else math.nan
                crs = src.crs
        except rasterio.errors.WindowError as exc:
            raise InputError(
                "the area of interest does not overlap the raster",
                path=path,
                fix="check that the raster and the reconstruction are of the same field and CRS",
            ) from exc
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(f"cannot read the raster: {exc}", path=path, fix="check that it is a GeoTIFF") from exc
        holes_to_nan(data, np.float32(nodata))  # and ODM's -9999 even when the file does not declare it
        return cls(data=data, transform=transform, crs=crs, path=path)

    @property
    def max_slope(self) -> float:
        """A bound on the slope (rise over run) of the bilinear surface anywhere: the hypotenuse of the steepest
        steps between neighbouring cells along x and along y. Computed once."""
        if self._max_slope is None:
            with np.errstate(invalid="ignore"):
                gx = np.nanmax(np.abs(np.diff(self.data, axis=1)), initial=0.0) / abs(self.transform.a)
                gy = np.nanmax(np.abs(np.diff(self.data, axis=0)), initial=0.0) / abs(self.transform.e)
            self._max_slope = float(math.hypot(gx, gy))
        return self._max_slope

    @property
    def pixel_size(self) -> float:
        """Pixel size in map units (the smaller of the two axes)."""
        return float(min(abs(self.transform.a), abs(self.transform.e)))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """Map extent ``(xmin, ymin, xmax, ymax)`` of the raster."""
        t = self.transform
        h, w = self.data.shape
        xs = (t.c, t.c + w * t.a)
        ys = (t.f, t.f + h * t.e)
        return min(xs), min(ys), max(xs), max(ys)

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height at map points; NaN outside the raster or where every neighbour is a hole."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        out = np.empty(x.shape, dtype=np.float64)
        sample_many(
            self.data, self._inv, np.ascontiguousarray(x).ravel(), np.ascontiguousarray(y).ravel(), out.reshape(-1)
        )
        return out

    def inside(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True for map points inside the raster's extent."""
        i = self._inv
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        col, row = i[0] * x + i[1] * y + i[2], i[3] * x + i[4] * y + i[5]
        rows, cols = self.data.shape
        return (col >= 0) & (col <= cols) & (row >= 0) & (row <= rows)

    def intersect(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        *,
        clearance: float = 0.0,
        settle: float = 0.0,
        max_steps: int = MAX_STEPS,
        heights: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First intersection of straight rays (in the raster's CRS) with the surface.

        Each ray is walked cell by cell between the heights of the highest and lowest valid cell (so slopes
        and plant edges are found, not a flat plane), and its first crossing is solved exactly on the
        bilinear surface, however thin (a leaf tip; :mod:`matchplant.core.geometry.raycast`). Over a gentle surface
        (``max_slope`` x the rays' tangent < :data:`GENTLE`: each ray crosses it once) a fixed-point iteration replaces
        the walk. ``clearance`` > 0 stops a ray where it first comes that close above the surface: a ray that
        grazes a plant's top (the edge of its silhouette) then stays on the plant instead of continuing to
        the ground behind it; ``settle`` > 0 then moves it on to the surface if the ray meets it within that
        many metres further down (an exact hit, not a grazing one). ``heights`` = (top, bottom) (N,) narrows
        the height range searched per ray when it is known (NaN: the whole range). Returns ``points (N, 3)``,
        ``s (N,)`` (the ray parameter) and ``status (N,)`` (:data:`STATUS_TEXT`); points without a hit are NaN.
        """
        o = np.ascontiguousarray(np.asarray(origins, dtype=np.float64).reshape(-1, 3))  # one, or one per ray
        d = np.ascontiguousarray(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
        d_all = d
        s = np.empty(d.shape[0], dtype=np.float64)
        status = np.empty(d.shape[0], dtype=np.int8)
        z_top, z_bottom = (
            (None, None) if heights is None else (np.asarray(h, dtype=np.float64).reshape(-1) for h in heights)
        )
        todo = slice(None)
        if clearance == 0.0 and d.shape[0] and self.max_slope * max_tangent(d) < GENTLE:
            done = np.empty(d.shape[0], dtype=np.bool_)
            intersect_gentle(self.raster, self.max_slope, o, d, s, done)
            status[done] = HIT
            todo = np.flatnonzero(~done)
            o = o if len(o) == 1 else np.ascontiguousarray(o[todo])
            d = np.ascontiguousarray(d[todo])
            z_top, z_bottom = (None, None) if heights is None else (z_top[todo], z_bottom[todo])
        if heights is None:  # the whole height range
            z_top, z_bottom = np.full(d.shape[0], np.nan), np.full(d.shape[0], np.nan)
        s_m = np.empty(d.shape[0], dtype=np.float64)
        st_m = np.empty(d.shape[0], dtype=np.int8)
        intersect_many(
            self.raster,
            Rays(o, d, np.ascontiguousarray(z_top), np.ascontiguousarray(z_bottom)),
            float(clearance),
            float(settle),
            int(max_steps),
            Hits(s_m, st_m),
        )
        s[todo], status[todo] = s_m, st_m
        points = np.empty(d_all.shape)
        ray_points(np.ascontiguousarray(np.asarray(origins, dtype=np.float64).reshape(-1, 3)), d_all, s, points)
        return points, s, status
