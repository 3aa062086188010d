"""``detect.cover``: detect only on the fewest photos that see every point of the field at least ``k`` times.

A survey flown at 80-85 % overlap sees each plant in 20-50 photos; module 8 needs a few views of a plant to place
it, not all of them, and detection on a CPU costs hours per hundred photos. The cover is chosen from the photos'
footprints on the DSM (:func:`matchplant.core.formats.footprints.compute_footprints`, the ones module 3 draws):

1. the field is sampled by points on a regular grid over the union of the footprints (``POINTS_ACROSS`` points
   across the narrowest footprint, so a gap between chosen photos is smaller than a thirtieth of a photo);
2. each point must be seen ``min(k, n)`` times, ``n`` being how many photos see it at all (a point at the edge of
   the flight seen by one photo needs that photo);
3. greedy multi-cover: the photo meeting the most unmet demand is taken, until every demand is met (the set-cover
   greedy, generalised to demands above one; within a factor ln(points) of the fewest photos); then photos the
   demand no longer needs are dropped, the least useful first.

Module 3 answers another question (the fewest images to *label* each plant once, with an overlap cap); this is
its k-fold version without the cap, kept here because steps do not import each other (docs/DESIGN.md §1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse

from matchplant.core.formats.footprints import Footprint, compute_footprints, open_dsm
from matchplant.core.formats.odm import SUBMODELS_DIR, ODMProject
from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.log import get_logger
from matchplant.model_test.inputs import check_images, list_images

log = get_logger("model_test")

POINTS_ACROSS = 30  # grid points across the narrowest footprint's short side
MAX_POINTS = 2_000_000
DSM_RESOLUTION = 0.05  # m: footprints need the relief at the scale of a photo's border sampling (as module 3)


@dataclass
class Cover:
    """The chosen photos and what they cost against all photos."""

    files: list[Path]  # the photos to detect on, in the order of detect.images
    every: list[Path]  # every photo of detect.images
    k: int
    points: int  # field points sampled
    short: int  # points seen by fewer than k chosen photos because fewer than k photos see them at all


def is_project(path: Path | None) -> bool:
    """Whether ``path`` is an ODM project folder (``opensfm/``, or the submodels of a split-merge project)."""
    p = Path(path) if path is not None else None
    return p is not None and ((p / "opensfm").is_dir() or (p / SUBMODELS_DIR).is_dir())


def cover_project(images: Path | None, project_dir: Path | None) -> Path:
    """The ODM project whose footprints choose the cover: ``detect.project_dir``, else ``detect.images`` when it
    is a project folder; a ConfigError before any work otherwise."""
    if project_dir is not None:
        return Path(project_dir)
    if is_project(images):
        return Path(images)
    raise ConfigError(
        "detect.cover needs the photos' footprints, from an ODM project, but detect.project_dir is not set and "
        f"detect.images ({images}) is not an ODM project folder",
        fix="set detect.project_dir to the ODM project the photos come from (the folder holding opensfm/ and "
        "odm_dem/dsm.tif), or detect.cover: 0 to detect on every photo",
    )


def footprints(project_dir: Path) -> list[Footprint]:
    """Every undistorted photo's footprint on the project's DSM (the same ones module 3 computes)."""
    project = ODMProject(project_dir)
    project.require("undistorted_reconstruction", "undistorted_images", "dsm")
    surface = open_dsm(project.path("dsm"), DSM_RESOLUTION)
    return compute_footprints(project, project.frame(), surface)


def incidence(polygons: list, points_across: int = POINTS_ACROSS) -> sparse.csr_matrix:
    """``A[i, p]``: polygon ``i`` holds grid point ``p`` (points over the polygons' union, only those inside one)."""
    import shapely  # lazy: GIS, only for a cover (module 7 detects on every photo without it)

    sides = []
    for poly in polygons:
        rect = poly.minimum_rotated_rectangle
        xy = np.asarray(rect.exterior.coords)
        sides.append(min(np.hypot(*(xy[1] - xy[0])), np.hypot(*(xy[2] - xy[1]))))
    x0, y0, x1, y1 = shapely.union_all(polygons).bounds
    # at most MAX_POINTS over the bounds: an oblique photo's footprint can reach far past the field
    step = max(min(sides) / points_across, np.sqrt((x1 - x0) * (y1 - y0) / MAX_POINTS), 1e-6)
    gx, gy = np.meshgrid(np.arange(x0 + step / 2, x1, step), np.arange(y0 + step / 2, y1, step))
    gx, gy = gx.ravel(), gy.ravel()
    rows, cols = [], []
    for i, poly in enumerate(polygons):
        bx0, by0, bx1, by1 = poly.bounds
        near = np.flatnonzero((gx >= bx0) & (gx <= bx1) & (gy >= by0) & (gy <= by1))
        inside = near[shapely.contains_xy(poly, gx[near], gy[near])]
        rows.append(np.full(inside.size, i))
        cols.append(inside)
    r, c = np.concatenate(rows), np.concatenate(cols)
    A = sparse.csr_matrix((np.ones(r.size, bool), (r, c)), shape=(len(polygons), gx.size))
    seen = np.asarray(A.sum(axis=0)).ravel() > 0
    return A[:, seen].tocsr()


def multi_cover(A: sparse.csr_matrix, k: int) -> list[int]:
    """The rows of ``A`` (photos) chosen so that every column (point) is held by ``min(k, its count)`` of them:
    greedy on unmet demand, then pruned. Pure arrays, checked against brute force in the tests."""
    n = A.shape[0]
    Af = A.astype(np.float64).tocsr()
    rows = [A.indices[A.indptr[i] : A.indptr[i + 1]] for i in range(n)]
    demand = np.minimum(k, np.asarray(A.sum(axis=0)).ravel()).astype(np.int64)
    unmet = demand.copy()
    chosen: list[int] = []
    taken = np.zeros(n, bool)
    while unmet.any():
        gain = Af @ (unmet > 0)
        gain[taken] = -1
        i = int(np.argmax(gain))
        chosen.append(i)
        taken[i] = True
        unmet[rows[i]] = np.maximum(unmet[rows[i]] - 1, 0)
    count = np.zeros(A.shape[1], np.int64)
    for i in chosen:
        count[rows[i]] += 1
    # prune: a photo whose every point keeps its demand without it goes, the last taken (least useful) first
    for i in chosen[::-1]:
        if (count[rows[i]] > demand[rows[i]]).all():
            count[rows[i]] -= 1
            chosen.remove(i)
    return sorted(chosen)


def choose(files: list[Path], k: int, project_dir: Path) -> Cover:
    """The photos of ``files`` that see every point of the field at least ``k`` times (see the module's text).
    A photo of ``files`` that the project does not place (no footprint) is kept, with a warning."""
    fps = footprints(project_dir)
    by_name = {}
    for f in files:  # undistorted photos are <shot>.tif; a folder of them or the project's own files
        by_name.setdefault(f.name, f)
        by_name.setdefault(Path(f.name).stem, f)
    placed = [fp for fp in fps if fp.file.name in by_name or fp.name in by_name]
    file_of = [by_name.get(fp.file.name) or by_name[fp.name] for fp in placed]
    if not placed:
        raise ConfigError(
            f"none of the {len(files)} photo(s) of detect.images is a photo of the ODM project {project_dir}",
            fix="set detect.project_dir to the project these photos come from, or detect.cover: 0",
        )
    A = incidence([fp.polygon for fp in placed])
    picked = {file_of[i] for i in multi_cover(A, k)}
    placed_files = set(file_of)
    unplaced = [f for f in files if f not in placed_files]
    if unplaced:
        log.warning(
            "%d photo(s) of detect.images have no footprint in %s (e.g. %s): detected all the same",
            len(unplaced),
            project_dir,
            unplaced[0].name,
        )
    chosen = [f for f in files if f in picked or f in unplaced]
    seen = np.asarray(A[[file_of.index(f) for f in chosen if f in picked]].sum(axis=0)).ravel()
    short = int((seen < k).sum())
    log.info(
        "detect.cover: %d: %d of %d photos see every point of the field at least %d time(s) (%d points sampled; "
        "%d at the flight's edge are seen by fewer photos in all, and by every one of those)",
        k,
        len(chosen),
        len(files),
        k,
        A.shape[1],
        short,
    )
    return Cover(files=chosen, every=list(files), k=k, points=A.shape[1], short=short)


def images_to_detect(dcfg) -> tuple[list[Path], list[Path]]:
    """The photos to detect on (the cover's when ``detect.cover`` is set), each checked whole (broken files named
    before any detection), and every photo of ``detect.images`` (``dcfg``: the ``detect`` section)."""
    every = list_images(Path(dcfg.images))
    files = choose(every, dcfg.cover, cover_project(dcfg.images, dcfg.project_dir)).files if dcfg.cover else every
    check_images(files, dcfg.tile_size)
    return files, every
