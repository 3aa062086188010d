"""Module 0: write GNSS positions into the images' EXIF (copies only, lossless).

A survey-grade GNSS receiver logs an *event* each time the camera fires. This module pairs every image
with its event by time and writes the event's position into a copy of the image:

1. read the log (the paper's ``events.txt``, a CSV with lat/lon, an RTKLIB/Emlid ``.pos`` file or a
   DJI ``*_Timestamp.MRK``) and convert its times to UTC seconds (GPS time = UTC + leap seconds) and its
   positions to WGS84;
2. read each image's EXIF ``DateTimeOriginal`` + ``SubSecTimeOriginal``;
3. estimate the camera-to-GNSS clock offset robustly: the offset on which most (image, event) time
   differences agree, i.e. the peak of the histogram of all pairwise differences (a wrong camera clock,
   a time zone or a missed first trigger cannot fool it, unlike "first image = first event");
4. assign images to events one-to-one within a tolerance (closest pairs first);
5. write the GPS IFD into a copy of each matched image by splicing a new EXIF segment into the JPEG: the
   compressed pixel data and every other segment (JFIF, XMP, ICC, ...) are copied byte for byte;
6. write ``match_report.csv`` (every image: its event and time difference, or why it has none) and,
   optionally, ODM's ``geo.txt``.

The EXIF reading and writing is :mod:`matchplant.core.exif` (step 1 reads what this step writes); the
log readers are :mod:`.gnss_log`, the matching :mod:`.matching`, the outputs :mod:`.copies`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matchplant.core.config import param
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.io import write_json
from matchplant.core.log import get_logger
from matchplant.gps_embeder.copies import write_copies, write_geo_txt, write_report
from matchplant.gps_embeder.gnss_log import LOG_FORMATS, read_gnss_log
from matchplant.gps_embeder.matching import match_images, read_images

log = get_logger("gps_embed")


@dataclass
class GpsEmbedConfig:
    """Module 0: write GNSS event positions into copies of the images (EXIF GPS), matched by time."""

    images: Path | None = param(None, "folder of the flight's JPEG images (not modified)", path="dir", required=True)
    gnss_log: Path | None = param(None, "GNSS event log: events.txt (TAB: Timestamp X Y Z), CSV with lat/lon, "
                                 "RTKLIB/Emlid .pos or DJI *_Timestamp.MRK", path="file", required=True)
    output_dir: Path = param(Path("gps_embed_out"), "output folder: images/ (the copies with GPS), "
                             "match_report.csv, geo.txt", path="out")
    log_format: str = param("auto", "format of the GNSS log ('auto' guesses from the name and header)",
                            choices=LOG_FORMATS)
    log_crs: str | None = param(None, "CRS of the log's X Y: an EPSG code (EPSG:32614), 'WGS84 UTM 14N' or a "
                                      "PROJ string; needed for events.txt, optional for lat/lon logs")
    time_base: str = param("gps", "the log's clock: 'gps' (GPS time = UTC + leap seconds) or 'utc'",
                           choices=("gps", "utc"))
    leap_seconds: float = param(18.0, "GPS - UTC leap seconds at the flight date (18 since 2017)", min=0, max=60)
    timestamp_epoch: str = param("auto", "origin of numeric timestamps: 'unix' (seconds since 1970), 'gps' "
                                         "(since 1980-01-06), a date YYYY-MM-DD, or 'auto' (below one week: GPS "
                                         "seconds of the flight's week, else unix)")
    camera_utc_offset_h: float = param(0.0, "hours the camera clock is ahead of UTC (its time zone); the "
                                            "automatic clock offset absorbs an error here", min=-14, max=14)
    clock_offset_s: float | None = param(None, "fixed seconds to add to camera times (after the time zone) to "
                                               "get log times; empty = estimate from the data")
    max_clock_offset_s: float | None = param(None, "largest clock offset the estimate may find (seconds); "
                                                   "empty = any", min=0)
    tolerance_s: float = param(0.5, "largest time difference for an image-event match (seconds)", min=0.001,
                               max=60)
    write_geo_txt: bool = param(True, "also write ODM's geo.txt (EPSG:4326, lon lat alt per image)")
    copy_unmatched: bool = param(False, "copy images without a match (unchanged, no GPS) to the output too")


def embed_gps(cfg: GpsEmbedConfig) -> list[dict]:
    """Run module 0; returns the match report rows (one per image)."""
    images = Path(cfg.images)
    out = Path(cfg.output_dir)
    out_images = out / "images"
    if out_images.resolve() == images.resolve():
        raise ConfigError("the output image folder is the input folder; the originals must not be modified",
                          path=images, fix="set 'output_dir' to another folder")
    records = read_images(images, cfg.camera_utc_offset_h)
    timed = [r.time for r in records if r.time is not None]
    gnss = read_gnss_log(cfg.gnss_log, cfg.log_format, cfg.log_crs, cfg.time_base, cfg.leap_seconds,
                         cfg.timestamp_epoch, float(np.median(timed)) if timed else None)
    log.info("GNSS log: %d events (%s, %s)", len(gnss.times), gnss.format, gnss.crs.name)
    idx, offset, support = match_images(records, gnss, cfg.tolerance_s, cfg.clock_offset_s, cfg.max_clock_offset_s,
                                        source=cfg.images)
    if support >= 0:
        log.info("clock offset (log - camera): %.3f s, supported by %d of %d images", offset, support,
                 sum(r.time is not None for r in records))
    rows, geo = write_copies(records, idx, gnss, offset, out_images, cfg.copy_unmatched)
    write_report(out / "match_report.csv", rows)
    if cfg.write_geo_txt:
        write_geo_txt(out / "geo.txt", geo)
    n_ok = sum(row["status"] == "matched" for row in rows)
    unused = len(gnss.times) - n_ok
    write_json(out / "match_summary.json", {
        "images": len(rows), "matched": n_ok, "events": len(gnss.times), "events_without_image": unused,
        "clock_offset_s": offset, "clock_offset_estimated": support >= 0, "offset_support": support,
        "log_format": gnss.format, "log_crs": gnss.crs.to_string()})
    log.info("%d of %d images matched; %d events without an image; report: %s", n_ok, len(rows), unused,
             out / "match_report.csv")
    for row in rows:
        if row["status"] != "matched":
            log.warning("  %s: %s", row["image"], row["reason"])
    if n_ok == 0:
        raise InputError("no image could be matched to a GNSS event", path=cfg.gnss_log,
                         fix="check that the log belongs to this flight; see match_report.csv for each image")
    return rows
