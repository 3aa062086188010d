"""Pairing images with GNSS events by time: the camera-to-log clock offset, then one-to-one matching.

The offset is the one on which most (image, event) time differences agree, i.e. the peak of the
histogram of all pairwise differences: a wrong camera clock, a time zone or a missed first trigger
cannot fool it, unlike "first image = first event".
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matchplant.core.errors import InputError
from matchplant.core.exif import exif_time, has_subseconds, load_exif
from matchplant.core.images import JPEG_SUFFIXES, list_images
from matchplant.core.log import get_logger
from matchplant.core.progress import progress
from matchplant.gps_embeder.gnss_log import GnssLog

log = get_logger("gps_embed")


def estimate_clock_offset(cam: np.ndarray, events: np.ndarray, tolerance: float,
                          max_offset: float | None = None, max_pairs: int = 4_000_000) -> tuple[float, int]:
    """The offset ``o`` (seconds) with ``event time ~ camera time + o`` on which most pairs agree.

    Every (image, event) difference is a candidate; the one with most differences within ``tolerance``
    of it wins (the peak of their histogram), refined to the median of its supporters. Returns the
    offset and its support (the number of supporting pairs). Large sets are thinned evenly.
    """
    cam = np.asarray(cam, dtype=float)
    cam = cam[np.isfinite(cam)]
    events = np.sort(np.asarray(events, dtype=float))
    if cam.size == 0 or events.size == 0:
        return float("nan"), 0
    if cam.size * events.size > max_pairs:
        keep = max(1, max_pairs // events.size)
        cam = np.sort(cam)[np.linspace(0, cam.size - 1, min(keep, cam.size)).astype(int)]
    d = (events[None, :] - cam[:, None]).ravel()
    if max_offset is not None:
        d = d[np.abs(d) <= max_offset]
        if d.size == 0:
            return float("nan"), 0
    d.sort()
    support = np.searchsorted(d, d + tolerance, side="right") - np.searchsorted(d, d - tolerance, side="left")
    best = int(np.argmax(support))
    lo, hi = np.searchsorted(d, d[best] - tolerance), np.searchsorted(d, d[best] + tolerance, side="right")
    offset = float(np.median(d[lo:hi]))
    lo, hi = np.searchsorted(d, offset - tolerance), np.searchsorted(d, offset + tolerance, side="right")
    return offset, int(hi - lo)


def assign_events(cam: np.ndarray, events: np.ndarray, tolerance: float) -> np.ndarray:
    """One-to-one assignment of (offset-corrected) camera times to event times within ``tolerance``.

    On one time axis the closest pairs are taken first, each image and event used at most once.
    Returns the event index per image (-1 when none).
    """
    cam = np.asarray(cam, dtype=float)
    events = np.asarray(events, dtype=float)
    order = np.argsort(events)
    ev = events[order]
    pairs = []
    for i, t in enumerate(cam):
        if not np.isfinite(t):
            continue
        lo, hi = np.searchsorted(ev, t - tolerance), np.searchsorted(ev, t + tolerance, side="right")
        pairs += [(abs(ev[k] - t), i, k) for k in range(lo, hi)]
    pairs.sort()
    result = np.full(cam.shape, -1, dtype=int)
    used = np.zeros(ev.size, dtype=bool)
    for _, i, k in pairs:
        if result[i] < 0 and not used[k]:
            result[i] = order[k]
            used[k] = True
    return result


@dataclass
class ImageRecord:
    """One image on its way through matching; ``reason`` says why it has no event, for the report."""

    name: str
    path: Path
    exif: dict | None = None
    time: float | None = None
    reason: str = ""


def read_images(folder: Path, utc_offset_h: float = 0.0) -> list[ImageRecord]:
    """Every JPEG of ``folder`` with its EXIF and capture time; an unreadable one is kept with a reason."""
    records = []
    files = list_images(folder, JPEG_SUFFIXES, key="images",
                        fix="point 'images' at the folder of the flight's .jpg files")
    for p in progress(files, desc="reading EXIF", unit="img"):
        r = ImageRecord(p.name, p)
        try:
            r.exif = load_exif(p)
        except InputError as exc:
            r.reason = f"unreadable EXIF: {exc.problem}"
            records.append(r)
            continue
        r.time = exif_time(r.exif, utc_offset_h)
        if r.time is None:
            r.reason = "no capture time in EXIF (DateTimeOriginal)"
        records.append(r)
    return records


def match_images(records: list[ImageRecord], gnss: GnssLog, tolerance: float, clock_offset: float | None = None,
                 max_offset: float | None = None, source: Path | None = None) -> tuple[np.ndarray, float, int]:
    """Event index per image (-1 none), the clock offset and its support; fills each record's reason.

    ``clock_offset`` (seconds) is used as given when set (support -1), else estimated within
    ``max_offset``; ``source`` (the image folder) is named in the error when nothing can be estimated.
    """
    cam = np.array([r.time if r.time is not None else np.nan for r in records], dtype=float)
    tol = tolerance
    timed = [r for r in records if r.time is not None]
    if timed and not any(has_subseconds(r.exif) for r in timed):
        tol = max(tol, 1.0)
        log.warning("the images have no sub-second times (SubSecTimeOriginal); matching with a %.1f s tolerance", tol)
    if clock_offset is not None:
        offset, support = float(clock_offset), -1
    else:
        offset, support = estimate_clock_offset(cam, gnss.times, tol, max_offset)
        if not np.isfinite(offset):
            raise InputError("no clock offset can be estimated: no image has a capture time, or no event lies "
                             "within 'max_clock_offset_s'", path=source,
                             fix="check the images' EXIF times and the log, or set 'clock_offset_s'")
    aligned = cam + offset
    idx = assign_events(aligned, gnss.times, tol)
    ev_sorted = np.sort(gnss.times)
    owner = {int(j): i for i, j in enumerate(idx) if j >= 0}
    for i, r in enumerate(records):
        if idx[i] >= 0 or r.time is None:
            continue
        t = aligned[i]
        if t < ev_sorted[0] - tol:
            r.reason = f"taken {ev_sorted[0] - t:.1f} s before the GNSS log starts"
        elif t > ev_sorted[-1] + tol:
            r.reason = f"taken {t - ev_sorted[-1]:.1f} s after the GNSS log ends"
        else:
            j = int(np.argmin(np.abs(gnss.times - t)))
            dt = gnss.times[j] - t
            if abs(dt) <= tol and j in owner:
                r.reason = f"its event {gnss.labels[j]} (dt {dt:+.3f} s) went to {records[owner[j]].name}, which is closer"
            else:
                r.reason = f"no GNSS event within {tol:g} s (nearest {dt:+.2f} s away): a gap in the log?"
    return idx, offset, support

