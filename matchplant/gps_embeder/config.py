"""Module 0's settings (the folder's config.yaml is generated from them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.core.runtime.config import param
from matchplant.gps_embeder.gnss_log import LOG_FORMATS
from matchplant.gps_embeder.log_checks import UNITS


@dataclass
class GpsEmbederConfig:
    """Module 0: write GNSS event positions into copies of the images (EXIF GPS), matched by time."""

    images: Path | None = param(None, "folder of the flight's JPEG images (not modified)", path="dir", required=True)
    gnss_log: Path | None = param(
        None,
        "GNSS event log: events.txt (TAB: Timestamp X Y Z), CSV with lat/lon, RTKLIB/Emlid .pos or DJI *_Timestamp.MRK",
        path="file",
        required=True,
    )
    output_dir: Path = param(
        Path("runs/gps_embeder"), "output folder: images/ (the copies with GPS), match_report.csv, geo.txt", path="out"
    )
    log_format: str = param(
        "auto", "format of the GNSS log ('auto' guesses from the name and header)", choices=LOG_FORMATS
    )
    log_crs: str | None = param(
        None,
        "CRS of the log's X Y: an EPSG code (EPSG:32614), 'WGS84 UTM 14N' or a "
        "PROJ string; needed for events.txt, optional for lat/lon logs",
    )
    time_base: str = param(
        "gps", "the log's clock: 'gps' (GPS time = UTC + leap seconds) or 'utc'", choices=("gps", "utc")
    )
    leap_seconds: float = param(18.0, "GPS - UTC leap seconds at the flight date (18 since 2017)", min=0, max=60)
    timestamp_epoch: str = param(
        "auto",
        "origin of numeric timestamps: 'unix' (seconds since 1970), 'gps' "
        "(since 1980-01-06), a date YYYY-MM-DD, or 'auto' (below one week: GPS "
        "seconds of the flight's week, else unix)",
    )
    timestamp_unit: str = param(
        "s", "unit of numeric timestamps in events.txt / CSV logs: s, ms, us or ns", choices=tuple(UNITS)
    )
    camera_utc_offset_h: float = param(
        0.0,
        "hours the camera clock is ahead of UTC (its time zone); the automatic clock offset absorbs an error here",
        min=-14,
        max=14,
    )
    clock_offset_s: float | None = param(
        None,
        "fixed seconds to add to camera times (after the time zone) to get log times; empty = estimate from the data",
    )
    max_clock_offset_s: float | None = param(
        None, "largest clock offset the estimate may find (seconds); empty = any", min=0
    )
    tolerance_s: float = param(0.5, "largest time difference for an image-event match (seconds)", min=0.001, max=60)
    write_geo_txt: bool = param(True, "also write ODM's geo.txt (EPSG:4326, lon lat alt per image)")
    copy_unmatched: bool = param(False, "copy images without a match (unchanged, no GPS) to the output too")
