"""Progress of long loops: a tqdm bar on a terminal, a log line every ~10 s elsewhere.

When stderr is a terminal, :func:`progress` shows a tqdm bar. When it is not (output piped or written to a
file, a pipeline run, a CI log), it logs ``<desc>: <done>/<total> <unit> (<rate>/s, ETA <time>)`` through the
``matchplant`` logger at most every ``MATCHPLANT_PROGRESS_INTERVAL`` seconds (default 10), and a final line for
loops that took longer than that, so a piped run is never silent for long. ``MATCHPLANT_QUIET=1`` silences
both; ``MATCHPLANT_PROGRESS=1`` forces the bar.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from typing import TypeVar

from tqdm.auto import tqdm
from tqdm.std import tqdm as std_tqdm

from matchplant.core.runtime.log import get_logger

T = TypeVar("T")
DEFAULT_INTERVAL_S = 10.0
log = get_logger("progress")


def duration(seconds: float) -> str:
    """A duration in words a user reads at a glance."""
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 120:
        return f"{seconds / 60:.0f} min"
    return f"{seconds:.0f} s"


def log_interval() -> float:
    """Seconds between two progress lines in a log (``MATCHPLANT_PROGRESS_INTERVAL``, default 10)."""
    try:
        return max(0.0, float(os.environ.get("MATCHPLANT_PROGRESS_INTERVAL", DEFAULT_INTERVAL_S)))
    except ValueError:
        return DEFAULT_INTERVAL_S


def _clock(seconds: float | None) -> str:
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "?"
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


def progress_line(desc: str, n: float, total: float | None, elapsed: float, unit: str = "it") -> str:
    """``desc: done/total unit (rate unit/s, ETA m:ss)``; the ETA from the mean rate so far."""
    rate = n / elapsed if elapsed > 0 else None
    done = f"{n:g}/{total:g}" if total else f"{n:g}"
    pct = f" {100 * n / total:.0f}%" if total else ""
    if rate is None or rate == 0:
        speed = ""
    elif rate >= 1:
        speed = f", {rate:.2f} {unit}/s"
    else:
        speed = f", {1 / rate:.1f} s/{unit}"
    eta = f", ETA {_clock((total - n) / rate)}" if total and rate else ""
    return f"{desc or 'progress'}: {done} {unit}{pct} ({_clock(elapsed)} elapsed{speed}{eta})"


class _Discard:
    def write(self, _text):
        pass

    def flush(self):
        pass


class LogProgress(std_tqdm):
    """A tqdm that logs one line at most every ``mininterval`` seconds instead of drawing a bar."""

    def __init__(self, *args, **kwargs):
        kwargs["file"] = _Discard()
        kwargs.setdefault("mininterval", log_interval())
        kwargs["miniters"] = 1
        kwargs["maxinterval"] = float("inf")  # no monitor thread raising miniters
        super().__init__(*args, **kwargs)

    def display(self, msg=None, pos=None):
        """Log a progress line instead of drawing, at most once per interval (always at the end)."""
        n = self.n
        if n == 0 or msg == "":  # the opening call, and the one close() makes to erase a bar
            return True
        now = self._time()
        # set_postfix() and refresh() also call display: keep to one line per interval whatever calls it
        if now - getattr(self, "_logged_at", self.start_t) < self.mininterval and n != self.total:
            return True
        self._logged_at = now
        log.info(progress_line(self.desc.rstrip(": "), n, self.total, now - self.start_t, self.unit))
        return True

    def close(self):
        """Log the final count unless already logged (a run shorter than one interval logs none), then close."""
        if self.disable:
            return
        elapsed = self._time() - self.start_t
        if elapsed >= self.mininterval and self.n != self.last_print_n:
            log.info(progress_line(self.desc.rstrip(": "), self.n, self.total, elapsed, self.unit))
        super().close()


def progress(
    iterable: Iterable[T] | None, desc: str = "", total: int | None = None, unit: str = "it", **kwargs
) -> Iterable[T]:
    """Wrap ``iterable`` (or, with ``None``, a bar to ``update()`` by hand) with progress reporting."""
    if os.environ.get("MATCHPLANT_QUIET") == "1":
        return tqdm(iterable, desc=desc, total=total, unit=unit, disable=True, **kwargs)
    if sys.stderr.isatty() or os.environ.get("MATCHPLANT_PROGRESS") == "1":
        return tqdm(iterable, desc=desc, total=total, unit=unit, dynamic_ncols=True, leave=False, **kwargs)
    return LogProgress(iterable, desc=desc, total=total, unit=unit, leave=False, **kwargs)
