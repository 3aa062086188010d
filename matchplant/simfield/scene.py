"""The field itself: terrain, maize plants, weeds, GCP targets, and their rasters.

All coordinates here are *local*: the map CRS minus the integer offset of ``coords.txt`` (which is also
the frame of ODM's ``reconstruction.json``), so x is east and y north in metres, z is height.

A plant is a star-shaped canopy around its centre: leaves are lobes ``L_k cos(theta - phi_k)^p_k`` mostly
across the row (maize leaves grow in one plane), scaled so that neighbours in the row never touch. Its
surface height above the ground is ``H (1 - rho^2)`` where ``rho`` is the distance from the centre relative
to the outline in that direction, so the top centre is at ``H`` and the leaf tips reach the soil. The
same functions give the rasters (by cell) and the exact ground-truth boxes (by outline points).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import maximum_filter

from matchplant.simfield.config import GROUND_ALTITUDE, Settings

ROW_SPACING = 0.76  # m between maize rows (30 in)
PLANT_SPACING = 0.20  # m between plants within a row
MAX_HALF_ACROSS = 0.33  # m: a plant's leaves stay within its half of the inter-row
GCP_SIZE = 0.5  # m, side of a black-and-white GCP target
MAX_LEAVES = 8
WEED, GCP_TARGET = -1, -2  # label values besides 0 (soil) and plant ids (1..N)


@dataclass
class Terrain:
    """Gentle plane plus a few long waves: ``z = z0 + g . (x, y) + sum a sin(k . (x, y) + phase)``."""

    z0: float
    grad: np.ndarray  # (2,) slope vector (dz/dx, dz/dy)
    k: np.ndarray  # (n, 2) wave vectors, rad/m
    amp: np.ndarray  # (n,)
    phase: np.ndarray  # (n,)

    @classmethod
    def random(cls, s: Settings, rng: np.random.Generator) -> Terrain:
        """A random gentle slope with long waves, for a preset's slope and undulation."""
        az = rng.uniform(0, 2 * np.pi)
        grad = s.slope_pct / 100.0 * np.array([np.cos(az), np.sin(az)])
        n = 3
        wavelength = rng.uniform(0.6, 1.6, n) * max(s.field_width, s.field_length, 4.0)
        direction = rng.uniform(0, 2 * np.pi, n)
        k = (2 * np.pi / wavelength)[:, None] * np.stack([np.cos(direction), np.sin(direction)], axis=1)
        amp = s.undulation * rng.uniform(0.4, 1.0, n) / np.sqrt(n)
        return cls(z0=GROUND_ALTITUDE, grad=grad, k=k, amp=amp, phase=rng.uniform(0, 2 * np.pi, n))

    def height(self, x, y) -> np.ndarray:
        """Terrain height at map points."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        z = self.z0 + self.grad[0] * x + self.grad[1] * y
        for (kx, ky), a, ph in zip(self.k, self.amp, self.phase):
            z = z + a * np.sin(kx * x + ky * y + ph)
        return z

    def gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(dz/dx, dz/dy) at map points."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        gx = np.full(np.broadcast(x, y).shape, self.grad[0])
        gy = np.full(gx.shape, self.grad[1])
        for (kx, ky), a, ph in zip(self.k, self.amp, self.phase):
            c = a * np.cos(kx * x + ky * y + ph)
            gx = gx + kx * c
            gy = gy + ky * c
        return gx, gy


@dataclass
class Plants:
    """Every plant's parameters as arrays (index i is plant id i + 1)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray  # ground height at the centre
    height: np.ndarray
    row: np.ndarray
    core: np.ndarray  # radius of the central whorl, m
    leaf_len: np.ndarray  # (n, MAX_LEAVES), 0 for no leaf
    leaf_dir: np.ndarray  # (n, MAX_LEAVES) rad
    leaf_sharp: np.ndarray  # (n, MAX_LEAVES) exponent p
    su: np.ndarray  # scale across the row (x)
    sv: np.ndarray  # scale along the row (y)
    tint: np.ndarray  # (n, 3) RGB multiplier
    ndvi: np.ndarray | None = None  # per-plant leaf NDVI (vigour); None: every leaf 0.8 (NIR 0.45, red 0.05)

    def __len__(self) -> int:
        return len(self.x)

    @property
    def ids(self) -> np.ndarray:
        """Plant ids, 1 to N."""
        return np.arange(1, len(self) + 1)

    def subset(self, keep: np.ndarray) -> Plants:
        """The plants where ``keep`` is true."""
        return Plants(**{k: None if v is None else v[keep] for k, v in self.__dict__.items()})

    def outline_radius(self, idx: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Unscaled outline distance ``r(theta)`` for plants ``idx`` (n,) at angles ``theta`` (n, m)."""
        d = theta[:, :, None] - self.leaf_dir[idx][:, None, :]
        lobes = self.leaf_len[idx][:, None, :] * np.clip(np.cos(d), 0, None) ** self.leaf_sharp[idx][:, None, :]
        return np.maximum(self.core[idx][:, None], lobes.max(axis=2))

    def rho(self, idx: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Relative distance from the centre (1 on the outline) and the angle, for offsets (n, m)."""
        ux = dx / self.su[idx][:, None]
        uy = dy / self.sv[idx][:, None]
        theta = np.arctan2(uy, ux)
        return np.hypot(ux, uy) / self.outline_radius(idx, theta), theta

    def surface_points(
        self,
        idx: np.ndarray,
        terrain: Terrain,
        n_theta: int = 72,
        rhos=(0.0, 0.25, 0.45, 0.6, 0.72, 0.82, 0.9, 0.96, 1.0),
    ) -> np.ndarray:
        """Points (n, len(rhos) * m, 3) on each plant's canopy surface, leaf tips included: the ground-truth
        geometry. Ring ``k`` (points ``k*m .. (k+1)*m``) is the outline scaled by ``rhos[k]``, in angle order."""
        idx = np.asarray(idx)
        base = np.linspace(-np.pi, np.pi, n_theta, endpoint=False)
        theta = np.concatenate(
            [np.broadcast_to(base, (len(idx), n_theta)), np.mod(self.leaf_dir[idx] + np.pi, 2 * np.pi) - np.pi], axis=1
        )
        theta = np.sort(theta, axis=1)  # each ring is a closed outline, in order
        r = self.outline_radius(idx, theta)
        rho = np.asarray(rhos, dtype=float)
        ox = (rho[None, :, None] * (r * np.cos(theta))[:, None, :]) * self.su[idx][:, None, None]
        oy = (rho[None, :, None] * (r * np.sin(theta))[:, None, :]) * self.sv[idx][:, None, None]
        x = self.x[idx][:, None, None] + ox
        y = self.y[idx][:, None, None] + oy
        h = self.height[idx][:, None, None] * (1.0 - rho[None, :, None] ** 2)
        z = terrain.height(x, y) + h
        return np.stack([x, y, z], axis=-1).reshape(len(idx), -1, 3)

    def surface_offsets(self, terrain: Terrain, chunk: int = 2000) -> np.ndarray:
        """:meth:`surface_points` of every plant relative to its centre ``(x, y, z)``, float32 (n, m, 3):
        computed once, shared by every image."""
        parts = []
        for start in range(0, len(self), chunk):
            idx = np.arange(start, min(start + chunk, len(self)))
            pts = self.surface_points(idx, terrain)
            pts -= np.stack([self.x[idx], self.y[idx], self.z[idx]], axis=1)[:, None, :]
            parts.append(pts.astype(np.float32))
        return np.concatenate(parts) if parts else np.zeros((0, 0, 3), np.float32)

    def extents(self, idx: np.ndarray | None = None) -> np.ndarray:
        """(n, 4) map-plane box of each plant's outline: xmin, ymin, xmax, ymax (local coordinates)."""
        idx = np.arange(len(self)) if idx is None else np.asarray(idx)
        theta = np.linspace(-np.pi, np.pi, 360, endpoint=False)
        theta = np.concatenate([np.broadcast_to(theta, (len(idx), 360)), self.leaf_dir[idx]], axis=1)
        r = self.outline_radius(idx, theta)
        ox = r * np.cos(theta) * self.su[idx][:, None]
        oy = r * np.sin(theta) * self.sv[idx][:, None]
        return np.stack(
            [self.x[idx] + ox.min(1), self.y[idx] + oy.min(1), self.x[idx] + ox.max(1), self.y[idx] + oy.max(1)], axis=1
        )

    def radius(self) -> np.ndarray:
        """Largest distance from the centre to the outline, m."""
        theta = np.linspace(-np.pi, np.pi, 360, endpoint=False)
        theta = np.concatenate([np.broadcast_to(theta, (len(self), 360)), self.leaf_dir], axis=1)
        idx = np.arange(len(self))
        r = self.outline_radius(idx, theta)
        return np.hypot(r * np.cos(theta) * self.su[:, None], r * np.sin(theta) * self.sv[:, None]).max(axis=1)


def row_layout(s: Settings) -> tuple[np.ndarray, np.ndarray]:
    """The sowing plan: x of each crop row and y of each seed position along the first row (local frame);
    row ``r`` has its seeds :func:`row_shift` further north (a skewed grid)."""
    n_rows = max(1, int(np.floor(s.field_width / ROW_SPACING)))
    row_x = (s.field_width - (n_rows - 1) * ROW_SPACING) / 2 + ROW_SPACING * np.arange(n_rows)
    rise = (row_x[-1] - row_x[0]) * np.tan(np.radians(s.plot_skew_deg))  # the last row starts this much later
    n_in_row = max(1, int(np.floor((s.field_length - 0.1 - rise) / PLANT_SPACING)))
    y0 = (s.field_length - (n_in_row - 1) * PLANT_SPACING - rise) / 2
    return row_x, y0 + PLANT_SPACING * np.arange(n_in_row)


def row_shift(s: Settings, row_x: np.ndarray) -> np.ndarray:
    """How much further north each row's seeds start than the first row's: 0 unless the grid is skewed
    (the ranges' edges run at ``plot_skew_deg`` off the perpendicular to the rows)."""
    return (row_x - row_x[0]) * np.tan(np.radians(s.plot_skew_deg))


def make_plants(s: Settings, terrain: Terrain, rng: np.random.Generator, gcps: np.ndarray) -> Plants:
    """Plants along the crop rows, with gaps, sized to stay in their half of the inter-row and clear of the GCPs."""
    row_x, slots = row_layout(s)
    shift = row_shift(s, row_x)
    n_in_row = len(slots)
    xs, ys, rows = [], [], []
    for r, rx in enumerate(row_x):
        keep = rng.random(n_in_row) > 0.07  # gaps: missing plants
        yy = slots + shift[r] + np.clip(rng.normal(0, 0.025, n_in_row), -0.05, 0.05)
        xx = rx + np.clip(rng.normal(0, 0.012, n_in_row), -0.03, 0.03)
        xs.append(xx[keep])
        ys.append(yy[keep])
        rows.append(np.full(keep.sum(), r + 1))
    x, y, row = np.concatenate(xs), np.concatenate(ys), np.concatenate(rows)
    n = len(x)
    mid, sd = (s.height_min + s.height_max) / 2, (s.height_max - s.height_min) / 4
    height = np.clip(rng.normal(mid, sd, n), s.height_min, s.height_max)
    n_leaves = np.clip(
        (3 + 5 * (height - s.height_min) / max(s.height_max - s.height_min, 1e-6)).astype(int) + rng.integers(0, 2, n),
        3,
        MAX_LEAVES,
    )
    k = np.arange(MAX_LEAVES)[None, :]
    has = k < n_leaves[:, None]
    side = np.where(k % 2 == 0, 0.0, np.pi)  # leaves alternate across the row
    flip = rng.random(n)[:, None] < 0.5
    leaf_dir = side + np.where(flip, np.pi, 0.0) + rng.normal(0, 0.45, (n, MAX_LEAVES))
    leaf_len = np.where(has, (0.04 + 0.55 * height[:, None]) * rng.uniform(0.6, 1.0, (n, MAX_LEAVES)), 0.0)
    leaf_sharp = rng.uniform(12.0, 30.0, (n, MAX_LEAVES))
    core = 0.02 + 0.05 * height
    plants = Plants(
        x=x,
        y=y,
        z=terrain.height(x, y),
        height=height,
        row=row,
        core=core,
        leaf_len=leaf_len,
        leaf_dir=leaf_dir,
        leaf_sharp=leaf_sharp,
        su=np.ones(n),
        sv=np.ones(n),
        tint=rng.uniform(0.85, 1.15, (n, 3)),
    )
    # Scale each canopy so that it stays in its half of the inter-row and clear of its row neighbours.
    ext = plants.extents()
    half_x = np.maximum(x - ext[:, 0], ext[:, 2] - x)
    su = np.minimum(1.0, MAX_HALF_ACROSS / half_x)
    order = np.lexsort((y, row))
    gap_next = np.full(n, np.inf)
    gap_prev = np.full(n, np.inf)
    same = row[order][1:] == row[order][:-1]
    d = np.diff(y[order])
    gap_next[order[:-1][same]] = d[same]
    gap_prev[order[1:][same]] = d[same]
    up = ext[:, 3] - y
    down = y - ext[:, 1]
    sv = np.minimum(1.0, np.minimum(0.45 * gap_next / up, 0.45 * gap_prev / down))
    plants.su, plants.sv = su, sv
    # Clear the ground around the GCP targets.
    if len(gcps):
        ext = plants.extents()
        clear = GCP_SIZE / 2 + 0.05
        near = np.zeros(n, dtype=bool)
        for gx, gy in gcps[:, :2]:
            near |= (
                (ext[:, 0] < gx + clear)
                & (ext[:, 2] > gx - clear)
                & (ext[:, 1] < gy + clear)
                & (ext[:, 3] > gy - clear)
            )
        plants = plants.subset(~near)
    return plants


def make_gcps(s: Settings, terrain: Terrain, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) GCP target centres, spread over the field (corners first, then the middle)."""
    fx, fy = s.field_width, s.field_length
    if s.n_gcps >= 9:
        grid = [(a, b) for b in (0.12, 0.5, 0.88) for a in (0.12, 0.5, 0.88)]
    else:
        grid = [(0.15, 0.15), (0.85, 0.15), (0.85, 0.85), (0.15, 0.85), (0.5, 0.5)]
    pts = np.array(grid[: s.n_gcps], dtype=float) * [fx, fy] + rng.normal(0, 0.05, (min(s.n_gcps, len(grid)), 2))
    return np.column_stack([pts, terrain.height(pts[:, 0], pts[:, 1])])


@dataclass
class Grid:
    """A north-up raster grid in local coordinates: column i spans x0 + [i, i+1) res, row j spans
    y1 - [j, j+1) res."""

    x0: float
    y1: float
    res: float
    width: int
    height: int

    @classmethod
    def covering(cls, xmin: float, ymin: float, xmax: float, ymax: float, res: float) -> Grid:
        """The grid of ``res`` cells, aligned to multiples of ``res``, that covers a box."""
        x0 = np.floor(xmin / res) * res
        y1 = np.ceil(ymax / res) * res
        return cls(
            x0=float(x0),
            y1=float(y1),
            res=res,
            width=int(np.ceil((xmax - x0) / res)),
            height=int(np.ceil((y1 - ymin) / res)),
        )

    def centres(self, rows: slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Map x and y of the cell centres of the given rows (the whole grid by default)."""
        j = np.arange(self.height)[rows]
        xs = self.x0 + (np.arange(self.width) + 0.5) * self.res
        ys = self.y1 - (j + 0.5) * self.res
        return np.meshgrid(xs, ys)

    def cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) of the cell holding each point, clipped to the grid."""
        col = np.clip(((x - self.x0) / self.res).astype(np.intp), 0, self.width - 1)
        row = np.clip(((self.y1 - y) / self.res).astype(np.intp), 0, self.height - 1)
        return row, col


@dataclass
class Rasters:
    """The field's rasters on one grid: canopy height, labels, albedo, red and NIR reflectance."""

    grid: Grid
    canopy: np.ndarray  # float32 height above the terrain
    label: np.ndarray  # int32: plant id, 0 soil, WEED, GCP_TARGET
    albedo: np.ndarray  # uint8 RGB
    red: np.ndarray  # float32 reflectance
    nir: np.ndarray

    def block_max(self, block: int = 6) -> tuple[int, np.ndarray]:
        """Highest canopy within one block of each ``block`` x ``block`` cell block (flattened), for
        skipping empty space when casting rays."""
        if getattr(self, "_block_max", None) is None:
            h, w = self.canopy.shape
            hb, wb = -(-h // block), -(-w // block)
            padded = np.zeros((hb * block, wb * block), np.float32)
            padded[:h, :w] = self.canopy
            coarse = padded.reshape(hb, block, wb, block).max(axis=(1, 3))
            self._block_max = (block, maximum_filter(coarse, size=3, mode="nearest"))
        return self._block_max[0], self._block_max[1]


def _noise(shape: tuple[int, int], cells: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth unit noise with a feature size of ``cells`` raster cells (upsampled white noise)."""
    h, w = shape
    ch, cw = max(2, int(np.ceil(h / cells)) + 2), max(2, int(np.ceil(w / cells)) + 2)
    coarse = rng.standard_normal((ch, cw)).astype(np.float32)
    if ch >= h and cw >= w:
        return coarse[:h, :w]
    return cv2.resize(coarse, (int(cw * cells), int(ch * cells)), interpolation=cv2.INTER_CUBIC)[:h, :w]


def rasterize(
    s: Settings,
    grid: Grid,
    plants: Plants,
    gcps: np.ndarray,
    rng: np.random.Generator,
    sun_az_deg: float = 135.0,
    sun_elev_deg: float = 55.0,
) -> Rasters:
    """The field's rasters at ``grid``: canopy height, labels (plant ids, GCP targets, weeds), the albedo
    orthophoto, red and NIR (``rng`` draws the weeds and the soil's texture, in that order)."""
    shape = (grid.height, grid.width)
    canopy = np.zeros(shape, np.float32)
    label = np.zeros(shape, np.int32)
    shade = np.ones(shape, np.float32)  # plant leaf brightness pattern
    res = grid.res

    # -- plants: every cell inside a canopy outline ----------------------------------------------
    _paint_plants(grid, plants, canopy, label, shade)

    # -- GCP targets: flat 2x2 checkerboards -----------------------------------------------------
    white = _paint_targets(grid, gcps, canopy, label)

    # -- weeds: small low rosettes on bare soil ----------------------------------------------------
    weed = _paint_weeds(grid, rng, canopy, label) if s.weeds else np.zeros(shape, bool)

    # -- colours ---------------------------------------------------------------------------------
    fine = _noise(shape, 0.004 / res, rng)
    mid = _noise(shape, 0.03 / res, rng)
    coarse = _noise(shape, 0.5 / res, rng)
    soil_b = np.clip(1.0 + 0.10 * fine + 0.08 * mid + 0.06 * coarse, 0.6, 1.4)
    rgb = np.empty(shape + (3,), np.float32)
    rgb[:] = np.array([0.46, 0.37, 0.28], np.float32)
    rgb *= soil_b[..., None]
    is_plant = label > 0
    pid = label[is_plant] - 1
    green = np.array([0.20, 0.46, 0.11], np.float32) * plants.tint[pid].astype(np.float32)
    leaf_b = shade[is_plant] * (1.0 + 0.05 * fine[is_plant])
    rgb[is_plant] = green * leaf_b[:, None]
    rgb[weed] = np.array([0.30, 0.50, 0.16], np.float32) * (1 + 0.08 * fine[weed])[:, None]
    target = label == GCP_TARGET
    rgb[target] = 0.06
    rgb[white] = 0.92
    red = (0.20 * soil_b).astype(np.float32)
    nir = (0.27 * soil_b).astype(np.float32)
    if plants.ndvi is None:
        red[is_plant] = 0.05 * leaf_b
        nir[is_plant] = 0.45 * leaf_b
    else:  # NIR + red as before (0.5 x brightness), split to give each plant its own NDVI
        v = plants.ndvi[pid].astype(np.float32)
        red[is_plant] = 0.25 * (1 - v) * leaf_b
        nir[is_plant] = 0.25 * (1 + v) * leaf_b
    red[weed], nir[weed] = 0.06, 0.40
    red[target], nir[target] = 0.04, 0.05
    red[white], nir[white] = 0.80, 0.82

    # -- shadows: splat each canopy cell onto the ground along the sun's direction -----------------
    if s.shadows and s.height_max > 0:
        shadow = _shadows(canopy, label, grid, sun_az_deg, sun_elev_deg)
        rgb[shadow] *= 0.55
        red[shadow] *= 0.55
        nir[shadow] *= 0.55
    albedo = np.clip(np.round(rgb * 255), 1, 255).astype(np.uint8)
    return Rasters(grid=grid, canopy=canopy, label=label, albedo=albedo, red=red, nir=nir)


def _paint_plants(grid: Grid, plants: Plants, canopy: np.ndarray, label: np.ndarray, shade: np.ndarray) -> None:
    """Every cell inside a plant's canopy outline gets its height, id and leaf brightness (in place), in chunks of
    plants sharing one window size; the highest canopy wins where two overlap."""
    res = grid.res
    ext = plants.extents()
    half_x = np.ceil(np.abs(ext[:, [0, 2]] - plants.x[:, None]).max(1) / res).astype(int) + 1
    half_y = np.ceil(np.abs(ext[:, [1, 3]] - plants.y[:, None]).max(1) / res).astype(int) + 1
    order = np.lexsort((half_y, half_x))
    budget = 2_000_000
    start = 0
    flat_all, h_all, id_all, b_all = [], [], [], []
    while start < len(order):
        first = order[start]
        count = max(1, budget // ((2 * half_x[first] + 3) * (2 * half_y[first] + 3) * MAX_LEAVES))
        idx = order[start : start + count]
        hx, hy = int(half_x[idx].max()), int(half_y[idx].max())
        start += len(idx)
        r0, c0 = grid.cell(plants.x[idx], plants.y[idx])
        rr = r0[:, None, None] + np.arange(-hy, hy + 1)[None, :, None]
        cc = c0[:, None, None] + np.arange(-hx, hx + 1)[None, None, :]
        rr, cc = np.broadcast_arrays(rr, cc)
        cx = grid.x0 + (cc + 0.5) * res
        cy = grid.y1 - (rr + 0.5) * res
        dx = (cx - plants.x[idx][:, None, None]).reshape(len(idx), -1)
        dy = (cy - plants.y[idx][:, None, None]).reshape(len(idx), -1)
        rho, theta = plants.rho(idx, dx, dy)
        inside = (
            (rho < 1.0)
            & (rr.reshape(len(idx), -1) >= 0)
            & (rr.reshape(len(idx), -1) < grid.height)
            & (cc.reshape(len(idx), -1) >= 0)
            & (cc.reshape(len(idx), -1) < grid.width)
        )
        pi, ci = np.nonzero(inside)
        h = plants.height[idx][pi] * (1.0 - rho[pi, ci] ** 2)
        # brightness: paler whorl, bright midribs along each leaf
        d = theta[pi, ci][:, None] - plants.leaf_dir[idx][pi]
        rib = (np.clip(np.cos(d), 0, None) ** (4 * plants.leaf_sharp[idx][pi])).max(axis=1)
        bright = 0.75 + 0.25 * (1 - rho[pi, ci]) + 0.12 * rib
        flat_all.append(rr.reshape(len(idx), -1)[pi, ci] * grid.width + cc.reshape(len(idx), -1)[pi, ci])
        h_all.append(h)
        id_all.append(idx[pi] + 1)
        b_all.append(bright)
    if flat_all:
        flat, h, ids, bright = (np.concatenate(a) for a in (flat_all, h_all, id_all, b_all))
        o = np.argsort(h, kind="stable")  # the highest canopy wins where two overlap
        canopy.ravel()[flat[o]] = h[o]
        label.ravel()[flat[o]] = ids[o]
        shade.ravel()[flat[o]] = bright[o]


def _paint_targets(grid: Grid, gcps: np.ndarray, canopy: np.ndarray, label: np.ndarray) -> np.ndarray:
    """The GCP targets, flat 2x2 checkerboards, into ``label`` and ``canopy`` (in place); returns their white
    squares."""
    white = np.zeros(label.shape, bool)
    for gx, gy, _ in gcps:
        r0, c0 = grid.cell(np.array([gx - GCP_SIZE / 2]), np.array([gy + GCP_SIZE / 2]))
        r1, c1 = grid.cell(np.array([gx + GCP_SIZE / 2]), np.array([gy - GCP_SIZE / 2]))
        cols = slice(int(c0[0]), int(c1[0]) + 1)
        xs, ys = grid.centres(slice(int(r0[0]), int(r1[0]) + 1))
        xs, ys = xs[:, cols], ys[:, cols]
        inside = (np.abs(xs - gx) < GCP_SIZE / 2) & (np.abs(ys - gy) < GCP_SIZE / 2)
        win = (slice(int(r0[0]), int(r1[0]) + 1), cols)
        label[win][inside] = GCP_TARGET
        canopy[win][inside] = 0.0
        white[win] |= inside & ((xs - gx) * (ys - gy) > 0)
    return white


def _paint_weeds(grid: Grid, rng: np.random.Generator, canopy: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Small low rosettes on bare soil (none over a plant or a target) into ``canopy`` and ``label`` (in place);
    returns where they are."""
    res = grid.res
    weed = np.zeros(label.shape, bool)
    area = grid.width * grid.height * res * res
    n = rng.poisson(1.5 * area)
    wx = grid.x0 + rng.uniform(0, grid.width * res, n)
    wy = grid.y1 - rng.uniform(0, grid.height * res, n)
    wr = rng.uniform(0.015, 0.045, n)
    wh = rng.uniform(0.01, 0.04, n)
    hw = int(np.ceil(0.045 / res)) + 1
    off = np.arange(-hw, hw + 1)
    r0, c0 = grid.cell(wx, wy)
    rr = np.clip(r0[:, None, None] + off[None, :, None], 0, grid.height - 1)
    cc = np.clip(c0[:, None, None] + off[None, None, :], 0, grid.width - 1)
    rr, cc = np.broadcast_arrays(rr, cc)
    dx = grid.x0 + (cc + 0.5) * res - wx[:, None, None]
    dy = grid.y1 - (rr + 0.5) * res - wy[:, None, None]
    ang = np.arctan2(dy, dx)
    lobes = 0.7 + 0.3 * np.cos(5 * ang + rng.uniform(0, 2 * np.pi, n)[:, None, None])
    rho = np.hypot(dx, dy) / (wr[:, None, None] * lobes)
    # keep only weeds that lie entirely on bare soil (no plant or target under them)
    clear = ~((rho < 1.3) & (label[rr, cc] != 0)).reshape(n, -1).any(axis=1)
    m = (rho < 1.0) & clear[:, None, None]
    hh = (wh[:, None, None] * (1 - rho**2))[m]
    canopy[rr[m], cc[m]] = np.maximum(canopy[rr[m], cc[m]], hh)
    label[rr[m], cc[m]] = WEED
    weed[rr[m], cc[m]] = True
    return weed


def _shadows(canopy: np.ndarray, label: np.ndarray, grid: Grid, az_deg: float, elev_deg: float) -> np.ndarray:
    r, c = np.nonzero(canopy > 0.01)
    h = canopy[r, c]
    away = np.radians(az_deg + 180.0)  # shadows fall away from the sun (azimuth clockwise from north)
    length = h / np.tan(np.radians(elev_deg)) / grid.res
    mask = np.zeros(canopy.shape, np.uint8)
    # the shadow of the column under each canopy cell: splat points along it (no gaps between them)
    n = int(np.ceil(length.max(initial=0.0))) + 1
    for f in np.linspace(0.0, 1.0, min(n, 24)):
        rr = np.clip(np.round(r - f * length * np.cos(away)).astype(int), 0, grid.height - 1)
        cc = np.clip(np.round(c + f * length * np.sin(away)).astype(int), 0, grid.width - 1)
        mask[rr, cc] = 1
    k = 3
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    return (mask > 0) & (label <= 0)  # on soil, weeds and targets; leaves are not darkened
