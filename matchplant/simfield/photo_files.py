"""The simulated drone's files: photos encoded as the camera writes them (JPEG with EXIF, GPS or none), the
undistorted TIFFs and the per-pixel plant-id masks (16-bit PNG)."""

from __future__ import annotations

import datetime as dt
import io
from pathlib import Path

import cv2
import numpy as np
import piexif

from matchplant.core.runtime.io import atomic_open
from matchplant.simfield.config import Settings
from matchplant.simfield.flight import SENSOR_WIDTH_MM

CAMERA_MAKE, CAMERA_MODEL = "MatchPlant", "SimCam"


def camera_model(s: Settings) -> str:
    """EXIF camera model: the simulated camera's model name plus the image width."""
    return f"{CAMERA_MODEL} {s.image_width}"


def encode(rgb: np.ndarray, ext: str, quality: int = 95) -> bytes:
    """An RGB image encoded as the format of ``ext`` (OpenCV writes BGR)."""
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if ext == ".jpg" else []
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:  # pragma: no cover - OpenCV always encodes these
        raise RuntimeError(f"could not encode {ext}")
    return buf.tobytes()


def write_bytes(path: Path, data: bytes) -> None:
    """Write bytes to a file whole, or nothing if it fails."""
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def write_image(path: Path, rgb: np.ndarray, ext: str) -> None:
    """Write an RGB image in the format of ``ext``."""
    write_bytes(path, encode(rgb, ext))


def write_mask(path: Path, ids: np.ndarray) -> None:
    """Write a mask of plant ids as a 16-bit PNG."""
    if ids.max(initial=0) > 65535:  # pragma: no cover - presets stay below
        raise ValueError("more than 65535 plants: the masks cannot be written as 16-bit PNG")
    ok, buf = cv2.imencode(".png", ids.astype(np.uint16))
    write_bytes(path, buf.tobytes())


def rational_dms(value: float) -> tuple:
    """EXIF rational degrees, minutes, seconds of an angle (sign dropped)."""
    micro = int(round(abs(value) * 3600e6))  # micro-arcseconds: exact to ~3e-11 degree
    deg, rest = divmod(micro, 3600 * 10**6)
    minutes, sec = divmod(rest, 60 * 10**6)
    return ((deg, 1), (minutes, 1), (sec, 10**6))


def with_exif(jpeg: bytes, s: Settings, cam_time: dt.datetime, gps: tuple | None) -> bytes:
    """The JPEG with the drone's EXIF: camera, time, focal length and, when ``gps`` is given, the GPS fix."""
    stamp = cam_time.strftime("%Y:%m:%d %H:%M:%S")
    sub = f"{cam_time.microsecond // 1000:03d}"
    focal_mm = s.focal * SENSOR_WIDTH_MM
    exif = {
        "0th": {
            piexif.ImageIFD.Make: CAMERA_MAKE,
            piexif.ImageIFD.Model: camera_model(s),
            piexif.ImageIFD.Software: "matchplant simfield",
            piexif.ImageIFD.Orientation: 1,
            piexif.ImageIFD.DateTime: stamp,
        },
        "Exif": {
            piexif.ExifIFD.DateTimeOriginal: stamp,
            piexif.ExifIFD.DateTimeDigitized: stamp,
            piexif.ExifIFD.SubSecTimeOriginal: sub,
            piexif.ExifIFD.SubSecTimeDigitized: sub,
            piexif.ExifIFD.FocalLength: (int(round(focal_mm * 1000)), 1000),
            piexif.ExifIFD.FocalLengthIn35mmFilm: int(round(s.focal * 36)),
            piexif.ExifIFD.PixelXDimension: s.image_width,
            piexif.ExifIFD.PixelYDimension: s.image_height,
            piexif.ExifIFD.FocalPlaneXResolution: (int(round(s.image_width / SENSOR_WIDTH_MM * 1000)), 1000),
            piexif.ExifIFD.FocalPlaneResolutionUnit: 4,
        },
        "GPS": {},
        "1st": {},
        "thumbnail": None,
    }
    if gps is not None:
        lat, lon, alt = gps
        exif["GPS"] = {
            piexif.GPSIFD.GPSVersionID: (2, 3, 0, 0),
            piexif.GPSIFD.GPSLatitudeRef: "N" if lat >= 0 else "S",
            piexif.GPSIFD.GPSLatitude: rational_dms(lat),
            piexif.GPSIFD.GPSLongitudeRef: "E" if lon >= 0 else "W",
            piexif.GPSIFD.GPSLongitude: rational_dms(lon),
            piexif.GPSIFD.GPSAltitudeRef: 0 if alt >= 0 else 1,
            piexif.GPSIFD.GPSAltitude: (int(round(abs(alt) * 1000)), 1000),
            piexif.GPSIFD.GPSMapDatum: "WGS-84",
        }
    out = io.BytesIO()
    piexif.insert(piexif.dump(exif), jpeg, out)
    return out.getvalue()
