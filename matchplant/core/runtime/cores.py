"""The CPU cores this process may use: its affinity (``taskset``, a container's cpuset) lowered by a cgroup CPU
quota, not the machine's count. Module 6 and 7's thread choice and module 9's worker processes both size
themselves from it."""

from __future__ import annotations

import os


def usable_cores() -> tuple[int, str]:
    """``(cores, where from)``: the cores this process may run on (its CPU affinity, e.g. ``taskset`` or a
    container's cpuset; a cgroup CPU quota lowers it), not the machine's count."""
    if hasattr(os, "sched_getaffinity"):
        cores, source = len(os.sched_getaffinity(0)), "CPU affinity"
    else:
        cores, source = os.cpu_count() or 1, "os.cpu_count()"
    quota = _cgroup_quota()
    if quota is not None and quota < cores:
        cores, source = max(1, int(quota + 0.5)), f"cgroup CPU quota {quota:g}"
    return max(1, cores), source


def _cgroup_quota() -> float | None:
    """CPUs allowed by a cgroup v2 quota (``cpu.max``: "quota period"), None when unlimited or unknown."""
    try:
        with open("/sys/fs/cgroup/cpu.max") as fh:
            quota, period = fh.read().split()[:2]
        return None if quota == "max" else float(quota) / float(period)
    except (OSError, ValueError):
        return None


__all__ = ["usable_cores"]
