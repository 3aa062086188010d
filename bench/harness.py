"""The benchmark harness: ours and a peer timed in turn (A B A B ...), on one core, one thread each.

A :class:`Comparison` holds two callables doing the same work (``ours`` and ``peer``), an optional
``reset`` run untimed before every call (e.g. removing the previous run's output) and an optional
``check`` that compares the two outputs. :func:`alternate` warms both up, then times ``pairs`` rounds
of ours-then-peer; :func:`summarise` turns the times into the medians and the per-pair speed ratio
(peer time / our time: above 1, ours is faster) with its min and max. Only ratios measured side by
side are stable on a shared machine; absolute times are recorded but not claimed.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata as _md
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field

THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMBA_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "GDAL_NUM_THREADS",
)


@dataclass
class Comparison:
    """One row of the benchmark table: the same work done by MatchPlant and by a peer tool."""

    name: str
    what: str  # the work, in words (sizes included)
    ours_label: str
    peer_label: str
    ours: Callable[[], object]
    peer: Callable[[], object] | None  # None: the peer is missing (see skip)
    reset: Callable[[str], None] | None = None  # untimed, before every call of a side ("ours"/"peer")
    check: Callable[[], dict] | None = None  # after the runs: agreement of the two outputs
    items: int = 0  # work items per call (images, boxes, tiles) for the per-second figures
    unit: str = "item"
    skip: str | None = None  # why the peer cannot run (printed; the row is then not a comparison)
    notes: dict = field(default_factory=dict)


def single_thread_env(env: dict | None = None) -> dict:
    """A copy of ``env`` (default: os.environ) with every thread pool limited to one thread."""
    out = dict(os.environ if env is None else env)
    for var in THREAD_VARS:
        out[var] = "1"
    return out


def pin_one_core() -> int | None:
    """Pin this process to one of its allowed cores (the last one); returns the core, None where
    the system has no affinity call (macOS, Windows)."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    core = max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})
    return core


def _timed(fn: Callable[[], object], reset: Callable[[], None] | None) -> float:
    """Wall time of ``fn()``; a callable that times its own measured section returns those seconds
    as a float (the training loops: the epoch loop without model building and checkpoints)."""
    if reset is not None:
        reset()  # not timed
    t = time.perf_counter()
    out = fn()
    wall = time.perf_counter() - t
    return out if isinstance(out, float) and 0 < out <= wall else wall


def alternate(
    ours: Callable[[], object],
    peer: Callable[[], object],
    pairs: int = 3,
    warmup: int = 1,
    reset: Callable[[str], None] | None = None,
    clock: Callable[[Callable, object], float] = _timed,
    on_pair: Callable[[int, float, float], None] | None = None,
) -> tuple[list[float], list[float]]:
    """Run ``warmup`` untimed pairs, then ``pairs`` timed rounds of ours then peer (A B A B ...).

    ``reset(side)`` runs untimed before each call ("ours" or "peer"), e.g. to remove that side's output."""
    if pairs < 1:
        raise ValueError("pairs must be at least 1")
    ra = rb = None
    if reset is not None:

        def ra():
            reset("ours")

        def rb():
            reset("peer")

    for _ in range(warmup):
        clock(ours, ra)
        clock(peer, rb)
    a, b = [], []
    for i in range(pairs):
        a.append(clock(ours, ra))
        b.append(clock(peer, rb))
        if on_pair is not None:
            on_pair(i, a[-1], b[-1])
    return a, b


def summarise(ours: list[float], peer: list[float]) -> dict:
    """Medians of each side and the speed ratio peer / ours of each pair (median, min, max).

    Pairs are ratioed one by one (ours[i] with peer[i], timed back to back), so a slow spell of the
    machine affects both sides of a pair rather than the ratio."""
    if len(ours) != len(peer) or not ours:
        raise ValueError("need the same, non-zero number of times for both sides")
    if min(ours) <= 0 or min(peer) <= 0:
        raise ValueError("times must be positive")
    ratios = [p / o for o, p in zip(ours, peer)]
    return {
        "ours_median_s": statistics.median(ours),
        "peer_median_s": statistics.median(peer),
        "ratio_median": statistics.median(ratios),
        "ratio_min": min(ratios),
        "ratio_max": max(ratios),
        "pairs": len(ours),
        "ours_s": list(ours),
        "peer_s": list(peer),
        "ratios": ratios,
    }


def overhead(summary: dict) -> dict:
    """The same ratio read as our extra time over the peer's: ours / peer - 1 (median, min, max)."""
    r = summary
    return {
        "overhead_median": 1 / r["ratio_median"] - 1,
        "overhead_min": 1 / r["ratio_max"] - 1,
        "overhead_max": 1 / r["ratio_min"] - 1,
    }


def cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else what the platform module knows."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """What the numbers were measured on."""
    info = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "date_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    if hasattr(os, "getloadavg"):
        info["load_average_1min_at_start"] = round(os.getloadavg()[0], 2)
    return info


def versions(packages: list[str]) -> dict:
    """Installed versions of ``packages`` (None when missing)."""
    out = {}
    for p in packages:
        try:
            out[p] = _md.version(p)
        except _md.PackageNotFoundError:
            out[p] = None
    return out


def across_runs(summaries: list[dict]) -> dict:
    """Several runs of one comparison (each a fresh process: warm-up, then its pairs) as one row.

    One run's pairs are timed minutes apart at most, so their spread is narrower than what another run, later
    or under another load, gives (module 9's row said 5.93-6.55 from one run; three runs gave medians 4.78,
    5.18 and 5.83). The row's figure is the median of the runs' medians and its spread the smallest and largest
    run median; the pairs' own extremes are kept as ``pair_min``/``pair_max``."""
    if not summaries:
        raise ValueError("need at least one run")
    medians = [r["ratio_median"] for r in summaries]
    ours = [r["ours_median_s"] for r in summaries]
    peer = [r["peer_median_s"] for r in summaries]
    return {
        "ours_median_s": statistics.median(ours),
        "peer_median_s": statistics.median(peer),
        "ratio_median": statistics.median(medians),
        "ratio_min": min(medians),
        "ratio_max": max(medians),
        "runs": len(summaries),
        "run_medians": medians,
        "pair_min": min(r["ratio_min"] for r in summaries),
        "pair_max": max(r["ratio_max"] for r in summaries),
        "pairs": sum(r["pairs"] for r in summaries),
        "per_run": summaries,
    }


def ratio_text(s: dict) -> str:
    """A comparison's speed ratio in words: median, spread over runs and pairs."""
    if s.get("runs", 1) > 1:
        return (
            f"{s['ratio_median']:.2f}x (runs' medians {s['ratio_min']:.2f}-{s['ratio_max']:.2f} over "
            f"{s['runs']} runs; pairs {s['pair_min']:.2f}-{s['pair_max']:.2f})"
        )
    return f"{s['ratio_median']:.2f}x (min {s['ratio_min']:.2f}, max {s['ratio_max']:.2f}; one run)"
