"""Module 3: the fewest undistorted images that cover the field, and the part of the field each one owns.

1. **Footprints.** Each undistorted image's true ground footprint: rays through points along its border
   (``border_samples`` per side, corners included) are intersected with the DSM
   (:func:`~matchplant.core.ground.pixels_to_ground`), giving a polygon in the map CRS that follows the relief
   - not the bounding box of an orthorectified image, and without ODM's slow orthorectification.
2. **Area of interest (AOI).** The orthophoto's valid-data area, read at reduced resolution and
   polygonised (``rasterio.features.shapes``), or a polygon file from the user.
3. **Selection: greedy weighted set cover with an overlap penalty and an overlap cap.** The AOI is cut into
   a grid of cells (each weighted by its area). Starting from nothing, the image adding the most uncovered
   area, minus ``overlap_penalty`` times the area it covers twice, is taken, among images whose overlap
   with every image already taken is at most ``max_overlap`` (the paper's overlap limit, so the same
   plants are not labelled many times); this repeats until the uncovered share of the AOI is at most
   ``uncovered_threshold`` (the paper's control). If the cap makes that impossible it is relaxed, with a
   warning. A final pass drops every image the coverage no longer needs. Greedy set cover is within a
   factor ln(n) of the optimum in theory and close to it on survey grids; ``method: milp`` solves the same
   problem exactly as an integer program (scipy's HiGHS ``milp``) for small flights.
4. **Owned areas.** Every covered point of the AOI is given to exactly one selected image: the one whose
   footprint centre is nearest (a Voronoi partition) when that image sees it, otherwise the selected image
   that sees most of the leftover piece. Each owned area is also mapped into its image's pixels
   (:func:`~matchplant.core.ground.ground_to_pixels` through the DSM), so module 4 can show the annotator which
   part of each photo to label: every plant is then labelled exactly once.

Outputs (``output_dir``): ``selected_images.csv``, the selected undistorted images (copied, hard-linked or
only listed), ``coverage.png``, ``footprints.gpkg`` (layers ``footprints``, ``owned``, ``aoi``,
``uncovered``), ``owned_areas.json`` (``{image file name: [[u, v], ...]}`` in that image's pixels) and
``selection.json`` (settings and results).
"""

from __future__ import annotations

import csv
import math
import os
import shutil
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import shapely
from scipy import sparse
from affine import Affine
from shapely.geometry import MultiPolygon, Polygon, box

from matchplant.core.config import param
from matchplant.core.errors import ConfigError, GeometryError, InputError
from matchplant.core.frames import Frame
from matchplant.core.ground import ground_to_pixels, pixels_to_ground
from matchplant.core.io import atomic_open, atomic_path, write_json
from matchplant.core.log import get_logger
from matchplant.core.odm import ODMProject
from matchplant.core.owned_areas import write_owned_areas
from matchplant.core.progress import progress
from matchplant.core.reconstruction import Shot
from matchplant.core.surface import HIT, Surface

log = get_logger("min_images")


# --------------------------------------------------------------------------------------------------
# configuration


@dataclass
class MinImagesConfig:
    """Choose the fewest undistorted images covering the field, and the part of the field each one owns."""

    project_dir: Path = param(None, "ODM project folder (opensfm/, odm_dem/dsm.tif, odm_orthophoto/)",
                              path="dir", required=True)
    aoi_file: Path | None = param(None, "polygon file of the area to cover (GeoPackage, Shapefile, GeoJSON); "
                                        "empty: the orthophoto's valid-data area", path="file")
    uncovered_threshold: float = param(5.0, "share of the area allowed to stay uncovered, percent "
                                            "(the paper's uncovered-area threshold)", min=0.0, max=90.0)
    max_overlap: float = param(30.0, "largest overlap between two selected images, percent of the smaller "
                                     "footprint (the paper's overlap limit; relaxed with a warning if the "
                                     "coverage cannot be reached)", min=0.0, max=100.0)
    overlap_penalty: float = param(0.2, "greedy score = new area - penalty x area covered twice", min=0.0, max=10.0)
    method: Literal["greedy", "milp"] = param("greedy", "greedy set cover (fast, any size) or milp (exact integer "
                                                        "program, small flights)", choices=["greedy", "milp"])
    milp_time_limit: float = param(60.0, "seconds the integer program may run (method: milp)", min=1.0)
    cell_size: float = param(0.0, "coverage grid cell size in metres; 0: automatic (about 40,000 cells)", min=0.0)
    border_samples: int = param(16, "rays cast along each side of an image for its footprint", min=2, max=500)
    dsm_resolution: float = param(0.05, "DSM resolution used for footprints, metres (coarser is faster); "
                                        "0: the file's own", min=0.0)
    preview_size: int = param(1500, "longest side, in pixels, of the orthophoto read for the AOI and the figure",
                              min=100, max=20000)
    copy_images: Literal["copy", "link", "none"] = param("copy", "put the selected images in output_dir/images: "
                                                                 "copy, link (hard link, no extra space), or none "
                                                                 "(only list them)",
                                                         choices=["copy", "link", "none"])
    output_dir: Path = param(Path("min_images_out"), "folder for the outputs", path="out")


# --------------------------------------------------------------------------------------------------
# footprints


@dataclass
class Footprint:
    name: str               # shot id (original image name)
    file: Path              # undistorted image
    shot: Shot              # with the camera sized to the undistorted image
    polygon: Polygon        # ground footprint in the map CRS
    border: np.ndarray      # (N, 3) map points where the border rays meet the DSM (or the fallback plane)
    border_uv: np.ndarray   # (N, 2) the border pixels
    hit: np.ndarray         # (N,) True where the ray met the DSM

    @property
    def centroid(self) -> tuple[float, float]:
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


def image_footprint(shot: Shot, frame: Frame, surface: Surface, per_side: int = 16) -> tuple[Polygon, np.ndarray, np.ndarray, np.ndarray]:
    """The ground polygon seen by ``shot``: its border rays intersected with the DSM.

    Rays that miss the DSM (they leave it, or meet a nodata hole) end on the horizontal plane at the median
    height of the rays that hit, so an image at the field's edge still gets a sensible outline.
    Returns ``(polygon, border points (N, 3), border pixels (N, 2), hit mask (N,))``.
    """
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
        raise GeometryError(f"image '{shot.id}' does not look at the ground (its border rays miss the DSM)",
                            fix="exclude it, or check that the DSM and the reconstruction are of the same field")
    poly = shapely.make_valid(Polygon(pts[good, :2]))
    if not isinstance(poly, Polygon):  # a self-crossing outline (extreme tilt): keep its largest piece
        parts = [g for g in getattr(poly, "geoms", []) if isinstance(g, Polygon)]
        poly = max(parts, key=lambda g: g.area) if parts else Polygon(pts[good, :2]).convex_hull
    return poly, pts, uv, hit


def open_dsm(path: Path, resolution: float = 0.0) -> Surface:
    """The DSM as a :class:`Surface`, averaged down to ``resolution`` metres when that is coarser."""
    import rasterio
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


def compute_footprints(project: ODMProject, frame: Frame, surface: Surface, per_side: int = 16,
                       names: Sequence[str] | None = None) -> list[Footprint]:
    """Footprints of every undistorted image in the reconstruction (sorted by name)."""
    rec = project.reconstruction(undistorted=True)
    files = project.undistorted_images()
    todo = sorted(n for n in (names or rec.shots) if n in files and n in rec.shots)
    if not todo:
        raise InputError("no undistorted image matches the undistorted reconstruction",
                         path=project.path("undistorted_images"),
                         fix="re-run ODM without --optimize-disk-space (module 2)")
    out = []
    for name in progress(todo, desc="footprints", unit="image"):
        shot = project.shot(name, undistorted=True)
        try:
            poly, pts, uv, hit = image_footprint(shot, frame, surface, per_side)
        except GeometryError as exc:
            log.warning("skipping %s: %s", name, exc.problem)
            continue
        out.append(Footprint(name=name, file=files[name], shot=shot, polygon=poly, border=pts, border_uv=uv, hit=hit))
    if not out:
        raise InputError("no image footprint could be placed on the DSM", path=project.path("dsm"),
                         fix="check that the DSM and the reconstruction are of the same field")
    return out


# --------------------------------------------------------------------------------------------------
# area of interest


def orthophoto_preview(path: Path, max_size: int = 1500) -> tuple[np.ndarray, np.ndarray, object, object]:
    """The orthophoto read at reduced resolution: ``(rgb (h, w, 3) uint8, valid mask (h, w), transform, crs)``."""
    import rasterio

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


def aoi_from_mask(mask: np.ndarray, transform) -> Polygon | MultiPolygon:
    """Polygonise a valid-data mask (``rasterio.features.shapes``) into one (multi)polygon."""
    from rasterio.features import shapes

    geoms = [shapely.geometry.shape(g) for g, v in shapes(mask.astype(np.uint8), mask=mask, transform=transform)
             if v == 1]
    if not geoms:
        raise InputError("the orthophoto has no valid pixels", fix="check the ODM run (module 2)")
    aoi = shapely.union_all(geoms)
    return aoi.simplify(abs(transform.a) * 0.5)


def read_aoi_file(path: Path, crs) -> Polygon | MultiPolygon:
    """The union of the polygons in a vector file, in ``crs``."""
    import geopandas as gpd

    try:
        gdf = gpd.read_file(path)
    except Exception as exc:  # noqa: BLE001 - any driver error means the file cannot be used
        raise InputError(f"cannot read the area-of-interest file: {exc}", path=path,
                         fix="use a GeoPackage, Shapefile or GeoJSON with polygons") from exc
    gdf = gdf[gdf.geometry.notna() & gdf.geometry.geom_type.isin(["Polygon", "MultiPolygon"])]
    if gdf.empty:
        raise InputError("the area-of-interest file holds no polygon", path=path,
                         fix="draw the field boundary as a polygon (e.g. in QGIS) and save it")
    if gdf.crs is None:
        raise InputError("the area-of-interest file has no coordinate system", path=path,
                         fix="set its CRS (in QGIS: Layer > Set CRS) and save it again")
    if crs is not None:
        gdf = gdf.to_crs(crs)
    return shapely.make_valid(shapely.union_all(gdf.geometry.values))


# --------------------------------------------------------------------------------------------------
# the coverage grid and the selection


@dataclass
class CoverageGrid:
    """AOI cells (centres inside the AOI) and which image sees each: ``A[i, c]`` is True when image i covers c."""

    x: np.ndarray          # (m,) cell centres
    y: np.ndarray
    cell: float            # cell side, m
    A: sparse.csr_matrix   # (n_images, m) bool
    weights: np.ndarray    # (m,) area of each cell, m^2

    @property
    def total(self) -> float:
        return float(self.weights.sum())

    def overlap_fraction(self) -> sparse.csr_matrix:
        """Pairwise overlap area / the smaller footprint's area (inside the AOI)."""
        Aw = self.A.multiply(self.weights[None, :]).tocsr()
        inter = (Aw @ self.A.T.astype(float)).tocoo()
        area = np.asarray(Aw.sum(axis=1)).ravel()
        smaller = np.minimum(area[inter.row], area[inter.col])
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(smaller > 0, inter.data / smaller, 0.0)
        keep = inter.row != inter.col
        return sparse.csr_matrix((frac[keep], (inter.row[keep], inter.col[keep])), shape=(self.A.shape[0],) * 2)

    def coverage(self, selected: Sequence[int]) -> float:
        if len(selected) == 0:
            return 0.0
        covered = np.asarray(self.A[list(selected)].sum(axis=0)).ravel() > 0
        return float(self.weights[covered].sum() / self.total)


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


@dataclass
class Selection:
    indices: list[int]                 # into the footprint list, in order of selection
    coverage: float                    # share of the AOI covered (grid)
    target: float                      # the requested share
    method: str
    relaxed: bool = False              # the overlap cap had to be relaxed
    optimal: bool | None = None        # milp: proven optimal
    seconds: float = 0.0
    gains: list[float] = field(default_factory=list)  # new area each image added, m^2 (greedy order)


def reachable_coverage(grid: CoverageGrid) -> float:
    covered = np.asarray(grid.A.sum(axis=0)).ravel() > 0
    return float(grid.weights[covered].sum() / grid.total)


def select_greedy(grid: CoverageGrid, target: float, max_overlap: float = 1.0, overlap_penalty: float = 0.2,
                  restarts: bool = True, all_starts_below: int = 150) -> Selection:
    """Greedy weighted set cover with an overlap penalty and a pairwise overlap cap, then local improvement.

    ``target`` and ``max_overlap`` are fractions (0..1). Plain greedy grabs the image in the middle first and
    then needs extra images for slivers at the edges, so it is also started from each corner of the area
    (as the paper's tool starts from the lower-left image); every run is pruned and improved by replacing
    two overlapping images with one, and the smallest result wins.
    """
    t0 = time.perf_counter()
    need = min(target, reachable_coverage(grid)) * grid.total * (1 - 1e-12)
    frac = grid.overlap_fraction() if max_overlap < 1.0 else None
    starts: list[int | None] = [None]
    if restarts:
        starts += corner_images(grid)
        if grid.A.shape[0] <= all_starts_below:  # small flights: try every image as the first one
            starts += list(range(grid.A.shape[0]))
    grid = compress(grid)  # same coverage arithmetic on far fewer columns
    cov = _Cover(grid)
    best = None
    for first in dict.fromkeys(starts):  # unique, in order
        chosen, gains, relaxed = _greedy_run(cov, need, frac, max_overlap, overlap_penalty, first)
        cap = max_overlap if not relaxed else 1.0
        chosen = prune(cov, chosen, need)
        chosen = swap_two_for_one(cov, chosen, need, frac, cap)
        chosen = prune(cov, swap_one_for_better(cov, chosen, frac, cap), need)
        key = (len(chosen), relaxed, -grid.coverage(chosen))
        if best is None or key < best[0]:
            best = (key, chosen, gains, relaxed)
    _, chosen, gains, relaxed = best
    return Selection(indices=chosen, coverage=grid.coverage(chosen), target=target, method="greedy",
                     relaxed=relaxed, seconds=time.perf_counter() - t0, gains=gains)


def compress(grid: CoverageGrid) -> CoverageGrid:
    """The grid with cells seen by the same images merged into one weighted column (see :func:`cell_atoms`)."""
    B, wa = cell_atoms(grid)
    nan = np.full(wa.size, np.nan)
    return CoverageGrid(x=nan, y=nan, cell=grid.cell, A=B, weights=wa)


def corner_images(grid: CoverageGrid) -> list[int]:
    """For each corner of the area (extreme cells along both diagonals), the largest image that covers it."""
    area = np.asarray(grid.A.multiply(grid.weights[None, :]).sum(axis=1)).ravel()
    At = grid.A.T.tocsr()
    out = []
    for score in (grid.x + grid.y, grid.x - grid.y, -grid.x + grid.y, -grid.x - grid.y):
        seen = np.diff(At.indptr) > 0
        if not seen.any():
            break
        c = int(np.flatnonzero(seen)[np.argmin(score[seen])])
        imgs = At.indices[At.indptr[c]:At.indptr[c + 1]]
        out.append(int(imgs[np.argmax(area[imgs])]))
    return out


class _Cover:
    """Fast coverage arithmetic for the local searches: each image's cells as an index array."""

    def __init__(self, grid: CoverageGrid):
        self.A = grid.A.astype(float).tocsr()
        self.w = grid.weights
        ptr, idx = self.A.indptr, self.A.indices
        self.rows = [idx[ptr[i]:ptr[i + 1]] for i in range(self.A.shape[0])]

    def counts(self, chosen: Sequence[int]) -> np.ndarray:
        c = np.zeros(self.A.shape[1], dtype=np.int32)
        for i in chosen:
            c[self.rows[i]] += 1
        return c

    def gains(self, free: np.ndarray) -> np.ndarray:
        """Area each image would add where ``free`` is True."""
        return self.A @ np.where(free, self.w, 0.0)

    def blocked(self, frac, others: Sequence[int], max_overlap: float) -> np.ndarray | None:
        """Images overlapping any of ``others`` more than the cap (None when there is no cap)."""
        if frac is None or max_overlap >= 1.0 or not len(others):
            return None
        return np.asarray((frac[list(others)] > max_overlap + 1e-9).sum(axis=0)).ravel() > 0


def _greedy_run(cov: _Cover, need: float, frac, max_overlap: float, overlap_penalty: float,
                first: int | None) -> tuple[list[int], list[float], bool]:
    n = cov.A.shape[0]
    w = cov.w
    covered = np.zeros(cov.A.shape[1], dtype=bool)
    taken = np.zeros(n, dtype=bool)
    allowed = np.ones(n, dtype=bool)
    chosen: list[int] = []
    gains: list[float] = []
    relaxed = False
    done = 0.0
    while done < need:
        new = cov.gains(~covered)
        if first is not None and not chosen:
            i = first
        else:
            candidates = allowed & ~taken & (new > 0)
            if not candidates.any():
                if frac is not None and not relaxed and (~taken & (new > 0)).any():
                    relaxed = True  # the cap blocks the coverage: lift it for the rest
                    allowed[:] = True
                    continue
                break
            score = new - overlap_penalty * cov.gains(covered) if overlap_penalty else new.copy()
            score[~candidates] = -np.inf
            i = int(np.argmax(score))
        chosen.append(i)
        gains.append(float(new[i]))
        taken[i] = True
        covered[cov.rows[i]] = True
        done = float(w[covered].sum())
        if frac is not None and not relaxed:
            row = frac[i]
            allowed[row.indices[row.data > max_overlap + 1e-9]] = False
    return chosen, gains, relaxed


def swap_one_for_better(cov: _Cover, chosen: list[int], frac, max_overlap: float, rounds: int = 3) -> list[int]:
    """Local search: replace a selected image by another that covers more with the rest (same count), so the
    pruning pass may then drop one."""
    chosen = list(chosen)
    w = cov.w
    for _ in range(rounds):
        improved = False
        for pos in range(len(chosen)):
            count = cov.counts(chosen)
            mine = cov.rows[chosen[pos]]
            lost = np.zeros(count.size, bool)
            lost[mine[count[mine] == 1]] = True
            gain = cov.gains((count == 0) | lost)
            gain[chosen] = -1.0
            bad = cov.blocked(frac, chosen[:pos] + chosen[pos + 1:], max_overlap)
            if bad is not None:
                gain[bad] = -1.0
            k = int(np.argmax(gain))
            if gain[k] > float(w[lost].sum()) * (1 + 1e-9) + 1e-12:
                chosen[pos] = k
                improved = True
        if not improved:
            break
    return chosen


def swap_two_for_one(cov: _Cover, chosen: list[int], need: float, frac, max_overlap: float) -> list[int]:
    """Local search: while two overlapping selected images can be replaced by one, do it."""
    chosen = list(chosen)
    w = cov.w
    improved = True
    while improved and len(chosen) > 1:
        improved = False
        count = cov.counts(chosen)
        for a in range(len(chosen)):
            for b in range(a + 1, len(chosen)):
                i, j = chosen[a], chosen[b]
                left = count.copy()
                left[cov.rows[i]] -= 1
                left[cov.rows[j]] -= 1
                lost = (left == 0) & (count > 0)
                deficit = need - float(w[left > 0].sum())
                gain = cov.gains(lost)
                gain[chosen] = -1.0
                bad = cov.blocked(frac, [c for c in chosen if c not in (i, j)], max_overlap)
                if bad is not None:
                    gain[bad] = -1.0
                k = int(np.argmax(gain))
                if gain[k] >= 0 and gain[k] >= deficit - 1e-9:
                    chosen = [c for c in chosen if c not in (i, j)] + [k]
                    improved = True
                    break
            if improved:
                break
    return chosen


def prune(grid_or_cov, chosen: list[int], need: float) -> list[int]:
    """Drop selected images the coverage does not need, the least useful first, until none can go."""
    cov = grid_or_cov if isinstance(grid_or_cov, _Cover) else _Cover(grid_or_cov)
    chosen = list(chosen)
    w = cov.w
    while len(chosen) > 1:
        count = cov.counts(chosen)
        done = float(w[count > 0].sum())
        unique = np.array([w[cov.rows[i][count[cov.rows[i]] == 1]].sum() for i in chosen])
        for k in np.argsort(unique, kind="stable"):
            if done - unique[k] >= need:
                del chosen[int(k)]
                break
        else:
            break
    return chosen


def cell_atoms(grid: CoverageGrid) -> tuple[sparse.csr_matrix, np.ndarray]:
    """Merge cells seen by exactly the same images: ``(B (n_images, k) bool, weights (k,))``.

    The integer program then has one coverage variable per distinct overlap region instead of per cell.
    """
    # a random 64-bit key per image; a cell's signature is the wrapping sum of its images' keys
    # (two different image sets colliding has probability ~2^-64 per pair)
    keys = np.random.default_rng(12345).integers(1, 2**63 - 1, size=grid.A.shape[0], dtype=np.uint64)
    At = grid.A.T.tocsr()
    sig = np.zeros(At.shape[0], dtype=np.uint64)
    rows = np.repeat(np.arange(At.shape[0]), np.diff(At.indptr))
    with np.errstate(over="ignore"):
        np.add.at(sig, rows, keys[At.indices])
    _, labels = np.unique(sig, return_inverse=True)
    labels = labels.ravel()
    k = int(labels.max()) + 1 if labels.size else 0
    weights = np.bincount(labels, weights=grid.weights, minlength=k)
    first = np.zeros(k, dtype=np.int64)
    first[labels[::-1]] = np.arange(At.shape[0])[::-1]
    B = grid.A[:, first].tocsr()
    return B, weights


def select_milp(grid: CoverageGrid, target: float, max_overlap: float = 1.0, time_limit: float = 60.0) -> Selection:
    """The fewest images reaching ``target`` coverage under the pairwise overlap cap, as an integer program.

    Variables: ``x_i`` (image i taken, binary) and ``y_a`` (region a covered, 0..1).
    Minimise sum x  s.t.  y_a <= sum_{i sees a} x_i;  sum w_a y_a >= target * area;  x_i + x_j <= 1 for pairs
    overlapping more than ``max_overlap``. Solved with scipy's HiGHS (``scipy.optimize.milp``).
    """
    from scipy.optimize import Bounds, LinearConstraint, milp

    t0 = time.perf_counter()
    B, wa = cell_atoms(grid)
    seen = np.asarray(B.sum(axis=0)).ravel() > 0
    B, wa = B[:, seen], wa[seen]
    n, k = B.shape
    wa = wa / grid.total  # shares of the area: keeps the coverage row well scaled for the solver
    need = min(target, reachable_coverage(grid)) * (1 - 1e-7)
    # y_a - sum_i B[i, a] x_i <= 0
    link = sparse.hstack([-B.T.astype(float), sparse.identity(k, format="csr")]).tocsr()
    cons = [LinearConstraint(link, -np.inf, 0.0),
            LinearConstraint(sparse.hstack([sparse.csr_matrix((1, n)), sparse.csr_matrix(wa[None, :])]), need, np.inf)]
    relaxed = False
    if max_overlap < 1.0:
        frac = sparse.triu(grid.overlap_fraction(), k=1).tocoo()
        bad = frac.data > max_overlap + 1e-9
        if bad.any():
            rows = np.repeat(np.arange(int(bad.sum())), 2)
            colidx = np.stack([frac.row[bad], frac.col[bad]], 1).ravel()
            pairs = sparse.csr_matrix((np.ones(rows.size), (rows, colidx)), shape=(int(bad.sum()), n + k))
            cons.append(LinearConstraint(pairs, -np.inf, 1.0))
    c = np.concatenate([np.ones(n), np.zeros(k)])
    integrality = np.concatenate([np.ones(n), np.zeros(k)])
    bounds = Bounds(np.zeros(n + k), np.ones(n + k))
    res = milp(c, constraints=cons, integrality=integrality, bounds=bounds,
               options={"time_limit": time_limit, "disp": False})
    if res.x is None and len(cons) > 2:
        log.warning("no selection satisfies max_overlap; solving again without the overlap cap")
        relaxed = True
        res = milp(c, constraints=cons[:2], integrality=integrality, bounds=bounds,
                   options={"time_limit": time_limit, "disp": False})
    if res.x is None:
        raise InputError(f"the integer program found no selection ({res.message})",
                         fix="use method: greedy, or raise milp_time_limit")
    chosen = [int(i) for i in np.flatnonzero(res.x[:n] > 0.5)]
    # order as a greedy pass would (largest new area first) so the CSV reads naturally
    chosen = _order_by_gain(grid, chosen)
    return Selection(indices=chosen, coverage=grid.coverage(chosen), target=target, method="milp", relaxed=relaxed,
                     optimal=res.status == 0, seconds=time.perf_counter() - t0)


def _order_by_gain(grid: CoverageGrid, chosen: Sequence[int]) -> list[int]:
    left = list(chosen)
    covered = np.zeros(grid.A.shape[1], dtype=bool)
    out = []
    while left:
        gains = [grid.weights[grid.A[i].indices[~covered[grid.A[i].indices]]].sum() for i in left]
        i = left.pop(int(np.argmax(gains)))
        out.append(i)
        covered[grid.A[i].indices] = True
    return out


# --------------------------------------------------------------------------------------------------
# owned areas


def owned_areas(aoi, polygons: Sequence[Polygon], min_area: float = 1e-6) -> list[Polygon | MultiPolygon]:
    """Split the covered AOI among the selected footprints: each point goes to exactly one image.

    First every image gets the part of its footprint nearer its own centre than any other selected centre
    (a Voronoi partition); what is left (seen, but not by the nearest image) goes piece by piece to the
    image that sees most of the piece.
    """
    if not polygons:
        return []
    fps = [shapely.make_valid(p.intersection(aoi)) for p in polygons]
    centres = shapely.MultiPoint([p.centroid for p in polygons])
    owned = [shapely.Polygon() for _ in polygons]
    if len(polygons) == 1:
        owned = [fps[0]]
    else:
        extent = box(*shapely.union_all([aoi, *polygons]).bounds).buffer(1.0)
        cells = shapely.voronoi_polygons(centres, extend_to=extent)
        by_site = {}
        for cell in cells.geoms:
            for j, p in enumerate(polygons):
                if j not in by_site and cell.contains(p.centroid):
                    by_site[j] = cell
                    break
        for j, fp in enumerate(fps):
            if j in by_site:
                owned[j] = fp.intersection(by_site[j])
    covered = shapely.union_all(fps)
    left = covered.difference(shapely.union_all(owned))
    pieces = [g for g in getattr(left, "geoms", [left]) if g.area > min_area]
    guard = 0
    while pieces and guard < 10_000:
        guard += 1
        piece = pieces.pop()
        shares = [fp.intersection(piece).area for fp in fps]
        j = int(np.argmax(shares))
        if shares[j] <= min_area:
            continue
        part = fps[j].intersection(piece)
        owned[j] = owned[j].union(part)
        rest = piece.difference(part)
        pieces += [g for g in getattr(rest, "geoms", [rest]) if g.area > min_area]
    return [polygonal(o) for o in owned]


def polygonal(geom):
    """Only the areas of a geometry: overlays can leave zero-area lines or points in a collection."""
    geom = shapely.make_valid(geom)
    parts = [g for g in shapely.get_parts(geom) if isinstance(g, (Polygon, MultiPolygon)) and g.area > 0]
    if not parts:
        return Polygon()
    return parts[0] if len(parts) == 1 else shapely.union_all(parts)


def largest_polygon(geom) -> Polygon:
    if isinstance(geom, Polygon):
        return geom
    parts = [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]
    return max(parts, key=lambda g: g.area) if parts else Polygon()


def polygon_to_pixels(poly: Polygon, shot: Shot, frame: Frame, surface: Surface, step: float) -> np.ndarray:
    """A ground polygon's outline in an image's pixels: densified, lifted onto the DSM, projected, clipped."""
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


# --------------------------------------------------------------------------------------------------
# the whole analysis (the CLI and the GUI share it)


@dataclass
class Result:
    selection: Selection
    footprints: list[Footprint]
    owned: dict[str, Polygon | MultiPolygon]   # shot id -> owned ground area
    owned_pixels: dict[str, np.ndarray]        # shot id -> (N, 2) pixels in its undistorted image
    exact_coverage: float                      # union of the selected footprints / AOI area (polygons)
    uncovered: Polygon | MultiPolygon

    @property
    def selected(self) -> list[Footprint]:
        return [self.footprints[i] for i in self.selection.indices]


class MinImageFinder:
    """Loads a project once (footprints, AOI, grid); selects, evaluates and saves many times (GUI)."""

    def __init__(self, cfg: MinImagesConfig):
        self.cfg = cfg
        t0 = time.perf_counter()
        self.project = ODMProject(cfg.project_dir)
        self.project.require("undistorted_reconstruction", "undistorted_images", "dsm")
        self.frame = self.project.frame()
        self.surface = open_dsm(self.project.path("dsm"), cfg.dsm_resolution)
        if self.surface.crs is not None and getattr(self.frame, "crs", None) is not None \
                and not _same_crs(self.surface.crs, self.frame.crs):
            raise InputError(f"the DSM's CRS ({self.surface.crs}) differs from the reconstruction's "
                             f"({self.frame.crs.to_string()})", path=self.project.path("dsm"),
                             fix="use the DSM of this ODM run, or reproject it to the reconstruction's CRS")
        self.preview = None
        if self.project.has("orthophoto"):
            self.preview = orthophoto_preview(self.project.path("orthophoto"), cfg.preview_size)
        if cfg.aoi_file is not None:
            self.aoi = read_aoi_file(Path(cfg.aoi_file), self.frame.crs)
        elif self.preview is not None:
            self.aoi = aoi_from_mask(self.preview[1], self.preview[2])
        else:
            raise InputError("no area of interest: the orthophoto is missing and no aoi_file is set",
                             path=self.project.path("orthophoto"),
                             fix="set aoi_file to a polygon file, or run ODM with the orthophoto step")
        self.footprints = compute_footprints(self.project, self.frame, self.surface, cfg.border_samples)
        self.footprint_seconds = time.perf_counter() - t0
        self.grid = build_grid(self.aoi, [f.polygon for f in self.footprints], cfg.cell_size)
        log.info("%d footprints on the DSM; area of interest %.1f m^2 in %d cells of %.3f m",
                 len(self.footprints), self.aoi.area, self.grid.A.shape[1], self.grid.cell)

    @property
    def names(self) -> list[str]:
        return [f.name for f in self.footprints]

    def select(self) -> Selection:
        cfg = self.cfg
        target = 1.0 - cfg.uncovered_threshold / 100.0
        reach = reachable_coverage(self.grid)
        if reach < target - 1e-9:
            log.warning("all images together cover only %.1f%% of the area; selecting for that", 100 * reach)
        if cfg.method == "milp":
            sel = select_milp(self.grid, target, cfg.max_overlap / 100.0, cfg.milp_time_limit)
        else:
            sel = select_greedy(self.grid, target, cfg.max_overlap / 100.0, cfg.overlap_penalty)
        # the grid approximates the AOI: add images until the exact (polygon) coverage reaches the target too
        goal = min(target, reach)
        for _ in range(len(self.footprints)):
            if self.exact_coverage(sel.indices) >= goal - 1e-6:
                break
            extra = self._best_addition(sel.indices)
            if extra is None:
                break
            sel.indices.append(extra)
            sel.coverage = self.grid.coverage(sel.indices)
        if sel.relaxed:
            log.warning("max_overlap %.0f%% could not reach the coverage; some selected images overlap more",
                        cfg.max_overlap)
        return sel

    def _best_addition(self, chosen: Sequence[int]) -> int | None:
        covered = np.asarray(self.grid.A[list(chosen)].sum(axis=0)).ravel() > 0 if chosen else \
            np.zeros(self.grid.A.shape[1], bool)
        gain = self.grid.A.astype(float) @ np.where(covered, 0.0, self.grid.weights)
        gain[list(chosen)] = -1
        return int(np.argmax(gain)) if gain.max() > 0 else None

    def exact_coverage(self, indices: Sequence[int]) -> float:
        if not indices:
            return 0.0
        union = shapely.union_all([self.footprints[i].polygon for i in indices])
        return float(union.intersection(self.aoi).area / self.aoi.area)

    def evaluate(self, selection: Selection) -> Result:
        """Owned areas (map and pixels), exact coverage and the uncovered area of a selection."""
        chosen = [self.footprints[i] for i in selection.indices]
        owned = owned_areas(self.aoi, [f.polygon for f in chosen])
        step = max(self.grid.cell, self.surface.pixel_size)
        pix = {}
        for fp, area in zip(chosen, owned):
            main = largest_polygon(area)
            if area.area - main.area > 0.01 * max(area.area, 1e-9):
                log.warning("%s owns %d separate pieces; owned_areas.json holds its largest", fp.name,
                            len(getattr(area, "geoms", [area])))
            pix[fp.name] = polygon_to_pixels(main, fp.shot, self.frame, self.surface, step)
        union = shapely.union_all([f.polygon for f in chosen]) if chosen else Polygon()
        uncovered = self.aoi.difference(union)
        exact = float(self.aoi.intersection(union).area / self.aoi.area) if chosen else 0.0
        return Result(selection=selection, footprints=self.footprints,
                      owned={f.name: a for f, a in zip(chosen, owned)}, owned_pixels=pix, exact_coverage=exact,
                      uncovered=uncovered)

    def with_indices(self, indices: Sequence[int], method: str = "manual") -> Selection:
        target = 1.0 - self.cfg.uncovered_threshold / 100.0
        return Selection(indices=list(indices), coverage=self.grid.coverage(indices), target=target, method=method)


def _same_crs(a, b) -> bool:
    from pyproj import CRS

    try:
        return CRS.from_user_input(a) == CRS.from_user_input(b)
    except Exception:  # noqa: BLE001 - undecidable: do not block the run
        return True


# --------------------------------------------------------------------------------------------------
# outputs


def write_outputs(finder: MinImageFinder, result: Result, output_dir: Path | None = None) -> dict[str, Path]:
    """Write the CSV, images, figure, GeoPackage, owned-area JSON and summary; return their paths."""
    cfg = finder.cfg
    out = Path(output_dir or cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    sel = result.selected
    frac = finder.grid.overlap_fraction()
    idx = result.selection.indices
    # copies first, so the CSV and JSON name files that exist
    if cfg.copy_images != "none":
        folder = out / "images"
        folder.mkdir(exist_ok=True)
        for fp in progress(sel, desc=f"{cfg.copy_images} images", unit="image"):
            place_image(fp.file, folder / fp.file.name, cfg.copy_images)
        paths["images"] = folder
    covered = np.zeros(finder.grid.A.shape[1], bool)
    with atomic_open(out / "selected_images.csv", "w") as fh:
        wr = csv.writer(fh)
        wr.writerow(["order", "image", "file", "footprint_area_m2", "owned_area_m2", "new_area_m2",
                     "cumulative_coverage_pct", "centroid_x", "centroid_y", "max_overlap_pct"])
        for k, (i, fp) in enumerate(zip(idx, sel), start=1):
            cells = finder.grid.A[i].indices
            new = float(finder.grid.weights[cells[~covered[cells]]].sum())
            covered[cells] = True
            row = frac[i]
            others = [row[0, j] for j in idx if j != i]
            cx, cy = fp.centroid
            wr.writerow([k, fp.name, fp.file.name, f"{fp.polygon.intersection(finder.aoi).area:.4f}",
                         f"{result.owned[fp.name].area:.4f}", f"{new:.4f}",
                         f"{100 * finder.grid.weights[covered].sum() / finder.grid.total:.3f}",
                         f"{cx:.3f}", f"{cy:.3f}", f"{100 * max(others, default=0.0):.2f}"])
    paths["csv"] = out / "selected_images.csv"
    write_owned_areas(out / "owned_areas.json", {fp.file.name: result.owned_pixels[fp.name] for fp in sel})
    paths["owned_areas"] = out / "owned_areas.json"
    paths["gpkg"] = write_geopackage(finder, result, out / "footprints.gpkg")
    paths["figure"] = coverage_figure(finder, result, out / "coverage.png")
    s = result.selection
    write_json(out / "selection.json", {
        "project_dir": str(cfg.project_dir), "images_total": len(finder.footprints), "images_selected": len(idx),
        "selected": [fp.name for fp in sel], "method": s.method, "optimal": s.optimal,
        "overlap_cap_relaxed": s.relaxed, "requested_coverage_pct": 100 * s.target,
        "coverage_pct": 100 * result.exact_coverage, "grid_coverage_pct": 100 * s.coverage,
        "aoi_area_m2": finder.aoi.area, "cell_size_m": finder.grid.cell, "crs": finder.frame.crs.to_string(),
        "settings": {k: getattr(cfg, k) for k in ("uncovered_threshold", "max_overlap", "overlap_penalty",
                                                   "border_samples", "dsm_resolution")},
        "selection_seconds": round(s.seconds, 4), "footprint_seconds": round(finder.footprint_seconds, 3)})
    paths["summary"] = out / "selection.json"
    return paths


def place_image(src: Path, dst: Path, mode: str) -> None:
    """Copy or hard-link an image into place (a hard link falls back to a copy across drives)."""
    if dst.exists() and dst.stat().st_size == src.stat().st_size and mode == "link" and os.path.samefile(src, dst):
        return
    if mode == "link":
        tmp = dst.with_name(f".{dst.name}.link")
        try:
            if tmp.exists():
                tmp.unlink()
            os.link(src, tmp)
            os.replace(tmp, dst)
            return
        except OSError:
            log.debug("hard link failed for %s; copying", src)
    with atomic_path(dst) as tmp:
        shutil.copy2(src, tmp)


def write_geopackage(finder: MinImageFinder, result: Result, path: Path) -> Path:
    import geopandas as gpd

    crs = finder.frame.crs
    order = {i: k for k, i in enumerate(result.selection.indices, start=1)}
    fps = gpd.GeoDataFrame({"image": finder.names,
                            "selected": [i in order for i in range(len(finder.footprints))],
                            "order": [order.get(i, 0) for i in range(len(finder.footprints))],
                            "area_m2": [f.polygon.area for f in finder.footprints]},
                           geometry=[f.polygon for f in finder.footprints], crs=crs)
    sel = result.selected
    owned = gpd.GeoDataFrame({"image": [f.name for f in sel], "file": [f.file.name for f in sel],
                              "order": list(range(1, len(sel) + 1)),
                              "area_m2": [result.owned[f.name].area for f in sel]},
                             geometry=[_multi(result.owned[f.name]) for f in sel], crs=crs)
    aoi = gpd.GeoDataFrame({"area_m2": [finder.aoi.area]}, geometry=[_multi(finder.aoi)], crs=crs)
    unc = gpd.GeoDataFrame({"area_m2": [result.uncovered.area]}, geometry=[_multi(result.uncovered)], crs=crs)
    with atomic_path(path) as tmp:
        for name, gdf in (("footprints", fps), ("owned", owned), ("aoi", aoi), ("uncovered", unc)):
            gdf.to_file(tmp, layer=name, driver="GPKG")
    return path


def _multi(geom):
    """Polygon or MultiPolygon only (GeoPackage layers want one geometry type)."""
    polys = [g for g in shapely.get_parts(geom) if isinstance(g, Polygon) and not g.is_empty]
    return MultiPolygon(polys) if polys else MultiPolygon()


def draw_coverage(ax, finder: MinImageFinder, result: Result, *, numbers: bool = True) -> None:
    """The coverage map: orthophoto, AOI, every footprint (grey), selected ones numbered with their owned
    areas, uncovered areas in red. Used by the figure and the GUI."""
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MPath

    ax.clear()
    if finder.preview is not None:
        rgb, mask, t, _ = finder.preview
        h, w = mask.shape
        ext = (t.c, t.c + w * t.a, t.f + h * t.e, t.f)
        ax.imshow(np.dstack([rgb, (mask * 255).astype(np.uint8)]), extent=ext, interpolation="nearest")
    for f in finder.footprints:
        x, y = f.polygon.exterior.xy
        ax.plot(x, y, color="0.55", lw=0.5, alpha=0.6)
    colors = _palette(len(result.selected))
    for k, fp in enumerate(result.selected):
        area = result.owned[fp.name]
        for part in shapely.get_parts(area):
            if isinstance(part, Polygon) and not part.is_empty:
                ax.add_patch(PathPatch(_mpl_path(part, MPath), facecolor=colors[k], alpha=0.28, lw=0))
        x, y = fp.polygon.exterior.xy
        ax.plot(x, y, color=colors[k], lw=1.6)
        if numbers:
            cx, cy = fp.centroid
            ax.text(cx, cy, str(k + 1), ha="center", va="center", fontsize=10, weight="bold", color="black",
                    bbox=dict(boxstyle="circle,pad=0.2", fc="white", ec=colors[k], alpha=0.85))
    for part in shapely.get_parts(result.uncovered):
        if isinstance(part, Polygon) and part.area > 0:
            ax.add_patch(PathPatch(_mpl_path(part, MPath), facecolor="red", alpha=0.45, lw=0, hatch="//"))
    for part in shapely.get_parts(finder.aoi):
        if isinstance(part, Polygon):
            x, y = part.exterior.xy
            ax.plot(x, y, color="yellow", lw=1.2, ls="--")
    xmin, ymin, xmax, ymax = shapely.union_all([finder.aoi] + [f.polygon for f in finder.footprints]).bounds
    pad = 0.03 * max(xmax - xmin, ymax - ymin)
    ax.set_xlim(xmin - pad, xmax + pad)
    ax.set_ylim(ymin - pad, ymax + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    s = result.selection
    ax.set_title(f"{len(s.indices)} of {len(finder.footprints)} images cover {100 * result.exact_coverage:.1f}% "
                 f"of the area (asked {100 * s.target:.0f}%)", fontsize=11)
    ax.ticklabel_format(useOffset=False, style="plain")


def _mpl_path(poly: Polygon, MPath):
    verts, codes = [], []
    for ring in [poly.exterior, *poly.interiors]:
        xy = np.asarray(ring.coords)[:, :2]
        verts.append(xy)
        codes += [MPath.MOVETO] + [MPath.LINETO] * (len(xy) - 2) + [MPath.CLOSEPOLY]
    return MPath(np.concatenate(verts), codes)


def _palette(n: int):
    import matplotlib

    cmap = matplotlib.colormaps["tab20"]
    return [cmap(i % 20) for i in range(n)]


def coverage_figure(finder: MinImageFinder, result: Result, path: Path) -> Path:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 8), dpi=110)
    ax = fig.add_subplot(111)
    draw_coverage(ax, finder, result)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


# --------------------------------------------------------------------------------------------------
# the module


def run(cfg: MinImagesConfig) -> Result:
    finder = MinImageFinder(cfg)
    selection = finder.select()
    result = finder.evaluate(selection)
    paths = write_outputs(finder, result)
    log.info("selected %d of %d images (%s, %.3f s) covering %.1f%% of the area; outputs in %s",
             len(selection.indices), len(finder.footprints), selection.method, selection.seconds,
             100 * result.exact_coverage, paths["csv"].parent)
    return result
