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

The EXIF helpers here (reading time and GPS, splicing EXIF into a JPEG) are also used by module 1.
"""

from __future__ import annotations

import calendar
import csv
import datetime as _dt
import re
import shutil
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from matchplant.core.config import param
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.io import atomic_open, write_json
from matchplant.core.log import get_logger
from matchplant.core.progress import progress

log = get_logger("gps_embed")

IMAGE_SUFFIXES = (".jpg", ".jpeg")
GPS_EPOCH = calendar.timegm((1980, 1, 6, 0, 0, 0))  # POSIX seconds of the GPS time origin
LOG_FORMATS = ("auto", "events", "csv", "pos", "mrk")


# ==================================================================================================
# EXIF: reading, GPS IFD, lossless splicing into a JPEG


def load_exif(path: str | Path) -> dict:
    """piexif's dictionary of an image's EXIF (empty IFDs when the image has none)."""
    import piexif

    try:
        return piexif.load(str(path))
    except Exception as exc:  # noqa: BLE001 - piexif raises several types for damaged files
        raise InputError(f"cannot read the EXIF of this image ({type(exc).__name__}: {exc})", path=path,
                         fix="check that the file is a complete JPEG/TIFF; remove it from the folder if not") from exc


def _text(value) -> str:
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    return str(value).strip().strip("\x00").strip()


def exif_time(exif: dict, utc_offset_h: float = 0.0) -> float | None:
    """``DateTimeOriginal`` + ``SubSecTimeOriginal`` as POSIX seconds (UTC), or None when absent.

    The camera clock is local time unless ``OffsetTimeOriginal`` says otherwise; ``utc_offset_h`` is the
    camera clock's offset from UTC in hours (the clock offset estimation absorbs any error in it).
    """
    import piexif

    e = exif.get("Exif") or {}
    raw = e.get(piexif.ExifIFD.DateTimeOriginal) or e.get(piexif.ExifIFD.DateTimeDigitized) or \
        (exif.get("0th") or {}).get(piexif.ImageIFD.DateTime)
    if not raw:
        return None
    try:
        t = _dt.datetime.strptime(_text(raw)[:19], "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    seconds = calendar.timegm(t.timetuple())
    sub = _text(e.get(piexif.ExifIFD.SubSecTimeOriginal, b""))
    if sub.isdigit():
        seconds += int(sub) / 10 ** len(sub)
    offset = _text(e.get(0x9011, b""))  # OffsetTimeOriginal, "+02:00"
    m = re.match(r"^([+-])(\d\d):(\d\d)$", offset)
    if m:
        sign = 1 if m.group(1) == "+" else -1
        return seconds - sign * (int(m.group(2)) * 3600 + int(m.group(3)) * 60)
    return seconds - utc_offset_h * 3600.0


def has_subseconds(exif: dict) -> bool:
    import piexif

    return _text((exif.get("Exif") or {}).get(piexif.ExifIFD.SubSecTimeOriginal, b"")).isdigit()


def _rational(r) -> float:
    return r[0] / r[1] if r[1] else float("nan")


def exif_gps(exif: dict) -> tuple[float, float, float | None] | None:
    """(lat, lon, altitude) in degrees / metres from the GPS IFD, or None without a position."""
    import piexif

    g = exif.get("GPS") or {}
    try:
        lat = sum(_rational(v) / 60 ** i for i, v in enumerate(g[piexif.GPSIFD.GPSLatitude]))
        lon = sum(_rational(v) / 60 ** i for i, v in enumerate(g[piexif.GPSIFD.GPSLongitude]))
    except (KeyError, TypeError, IndexError):
        return None
    if _text(g.get(piexif.GPSIFD.GPSLatitudeRef, b"N")).upper() == "S":
        lat = -lat
    if _text(g.get(piexif.GPSIFD.GPSLongitudeRef, b"E")).upper() == "W":
        lon = -lon
    alt = None
    if piexif.GPSIFD.GPSAltitude in g:
        alt = _rational(g[piexif.GPSIFD.GPSAltitude])
        if g.get(piexif.GPSIFD.GPSAltitudeRef, 0) in (1, b"\x01"):
            alt = -alt
    return lat, lon, alt


def _dms(deg: float) -> tuple:
    """Degrees as EXIF (deg, min, sec) rationals with 1e-6 arc-second resolution (3e-10 degrees)."""
    micro = int(round(abs(deg) * 3600 * 1_000_000))
    d, rem = divmod(micro, 3600 * 1_000_000)
    m, s = divmod(rem, 60 * 1_000_000)
    return ((d, 1), (m, 1), (s, 1_000_000))


def gps_ifd(lat: float, lon: float, alt: float | None, utc_time: float | None = None) -> dict:
    """A GPS IFD for piexif; ``utc_time`` (POSIX seconds of the fix) fills GPSDateStamp/GPSTimeStamp."""
    import piexif

    G = piexif.GPSIFD
    ifd = {G.GPSVersionID: (2, 3, 0, 0),
           G.GPSLatitudeRef: b"N" if lat >= 0 else b"S", G.GPSLatitude: _dms(lat),
           G.GPSLongitudeRef: b"E" if lon >= 0 else b"W", G.GPSLongitude: _dms(lon),
           G.GPSMapDatum: b"WGS-84"}
    if alt is not None and np.isfinite(alt):
        ifd[G.GPSAltitudeRef] = 0 if alt >= 0 else 1
        ifd[G.GPSAltitude] = (int(round(abs(alt) * 1000)), 1000)
    if utc_time is not None and np.isfinite(utc_time):
        t = _dt.datetime.fromtimestamp(utc_time, _dt.timezone.utc)
        if t.year >= 2000:  # an absolute time, not seconds of an unknown day or week
            ms = int(round((t.second + t.microsecond / 1e6) * 1000))
            ifd[G.GPSTimeStamp] = ((t.hour, 1), (t.minute, 1), (ms, 1000))
            ifd[G.GPSDateStamp] = t.strftime("%Y:%m:%d").encode()
    return ifd


def jpeg_segments(data: bytes) -> tuple[list[tuple[int, int, int]], int]:
    """The marker segments before the image data: ``[(marker, start, end)], start_of_scan``."""
    if data[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG (no SOI marker)")
    segments, pos, n = [], 2, len(data)
    while pos + 4 <= n:
        if data[pos] != 0xFF:
            raise ValueError(f"corrupt JPEG header at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker == 0xDA:  # start of scan: the compressed image follows
            return segments, pos
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # markers without a length
            segments.append((marker, pos, pos + 2))
            pos += 2
            continue
        length = struct.unpack(">H", data[pos + 2:pos + 4])[0]
        segments.append((marker, pos, pos + 2 + length))
        pos += 2 + length
    raise ValueError("truncated JPEG (no start-of-scan marker)")


def splice_exif(data: bytes, exif_bytes: bytes) -> bytes:
    """``data`` (a JPEG) with its EXIF APP1 replaced by ``exif_bytes`` (from ``piexif.dump``).

    Every other byte is kept: APP0/JFIF, XMP (also an APP1), ICC, quantisation tables and the compressed
    scan. (``piexif.insert`` drops the JFIF APP0 segment and can duplicate EXIF after an XMP segment.)
    """
    if not exif_bytes.startswith(b"Exif\x00\x00"):
        raise ValueError("EXIF bytes must start with 'Exif\\0\\0'")
    if len(exif_bytes) + 2 > 0xFFFF:
        raise ValueError("EXIF block larger than a JPEG segment (64 KiB); the thumbnail is too big")
    segments, _ = jpeg_segments(data)
    new = b"\xff\xe1" + struct.pack(">H", len(exif_bytes) + 2) + exif_bytes
    exif_segs = [(s, e) for m, s, e in segments if m == 0xE1 and data[s + 4:s + 10] == b"Exif\x00\x00"]
    if exif_segs:
        insert_at = exif_segs[0][0]
    else:  # after SOI and a leading JFIF APP0, where EXIF readers look for it
        insert_at = 2
        for m, s, e in segments:
            if m == 0xE0 and s == insert_at:
                insert_at = e
            else:
                break
    out, pos = [], 0
    for s, e in exif_segs:
        if s == insert_at:
            out += [data[pos:s], new]
        else:
            out.append(data[pos:s])
        pos = e
    if not exif_segs:
        out += [data[:insert_at], new]
        pos = insert_at
    out.append(data[pos:])
    return b"".join(out)


def jpeg_scan_data(data: bytes) -> bytes:
    """The compressed image (from the start-of-scan marker to the end): equal bytes = equal pixels."""
    return data[jpeg_segments(data)[1]:]


def _dump_exif(exif: dict, src: Path) -> bytes:
    """``piexif.dump``, dropping (with a warning) tags a camera wrote with a type piexif cannot write."""
    import piexif

    try:
        return piexif.dump(exif)
    except Exception:  # noqa: BLE001 - piexif raises several types for malformed vendor tags
        pass
    dropped = []
    for ifd in ("0th", "Exif", "GPS", "Interop", "1st"):
        for tag, value in list((exif.get(ifd) or {}).items()):
            try:
                piexif.dump({ifd: {tag: value}} if ifd != "Interop" else {"Exif": {}, ifd: {tag: value}})
            except Exception:  # noqa: BLE001
                del exif[ifd][tag]
                dropped.append(f"{ifd}:{tag}")
    log.warning("%s: EXIF tags piexif cannot rewrite were left out: %s", src.name, ", ".join(dropped) or "none")
    try:
        return piexif.dump(exif)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"cannot rewrite this image's EXIF ({exc})", path=src,
                         fix="remove the image, or strip its EXIF maker notes with exiftool") from exc


def write_gps_copy(src: Path, dst: Path, exif: dict, lat: float, lon: float, alt: float | None,
                   utc_time: float | None = None) -> None:
    """Copy ``src`` to ``dst`` with the GPS IFD set; the pixel data and other segments are untouched."""
    import piexif

    exif = {k: v for k, v in exif.items() if k != "GPS"}
    exif["GPS"] = gps_ifd(lat, lon, alt, utc_time)
    exif_bytes = _dump_exif(exif, src)
    data = src.read_bytes()
    try:
        out = splice_exif(data, exif_bytes)
    except ValueError as exc:
        raise InputError(f"cannot write EXIF into this image: {exc}", path=src,
                         fix="check that the file is a complete JPEG") from exc
    with atomic_open(dst, "wb") as fh:
        fh.write(out)


# ==================================================================================================
# GNSS logs


@dataclass
class GnssLog:
    """Events of a GNSS log: UTC POSIX times and positions in the log's CRS (``crs``)."""

    times: np.ndarray        # (M,) seconds, UTC
    xyz: np.ndarray          # (M, 3) in ``crs`` (x = easting or longitude)
    crs: object              # pyproj CRS
    path: Path
    format: str
    labels: list[str] = field(default_factory=list)  # event numbers as written in the log

    def wgs84(self) -> np.ndarray:
        """(M, 3) longitude, latitude (degrees, WGS84) and the height as logged."""
        from pyproj import CRS, Transformer

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


def _epoch_seconds(epoch: str, values: np.ndarray | None = None, reference: float | None = None,
                   leap: float = 18.0) -> float:
    """POSIX seconds of a numeric timestamp's origin: 'unix', 'gps', a date 'YYYY-MM-DD', or 'auto'.

    'auto': values below one week are GPS seconds of the week (the paper's events.txt), the week being
    the one of ``reference`` (the images' capture time); larger values are seconds since 1970.
    """
    e = epoch.strip().lower()
    if e == "auto":
        if values is not None and len(values) and np.nanmax(values) < 604800 and reference is not None:
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
        raise ConfigError(f"config key 'timestamp_epoch' = {epoch!r} is not 'auto', 'unix', 'gps' or a date",
                          fix="use 'unix' (seconds since 1970), 'gps' (since 1980-01-06) or a date like "
                              "2024-06-03 (seconds since that day's 00:00)") from None
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


def _read_table(path: Path, epoch: str, gps_base: bool, leap: float, reference: float | None = None):
    """events.txt (TAB, ``Timestamp X Y Z``) or a CSV with lat/lon (or x/y): times and (x, y, z)."""
    lines = [ln for ln in path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
             if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise InputError("the GNSS log has no events (a header line and at least one row are needed)", path=path,
                         fix="check that this is the log of the flight")
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
        raise InputError(f"the GNSS log's header {header} lacks a time column and position columns",
                         path=path, fix="the header must name a time column (Timestamp) and either X Y Z "
                                        "(projected) or lat lon alt, e.g. 'Timestamp\tX\tY\tZ'")
    cx, cy = (ilon, ilat) if geographic else (ix, iy)
    times, xyz, numeric = [], [], []
    for lineno, r in enumerate(rows[1:], start=2):
        try:
            cell = r[it].strip()
            try:
                t = float(cell)
                numeric.append(len(times))
            except ValueError:
                t = _parse_time(cell)
                if t is None:
                    raise ValueError(f"time {cell!r}")
            z = float(r[iz]) if iz is not None and iz < len(r) and r[iz].strip() else float("nan")
            xyz.append((float(r[cx]), float(r[cy]), z))
            times.append(t)
        except (ValueError, IndexError) as exc:
            raise InputError(f"GNSS log line {lineno} cannot be read ({exc}): {lines[lineno - 1]!r}", path=path,
                             fix="repair or delete that line") from None
    times = np.asarray(times, dtype=float)
    if numeric:
        times[numeric] += _epoch_seconds(epoch, times[numeric], reference, leap)
    return times - (leap if gps_base else 0.0), np.asarray(xyz, dtype=float), geographic


def _read_pos(path: Path, gps_base: bool, leap: float):
    """RTKLIB / Emlid ``.pos``: time (date+time or week+seconds), lat/lon/height (deg or d m s) or ECEF."""
    header, times, xyz = "", [], []
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
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
            raise InputError(f".pos line {lineno} cannot be read: {line!r}", path=path,
                             fix="export the solution from RTKLIB/Emlid Studio with lat/lon/height output") from None
        times.append(t)
        xyz.append(p)
    if not times:
        raise InputError("the .pos file holds no solutions", path=path, fix="check the file")
    # the header says whether times are GPST or UTC; it overrides the configured time base
    if "utc" in header.split("latitude")[0] or " utc " in f" {header} ":
        gps_base = False
    elif "gpst" in header:
        gps_base = True
    crs = 4978 if "x-ecef" in header else 4979
    return np.asarray(times) - (leap if gps_base else 0.0), np.asarray(xyz, dtype=float), crs


_MRK = re.compile(r"^\s*(\d+)\s+([\d.]+)\s+\[(\d+)\].*?([-\d.]+)\s*,\s*Lat\s+([-\d.]+)\s*,\s*Lon\s+([-\d.]+)\s*,\s*Ellh",
                  re.IGNORECASE)


def _read_mrk(path: Path, leap: float):
    """DJI ``*_Timestamp.MRK``: event number, GPS seconds of week, [week], ..., lat,Lat lon,Lon h,Ellh."""
    times, xyz, labels = [], [], []
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        if not line.strip():
            continue
        m = _MRK.match(line)
        if not m:
            raise InputError(f"MRK line {lineno} is not a DJI timestamp record: {line!r}", path=path,
                             fix="use the *_Timestamp.MRK file of the flight (not the PPK or .obs file)")
        labels.append(m.group(1))
        times.append(GPS_EPOCH + int(m.group(3)) * 604800.0 + float(m.group(2)) - leap)
        xyz.append((float(m.group(5)), float(m.group(4)), float(m.group(6))))
    if not times:
        raise InputError("the MRK file holds no events", path=path, fix="check the file")
    return np.asarray(times), np.asarray(xyz, dtype=float), labels


def detect_format(path: Path) -> str:
    name = path.name.lower()
    if name.endswith(".mrk"):
        return "mrk"
    if name.endswith(".pos"):
        return "pos"
    first = next((ln for ln in path.read_text(encoding="utf-8-sig", errors="replace").splitlines() if ln.strip()), "")
    if first.lstrip().startswith("%"):
        return "pos"
    if _pick(re.split(r"[,;\t ]+", first.strip()), "lat") is not None:
        return "csv"
    return "events"


def read_gnss_log(path: str | Path, fmt: str = "auto", crs: str | None = None, time_base: str = "gps",
                  leap_seconds: float = 18.0, timestamp_epoch: str = "auto",
                  reference_time: float | None = None) -> GnssLog:
    """Read a GNSS event log; times become UTC POSIX seconds, the CRS comes from ``crs`` or the format.

    ``reference_time`` (a capture time of the flight, UTC) dates GPS seconds-of-week timestamps."""
    from matchplant.core.frames import parse_crs

    path = Path(path)
    if not path.is_file():
        raise InputError("GNSS log not found", path=path, fix="set 'gnss_log' to the events file of the flight")
    fmt = detect_format(path) if fmt == "auto" else fmt
    gps_base = time_base == "gps"
    labels: list[str] = []
    if fmt == "mrk":
        times, xyz, labels = _read_mrk(path, leap_seconds)
        default_crs = 4979
    elif fmt == "pos":
        times, xyz, default_crs = _read_pos(path, gps_base, leap_seconds)
    else:
        times, xyz, geographic = _read_table(path, timestamp_epoch, gps_base, leap_seconds, reference_time)
        if geographic:
            default_crs = 4326
        elif not crs:
            raise ConfigError("the GNSS log has projected X Y coordinates but no CRS is set", path=path,
                              fix="set 'log_crs' to the log's EPSG code, e.g. EPSG:32614 or 'WGS84 UTM 14N'")
        else:
            default_crs = None
    from pyproj import CRS
    the_crs = parse_crs(crs, source=path) if crs else CRS.from_epsg(default_crs)
    if len(times) and not np.all(np.isfinite(times)):
        raise InputError("the GNSS log has invalid times", path=path, fix="check the time column")
    return GnssLog(times=times, xyz=xyz, crs=the_crs, path=path, format=fmt,
                   labels=labels or [str(i + 1) for i in range(len(times))])


# ==================================================================================================
# Matching


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


# ==================================================================================================
# The module


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


@dataclass
class ImageRecord:
    name: str
    path: Path
    exif: dict | None = None
    time: float | None = None
    reason: str = ""


def _list_images(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        others = sorted({p.suffix.lower() for p in folder.iterdir() if p.is_file()})
        raise InputError("no JPEG images in the image folder" + (f" (found {', '.join(others)})" if others else ""),
                         path=folder, fix="point 'images' at the folder of the flight's .jpg files")
    return files


def read_images(folder: Path, utc_offset_h: float = 0.0) -> list[ImageRecord]:
    records = []
    for p in progress(_list_images(folder), desc="reading EXIF", unit="img"):
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


def match_images(records: list[ImageRecord], gnss: GnssLog, cfg: GpsEmbedConfig) -> tuple[np.ndarray, float, int]:
    """Event index per image (-1 none), the clock offset and its support; fills each record's reason."""
    cam = np.array([r.time if r.time is not None else np.nan for r in records], dtype=float)
    tol = cfg.tolerance_s
    timed = [r for r in records if r.time is not None]
    if timed and not any(has_subseconds(r.exif) for r in timed):
        tol = max(tol, 1.0)
        log.warning("the images have no sub-second times (SubSecTimeOriginal); matching with a %.1f s tolerance", tol)
    if cfg.clock_offset_s is not None:
        offset, support = float(cfg.clock_offset_s), -1
    else:
        offset, support = estimate_clock_offset(cam, gnss.times, tol, cfg.max_clock_offset_s)
        if not np.isfinite(offset):
            raise InputError("no clock offset can be estimated: no image has a capture time, or no event lies "
                             "within 'max_clock_offset_s'", path=cfg.images,
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


REPORT_FIELDS = ("image", "status", "event", "camera_time_utc", "event_time_utc", "dt_s", "x", "y", "z",
                 "longitude", "latitude", "altitude", "reason")


def _iso(t: float | None) -> str:
    if t is None or not np.isfinite(t):
        return ""
    return _dt.datetime.fromtimestamp(t, _dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3]


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
    idx, offset, support = match_images(records, gnss, cfg)
    if support >= 0:
        log.info("clock offset (log - camera): %.3f s, supported by %d of %d images", offset, support,
                 sum(r.time is not None for r in records))
    lla = gnss.wgs84()
    rows, geo = [], []
    out_images.mkdir(parents=True, exist_ok=True)
    for i, r in enumerate(progress(records, desc="writing GPS", unit="img")):
        j = int(idx[i])
        row = dict.fromkeys(REPORT_FIELDS, "")
        row.update(image=r.name, camera_time_utc=_iso(r.time))
        if j >= 0:
            lon, lat, alt = lla[j]
            alt_val = float(alt) if np.isfinite(alt) else None
            write_gps_copy(r.path, out_images / r.name, r.exif, float(lat), float(lon), alt_val, gnss.times[j])
            row.update(status="matched", event=gnss.labels[j], event_time_utc=_iso(gnss.times[j]),
                       dt_s=f"{gnss.times[j] - (r.time + offset):+.3f}",
                       x=repr(float(gnss.xyz[j, 0])), y=repr(float(gnss.xyz[j, 1])), z=repr(float(gnss.xyz[j, 2])),
                       longitude=f"{lon:.9f}", latitude=f"{lat:.9f}", altitude=f"{alt:.3f}")
            geo.append(f"{r.name} {lon:.9f} {lat:.9f} {alt:.3f}" if alt_val is not None else
                       f"{r.name} {lon:.9f} {lat:.9f}")
        else:
            row.update(status="unmatched", reason=r.reason)
            if cfg.copy_unmatched:
                with atomic_open(out_images / r.name, "wb") as fh, open(r.path, "rb") as src:
                    shutil.copyfileobj(src, fh)
        rows.append(row)
    with atomic_open(out / "match_report.csv", "w") as fh:
        w = csv.DictWriter(fh, fieldnames=REPORT_FIELDS)
        w.writeheader()
        w.writerows(rows)
    if cfg.write_geo_txt:
        with atomic_open(out / "geo.txt", "w") as fh:
            fh.write("EPSG:4326\n" + "".join(line + "\n" for line in geo))
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
