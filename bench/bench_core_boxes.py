"""Overlapping box pairs (``matchplant.core.geometry.boxes.overlapping_pairs``, module 8's merge) against shapely's
STRtree.

    NUMBA_NUM_THREADS=1 taskset -c 1 python -m bench.bench_core_boxes           # 21,000 plants x 25 views
    NUMBA_NUM_THREADS=1 taskset -c 1 python -m bench.bench_core_boxes --quick   # 2,000 plants x 25 views
    NUMBA_NUM_THREADS=1 taskset -c 1 python -m bench.bench_core_boxes --unordered   # ours without the (i, j) sort

The boxes are shaped like the views of the large synthetic field: plants on a grid 0.3 m apart at UTM
coordinates, 0.1-0.4 m across, each seen 25 times with a jitter of 3 cm and 10 % in size, in random order
(a views table is ordered by photo, not by plant). The peer is the shapely version MatchPlant used before
(shapely boxes, one bulk STRtree query, IoU of the candidates; :func:`shapely_pairs`). Both run in turn on
one core (``bench.harness.alternate``: a warm-up pair, then ``--pairs`` timed pairs); the speed ratio is
the peer's time over ours, pair by pair (median, min, max), and both outputs are compared (same pairs,
largest IoU difference). Each side reports its CPU time (user and system, page faults included; one
thread each), so that waiting for a shared core does not count. ``python -m bench --only box-pairs`` runs
the same comparison in the harness.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # bench.harness, when run as a script

import numpy as np  # noqa: E402
import shapely  # noqa: E402

from bench.harness import Comparison, alternate, pin_one_core, ratio_text, summarise  # noqa: E402
from matchplant.core.geometry.boxes import iou_pairs, overlapping_pairs  # noqa: E402

SPACING = 0.3  # metres between plants
VIEWS = 25  # views per plant
JITTER = 0.03  # metres: each view's centre within this of the plant's
SIZE = (0.1, 0.4)  # metres: plant box sides
ORIGIN = (500000.0, 4000000.0)  # UTM-sized coordinates


def field_boxes(plants: int, views: int = VIEWS, seed: int = 0) -> np.ndarray:
    """``plants * views`` map boxes (N, 4) of plants on a square grid, in random order."""
    rng = np.random.default_rng(seed)
    cols = int(np.ceil(np.sqrt(plants)))
    k = np.arange(plants)
    centre = np.column_stack([ORIGIN[0] + SPACING * (k % cols), ORIGIN[1] + SPACING * (k // cols)])
    size = rng.uniform(*SIZE, (plants, 1))
    c = np.repeat(centre, views, axis=0) + rng.uniform(-JITTER, JITTER, (plants * views, 2))
    half = np.repeat(size, views, axis=0) * rng.uniform(0.9, 1.1, (plants * views, 2)) / 2
    return np.hstack([c - half, c + half])[rng.permutation(plants * views)]


def shapely_pairs(a: np.ndarray, b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The former implementation: shapely boxes, one bulk STRtree query, the IoU of the candidates."""
    same = b is None
    b = a if same else b
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    gb = shapely.box(b[:, 0], b[:, 1], b[:, 2], b[:, 3])
    i, j = shapely.STRtree(gb).query(gb if same else shapely.box(a[:, 0], a[:, 1], a[:, 2], a[:, 3]))
    if same:
        keep = i < j
        i, j = i[keep], j[keep]
    iou = iou_pairs(a[i], b[j])
    keep = iou > 0
    return i[keep], j[keep], iou[keep]


def agreement(ours: tuple, peer: tuple, ordered: bool = True) -> dict:
    """Same pairs (peer's put in (i, j) order, and ours when not ``ordered``), ours in (i, j) order,
    largest IoU difference."""
    if not ordered:
        k = np.lexsort((ours[1], ours[0]))
        ours = tuple(x[k] for x in ours)
    o = np.lexsort((peer[1], peer[0]))
    same = len(ours[0]) == len(peer[0]) and bool(
        np.array_equal(ours[0], peer[0][o]) and np.array_equal(ours[1], peer[1][o])
    )
    sorted_ij = bool(np.all(np.diff(ours[0] * (int(ours[1].max(initial=0)) + 1) + ours[1]) > 0))
    return {
        "pairs": len(ours[0]),
        "same_pairs": same,
        "sorted_ij": sorted_ij,
        "max_iou_diff": float(np.abs(ours[2] - peer[2][o]).max(initial=0)) if same else float("nan"),
    }


def comparison(name: str, work: Path, quick: bool, device: str, ordered: bool = True) -> Comparison:
    """For ``python -m bench``: overlapping pairs of one field's views, ours against shapely's STRtree
    (``ordered=False``: ours without sorting the pairs)."""
    plants = 2000 if quick else 21000
    boxes = field_boxes(plants)
    out: dict = {}

    def ours() -> float:
        t = time.process_time()
        out["ours"] = overlapping_pairs(boxes, ordered=ordered)
        return time.process_time() - t

    def peer() -> float:
        t = time.process_time()
        out["peer"] = shapely_pairs(boxes)
        return time.process_time() - t

    overlapping_pairs(boxes[:1000])  # compile (or load numba's cache) before timing
    return Comparison(
        name,
        f"{len(boxes):,} map boxes ({plants:,} plants x {VIEWS} views, {SIZE[0]}-{SIZE[1]} m, "
        f"{SPACING} m apart), pairs with IoU > 0 within the set",
        f"matchplant overlapping_pairs{'' if ordered else ' (unordered)'}",
        f"shapely {shapely.__version__} STRtree",
        ours,
        peer,
        check=lambda: agreement(out["ours"], out["peer"], ordered),
        items=len(boxes),
        unit="boxes",
    )


def main(argv: list[str] | None = None) -> int:
    """Parse the options, time our box pairs against shapely's STRtree on one pinned core; 1 when the pairs differ."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2,000 plants instead of 21,000")
    ap.add_argument("--pairs", type=int, default=3, help="timed ours/peer pairs after the warm-up")
    ap.add_argument("--unordered", action="store_true", help="ours with ordered=False (pairs not sorted)")
    args = ap.parse_args(argv)
    core = pin_one_core()
    cmp = comparison("box-pairs", ROOT, args.quick, "cpu", ordered=not args.unordered)
    print(f"{cmp.what}; pinned to core {core}")

    def show(i, a, b):
        print(f"  pair {i + 1}: {cmp.ours_label} {a:.3f} s, {cmp.peer_label} {b:.3f} s, ratio {b / a:.2f}", flush=True)

    a, b = alternate(cmp.ours, cmp.peer, pairs=args.pairs, warmup=1, on_pair=show)
    s = summarise(a, b)
    print(
        f"ours {s['ours_median_s']:.3f} s ({cmp.items / s['ours_median_s']:,.0f} boxes/s), peer "
        f"{s['peer_median_s']:.3f} s ({cmp.items / s['peer_median_s']:,.0f} boxes/s); speed ratio {ratio_text(s)}"
    )
    check = cmp.check()
    print("check: " + ", ".join(f"{k} {v}" for k, v in check.items()))
    return 0 if check["same_pairs"] and check["sorted_ij"] and check["max_iou_diff"] <= 1e-12 else 1


if __name__ == "__main__":
    raise SystemExit(main())
