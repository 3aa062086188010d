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

Nothing is written before everything is checked: damaged JPEGs (cut short, empty, not a JPEG), log
values that cannot be an event (NaN, absurd or repeated timestamps, times in another unit, degrees in
metre columns or the reverse, heights in mm: :mod:`.log_checks`), a clock offset that few images support
or that ties with another, and log positions far from the GPS the photos already carry (a wrong CRS).
The outputs are written into a temporary folder moved into place at the end (:mod:`matchplant.core.runtime.guard`).

The EXIF reading and writing is :mod:`matchplant.core.formats.exif` (step 1 reads what this step writes); the
log readers are :mod:`.gnss_log`, the matching :mod:`.matching`, the outputs :mod:`.copies`.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import numpy as np

from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.guard import check_outputs, staged_outputs
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.gps_embeder.config import GpsEmbederConfig
from matchplant.gps_embeder.copies import write_copies, write_geo_txt, write_report
from matchplant.gps_embeder.gnss_log import read_gnss_log
from matchplant.gps_embeder.matching import check_against_exif_gps, match_images, read_images

log = get_logger("gps_embeder")


@contextlib.contextmanager
def warnings_after_success(logger: logging.Logger):
    """Hold this step's warnings until it succeeds: a failed run prints its one error message alone, and
    the held warnings go to the run's log file only (as debug lines)."""
    held: list[logging.LogRecord] = []

    def catch(record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        held.append(record)
        return False

    logger.addFilter(catch)
    try:
        yield
    except BaseException:
        logger.removeFilter(catch)
        for record in held:
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
            logger.handle(record)
        raise
    logger.removeFilter(catch)
    for record in held:
        logger.handle(record)


def run(cfg: GpsEmbederConfig) -> list[dict]:
    """Run module 0: write each photo's GNSS position into a copy of it; warnings are printed at the end.

    Parameters
    ----------
    cfg : GpsEmbederConfig
        The step's settings, as loaded from its YAML config (``0_gps_embeder/config.yaml``) or built in Python.

    Returns
    -------
    list of dict
        The match report rows (match_report.csv), one per image.
    """
    with warnings_after_success(log):
        return _run(cfg)


def _run(cfg: GpsEmbederConfig) -> list[dict]:
    """Run module 0; returns the match report rows (one per image).

    Everything is checked before the first copy is written, and the copies and reports are written into a
    temporary folder that is moved into ``output_dir`` only at the end: a failed run leaves no copies.
    When no image matches, only ``match_report.csv`` (why each image has no event) is kept."""
    images = Path(cfg.images)
    out = Path(cfg.output_dir)
    if (out / "images").resolve() == images.resolve():
        raise ConfigError(
            "the output image folder is the input folder; the originals must not be modified",
            path=images,
            fix="set 'output_dir' to another folder",
        )
    check_outputs(cfg)
    records = read_images(images, cfg.camera_utc_offset_h)
    timed = [r.time for r in records if r.time is not None]
    gnss = read_gnss_log(
        cfg.gnss_log,
        cfg.log_format,
        cfg.log_crs,
        cfg.time_base,
        cfg.leap_seconds,
        cfg.timestamp_epoch,
        float(np.median(timed)) if timed else None,
        cfg.timestamp_unit,
    )
    log.info("GNSS log: %d events (%s, %s)", len(gnss.times), gnss.format, gnss.crs.name)
    idx, offset, support = match_images(
        records, gnss, cfg.tolerance_s, cfg.clock_offset_s, cfg.max_clock_offset_s, source=cfg.images
    )
    if support >= 0:
        log.info("clock offset (log - camera): %.3f s, supported by %d of %d images", offset, support, len(timed))
    check_against_exif_gps(records, idx, gnss)
    n_ok = int((idx >= 0).sum())
    with staged_outputs(out) as stage:
        rows, geo = write_copies(records, idx, gnss, offset, stage / "images", cfg.copy_unmatched and n_ok > 0)
        write_report(stage / "match_report.csv", rows)
        if n_ok:
            if cfg.write_geo_txt:
                write_geo_txt(stage / "geo.txt", geo)
            write_json(
                stage / "match_summary.json",
                {
                    "images": len(rows),
                    "matched": n_ok,
                    "events": len(gnss.times),
                    "events_without_image": len(gnss.times) - n_ok,
                    "clock_offset_s": offset,
                    "clock_offset_estimated": support >= 0,
                    "offset_support": support,
                    "log_format": gnss.format,
                    "log_crs": gnss.crs.to_string(),
                },
            )
    if n_ok == 0:
        raise InputError(
            f"no image could be matched to a GNSS event (clock offset {offset:+.3f} s)",
            path=cfg.gnss_log,
            fix="check that the log belongs to this flight and 'clock_offset_s'; "
            f"{out / 'match_report.csv'} says why for each image",
        )
    unmatched = [row for row in rows if row["status"] != "matched"]
    log.info(
        "%d of %d images matched; %d events without an image; report: %s",
        n_ok,
        len(rows),
        len(gnss.times) - n_ok,
        out / "match_report.csv",
    )
    if unmatched:
        log.warning(
            "%d of %d images have no GNSS event and get no GPS (ODM will not place them without it); reasons in %s:",
            len(unmatched),
            len(rows),
            out / "match_report.csv",
        )
        for row in unmatched:
            log.warning("  %s: %s", row["image"], row["reason"])
    return rows
