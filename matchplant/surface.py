"""A DSM (or any elevation raster) in memory: bilinear sampling with holes masked, and ray intersection.

Only the window that is needed is read from the file. Nodata (ODM writes -9999) and NaN are holes:
bilinear interpolation renormalises over the valid neighbours, so hole edges stay usable, and a ray that
meets the surface inside a hole is reported, not placed on an invented height.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

HIT, NOT_DOWNWARD, OUTSIDE, NODATA, NO_HIT = 0, 1, 2, 3, 4
STATUS_TEXT = {
    HIT: "ok",
    NOT_DOWNWARD: "ray does not point towards the ground",
    OUTSIDE: "ray leaves the DSM before reaching the ground",
    NODATA: "ray meets the ground in a DSM nodata area",
    NO_HIT: "no intersection with the DSM (camera below the surface?)",
}


@dataclass
class Surface:
    data: np.ndarray  # float64, NaN for holes
    transform: "object"  # affine.Affine, north-up
    crs: "object" = None
    path: Path | None = None

    def __post_init__(self):
        t = self.transform
        if abs(t.b) > 1e-12 or abs(t.d) > 1e-12:
            raise InputError("rotated rasters are not supported", path=self.path,
                             fix="warp the raster to a north-up grid (gdalwarp)")
        self.data = np.asarray(self.data, dtype=float)
        self._inv = ~t
        finite = self.data[np.isfinite(self.data)]
        if finite.size == 0:
            raise InputError("the elevation raster holds no valid data in the area of interest", path=self.path,
                             fix="check that the DSM covers the images (same CRS, same field)")
        self.zmin, self.zmax = float(finite.min()), float(finite.max())

    @classmethod
    def open(cls, path: str | Path, bounds: tuple[float, float, float, float] | None = None,
             band: int = 1) -> "Surface":
        """Read ``path`` (only the window covering ``bounds = (xmin, ymin, xmax, ymax)``, if given)."""
        import rasterio
        from rasterio.windows import from_bounds

        path = Path(path)
        if not path.is_file():
            raise InputError("elevation raster not found", path=path,
                             fix="run ODM with --dsm, or point the config at the DSM GeoTIFF")
        try:
            with rasterio.open(path) as src:
                if bounds is not None:
                    win = from_bounds(*bounds, transform=src.transform)
                    # whole pixels, one extra on each side so bilinear sampling at the edge has neighbours
                    col0, row0 = int(np.floor(win.col_off)) - 1, int(np.floor(win.row_off)) - 1
                    col1 = int(np.ceil(win.col_off + win.width)) + 1
                    row1 = int(np.ceil(win.row_off + win.height)) + 1
                    win = rasterio.windows.Window(col0, row0, col1 - col0, row1 - row0).intersection(
                        rasterio.windows.Window(0, 0, src.width, src.height))
                    transform = src.window_transform(win)
                    arr = src.read(band, window=win, masked=True)
                else:
                    transform = src.transform
                    arr = src.read(band, masked=True)
                crs = src.crs
        except rasterio.errors.WindowError as exc:
            raise InputError("the area of interest does not overlap the raster", path=path,
                             fix="check that the raster and the reconstruction are of the same field and CRS") from exc
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(f"cannot read the raster: {exc}", path=path, fix="check that it is a GeoTIFF") from exc
        data = arr.astype(float).filled(np.nan)
        data[data <= -9999] = np.nan  # ODM's nodata even when the file does not declare it
        return cls(data=data, transform=transform, crs=crs, path=path)

    @property
    def pixel_size(self) -> float:
        return float(min(abs(self.transform.a), abs(self.transform.e)))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        t = self.transform
        h, w = self.data.shape
        xs = (t.c, t.c + w * t.a)
        ys = (t.f, t.f + h * t.e)
        return min(xs), min(ys), max(xs), max(ys)

    def _pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map coordinates to fractional (column, row), pixel corners at integers."""
        i = self._inv
        return i.a * x + i.b * y + i.c, i.d * x + i.e * y + i.f

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear height at map points; NaN outside the raster or where every neighbour is a hole."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        col, row = self._pixel(x, y)
        rows, cols = self.data.shape
        outside = (col < 0) | (col > cols) | (row < 0) | (row > rows) | ~np.isfinite(col) | ~np.isfinite(row)
        cf = np.where(outside, 0.0, col - 0.5)
        rf = np.where(outside, 0.0, row - 0.5)
        c0 = np.clip(np.floor(cf), 0, max(cols - 2, 0)).astype(np.intp)
        r0 = np.clip(np.floor(rf), 0, max(rows - 2, 0)).astype(np.intp)
        c1 = np.minimum(c0 + 1, cols - 1)
        r1 = np.minimum(r0 + 1, rows - 1)
        fc = np.clip(cf - c0, 0.0, 1.0)
        fr = np.clip(rf - r0, 0.0, 1.0)
        total = np.zeros_like(fc)
        weight = np.zeros_like(fc)
        for rr, cc, w in ((r0, c0, (1 - fr) * (1 - fc)), (r0, c1, (1 - fr) * fc),
                          (r1, c0, fr * (1 - fc)), (r1, c1, fr * fc)):
            v = self.data[rr, cc]
            ok = np.isfinite(v)
            total += np.where(ok, v, 0.0) * w
            weight += np.where(ok, w, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(weight > 1e-9, total / weight, np.nan)
        z[outside] = np.nan
        return z

    def inside(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        col, row = self._pixel(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        rows, cols = self.data.shape
        return (col >= 0) & (col <= cols) & (row >= 0) & (row <= rows)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, *, max_samples: int = 4_000_000,
                  max_steps: int = 20_000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First intersection of straight rays (in the raster's CRS) with the surface.

        Marches each ray in half-pixel horizontal steps between the heights of the highest and lowest
        valid cell (so slopes and plant edges are found, not a flat plane), then bisects the bracket.
        Returns ``points (N, 3)``, ``s (N,)`` (the ray parameter) and ``status (N,)``
        (:data:`STATUS_TEXT`); points without a hit are NaN.
        """
        o = np.asarray(origins, dtype=float).reshape(-1, 3)
        d = np.asarray(directions, dtype=float).reshape(-1, 3)
        if o.shape[0] == 1 and d.shape[0] > 1:
            o = np.repeat(o, d.shape[0], axis=0)
        n = d.shape[0]
        s_out = np.full(n, np.nan)
        status = np.full(n, NO_HIT, dtype=np.int8)
        down = d[:, 2] < -1e-12
        status[~down] = NOT_DOWNWARD
        idx = np.flatnonzero(down)
        if idx.size == 0:
            return np.full((n, 3), np.nan), s_out, status
        margin = 0.01 + 1e-6 * (abs(self.zmax) + abs(self.zmin))
        dz = -d[idx, 2]
        s_top = np.maximum(0.0, (o[idx, 2] - (self.zmax + margin)) / dz)
        s_bot = (o[idx, 2] - (self.zmin - margin)) / dz
        horiz = np.hypot(d[idx, 0], d[idx, 1])
        step = 0.5 * self.pixel_size / np.maximum(horiz, 1e-12)
        steps = np.clip(np.ceil((s_bot - s_top) / step).astype(np.int64) + 1, 2, max_steps)
        valid = s_bot > s_top
        status[idx[~valid]] = NO_HIT
        order = np.argsort(steps, kind="stable")
        start = 0
        while start < order.size:
            k = int(steps[order[start]])
            count = max(1, max_samples // max(k, 1))
            # rays sorted by step count: the chunk's largest count bounds its memory
            sel = order[start:start + count]
            k = int(steps[sel].max())
            sel = sel[valid[sel]]
            start += count
            if sel.size == 0:
                continue
            self._march(o[idx[sel]], d[idx[sel]], s_top[sel], s_bot[sel], k, idx[sel], s_out, status)
        points = o + s_out[:, None] * d
        return points, s_out, status

    def _march(self, o, d, s0, s1, k, where, s_out, status) -> None:
        t = np.linspace(0.0, 1.0, k)
        s = s0[:, None] + (s1 - s0)[:, None] * t[None, :]
        px = o[:, None, 0] + s * d[:, None, 0]
        py = o[:, None, 1] + s * d[:, None, 1]
        pz = o[:, None, 2] + s * d[:, None, 2]
        f = pz - self.sample(px, py)
        above = f > 0
        below = f <= 0
        cross = above[:, :-1] & below[:, 1:]
        has = cross.any(axis=1)
        first = np.argmax(cross, axis=1)
        rows = np.arange(f.shape[0])
        # rays without a crossing: say why
        nan = ~np.isfinite(f)
        outside = ~self.inside(px, py)
        miss = ~has
        status[where[miss & (outside & nan).any(axis=1)]] = OUTSIDE
        status[where[miss & (nan & ~outside).any(axis=1)]] = NODATA
        if not has.any():
            return
        r = rows[has]
        a = s[r, first[has]]
        b = s[r, first[has] + 1]
        oo, dd = o[has], d[has]
        for _ in range(60):
            m = 0.5 * (a + b)
            p = oo + m[:, None] * dd
            fm = p[:, 2] - self.sample(p[:, 0], p[:, 1])
            up = fm > 0
            a = np.where(up, m, a)
            b = np.where(up, b, m)
        s_out[where[has]] = 0.5 * (a + b)
        status[where[has]] = HIT
