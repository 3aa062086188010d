"""What a GNSS log must satisfy before one of its positions goes into an image.

A log that reads without a syntax error can still be wrong in ways that geotag a field on another
continent or at the wrong second: times in milliseconds, one absurd or repeated timestamp, a NaN
position, lat/lon columns that hold projected metres (or X Y columns that hold degrees). Each check
here names the log's line and says what to change, instead of letting the value reach the EXIF writer.
"""

from __future__ import annotations

import calendar
import datetime as _dt
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger

log = get_logger("gps_embeder")

EARLIEST = calendar.timegm((1980, 1, 6, 0, 0, 0))  # GPS time origin: no GNSS log is older
LATEST = calendar.timegm((2100, 1, 1, 0, 0, 0))
WEEK = 604800.0
MAX_SPAN_S = 2 * 86400.0  # an event this far from the log's median time is a typo, not the flight
MAX_ABS_HEIGHT_M = 10000.0  # no drone flies higher; a larger Z is in another unit
UNITS = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}


def date_text(t: float) -> str:
    """UTC date and time of POSIX seconds ``t``, for messages ("no valid date" when out of range)."""
    try:
        return _dt.datetime.fromtimestamp(float(t), _dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, ValueError, OSError):
        return "no valid date"


def _lines_text(lines: list[int], rows: np.ndarray) -> str:
    shown = ", ".join(str(lines[i]) for i in rows[:5])
    return shown + (f" and {len(rows) - 5} more" if len(rows) > 5 else "")


def _unit_guess(raw: np.ndarray, unit: str) -> str | None:
    """The time unit under which the log's numeric timestamps make sense, when seconds do not."""
    med = float(np.median(raw))
    if 0 <= med < WEEK or EARLIEST <= med < LATEST:
        return None  # plausible as they are: the epoch, not the unit, is wrong
    med *= UNITS[unit]  # back to the values as written
    for name, factor in UNITS.items():
        if name == unit:
            continue
        v = med / factor
        if 0 <= v < WEEK:
            return f"{name} (divided by {factor:g} they are GPS seconds of the week, {v:.3f})"
        if EARLIEST <= v < LATEST:
            return f"{name} (divided by {factor:g} they are seconds since 1970: {date_text(v)})"
    return None


def check_times(times: np.ndarray, lines: list[int], path: Path, raw_numeric: np.ndarray | None, unit: str) -> None:
    """Every event time is a real date near the others; numeric timestamps are in the configured unit.

    ``times`` are UTC seconds, ``raw_numeric`` the numeric timestamps as read (after ``unit``), or None.
    """
    if not len(times):
        return
    med = float(np.median(times))
    if not EARLIEST <= med < LATEST:
        guess = _unit_guess(raw_numeric, unit) if raw_numeric is not None and len(raw_numeric) else None
        if guess:
            raise InputError(
                f"the GNSS log's timestamps are not in {unit!r}: read so, they date from "
                f"{date_text(med)} (line {lines[0]}); they look like {guess}",
                path=path,
                fix=f"set 'timestamp_unit' to {guess.split()[0]} (or convert the time column to seconds)",
            )
        raise InputError(
            f"the GNSS log's timestamps give no valid date (median {date_text(med)}, line {lines[0]})",
            path=path,
            fix="check the time column and 'timestamp_epoch' / 'timestamp_unit' "
            "(seconds since 1970, GPS seconds of the week, or ISO date-times)",
        )
    bad = np.flatnonzero((times < EARLIEST) | (times >= LATEST) | (np.abs(times - med) > MAX_SPAN_S))
    if bad.size:
        k = int(bad[0])
        when = (
            f"{date_text(times[k])}, {abs(times[k] - med) / 86400:.1f} days from"
            if EARLIEST <= times[k] < LATEST
            else "beyond any date of"
        )
        raise InputError(
            f"GNSS log line(s) {_lines_text(lines, bad)} have an absurd timestamp: line {lines[k]} "
            f"is {when} the rest of the log ({date_text(med)})",
            path=path,
            fix="repair the timestamp on that line or delete the line",
        )


def duplicate_events(times: np.ndarray, xyz: np.ndarray, lines: list[int], path: Path) -> np.ndarray:
    """Indices of events to keep: a line logged twice (same time, same position) is kept once with a
    warning; the same time at two different positions is an error (which one is the camera's?)."""
    order = np.argsort(times, kind="stable")
    drop = []
    for a, b in zip(order[:-1], order[1:]):
        if times[b] - times[a] > 1e-6:
            continue
        if np.allclose(xyz[a], xyz[b], rtol=0, atol=1e-9, equal_nan=True):
            drop.append(int(b))
            continue
        raise InputError(
            f"GNSS log lines {lines[a]} and {lines[b]} have the same timestamp but different "
            "positions: which one is the camera's event cannot be told",
            path=path,
            fix="delete the wrong line (or repair its timestamp)",
        )
    if drop:
        log.warning(
            "%s: %d event(s) logged twice (the same time and position again on line(s) %s); each is used once",
            path.name,
            len(drop),
            _lines_text(lines, np.array(drop)),
        )
    return np.setdiff1d(np.arange(len(times)), np.array(drop, dtype=int))


def check_finite(values: np.ndarray, lines: list[int], path: Path, what: str) -> None:
    """Raise an error naming the log lines whose ``what`` (timestamp, position) is NaN or infinite."""
    bad = np.flatnonzero(~np.isfinite(values).all(axis=-1) if values.ndim > 1 else ~np.isfinite(values))
    if bad.size:
        raise InputError(
            f"GNSS log line(s) {_lines_text(lines, bad)} have no valid {what} (NaN or infinite): "
            f"line {lines[int(bad[0])]}",
            path=path,
            fix="repair or delete those lines",
        )


def check_positions(xyz: np.ndarray, crs: CRS, lines: list[int], path: Path, by_header: bool) -> None:
    """Positions agree with their CRS: degrees where it is geographic, metres inside its area where projected.

    ``by_header``: the log's own column names (lat/lon) made it geographic, rather than 'log_crs'."""
    check_finite(xyz[:, :2], lines, path, "position")
    if crs.is_geocentric:
        return
    lon, lat = xyz[:, 0], xyz[:, 1]
    if crs.is_geographic:
        bad = np.flatnonzero((np.abs(lat) > 90) | (np.abs(lon) > 180))
        if bad.size and (np.abs(lon) <= 90).all() and (np.abs(lat) <= 180).all():
            k = int(bad[0])
            raise InputError(
                f"GNSS log line {lines[k]}: latitude {lat[k]:g} is beyond ±90° and longitude {lon[k]:g} "
                "is not: latitude and longitude look swapped",
                path=path,
                fix="swap the two columns' names (or values)",
            )
        if bad.size:
            k = int(bad[0])
            metres = np.abs(xyz[bad, :2]).max() > 1000
            where = "its columns are named lat/lon" if by_header else f"'log_crs' is {crs.name}"
            fix = (
                "rename the columns X Y Z and set 'log_crs' to the projected CRS (e.g. EPSG:32614)"
                if by_header
                else "set 'log_crs' to the projected CRS of the log (e.g. EPSG:32614 or 'WGS84 UTM 14N')"
            )
            why = "they look like projected metres" if metres else "latitude beyond ±90° or longitude beyond ±180°"
            raise InputError(
                f"GNSS log line {lines[k]}: longitude {lon[k]:g}, latitude {lat[k]:g} are not degrees "
                f"({why}), but {where} ({bad.size} such line(s))",
                path=path,
                fix=fix,
            )
    else:
        degrees = bool((np.abs(lon) <= 180).all() and (np.abs(lat) <= 90).all() and np.ptp(lon) < 1 and np.ptp(lat) < 1)
        if degrees:  # a flight spans tens of metres: projected values this small and close are degrees
            raise InputError(
                f"GNSS log line {lines[0]}: X {lon[0]:g}, Y {lat[0]:g} look like degrees (longitude, "
                f"latitude), but 'log_crs' is the projected {crs.name}",
                path=path,
                fix="name the columns lat lon (alt), or set 'log_crs' to EPSG:4326",
            )
        t = Transformer.from_crs(crs, CRS.from_epsg(4326), always_xy=True)
        glon, glat = t.transform(xyz[:, 0], xyz[:, 1])
        area = crs.area_of_use
        outside = ~np.isfinite(glon) | ~np.isfinite(glat)
        if area is not None:
            margin = 5.0
            outside |= (
                (glon < area.west - margin)
                | (glon > area.east + margin)
                | (glat < area.south - margin)
                | (glat > area.north + margin)
            )
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            slon, slat = t.transform(xyz[k, 1], xyz[k, 0])
            swapped = area is not None and area.west <= slon <= area.east and area.south <= slat <= area.north
            raise InputError(
                f"GNSS log line {lines[k]}: X {lon[k]:g}, Y {lat[k]:g} lie outside the area of "
                f"'log_crs' ({crs.name})"
                f"{'; X and Y look swapped (easting, northing)' if swapped else ''}",
                path=path,
                fix="swap the X and Y columns' names"
                if swapped
                else "set 'log_crs' to the CRS the log was exported in (see the receiver's export settings)",
            )
    z = xyz[:, 2]
    bad = np.flatnonzero(np.isfinite(z) & (np.abs(z) > MAX_ABS_HEIGHT_M))
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"GNSS log line {lines[k]}: height {z[k]:g} m is not a flight altitude ({bad.size} such "
            "line(s)): is the Z column in another unit (mm, cm)?",
            path=path,
            fix="convert the Z column to metres, or delete those lines",
        )
