"""Writing step 0's outputs: the geotagged copies, ``match_report.csv`` and ODM's ``geo.txt``.

The report has a row for every image, matched or not, because an image left without GPS is silently
dropped by ODM; the row's reason is what lets the user repair the log or the camera clock.
"""

from __future__ import annotations

import csv
import datetime as _dt
from pathlib import Path

import numpy as np

from matchplant.core.formats.exif import write_gps_copy
from matchplant.core.runtime.io import BatchedWrites, atomic_open
from matchplant.core.runtime.progress import progress
from matchplant.gps_embeder.gnss_log import GnssLog
from matchplant.gps_embeder.matching import ImageRecord

COPY_BATCH = 128  # copies per disk sync
REPORT_FIELDS = (
    "image",
    "status",
    "event",
    "camera_time_utc",
    "event_time_utc",
    "dt_s",
    "x",
    "y",
    "z",
    "longitude",
    "latitude",
    "altitude",
    "reason",
)


def iso_utc(t: float | None) -> str:
    """POSIX seconds as an ISO UTC time to the millisecond ('' for none)."""
    if t is None or not np.isfinite(t):
        return ""
    return _dt.datetime.fromtimestamp(t, _dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3]


def write_copies(
    records: list[ImageRecord],
    idx: np.ndarray,
    gnss: GnssLog,
    offset: float,
    out_images: Path,
    copy_unmatched: bool = False,
) -> tuple[list[dict], list[str]]:
    """Write each matched image's copy with its event's position; returns the report rows and geo.txt lines.

    ``idx`` is the event index per image (-1: none), ``offset`` the clock offset (log - camera). The
    copies are written under temporary names and made durable in batches (one disk sync per batch,
    then renamed into place): an interrupted run leaves only complete images."""
    lla = gnss.wgs84()
    rows, geo = [], []
    with BatchedWrites(out_images, batch=COPY_BATCH) as writer:
        for i, r in enumerate(progress(records, desc="writing GPS", unit="img")):
            rows.append(_write_one(r, int(idx[i]), gnss, lla, offset, writer, copy_unmatched, geo))
    return rows, geo


def _write_one(
    r: ImageRecord,
    j: int,
    gnss: GnssLog,
    lla: np.ndarray,
    offset: float,
    writer: BatchedWrites,
    copy_unmatched: bool,
    geo: list[str],
) -> dict:
    """One image's copy (when matched, or asked for) and its report row; appends its geo.txt line."""
    row = dict.fromkeys(REPORT_FIELDS, "")
    row.update(image=r.name, camera_time_utc=iso_utc(r.time))
    if j >= 0:
        lon, lat, alt = lla[j]
        alt_val = float(alt) if np.isfinite(alt) else None
        write_gps_copy(
            r.path, writer.folder / r.name, r.exif, float(lat), float(lon), alt_val, gnss.times[j], writer=writer
        )
        row.update(
            status="matched",
            event=gnss.labels[j],
            event_time_utc=iso_utc(gnss.times[j]),
            dt_s=f"{gnss.times[j] - (r.time + offset):+.3f}",
            x=repr(float(gnss.xyz[j, 0])),
            y=repr(float(gnss.xyz[j, 1])),
            z=repr(float(gnss.xyz[j, 2])),
            longitude=f"{lon:.9f}",
            latitude=f"{lat:.9f}",
            altitude=f"{alt:.3f}",
        )
        geo.append(
            f"{r.name} {lon:.9f} {lat:.9f} {alt:.3f}" if alt_val is not None else f"{r.name} {lon:.9f} {lat:.9f}"
        )
    else:
        row.update(status="unmatched", reason=r.reason)
        if copy_unmatched:
            writer.write(r.name, Path(r.path).read_bytes())
    return row


def write_report(path: Path, rows: list[dict]) -> Path:
    """``match_report.csv``: one row per image (:data:`REPORT_FIELDS`)."""
    with atomic_open(path, "w") as fh:
        w = csv.DictWriter(fh, fieldnames=REPORT_FIELDS)
        w.writeheader()
        w.writerows(rows)
    return path


def write_geo_txt(path: Path, lines: list[str]) -> Path:
    """ODM's optional ``geo.txt``: the CRS, then ``image lon lat [alt]`` per geotagged image."""
    with atomic_open(path, "w") as fh:
        fh.write("EPSG:4326\n" + "".join(line + "\n" for line in lines))
    return path
