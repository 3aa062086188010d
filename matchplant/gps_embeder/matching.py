"""Pairing images with GNSS events by time: the camera-to-log clock offset, then one-to-one matching.

The offset is the one on which most (image, event) time differences agree, i.e. the peak of the
histogram of all pairwise differences: a wrong camera clock, a time zone or a missed first trigger
cannot fool it, unlike "first image = first event".
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matchplant.core.formats.exif import exif_gps, exif_time, has_subseconds, load_exif
from matchplant.core.formats.images import JPEG_SUFFIXES, list_images
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.core.runtime.validate import check_jpeg
from matchplant.gps_embeder.gnss_log import GnssLog

log = get_logger("gps_embeder")


def estimate_clock_offset(
    cam: np.ndarray, events: np.ndarray, tolerance: float, max_offset: float | None = None, max_pairs: int = 4_000_000
) -> tuple[float, int]:
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
    """Every JPEG of ``folder`` with its EXIF and capture time; an image without a time is kept with a
    reason. A damaged JPEG (empty, cut short, not a JPEG) stops the run: naming it beats losing it."""
    records, damaged = [], []
    files = list_images(
        folder, JPEG_SUFFIXES, key="images", fix="point 'images' at the folder of the flight's .jpg files"
    )
    for p in progress(files, desc="reading EXIF", unit="img"):
        r = ImageRecord(p.name, p)
        try:
            check_jpeg(p)  # a copy cut short still opens and has its EXIF: it would be geotagged as if whole
            r.exif = load_exif(p)
        except InputError as exc:
            damaged.append(f"{p.name}: {exc.problem}")
            continue
        r.time = exif_time(r.exif, utc_offset_h)
        if r.time is None:
            r.reason = "no capture time in EXIF (DateTimeOriginal)"
        records.append(r)
    if damaged:
        more = f" (and {len(damaged) - 5} more)" if len(damaged) > 5 else ""
        raise InputError(
            f"{len(damaged)} damaged image(s) in the flight's folder: {'; '.join(damaged[:5])}{more}",
            path=folder,
            fix="copy those images again from the camera's card, or move them out of "
            "the folder; the originals are not modified",
        )
    if not any(r.time is not None for r in records):
        raise InputError(
            f"none of the {len(records)} images has a capture time in its EXIF (DateTimeOriginal)",
            path=folder,
            fix="use the camera's original JPEGs (some editors strip EXIF), or write the "
            "positions another way (ODM's geo.txt)",
        )
    return records


def interval_hint(cam: np.ndarray, events: np.ndarray) -> str:
    """Compare the typical spacing of the images and of the events: a log in another time unit shows here."""
    cam = np.sort(cam[np.isfinite(cam)])
    events = np.sort(events)
    if cam.size < 2 or events.size < 2:
        return ""
    dc, de = np.diff(cam), np.diff(events)
    dc, de = dc[dc > 0], de[de > 0]
    if not dc.size or not de.size:
        return ""
    dc, de = float(np.median(dc)), float(np.median(de))
    text = f"; the images are {dc:.3g} s apart (median), the log's events {de:.3g} s"
    ratio = de / dc
    unit = next((u for u, f in (("ms", 1e3), ("us", 1e6), ("ns", 1e9)) if f / 2 < ratio < f * 2), None)
    if unit:
        text += f" ({ratio:.3g} times as far): the log's timestamps look like {unit}, set 'timestamp_unit' to {unit}"
    elif ratio > 3 or ratio < 1 / 3:
        text += ": is it the log of this flight?"
    return text


def match_images(
    records: list[ImageRecord],
    gnss: GnssLog,
    tolerance: float,
    clock_offset: float | None = None,
    max_offset: float | None = None,
    source: Path | None = None,
) -> tuple[np.ndarray, float, int]:
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
            raise InputError(
                "no clock offset can be estimated: no image has a capture time, or no event lies "
                "within 'max_clock_offset_s'",
                path=source,
                fix="check the images' EXIF times and the log, or set 'clock_offset_s'",
            )
        check_support(support, offset, cam, gnss, tol, max_offset)
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
                r.reason = (
                    f"its event {gnss.labels[j]} (dt {dt:+.3f} s) went to {records[owner[j]].name}, which is closer"
                )
            else:
                r.reason = f"no GNSS event within {tol:g} s (nearest {dt:+.2f} s away): a gap in the log?"
    return idx, offset, support


def rival_offset(
    offset: float, support: int, cam: np.ndarray, events: np.ndarray, tol: float, max_offset: float | None = None
) -> float | None:
    """Another offset, well apart from ``offset``, that as many images agree on (None when there is none).

    With few images or events (one event and nine images: any image fits), the best offset is a tie
    between several, and picking one would geotag an arbitrary image."""
    cam = cam[np.isfinite(cam)]
    if cam.size * events.size > 4_000_000:
        return None  # large flights: a tie of the best support does not happen by chance
    d = np.sort((events[None, :] - cam[:, None]).ravel())
    if max_offset is not None:
        d = d[np.abs(d) <= max_offset]
    counts = np.searchsorted(d, d + tol, side="right") - np.searchsorted(d, d - tol, side="left")
    rivals = d[(counts >= support) & (np.abs(d - offset) > 2 * tol)]
    return float(rivals[0]) if rivals.size else None


def check_support(
    support: int, offset: float, cam: np.ndarray, gnss: GnssLog, tol: float, max_offset: float | None = None
) -> None:
    """An offset on which fewer than half the images (or events) agree is chance, not the camera's clock:
    geotagging with it would put the images at wrong positions. So is one that ties with another."""
    timed = int(np.isfinite(cam).sum())
    base = min(timed, len(gnss.times))
    needed = max(1, int(np.ceil(base / 2)))
    fix = (
        "check that the log belongs to this flight and its time unit ('timestamp_unit'), epoch "
        "('timestamp_epoch') and clock ('time_base'); or raise 'tolerance_s', or set 'clock_offset_s' if you "
        "know the offset"
    )
    if support < needed:
        raise InputError(
            f"the images' times and the GNSS log do not agree: the best clock offset ({offset:+.1f} s) "
            f"is supported by only {support} of {timed} images (within {tol:g} s; at least {needed} "
            f"needed){interval_hint(cam, gnss.times)}",
            path=gnss.path,
            fix=fix,
        )
    rival = rival_offset(offset, support, cam, np.asarray(gnss.times, dtype=float), tol, max_offset)
    if rival is not None:
        raise InputError(
            f"the clock offset between the images and the GNSS log is ambiguous: {offset:+.1f} s and "
            f"{rival:+.1f} s fit equally well ({support} of {timed} images each, {len(gnss.times)} "
            "events)",
            path=gnss.path,
            fix="set 'clock_offset_s' (seconds to add to the camera's times "
            "to get the log's) or a small 'max_clock_offset_s', or use "
            "the flight's complete log",
        )


MAX_EXIF_DISTANCE_M = 1000.0  # a camera's own GPS is off by metres, a wrong CRS or log by kilometres


def check_against_exif_gps(records: list[ImageRecord], idx: np.ndarray, gnss: GnssLog) -> None:
    """When the images already carry their own (rough) GPS, the log's positions must land near it: a wrong
    'log_crs' (another UTM zone or hemisphere) or the log of another field is caught here."""
    lla = gnss.wgs84()
    pairs = []
    for r, j in zip(records, idx):
        own = exif_gps(r.exif) if j >= 0 and r.exif else None
        if own is None or not (np.isfinite(own[0]) and np.isfinite(own[1])) or (own[0] == 0 and own[1] == 0):
            continue  # no position, or the 0,0 some cameras write without a fix
        pairs.append((own[0], own[1], lla[j, 1], lla[j, 0], r.name, int(j)))
    if not pairs:
        return
    a = np.radians(np.array([p[:4] for p in pairs], dtype=float))
    h = np.sin((a[:, 2] - a[:, 0]) / 2) ** 2 + np.cos(a[:, 0]) * np.cos(a[:, 2]) * np.sin((a[:, 3] - a[:, 1]) / 2) ** 2
    dist = 2 * 6371008.8 * np.arcsin(np.sqrt(np.clip(h, 0, 1)))
    if float(np.median(dist)) <= MAX_EXIF_DISTANCE_M:
        return
    k = int(np.argsort(dist)[len(dist) // 2])
    name, j = pairs[k][4], pairs[k][5]
    line = f" (line {gnss.lines[j]})" if gnss.lines else ""
    raise InputError(
        f"the GNSS log's positions lie {np.median(dist) / 1000:.1f} km (median of {len(dist)} images) "
        f"from the GPS the images already carry: e.g. {name} is at {pairs[k][0]:.6f}, "
        f"{pairs[k][1]:.6f} (lat, lon), its event{line} at {pairs[k][2]:.6f}, {pairs[k][3]:.6f}",
        path=gnss.path,
        fix=f"check 'log_crs' (now {gnss.crs.name}: the UTM zone and hemisphere) and "
        "that the log belongs to this flight",
    )
