"""Image metadata: EXIF capture time, GPS and camera, the XMP packet, and writing GPS into a JPEG copy.

One reader/writer pair for every step: step 0 writes GNSS positions into copies of the images, step 1
reads them back (with the camera and DJI's XMP) to predict where each GCP appears.

Writing splices a new EXIF segment into the JPEG instead of re-encoding it: the compressed pixels and
every other segment (JFIF, XMP with DJI's gimbal angles, ICC) are copied byte for byte, so the copy is
the same photo for ODM and for the detector.
"""

from __future__ import annotations

import calendar
import datetime as _dt
import re
import struct
from pathlib import Path

import numpy as np
import piexif
from PIL import Image

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import BatchedWrites, atomic_open
from matchplant.core.runtime.log import get_logger

log = get_logger("exif")

OFFSET_TIME_ORIGINAL = 0x9011  # "+02:00"; piexif has no name for it


# ==================================================================================================
# reading


def load_exif(path: str | Path) -> dict:
    """piexif's dictionary of an image's EXIF (empty IFDs when the image has none): JPEG, TIFF, WebP, and
    PNG (its eXIf chunk, which piexif cannot find itself, read through PIL)."""
    try:
        if Path(path).suffix.lower() == ".png":
            with Image.open(path) as im:
                return piexif.load(im.getexif().tobytes())
        return piexif.load(str(path))
    except Exception as exc:  # noqa: BLE001 - piexif raises several types for damaged files
        raise InputError(
            f"cannot read the EXIF of this image ({type(exc).__name__}: {exc})",
            path=path,
            fix="check that the file is a complete JPEG/TIFF; remove it from the folder if not",
        ) from exc


def exif_text(value) -> str:
    """An EXIF ASCII value as clean text: cameras pad with NULs and spaces, some store str, most bytes."""
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    return str(value).strip().strip("\x00").strip()


def exif_time(exif: dict, utc_offset_h: float = 0.0) -> float | None:
    """``DateTimeOriginal`` + ``SubSecTimeOriginal`` as POSIX seconds (UTC), or None when absent.

    The camera clock is local time unless ``OffsetTimeOriginal`` says otherwise; ``utc_offset_h`` is the
    camera clock's offset from UTC in hours (the clock offset estimation absorbs any error in it).
    """
    e = exif.get("Exif") or {}
    raw = (
        e.get(piexif.ExifIFD.DateTimeOriginal)
        or e.get(piexif.ExifIFD.DateTimeDigitized)
        or (exif.get("0th") or {}).get(piexif.ImageIFD.DateTime)
    )
    if not raw:
        return None
    try:
        t = _dt.datetime.strptime(exif_text(raw)[:19], "%Y:%m:%d %H:%M:%S")
    except ValueError:
        return None
    seconds = calendar.timegm(t.timetuple())
    sub = exif_text(e.get(piexif.ExifIFD.SubSecTimeOriginal, b""))
    if sub.isdigit():
        seconds += int(sub) / 10 ** len(sub)
    offset = exif_text(e.get(OFFSET_TIME_ORIGINAL, b""))
    m = re.match(r"^([+-])(\d\d):(\d\d)$", offset)
    if m:
        sign = 1 if m.group(1) == "+" else -1
        return seconds - sign * (int(m.group(2)) * 3600 + int(m.group(3)) * 60)
    return seconds - utc_offset_h * 3600.0


def has_subseconds(exif: dict) -> bool:
    """Whether the capture time has sub-seconds (without them, whole-second times need a wider match)."""
    return exif_text((exif.get("Exif") or {}).get(piexif.ExifIFD.SubSecTimeOriginal, b"")).isdigit()


def rational(r) -> float:
    """An EXIF rational (numerator, denominator) as a float; NaN for a zero denominator."""
    return r[0] / r[1] if r[1] else float("nan")


def exif_gps(exif: dict) -> tuple[float, float, float | None] | None:
    """(lat, lon, altitude) in degrees / metres from the GPS IFD, or None without a position."""
    g = exif.get("GPS") or {}
    try:
        lat = sum(rational(v) / 60**i for i, v in enumerate(g[piexif.GPSIFD.GPSLatitude]))
        lon = sum(rational(v) / 60**i for i, v in enumerate(g[piexif.GPSIFD.GPSLongitude]))
    except (KeyError, TypeError, IndexError):
        return None
    if exif_text(g.get(piexif.GPSIFD.GPSLatitudeRef, b"N")).upper() == "S":
        lat = -lat
    if exif_text(g.get(piexif.GPSIFD.GPSLongitudeRef, b"E")).upper() == "W":
        lon = -lon
    alt = None
    if piexif.GPSIFD.GPSAltitude in g:
        alt = rational(g[piexif.GPSIFD.GPSAltitude])
        if g.get(piexif.GPSIFD.GPSAltitudeRef, 0) in (1, b"\x01"):
            alt = -alt
    return lat, lon, alt


def image_gps(path: str | Path) -> tuple[float, float, float | None] | None:
    """:func:`exif_gps` of an image file; None as well when the file has no readable EXIF."""
    try:
        return exif_gps(load_exif(path))
    except InputError:
        return None


def exif_camera(exif: dict) -> tuple[str, str, float | None, float | None]:
    """(make, model, focal length mm, 35 mm-equivalent focal length mm); a missing focal is None."""
    zeroth, ex = exif.get("0th") or {}, exif.get("Exif") or {}
    make = exif_text(zeroth.get(piexif.ImageIFD.Make, b""))
    model = exif_text(zeroth.get(piexif.ImageIFD.Model, b""))
    focal = focal35 = None
    fl = ex.get(piexif.ExifIFD.FocalLength)
    if fl and fl[1]:
        focal = fl[0] / fl[1]
    f35 = ex.get(piexif.ExifIFD.FocalLengthIn35mmFilm)
    if f35:
        focal35 = float(f35)
    return make, model, focal, focal35


def read_xmp(path: str | Path, limit: int = 1 << 19) -> str:
    """The XMP packet (JPEG APP1 or TIFF tag), found in the file's first bytes, or ''.

    A text search, not a parser: vendors write XMP in both attribute and element form, and the packet
    sits near the start of the file in every layout met so far."""
    with open(path, "rb") as fh:
        head = fh.read(limit)
    start = head.find(b"<x:xmpmeta")
    if start < 0:
        return ""
    end = head.find(b"</x:xmpmeta>", start)
    return head[start : end if end > 0 else len(head)].decode("utf-8", errors="replace")


# ==================================================================================================
# writing


def dms_rationals(deg: float) -> tuple:
    """Degrees as EXIF (deg, min, sec) rationals with 1e-6 arc-second resolution (3e-10 degrees)."""
    micro = int(round(abs(deg) * 3600 * 1_000_000))
    d, rem = divmod(micro, 3600 * 1_000_000)
    m, s = divmod(rem, 60 * 1_000_000)
    return ((d, 1), (m, 1), (s, 1_000_000))


def gps_ifd(lat: float, lon: float, alt: float | None, utc_time: float | None = None) -> dict:
    """A GPS IFD for piexif; ``utc_time`` (POSIX seconds of the fix) fills GPSDateStamp/GPSTimeStamp."""
    G = piexif.GPSIFD
    ifd = {
        G.GPSVersionID: (2, 3, 0, 0),
        G.GPSLatitudeRef: b"N" if lat >= 0 else b"S",
        G.GPSLatitude: dms_rationals(lat),
        G.GPSLongitudeRef: b"E" if lon >= 0 else b"W",
        G.GPSLongitude: dms_rationals(lon),
        G.GPSMapDatum: b"WGS-84",
    }
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
        length = struct.unpack(">H", data[pos + 2 : pos + 4])[0]
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
    exif_segs = [(s, e) for m, s, e in segments if m == 0xE1 and data[s + 4 : s + 10] == b"Exif\x00\x00"]
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
    return data[jpeg_segments(data)[1] :]


def dump_exif(exif: dict, src: Path) -> bytes:
    """``piexif.dump``, dropping (with a warning) tags a camera wrote with a type piexif cannot write."""
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
        raise InputError(
            f"cannot rewrite this image's EXIF ({exc})",
            path=src,
            fix="remove the image, or strip its EXIF maker notes with exiftool",
        ) from exc


def write_gps_copy(
    src: Path,
    dst: Path,
    exif: dict,
    lat: float,
    lon: float,
    alt: float | None,
    utc_time: float | None = None,
    writer: BatchedWrites | None = None,
) -> None:
    """Copy ``src`` to ``dst`` with the GPS IFD set; the pixel data and other segments are untouched.

    With ``writer`` (a :class:`~matchplant.core.runtime.io.BatchedWrites` on ``dst``'s folder) the copy is made
    durable with its batch (one sync per batch); without, on its own (an fsync per file)."""
    exif = {k: v for k, v in exif.items() if k != "GPS"}
    exif["GPS"] = gps_ifd(lat, lon, alt, utc_time)
    exif_bytes = dump_exif(exif, src)
    data = src.read_bytes()
    try:
        out = splice_exif(data, exif_bytes)
    except ValueError as exc:
        raise InputError(
            f"cannot write EXIF into this image: {exc}", path=src, fix="check that the file is a complete JPEG"
        ) from exc
    if writer is not None:
        writer.write(Path(dst).name, out)
        return
    with atomic_open(dst, "wb") as fh:
        fh.write(out)
