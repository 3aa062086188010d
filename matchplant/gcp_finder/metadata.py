"""What step 1 needs from each image, read once without decoding pixels: size, EXIF and DJI's XMP.

The camera's focal length relative to its sensor decides where a GCP lands in the image; EXIF gives
the focal length in mm but not the sensor size, hence the table of common drone cameras below.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from matchplant.core.formats.exif import exif_camera, exif_gps, exif_time, load_exif, read_xmp
from matchplant.core.formats.images import JPEG_SUFFIXES
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate import check_jpeg

# Sensor width in mm (the long side) of common drone cameras, keyed by lower-case EXIF Model.
SENSOR_WIDTH_MM: dict[str, float] = {
    "fc6310": 13.2,
    "fc6310s": 13.2,
    "fc6310r": 13.2,  # Phantom 4 Pro / V2.0 / RTK
    "fc6360": 4.96,  # Phantom 4 Multispectral
    "fc330": 6.17,
    "fc300x": 6.17,
    "fc300s": 6.17,  # Phantom 4, Phantom 3
    "fc220": 6.17,
    "fc2103": 6.17,
    "fc2204": 6.3,  # Mavic Pro, Mavic Air, Mini
    "fc3170": 6.4,
    "fc3411": 13.2,
    "fc3582": 9.7,  # Mavic Air 2, Air 2S, Mini 3 Pro
    "fc7303": 6.3,
    "fc8482": 9.6,  # Mini 2, Mini 4 Pro
    "l1d-20c": 13.2,
    "l2d-20c": 17.3,  # Mavic 2 Pro, Mavic 3
    "m3e": 17.3,
    "m3m": 17.3,
    "m3t": 6.4,  # Mavic 3 Enterprise / Multispectral / Thermal
    "zenmusep1": 35.9,
    "zenmusex5s": 17.3,
    "zenmusex7": 23.5,
    "zh20": 7.6,
    "zenmuseh20": 7.6,
    "fc6520": 17.3,
    "fc6540": 23.5,  # Zenmuse X5S, X7 (Inspire 2)
    "rededge-m": 4.8,
    "rededge-mx": 4.8,
    "rededge": 4.8,
    "altum": 7.12,
    "altum-pt": 7.12,
    "sequoia": 4.8,
    "anafi": 6.17,
    "anafiusa": 6.4,
    "ilce-6000": 23.5,
    "ilce-5100": 23.5,
    "ilce-6100": 23.5,
    "ilce-7rm2": 35.9,
    "ilce-7rm4": 35.7,
    "dsc-rx1rm2": 35.9,
    "hero4 black": 6.17,
    "hero4 silver": 6.17,
    "gopro hero5 black": 6.17,
    "canon eos digital rebel xsi": 22.2,
    "canon eos 450d": 22.2,
}


@dataclass
class ImageInfo:
    """What the finder needs from one image, read once."""

    name: str
    path: Path
    width: int
    height: int
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    focal_mm: float | None = None
    focal35_mm: float | None = None
    make: str = ""
    model: str = ""
    time: float | None = None
    yaw: float | None = None  # degrees clockwise from north of the image top (camera heading)
    pitch: float | None = None  # gimbal pitch, degrees (-90 = straight down)
    relative_alt: float | None = None  # DJI: metres above the take-off point
    xyz: np.ndarray | None = None  # camera position in the output CRS (set by the finder)


_XMP_KEYS = {
    "GimbalYawDegree": "gimbal_yaw",
    "FlightYawDegree": "flight_yaw",
    "GimbalPitchDegree": "pitch",
    "RelativeAltitude": "relative_alt",
}


def parse_dji_xmp(text: str) -> dict[str, float]:
    """DJI's drone-dji XMP values (attribute or element form) as floats."""
    out = {}
    for key, name in _XMP_KEYS.items():
        m = re.search(rf'drone-dji:{key}\s*=\s*"([^"]+)"', text) or re.search(
            rf"<drone-dji:{key}>([^<]+)</drone-dji:{key}>", text
        )
        if m:
            try:
                out[name] = float(m.group(1))
            except ValueError:
                pass
    return out


def read_image_info(path: str | Path) -> ImageInfo:
    """Read an image's size, EXIF and DJI XMP once (pixels are not decoded; a JPEG cut short is refused,
    since its header alone looks whole)."""
    path = Path(path)
    if path.suffix.lower() in JPEG_SUFFIXES:
        check_jpeg(path)
    try:
        with Image.open(path) as im:
            width, height = im.size
    except Exception as exc:  # noqa: BLE001
        raise InputError(
            f"cannot open the image ({exc})",
            path=path,
            fix="check that it is a complete JPEG or TIFF; remove it from the folder if not",
        ) from exc
    info = ImageInfo(path.name, path, int(width), int(height))
    exif = load_exif(path)
    info.make, info.model, info.focal_mm, info.focal35_mm = exif_camera(exif)
    gps = exif_gps(exif)
    if gps is not None and np.isfinite(gps[:2]).all() and gps[:2] != (0.0, 0.0):  # 0, 0: a camera without a fix
        info.lat, info.lon, info.alt = gps
    info.time = exif_time(exif)
    xmp = parse_dji_xmp(read_xmp(path))
    info.yaw = xmp.get("gimbal_yaw", xmp.get("flight_yaw"))
    info.pitch = xmp.get("pitch")
    info.relative_alt = xmp.get("relative_alt")
    return info


def sensor_width_mm(info: ImageInfo, override: float | None = None) -> float | None:
    """The configured sensor width, else the built-in table's for the EXIF model (None if unknown)."""
    if override:
        return override
    model = info.model.lower().strip()
    for key in (model, model.replace(" ", ""), f"{info.make.lower()} {model}".strip()):
        if key in SENSOR_WIDTH_MM:
            return SENSOR_WIDTH_MM[key]
    return None


def focal_ratio(info: ImageInfo, sensor_width: float | None = None, focal_mm: float | None = None) -> float:
    """Focal length / sensor long side (OpenSfM's normalised focal)."""
    f = focal_mm or info.focal_mm
    sw = sensor_width_mm(info, sensor_width)
    if f and sw:
        return f / sw
    if info.focal35_mm:
        return info.focal35_mm / 36.0
    raise InputError(
        f"the camera '{info.make} {info.model}' is not in the built-in sensor table and the image "
        "has no 35 mm-equivalent focal length",
        path=info.path,
        fix="set 'sensor_width_mm' (the sensor's long side in mm) in the config",
    )
