"""Weighted set cover with a pairwise overlap cap: which images to keep so the field stays covered.

Pure arithmetic on a sparse incidence matrix (``A[i, c]``: image i sees cell c) and cell weights, with no
notion of cameras, DSMs or polygons, so the solver can be checked against brute force on hand-made arrays
(``tests/test_min_img_finder.py``) and reused for any "fewest sets covering a weighted universe" question.
The grid is built from the footprints in :mod:`matchplant.min_img_finder.aoi`.

Two solvers share one problem: :func:`select_greedy` (greedy with an overlap penalty, started from several
images, then pruned and improved by local swaps; any size) and :func:`select_milp` (the exact integer
program, scipy's HiGHS, for small flights and for measuring how far greedy is from the optimum).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, milp

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("min_img_finder")


@dataclass
class CoverageGrid:
    """AOI cells (centres inside the AOI) and which image sees each: ``A[i, c]`` is True when image i covers c."""

    x: np.ndarray  # (m,) cell centres
    y: np.ndarray
    cell: float  # cell side, m
    A: sparse.csr_matrix  # (n_images, m) bool
    weights: np.ndarray  # (m,) area of each cell, m^2

    @property
    def total(self) -> float:
        """Area of the AOI's cells, m^2."""
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
        """Fraction of the cells' area that the ``selected`` images cover."""
        if len(selected) == 0:
            return 0.0
        covered = np.asarray(self.A[list(selected)].sum(axis=0)).ravel() > 0
        return float(self.weights[covered].sum() / self.total)


@dataclass
class Selection:
    """What a solver chose, and what a report must say about it (relaxed cap, proven optimum)."""

    indices: list[int]  # into the footprint list, in order of selection
    coverage: float  # share of the AOI covered (grid)
    target: float  # the requested share
    method: str
    relaxed: bool = False  # the overlap cap had to be relaxed
    optimal: bool | None = None  # milp: proven optimal
    seconds: float = 0.0
    gains: list[float] = field(default_factory=list)  # new area each image added, m^2 (greedy order)


def reachable_coverage(grid: CoverageGrid) -> float:
    """Fraction of the cells' area that all images together cover: the most any selection can reach."""
    covered = np.asarray(grid.A.sum(axis=0)).ravel() > 0
    return float(grid.weights[covered].sum() / grid.total)


def select_greedy(
    grid: CoverageGrid,
    target: float,
    max_overlap: float = 1.0,
    overlap_penalty: float = 0.2,
    restarts: bool = True,
    all_starts_below: int = 150,
) -> Selection:
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
    return Selection(
        indices=chosen,
        coverage=grid.coverage(chosen),
        target=target,
        method="greedy",
        relaxed=relaxed,
        seconds=time.perf_counter() - t0,
        gains=gains,
    )


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
        imgs = At.indices[At.indptr[c] : At.indptr[c + 1]]
        out.append(int(imgs[np.argmax(area[imgs])]))
    return out


class _Cover:
    """Fast coverage arithmetic for the local searches: each image's cells as an index array."""

    def __init__(self, grid: CoverageGrid):
        self.A = grid.A.astype(float).tocsr()
        self.w = grid.weights
        ptr, idx = self.A.indptr, self.A.indices
        self.rows = [idx[ptr[i] : ptr[i + 1]] for i in range(self.A.shape[0])]

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


def _greedy_run(
    cov: _Cover, need: float, frac, max_overlap: float, overlap_penalty: float, first: int | None
) -> tuple[list[int], list[float], bool]:
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
            bad = cov.blocked(frac, chosen[:pos] + chosen[pos + 1 :], max_overlap)
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
    t0 = time.perf_counter()
    B, wa = cell_atoms(grid)
    seen = np.asarray(B.sum(axis=0)).ravel() > 0
    B, wa = B[:, seen], wa[seen]
    n, k = B.shape
    wa = wa / grid.total  # shares of the area: keeps the coverage row well scaled for the solver
    need = min(target, reachable_coverage(grid)) * (1 - 1e-7)
    # y_a - sum_i B[i, a] x_i <= 0
    link = sparse.hstack([-B.T.astype(float), sparse.identity(k, format="csr")]).tocsr()
    cons = [
        LinearConstraint(link, -np.inf, 0.0),
        LinearConstraint(sparse.hstack([sparse.csr_matrix((1, n)), sparse.csr_matrix(wa[None, :])]), need, np.inf),
    ]
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
    res = milp(
        c, constraints=cons, integrality=integrality, bounds=bounds, options={"time_limit": time_limit, "disp": False}
    )
    if res.x is None and len(cons) > 2:
        log.warning("no selection satisfies max_overlap; solving again without the overlap cap")
        relaxed = True
        res = milp(
            c,
            constraints=cons[:2],
            integrality=integrality,
            bounds=bounds,
            options={"time_limit": time_limit, "disp": False},
        )
    if res.x is None:
        raise InputError(
            f"the integer program found no selection ({res.message})",
            fix="use method: greedy, or raise milp_time_limit",
        )
    chosen = [int(i) for i in np.flatnonzero(res.x[:n] > 0.5)]
    # order as a greedy pass would (largest new area first) so the CSV reads naturally
    chosen = _order_by_gain(grid, chosen)
    return Selection(
        indices=chosen,
        coverage=grid.coverage(chosen),
        target=target,
        method="milp",
        relaxed=relaxed,
        optimal=res.status == 0,
        seconds=time.perf_counter() - t0,
    )


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
