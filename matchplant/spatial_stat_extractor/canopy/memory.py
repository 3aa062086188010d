"""The memory budget of the canopy strips: the ``max_memory`` setting, a run's peak memory, a clear error when short.

The peak is the operating system's own count of the process's largest resident set (``getrusage``: the
pixels, tables and GDAL's block cache alike, not only Python objects), and of the largest worker process
when outlines run in parallel. Windows has no ``resource`` module: there the peak comes from psutil when it
is installed, else it is not reported.
"""

from __future__ import annotations

import contextlib
import re
import sys
from concurrent.futures.process import BrokenProcessPool

from matchplant.core.runtime.errors import ConfigError, DependencyError

try:
    import resource
except ImportError:  # pragma: no cover - Windows
    resource = None

_UNITS = {
    "": 1,
    "b": 1,
    "k": 1024,
    "kb": 1024,
    "m": 1024**2,
    "mb": 1024**2,
    "g": 1024**3,
    "gb": 1024**3,
    "t": 1024**4,
    "tb": 1024**4,
}
DEFAULT_MAX_MEMORY = "3GB"  # max_memory's default, the settings' too: room for the system and a browser on 8 GB
MIN_MEMORY = 256 * 1024**2  # below this the strips would be a few rows: not a useful setting


def parse_memory(text, key: str = "max_memory") -> int:
    """Bytes of a size such as ``3GB``, ``512MB``, ``1.5g`` or a plain number of bytes."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*", str(text))
    unit = m.group(2).lower() if m else ""
    if m is None or unit not in _UNITS:
        raise ConfigError(f"{key}: '{text}' is not a memory size", fix=f"write e.g. {key}: 3GB (or 512MB)")
    size = int(float(m.group(1)) * _UNITS[unit])
    if size < MIN_MEMORY:
        raise ConfigError(
            f"{key}: {text} is too little for module 9 (at least 256MB)",
            fix=f"set {key} to at least 256MB; 2GB-3GB suit an 8 GB laptop",
        )
    return size


DEFAULT_MEMORY = parse_memory(DEFAULT_MAX_MEMORY)  # the same default in bytes, for library calls


def gdal_cache_bytes(max_memory: int) -> int:
    """GDAL's block cache for a budget: a sixteenth of it, 64 MB to 512 MB (room for rows of tiles)."""
    return int(min(512 * 1024**2, max(64 * 1024**2, max_memory // 16)))


def format_memory(size: float) -> str:
    """A byte count for a log line: GB from 1 GB on, else MB."""
    return f"{size / 1024**3:.2f} GB" if size >= 1024**3 else f"{size / 1024**2:.0f} MB"


def _maxrss(who) -> float | None:
    if resource is None:
        return None
    kb = resource.getrusage(who).ru_maxrss
    return float(kb) if sys.platform == "darwin" else float(kb) * 1024  # macOS counts bytes, Linux KiB


def peak_memory() -> dict[str, float | None]:
    """Peak resident memory in bytes of this process (``self``) and of its largest finished child
    process (``workers``: the strips' process pool; 0 when there was none)."""
    if resource is None:  # pragma: no cover - Windows
        try:
            import psutil
        except ImportError:
            return {"self": None, "workers": None}
        info = psutil.Process().memory_info()
        return {"self": float(getattr(info, "peak_wset", info.rss)), "workers": None}
    return {"self": _maxrss(resource.RUSAGE_SELF), "workers": _maxrss(resource.RUSAGE_CHILDREN)}


def memory_report(max_memory: int) -> dict:
    """What ``stats_report.json`` records: the setting and the peaks so far, in MB."""
    peak = peak_memory()
    mb = {k: (round(v / 1024**2, 1) if v is not None else None) for k, v in peak.items()}
    return {"max_memory_mb": round(max_memory / 1024**2, 1), "peak_mb": mb["self"], "peak_worker_mb": mb["workers"]}


@contextlib.contextmanager
def memory_stage(stage: str, max_memory: int):
    """Turn a memory shortage inside ``stage`` into an error that names the stage and the setting."""
    try:
        yield
    except (MemoryError, BrokenProcessPool) as exc:
        # a worker killed by the system for lack of memory breaks the pool: the same shortage
        lower = max(MIN_MEMORY, max_memory // 2)
        raise DependencyError(
            f"out of memory in {stage} (max_memory: {format_memory(max_memory)}; "
            f"{type(exc).__name__}: {exc or 'no detail'})",
            fix=f"set max_memory lower than the memory this computer has free, e.g. max_memory: "
            f"{lower // 1024**2}MB (the rasters are then read in smaller strips), set workers: 1, "
            "or close other programs",
        ) from exc
