"""GNSS event logs: the paper's ``events.txt``, a CSV with lat/lon, RTKLIB/Emlid ``.pos``, DJI ``.MRK``.

Every reader ends in the same place: UTC POSIX seconds per event (GPS time = UTC + leap seconds) and
positions in the log's CRS, so that matching never needs to know which receiver wrote the log.
"""

from __future__ import annotations

import calendar
import csv
import datetime as _dt
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pyproj import CRS, Transformer

from matchplant.core.geometry.frames import parse_crs
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import read_text
from matchplant.gps_embeder.log_checks import UNITS, check_finite, check_positions, check_times, duplicate_events

log = get_logger("gps_embeder")

GPS_EPOCH = calendar.timegm((1980, 1, 6, 0, 0, 0))  # POSIX seconds of the GPS time origin
LOG_FORMATS = ("auto", "events", "csv", "pos", "mrk")


@dataclass
class GnssLog:
    """Events of a GNSS log: UTC POSIX times and positions in the log's CRS (``crs``)."""

    times: np.ndarray  # (M,) seconds, UTC
    xyz: np.ndarray  # (M, 3) in ``crs`` (x = easting or longitude)
    crs: object  # pyproj CRS
    path: Path
    format: str
    labels: list[str] = field(default_factory=list)  # event numbers as written in the log
    lines: list[int] = field(default_factory=list)  # the log's line of each event, for messages

    def wgs84(self) -> np.ndarray:
        """(M, 3) longitude, latitude (degrees, WGS84) and the height as logged."""
        src = self.crs
        if src.equals(CRS.from_epsg(4326)) or src.equals(CRS.from_epsg(4979)):
            return self.xyz.copy()
        if src.is_geocentric:
            t = Transformer.from_crs(src, CRS.from_epsg(4979), always_xy=True)
            lon, lat, h = t.transform(self.xyz[:, 0], self.xyz[:, 1], self.xyz[:, 2])
            return np.stack([lon, lat, h], axis=-1)
        t = Transformer.from_crs(src, CRS.from_epsg(4326), always_xy=True)
        lon, lat = t.transform(self.xyz[:, 0], self.xyz[:, 1])
        return np.stack([lon, lat, self.xyz[:, 2]], axis=-1)


def _epoch_seconds(
    epoch: str, values: np.ndarray | None = None, reference: float | None = None, leap: float = 18.0
) -> float:
    """POSIX seconds of a numeric timestamp's origin: 'unix', 'gps', a date 'YYYY-MM-DD', or 'auto'.

    'auto': values below one week are GPS seconds of the week (the paper's events.txt), the week being
    the one of ``reference`` (the images' capture time); larger values are seconds since 1970.
    """
    e = epoch.strip().lower()
    if e == "auto":
        if values is not None and len(values) and np.nanmedian(values) < 604800 and reference is not None:
            week = np.floor((reference + leap - GPS_EPOCH) / 604800.0)
            return float(GPS_EPOCH + week * 604800.0)
        return 0.0
    if e == "unix":
        return 0.0
    if e == "gps":
        return float(GPS_EPOCH)
    try:
        d = _dt.date.fromisoformat(e)
    except ValueError:
        raise ConfigError(
            f"config key 'timestamp_epoch' = {epoch!r} is not 'auto', 'unix', 'gps' or a date",
            fix="use 'unix' (seconds since 1970), 'gps' (since 1980-01-06) or a date like "
            "2024-06-03 (seconds since that day's 00:00)",
        ) from None
    return float(calendar.timegm(d.timetuple()))


def _parse_time(text: str) -> float | None:
    """A date-time string (ISO or 'YYYY/MM/DD hh:mm:ss.sss') as POSIX seconds of that clock, or None."""
    t = text.strip().replace("/", "-")
    try:
        d = _dt.datetime.fromisoformat(t)
    except ValueError:
        return None
    if d.tzinfo is not None:
        return d.timestamp()
    return calendar.timegm(d.timetuple()) + d.microsecond / 1e6


_COLUMNS = {
    "time": ("timestamp", "time", "gps_time", "gpstime", "datetime", "utc", "gpst", "t", "date_time"),
    "x": ("x", "easting", "east", "e", "utm_x"),
    "y": ("y", "northing", "north", "n", "utm_y"),
    "z": ("z", "alt", "altitude", "height", "elevation", "ellh", "h", "elev", "alt_m", "height_m"),
    "lat": ("lat", "latitude", "lat_deg", "latitude_deg"),
    "lon": ("lon", "long", "lng", "longitude", "lon_deg", "longitude_deg"),
}


def _pick(header: list[str], key: str) -> int | None:
    norm = [re.sub(r"[\s()\[\]]+", "_", h.strip().lower()).strip("_") for h in header]
    for name in _COLUMNS[key]:
        if name in norm:
            return norm.index(name)
    return None


def _read_table(path: Path, epoch: str, gps_base: bool, leap: float, reference: float | None = None, unit: str = "s"):
    """events.txt (TAB, ``Timestamp X Y Z``) or a CSV with lat/lon (or x/y): times, (x, y, z), whether the
    columns are lat/lon, the line of each event and the numeric timestamps as read (for unit checks)."""
    numbered = [
        (i, ln)
        for i, ln in enumerate(read_text(path, what="GNSS log").splitlines(), start=1)
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if len(numbered) < 2:
        what = "is empty" if not numbered else "holds only a header line"
        raise InputError(
            f"the GNSS log {what}: it has no events",
            path=path,
            fix="use the flight's complete log (a header line, then one line per camera event)",
        )
    lines = [ln for _, ln in numbered]
    head = lines[0]
    delim = "," if "," in head else ";" if ";" in head else "\t" if "\t" in head else None
    rows = [r for r in csv.reader(lines, delimiter=delim)] if delim else [ln.split() for ln in lines]
    header = [h.strip() for h in rows[0]]
    it, ix, iy, iz = (_pick(header, k) for k in ("time", "x", "y", "z"))
    ilat, ilon = _pick(header, "lat"), _pick(header, "lon")
    geographic = ilat is not None and ilon is not None
    if not geographic:
        ilat = ilon = None
    if it is None or (not geographic and (ix is None or iy is None)):
        raise InputError(
            f"the GNSS log's header (line {numbered[0][0]}: {header}) lacks a time column and position columns",
            path=path,
            fix="the header must name a time column (Timestamp) and either X Y Z "
            "(projected) or lat lon alt, e.g. 'Timestamp\tX\tY\tZ'",
        )
    cx, cy = (ilon, ilat) if geographic else (ix, iy)
    times, xyz, numeric, where = [], [], [], []
    for (lineno, text), r in zip(numbered[1:], rows[1:]):
        try:
            if delim == ";":  # European spreadsheets: decimal commas
                r = [c.replace(",", ".") for c in r]
            cell = r[it].strip()
            try:
                t = float(cell) / UNITS[unit]
                numeric.append(len(times))
            except ValueError:
                t = _parse_time(cell)
                if t is None:
                    raise ValueError(f"time {cell!r} is neither a number nor a date-time") from None
            z = float(r[iz]) if iz is not None and iz < len(r) and r[iz].strip() else float("nan")
            xyz.append((float(r[cx]), float(r[cy]), z))
            times.append(t)
            where.append(lineno)
        except (ValueError, IndexError) as exc:
            raise InputError(
                f"GNSS log line {lineno} cannot be read ({exc}): {text!r}", path=path, fix="repair or delete that line"
            ) from None
    times = np.asarray(times, dtype=float)
    raw = times[numeric].copy()
    if numeric:
        times[numeric] += _epoch_seconds(epoch, times[numeric], reference, leap)
    return times - (leap if gps_base else 0.0), np.asarray(xyz, dtype=float), geographic, where, raw


def _read_pos(path: Path, gps_base: bool, leap: float):
    """RTKLIB / Emlid ``.pos``: time (date+time or week+seconds), lat/lon/height (deg or d m s) or ECEF."""
    header, times, xyz, where = "", [], [], []
    for lineno, line in enumerate(read_text(path, what="GNSS log").splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("%"):
            header = s.lower()
            continue
        tok = s.split()
        try:
            if "/" in tok[0] or "-" in tok[0][1:]:
                t = _parse_time(f"{tok[0]} {tok[1]}")
                if t is None:
                    raise ValueError("time")
            else:
                t = GPS_EPOCH + float(tok[0]) * 604800.0 + float(tok[1])
            vals = tok[2:]
            if "d'" in header or 'd"' in header or "dms" in header:  # latitude(d'") in degrees minutes seconds

                def dms(a, b, c):
                    sign = -1 if a.strip().startswith("-") else 1
                    return sign * (abs(float(a)) + float(b) / 60 + float(c) / 3600)

                p = (dms(*vals[3:6]), dms(*vals[0:3]), float(vals[6]))
            elif "x-ecef" in header:
                p = (float(vals[0]), float(vals[1]), float(vals[2]))
            else:
                p = (float(vals[1]), float(vals[0]), float(vals[2]))
        except (ValueError, IndexError):
            raise InputError(
                f".pos line {lineno} cannot be read: {line!r}",
                path=path,
                fix="export the solution from RTKLIB/Emlid Studio with lat/lon/height output",
            ) from None
        times.append(t)
        xyz.append(p)
        where.append(lineno)
    if not times:
        raise InputError("the .pos file holds no solutions", path=path, fix="check the file")
    # the header says whether times are GPST or UTC; it overrides the configured time base
    if "utc" in header.split("latitude")[0] or " utc " in f" {header} ":
        gps_base = False
    elif "gpst" in header:
        gps_base = True
    crs = 4978 if "x-ecef" in header else 4979
    return np.asarray(times) - (leap if gps_base else 0.0), np.asarray(xyz, dtype=float), crs, where


_MRK = re.compile(
    r"^\s*(\d+)\s+([\d.]+)\s+\[(\d+)\].*?([-\d.]+)\s*,\s*Lat\s+([-\d.]+)\s*,\s*Lon\s+([-\d.]+)\s*,\s*Ellh",
    re.IGNORECASE,
)


def _read_mrk(path: Path, leap: float):
    """DJI ``*_Timestamp.MRK``: event number, GPS seconds of week, [week], ..., lat,Lat lon,Lon h,Ellh."""
    times, xyz, labels, where = [], [], [], []
    for lineno, line in enumerate(read_text(path, what="GNSS log").splitlines(), start=1):
        if not line.strip():
            continue
        m = _MRK.match(line)
        if not m:
            raise InputError(
                f"MRK line {lineno} is not a DJI timestamp record: {line!r}",
                path=path,
                fix="use the *_Timestamp.MRK file of the flight (not the PPK or .obs file)",
            )
        labels.append(m.group(1))
        times.append(GPS_EPOCH + int(m.group(3)) * 604800.0 + float(m.group(2)) - leap)
        xyz.append((float(m.group(5)), float(m.group(4)), float(m.group(6))))
        where.append(lineno)
    if not times:
        raise InputError("the MRK file holds no events", path=path, fix="check the file")
    return np.asarray(times), np.asarray(xyz, dtype=float), labels, where


def detect_format(path: Path) -> str:
    """Format of a GNSS log from its name and first line: "mrk", "pos", "csv" (a lat column) or "events"."""
    name = path.name.lower()
    if name.endswith(".mrk"):
        return "mrk"
    if name.endswith(".pos"):
        return "pos"
    first = next((ln for ln in read_text(path, what="GNSS log").splitlines() if ln.strip()), "")
    if first.lstrip().startswith("%"):
        return "pos"
    if _pick(re.split(r"[,;\t ]+", first.strip()), "lat") is not None:
        return "csv"
    return "events"


def _log_crs(crs: str | None, default: int | None, own: bool, path: Path) -> CRS:
    """The CRS of the log's positions. ``own``: the log states what its coordinates are (lat/lon columns,
    .pos, .MRK); then a 'log_crs' of another kind (a projected one, say) is ignored with a warning."""
    if not crs:
        return CRS.from_epsg(default)
    the_crs = parse_crs(crs, key="log_crs")
    if own:
        stated = CRS.from_epsg(default)
        if (the_crs.is_geographic, the_crs.is_geocentric) != (stated.is_geographic, stated.is_geocentric):
            log.warning(
                "%s states its coordinates (%s): 'log_crs' (%s) is ignored", path.name, stated.name, the_crs.name
            )
            return stated
    return the_crs


def read_gnss_log(
    path: str | Path,
    fmt: str = "auto",
    crs: str | None = None,
    time_base: str = "gps",
    leap_seconds: float = 18.0,
    timestamp_epoch: str = "auto",
    reference_time: float | None = None,
    timestamp_unit: str = "s",
) -> GnssLog:
    """Read a GNSS event log; times become UTC POSIX seconds, the CRS comes from ``crs`` or the format.

    ``reference_time`` (a capture time of the flight, UTC) dates GPS seconds-of-week timestamps;
    ``timestamp_unit`` is the unit of numeric timestamps in events.txt / CSV logs. Every time and
    position is checked (:mod:`.log_checks`) before it can reach an image."""
    path = Path(path)
    if not path.is_file():
        raise InputError("GNSS log not found", path=path, fix="set 'gnss_log' to the events file of the flight")
    if timestamp_unit not in UNITS:
        raise ConfigError(
            f"config key 'timestamp_unit' = {timestamp_unit!r} is not one of {', '.join(UNITS)}",
            fix="use s (seconds), ms, us or ns",
        )
    fmt = detect_format(path) if fmt == "auto" else fmt
    gps_base = time_base == "gps"
    labels: list[str] = []
    raw = None
    geographic = False
    if fmt == "mrk":
        times, xyz, labels, where = _read_mrk(path, leap_seconds)
        default_crs = 4979
    elif fmt == "pos":
        times, xyz, default_crs, where = _read_pos(path, gps_base, leap_seconds)
    else:
        times, xyz, geographic, where, raw = _read_table(
            path, timestamp_epoch, gps_base, leap_seconds, reference_time, timestamp_unit
        )
        if geographic:
            default_crs = 4326
        elif not crs:
            raise ConfigError(
                "the GNSS log has projected X Y coordinates but no CRS is set",
                path=path,
                fix="set 'log_crs' to the log's EPSG code, e.g. EPSG:32614 or 'WGS84 UTM 14N'",
            )
        else:
            default_crs = None
    own = geographic or fmt in ("mrk", "pos")
    the_crs = _log_crs(crs, default_crs, own, path)
    check_finite(times, where, path, "timestamp")
    check_times(times, where, path, raw, timestamp_unit)
    check_positions(xyz, the_crs, where, path, by_header=own)
    labels = labels or [str(i + 1) for i in range(len(times))]
    keep = duplicate_events(times, xyz, where, path)
    return GnssLog(
        times=times[keep],
        xyz=xyz[keep],
        crs=the_crs,
        path=path,
        format=fmt,
        labels=[labels[i] for i in keep],
        lines=[where[i] for i in keep],
    )
