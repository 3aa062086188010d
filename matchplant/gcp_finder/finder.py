"""Module 1: find the images that see each ground control point, mark them, write ODM's ``gcp_list.txt``.

1. Read each image's metadata once (:func:`read_image_info`): size, EXIF focal length and GPS, and DJI
   XMP (relative altitude, gimbal/flight yaw, gimbal pitch) when present.
2. Read the GCP survey (``id,x,y,z`` in a stated CRS, lon/lat or projected) and convert it to the
   output CRS (a metric one: the survey's own, or the GCPs' UTM zone).
3. Predict where each GCP appears in each image (:func:`predict_pixels`): a pinhole camera at the GPS
   position, rotated by yaw and pitch, at its height above the GCP; the sensor width comes from a
   built-in table of common drone cameras or the config. An image is a candidate for a GCP when the
   prediction lies inside it and within ``max_center_distance`` of its centre; candidates are ranked by
   that distance (the centre has the least distortion and relief error).
4. Mark the exact pixel in the GUI (:mod:`matchplant.gcp_finder.gui`) or let ``auto`` find the target
   (a black-and-white square) near each prediction to sub-pixel precision (:func:`detect_target`).
5. Write ``gcp_list.txt`` (:func:`write_gcp_list`): line 1 the CRS, then
   ``geo_x geo_y geo_z im_x im_y image_name gcp_name`` with pixel coordinates in the original image
   (the centre of the first pixel is 0, 0). ODM wants every GCP in at least 3 images.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from matchplant.core.config import param
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.io import atomic_open
from matchplant.core.log import get_logger
from matchplant.core.progress import progress

log = get_logger("gcp_finder")

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff")
MIN_IMAGES_PER_GCP = 3

# Sensor width in mm (the long side) of common drone cameras, keyed by lower-case EXIF Model.
SENSOR_WIDTH_MM: dict[str, float] = {
    "fc6310": 13.2, "fc6310s": 13.2, "fc6310r": 13.2,      # Phantom 4 Pro / V2.0 / RTK
    "fc6360": 4.96,                                          # Phantom 4 Multispectral
    "fc330": 6.17, "fc300x": 6.17, "fc300s": 6.17,          # Phantom 4, Phantom 3
    "fc220": 6.17, "fc2103": 6.17, "fc2204": 6.3,           # Mavic Pro, Mavic Air, Mini
    "fc3170": 6.4, "fc3411": 13.2, "fc3582": 9.7,           # Mavic Air 2, Air 2S, Mini 3 Pro
    "fc7303": 6.3, "fc8482": 9.6,                            # Mini 2, Mini 4 Pro
    "l1d-20c": 13.2, "l2d-20c": 17.3,                       # Mavic 2 Pro, Mavic 3
    "m3e": 17.3, "m3m": 17.3, "m3t": 6.4,                   # Mavic 3 Enterprise / Multispectral / Thermal
    "zenmusep1": 35.9, "zenmusex5s": 17.3, "zenmusex7": 23.5, "zh20": 7.6, "zenmuseh20": 7.6,
    "fc6520": 17.3, "fc6540": 23.5,                          # Zenmuse X5S, X7 (Inspire 2)
    "rededge-m": 4.8, "rededge-mx": 4.8, "rededge": 4.8, "altum": 7.12, "altum-pt": 7.12,
    "sequoia": 4.8, "anafi": 6.17, "anafiusa": 6.4,
    "ilce-6000": 23.5, "ilce-5100": 23.5, "ilce-6100": 23.5, "ilce-7rm2": 35.9, "ilce-7rm4": 35.7,
    "dsc-rx1rm2": 35.9, "hero4 black": 6.17, "hero4 silver": 6.17, "gopro hero5 black": 6.17,
    "canon eos digital rebel xsi": 22.2, "canon eos 450d": 22.2,
}


# ==================================================================================================
# Image metadata


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
    yaw: float | None = None             # degrees clockwise from north of the image top (camera heading)
    pitch: float | None = None           # gimbal pitch, degrees (-90 = straight down)
    relative_alt: float | None = None    # DJI: metres above the take-off point
    xyz: np.ndarray | None = None        # camera position in the output CRS (set by the finder)


_XMP_KEYS = {"GimbalYawDegree": "gimbal_yaw", "FlightYawDegree": "flight_yaw",
             "GimbalPitchDegree": "pitch", "RelativeAltitude": "relative_alt"}


def parse_dji_xmp(text: str) -> dict[str, float]:
    """DJI's drone-dji XMP values (attribute or element form) as floats."""
    out = {}
    for key, name in _XMP_KEYS.items():
        m = re.search(rf'drone-dji:{key}\s*=\s*"([^"]+)"', text) or \
            re.search(rf"<drone-dji:{key}>([^<]+)</drone-dji:{key}>", text)
        if m:
            try:
                out[name] = float(m.group(1))
            except ValueError:
                pass
    return out


def _read_xmp(path: Path, limit: int = 1 << 19) -> str:
    """The XMP packet (JPEG APP1 or TIFF tag), found in the file's first bytes, or ''."""
    with open(path, "rb") as fh:
        head = fh.read(limit)
    start = head.find(b"<x:xmpmeta")
    if start < 0:
        return ""
    end = head.find(b"</x:xmpmeta>", start)
    return head[start:end if end > 0 else len(head)].decode("utf-8", errors="replace")


def read_image_info(path: str | Path) -> ImageInfo:
    """Read an image's size, EXIF and DJI XMP once (pixels are not decoded)."""
    import piexif
    from PIL import Image

    from matchplant.gps_embeder.embed import _text, exif_gps, exif_time, load_exif

    path = Path(path)
    try:
        with Image.open(path) as im:
            width, height = im.size
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"cannot open the image ({exc})", path=path,
                         fix="check that it is a complete JPEG or TIFF; remove it from the folder if not") from exc
    info = ImageInfo(path.name, path, int(width), int(height))
    exif = load_exif(path)
    zeroth, ex = exif.get("0th") or {}, exif.get("Exif") or {}
    info.make = _text(zeroth.get(piexif.ImageIFD.Make, b""))
    info.model = _text(zeroth.get(piexif.ImageIFD.Model, b""))
    fl = ex.get(piexif.ExifIFD.FocalLength)
    if fl and fl[1]:
        info.focal_mm = fl[0] / fl[1]
    f35 = ex.get(piexif.ExifIFD.FocalLengthIn35mmFilm)
    if f35:
        info.focal35_mm = float(f35)
    gps = exif_gps(exif)
    if gps is not None:
        info.lat, info.lon, info.alt = gps
    info.time = exif_time(exif)
    xmp = parse_dji_xmp(_read_xmp(path))
    info.yaw = xmp.get("gimbal_yaw", xmp.get("flight_yaw"))
    info.pitch = xmp.get("pitch")
    info.relative_alt = xmp.get("relative_alt")
    return info


def list_images(folder: Path) -> list[Path]:
    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError("no JPEG or TIFF images in the image folder", path=folder,
                         fix="point 'images' at the folder of the flight's images")
    return files


def sensor_width_mm(info: ImageInfo, override: float | None = None) -> float | None:
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
    raise InputError(f"the camera '{info.make} {info.model}' is not in the built-in sensor table and the image "
                     "has no 35 mm-equivalent focal length", path=info.path,
                     fix="set 'sensor_width_mm' (the sensor's long side in mm) in the config")


# ==================================================================================================
# GCP survey and gcp_list.txt


@dataclass
class GCP:
    id: str
    x: float  # output CRS
    y: float
    z: float


_SURVEY_COLUMNS = {
    "id": ("id", "name", "gcp", "gcp_id", "label", "point", "point_name", "gcp_name"),
    "x": ("x", "easting", "east", "e", "lon", "long", "longitude", "lng"),
    "y": ("y", "northing", "north", "n", "lat", "latitude"),
    "z": ("z", "elevation", "elev", "alt", "altitude", "height", "h", "ellh"),
}


def read_survey(path: str | Path, crs_text: str, output_crs=None) -> tuple[list[GCP], object]:
    """GCP table ``id,x,y,z`` in ``crs_text``; returns the GCPs in the output CRS and that CRS.

    The output CRS is ``output_crs`` if given, else the survey's own CRS when projected, else the UTM
    zone of the GCPs (ODM wants metres).
    """
    from pyproj import CRS, Transformer

    from matchplant.core.frames import parse_crs, utm_crs_for

    path = Path(path)
    if not path.is_file():
        raise InputError("GCP survey file not found", path=path, fix="set 'survey' to the GCP table (id,x,y,z)")
    if not crs_text:
        raise ConfigError("the GCP survey's CRS is not set", path=path,
                          fix="set 'survey_crs' to its EPSG code, e.g. EPSG:32614 (UTM 14N) or EPSG:4326 (lon/lat)")
    src = parse_crs(crs_text, source=path)
    lines = [ln for ln in path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
             if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 2:
        raise InputError("the GCP survey holds no points (a header line and one line per GCP are needed)",
                         path=path, fix="write it as CSV with the header id,x,y,z")
    head = lines[0]
    delim = "," if "," in head else ";" if ";" in head else "\t" if "\t" in head else None
    rows = list(csv.reader(lines, delimiter=delim)) if delim else [ln.split() for ln in lines]
    norm = [h.strip().lower() for h in rows[0]]
    cols = {}
    for key, names in _SURVEY_COLUMNS.items():
        hits = [norm.index(n) for n in names if n in norm]
        if hits:
            cols[key] = hits[0]
    # lon/lat named columns: x must be the longitude whatever the order in the file
    if "lon" in norm or "longitude" in norm:
        cols["x"] = norm.index("lon") if "lon" in norm else norm.index("longitude")
    if "lat" in norm or "latitude" in norm:
        cols["y"] = norm.index("lat") if "lat" in norm else norm.index("latitude")
    missing = [k for k in ("id", "x", "y", "z") if k not in cols]
    if missing:
        raise InputError(f"the GCP survey lacks the column(s) {', '.join(missing)} (header: {rows[0]})", path=path,
                         fix="the first line must name the columns id,x,y,z (x = easting or longitude)")
    ids, pts = [], []
    for lineno, r in enumerate(rows[1:], start=2):
        try:
            ids.append(r[cols["id"]].strip())
            pts.append([float(r[cols[k]]) for k in ("x", "y", "z")])
        except (ValueError, IndexError):
            raise InputError(f"survey line {lineno} cannot be read: {lines[lineno - 1]!r}", path=path,
                             fix="each line needs an id and numeric x, y, z") from None
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise InputError(f"duplicate GCP ids in the survey: {', '.join(dup)}", path=path, fix="give each GCP its own id")
    pts = np.asarray(pts, dtype=float)
    if src.is_geographic and (np.abs(pts[:, 1]) > 90).any():
        raise InputError("survey latitudes beyond ±90°: are x and y swapped, or is the CRS projected?", path=path,
                         fix="x is the longitude and y the latitude; or set 'survey_crs' to the projected CRS")
    if output_crs is not None:
        dst = parse_crs(output_crs) if isinstance(output_crs, str) else output_crs
    elif src.is_projected:
        dst = src
    else:
        lonlat = Transformer.from_crs(src, CRS.from_epsg(4326), always_xy=True).transform(pts[:, 0].mean(),
                                                                                         pts[:, 1].mean())
        dst = utm_crs_for(*lonlat)
    if not dst.equals(src):
        x, y = Transformer.from_crs(src, dst, always_xy=True).transform(pts[:, 0], pts[:, 1])
        pts = np.stack([x, y, pts[:, 2]], axis=-1)
    if not np.all(np.isfinite(pts)):
        raise InputError("some GCPs cannot be converted to the output CRS", path=path,
                         fix="check 'survey_crs' (x = easting or longitude, y = northing or latitude)")
    return [GCP(i, *p) for i, p in zip(ids, pts)], dst


def crs_header(crs) -> str:
    """Line 1 of gcp_list.txt: 'EPSG:nnnn' when the CRS has a code, else its PROJ string."""
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_proj4()


@dataclass
class Mark:
    """One line of gcp_list.txt: a GCP's map position and its pixel in one image."""

    x: float
    y: float
    z: float
    u: float
    v: float
    image: str
    gcp: str = ""
    extra: list[str] = field(default_factory=list)


def read_gcp_list(path: str | Path) -> tuple[str, object, list[Mark]]:
    """Read an ODM gcp_list.txt: (header line, its CRS, marks). Any header ODM accepts."""
    from matchplant.core.frames import parse_crs

    path = Path(path)
    if not path.is_file():
        raise InputError("gcp_list.txt not found", path=path, fix="check the path")
    lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    body = [(i, ln) for i, ln in enumerate(lines, start=1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise InputError("gcp_list.txt is empty", path=path, fix="line 1 must be the CRS, e.g. EPSG:32614")
    header = body[0][1].strip()
    crs = parse_crs(header, source=path)
    marks = []
    for lineno, ln in body[1:]:
        tok = ln.split()
        try:
            if len(tok) < 6:
                raise ValueError
            x, y, z, u, v = (float(t) for t in tok[:5])
        except ValueError:
            raise InputError(f"gcp_list.txt line {lineno} is not 'geo_x geo_y geo_z im_x im_y image [gcp_name]': "
                             f"{ln.strip()!r}", path=path, fix="repair or delete that line") from None
        marks.append(Mark(x, y, z, u, v, tok[5], tok[6] if len(tok) > 6 else "", tok[7:]))
    return header, crs, marks


def write_gcp_list(path: str | Path, header: str, marks: list[Mark]) -> Path:
    """Write gcp_list.txt atomically (TAB-separated, pixel coordinates to 1/1000 px)."""
    with atomic_open(path, "w") as fh:
        fh.write(header.strip() + "\n")
        for m in marks:
            fh.write(f"{m.x:.4f}\t{m.y:.4f}\t{m.z:.4f}\t{m.u:.3f}\t{m.v:.3f}\t{m.image}\t{m.gcp}\n")
    return Path(path)


# ==================================================================================================
# Geometry: where each GCP appears


def camera_rotation(yaw_deg: float, pitch_deg: float = -90.0) -> np.ndarray:
    """World (east, north, up) -> camera (x right, y down, z forward) rotation for a gimbal camera.

    ``yaw`` is the heading of the image's top edge (clockwise from north); ``pitch`` the gimbal pitch
    (-90 straight down, 0 horizontal). Roll is taken as zero (a gimbal keeps it small).
    """
    psi, p = math.radians(yaw_deg), math.radians(pitch_deg)
    h = np.array([math.sin(psi), math.cos(psi), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    z = math.cos(p) * h + math.sin(p) * up
    y = math.sin(p) * h - math.cos(p) * up
    x = np.cross(y, z)
    return np.stack([x, y, z])


def track_yaw(positions: np.ndarray) -> np.ndarray:
    """Heading (degrees from north) of the flight line each image was taken on.

    Consecutive steps in about the same direction (within 30°) form a flight line; a line's heading is
    from its first to its last image, which averages out the GPS noise of single steps. A turn between
    lines is a lone step; images at the ends of a line take that line's heading.
    """
    p = np.asarray(positions, dtype=float)[:, :2]
    n = len(p)
    if n < 2:
        return np.zeros(n)
    seg = np.diff(p, axis=0)
    unit = seg / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
    agree = np.einsum("ij,ij->i", unit[1:], unit[:-1]) > math.cos(math.radians(30))
    run = np.r_[0, np.cumsum(~agree)]  # run id of each step
    heading, is_line = {}, {}
    for r in np.unique(run):
        k = np.flatnonzero(run == r)
        d = p[k[-1] + 1] - p[k[0]]
        heading[r], is_line[r] = d, len(k) >= 2
    if not any(is_line.values()):
        is_line = dict.fromkeys(is_line, True)
    out = np.zeros((n, 2))
    for i in range(n):
        arriving = run[i - 1] if i > 0 else None
        leaving = run[i] if i < n - 1 else None
        use = [r for r in (arriving, leaving) if r is not None and is_line[r]] or \
              [r for r in (arriving, leaving) if r is not None]
        out[i] = heading[use[0]] / max(np.linalg.norm(heading[use[0]]), 1e-9)
    return np.degrees(np.arctan2(out[:, 0], out[:, 1])) % 360.0


@dataclass
class Candidate:
    gcp: str
    image: str
    u: float   # predicted pixel
    v: float
    center_distance: float  # 0 at the centre, 1 at a corner
    rank: int = 0


def _pinhole(info: ImageInfo, ratio: float):
    from matchplant.core.camera import PinholeCamera

    return PinholeCamera(id=info.model or "camera", projection_type="perspective", width=info.width,
                         height=info.height, focal_x=ratio, focal_y=ratio)


def predict_pixels(info: ImageInfo, ratio: float, yaw: float, pitch: float, camera_z: np.ndarray,
                   points: np.ndarray) -> np.ndarray:
    """Predicted pixels (N, 2) of map points (N, 3) in one image; ``camera_z`` (N,) is the camera height
    used for each point (so each point's own height above ground can be applied)."""
    R = camera_rotation(yaw, pitch)
    centre = np.broadcast_to(np.r_[info.xyz[:2], 0.0], points.shape).copy()
    centre[:, 2] = camera_z
    return _pinhole(info, ratio).project((points - centre) @ R.T)


def footprint(info: ImageInfo, ratio: float, yaw: float, pitch: float, height: float) -> np.ndarray:
    """The image's four corners on a level ground ``height`` metres below the camera (map x, y)."""
    cam = _pinhole(info, ratio)
    corners = np.array([[-0.5, -0.5], [info.width - 0.5, -0.5], [info.width - 0.5, info.height - 0.5],
                        [-0.5, info.height - 0.5]])
    rays = cam.bearings(corners) @ camera_rotation(yaw, pitch)
    s = height / np.maximum(-rays[:, 2], 1e-6)
    return info.xyz[:2] + rays[:, :2] * s[:, None]


# ==================================================================================================
# Target detection (--auto)


def symmetry_peaks(gray: np.ndarray, u0: float, v0: float, radius: int = 60, min_contrast: float = 40.0,
                   n: int = 1) -> list[tuple[float, float]]:
    """Up to ``n`` sub-pixel centres of point symmetry near (u0, v0), strongest first.

    A black-and-white square target (black and white quadrants, or a square of one tone on the other)
    is point-symmetric about its centre. The (high-passed) window is correlated with itself rotated by
    180°: a peak at lag p means symmetry about the point half-way, refined by a parabola fit. Empty when
    the window has no contrast (no target there).
    """
    import cv2

    h, w = gray.shape[:2]
    u0i, v0i = int(round(u0)), int(round(v0))
    x0, x1 = max(0, u0i - radius), min(w, u0i + radius + 1)
    y0, y1 = max(0, v0i - radius), min(h, v0i + radius + 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return []
    win = gray[y0:y1, x0:x1].astype(np.float32)
    lo, hi = np.percentile(win, [1, 99])
    if hi - lo < min_contrast:
        return []
    win = win - cv2.GaussianBlur(win, (0, 0), radius / 2.0)  # remove the soil's slow shading
    sub = win[::-1, ::-1]
    cc = cv2.filter2D(win, cv2.CV_32F, sub, borderType=cv2.BORDER_CONSTANT)
    # local maxima, strongest first
    dil = cv2.dilate(cc, np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero((cc >= dil) & (cc > 0))
    order = np.argsort(-cc[ys, xs])[:n]

    def parabola(a, b, c):
        den = a - 2 * b + c
        return 0.0 if den == 0 else 0.5 * (a - c) / den

    # filter2D anchors the kernel at its centre k: a peak at px means symmetry about (px + n - 1 - k) / 2
    kx, ky = (sub.shape[1] - 1) / 2.0, (sub.shape[0] - 1) / 2.0
    out = []
    for py, px in zip(ys[order], xs[order]):
        dx = parabola(cc[py, px - 1], cc[py, px], cc[py, px + 1]) if 0 < px < cc.shape[1] - 1 else 0.0
        dy = parabola(cc[py - 1, px], cc[py, px], cc[py + 1, px]) if 0 < py < cc.shape[0] - 1 else 0.0
        out.append((x0 + (px + dx + win.shape[1] - 1 - kx) / 2.0, y0 + (py + dy + win.shape[0] - 1 - ky) / 2.0))
    return out


def detect_target(gray: np.ndarray, u0: float, v0: float, radius: int = 60, min_contrast: float = 40.0
                  ) -> tuple[float, float] | None:
    """The strongest centre of symmetry near (u0, v0) (see :func:`symmetry_peaks`), or None."""
    peaks = symmetry_peaks(gray, u0, v0, radius, min_contrast, n=1)
    return peaks[0] if peaks else None


def symmetry_score(gray: np.ndarray, uv: tuple[float, float], r: int, pattern: str = "checker") -> float:
    """How much the (2r+1)-pixel patch centred at ``uv`` looks like the centre of a target (up to 1).

    Both target kinds are symmetric under a 180° turn. Under a 90° turn a 2x2 checker's centre is
    anti-symmetric (black and white quadrants swap) and a plain square's symmetric; the score is the
    smaller of the two correlations (with the sign the pattern calls for), so the centre of one
    checker quadrant - a plain square of its own - does not pass for a checker's centre.
    """
    import cv2

    patch = cv2.getRectSubPix(np.ascontiguousarray(gray, dtype=np.float32), (2 * r + 1, 2 * r + 1),
                              (float(uv[0]), float(uv[1])))
    a = patch - patch.mean()
    energy = max(float((a * a).sum()), 1e-6)
    c180 = float((a * a[::-1, ::-1]).sum()) / energy
    c90 = float((a * np.rot90(a)).sum()) / energy
    return min(c180, -c90 if pattern == "checker" else c90)


def symmetry_map(gray: np.ndarray, u: float, v: float, radius: int, r: int, pattern: str = "checker"
                 ) -> tuple[np.ndarray, int, int] | None:
    """:func:`symmetry_score` of the (2r+1)-pixel patch centred on every pixel within ``radius`` of
    (u, v) (patches inside the image only), vectorised: sums of products of shifted views.

    Returns (score map, x of its first column, y of its first row), or None when no patch fits.
    """
    import cv2

    h, w = gray.shape[:2]
    x0, x1 = max(r, int(round(u)) - radius), min(w - 1 - r, int(round(u)) + radius)
    y0, y1 = max(r, int(round(v)) - radius), min(h - 1 - r, int(round(v)) + radius)
    if x1 < x0 or y1 < y0:
        return None
    g = gray[y0 - r:y1 + r + 1, x0 - r:x1 + r + 1].astype(np.float64)
    ny, nx = y1 - y0 + 1, x1 - x0 + 1

    def view(dy: int, dx: int) -> np.ndarray:
        return g[r + dy:r + dy + ny, r + dx:r + dx + nx]

    s180 = np.zeros((ny, nx))
    s90 = np.zeros((ny, nx))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            a = view(dy, dx)
            s180 += a * view(-dy, -dx)
            s90 += a * view(dx, -dy)
    n = (2 * r + 1) ** 2
    box = (2 * r + 1, 2 * r + 1)
    mean = cv2.boxFilter(g, -1, box, normalize=True, borderType=cv2.BORDER_ISOLATED)[r:r + ny, r:r + nx]
    sq = cv2.boxFilter(g * g, -1, box, normalize=True, borderType=cv2.BORDER_ISOLATED)[r:r + ny, r:r + nx]
    var = n * (sq - mean * mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        c180 = (s180 - n * mean * mean) / var
        c90 = (s90 - n * mean * mean) / var
    score = np.minimum(c180, -c90 if pattern == "checker" else c90)
    score[~(var > n * 25.0)] = -1.0  # flat patches (std below 5 grey levels) are no target
    return score, x0, y0


def locate_target(gray: np.ndarray, u: float, v: float, target_px: float, search_px: int = 0,
                  pattern: str = "checker", min_symmetry: float = 0.6, tries: int = 5
                  ) -> tuple[float, float] | None:
    """Find a target of about ``target_px`` pixels near a predicted (u, v).

    Every pixel of the search window is scored by how much its neighbourhood looks like a target's
    centre (:func:`symmetry_map`); the best few local maxima are refined to sub-pixel precision with a
    window fitted to the target (kept inside the image, so a target cut by the edge still has a
    symmetric neighbourhood around its centre) and checked again (:func:`symmetry_score` above
    ``min_symmetry``; ``pattern`` is 'checker' for black and white quadrants, 'square' for a plain
    square). Returns the best, or None (not found, or its centre too close to the edge).
    """
    import cv2

    h, w = gray.shape[:2]
    radius = search_px or max(16, int(0.06 * w), int(0.75 * target_px))
    found = symmetry_map(gray, u, v, radius, int(np.clip(0.15 * target_px, 3, 8)), pattern)
    if found is None:
        return None
    score, x0, y0 = found
    score = score.astype(np.float32)
    peaks = (score >= cv2.dilate(score, np.ones((5, 5), np.uint8))) & (score > 0.5 * min_symmetry)
    ys, xs = np.nonzero(peaks)
    best, best_score = None, min_symmetry
    for k in np.argsort(-score[ys, xs])[:tries]:
        uv: tuple[float, float] | None = (float(x0 + xs[k]), float(y0 + ys[k]))
        for _ in range(2):
            edge = min(uv[0], uv[1], w - 1 - uv[0], h - 1 - uv[1])
            uv = detect_target(gray, uv[0], uv[1], max(4, min(int(0.9 * target_px), int(edge) - 1)))
            if uv is None:
                break
        if uv is None:
            continue
        r = int(min(0.25 * target_px, min(uv[0], uv[1], w - 1 - uv[0], h - 1 - uv[1]) - 1))
        if r >= 3:
            s = symmetry_score(gray, uv, r, pattern)
            if s > best_score:
                best, best_score = uv, s
    return best


def load_gray(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("L"), dtype=np.float32)


# ==================================================================================================
# The module


@dataclass
class GcpFinderConfig:
    """Module 1: find the images that see each GCP, mark the GCPs (GUI or auto), write gcp_list.txt."""

    images: Path | None = param(None, "folder of the flight's images (JPEG or TIFF, with EXIF GPS)", path="dir",
                                required=True)
    survey: Path | None = param(None, "GCP survey table: CSV with the header id,x,y,z", path="file", required=True)
    survey_crs: str | None = param(None, "CRS of the survey: EPSG code (EPSG:32614, EPSG:4326 = lon/lat), "
                                         "'WGS84 UTM 14N' or a PROJ string", required=True)
    output_dir: Path = param(Path("gcp_finder_out"), "output folder: gcp_list.txt, candidates.csv, "
                             "candidates.png", path="out")
    output_crs: str | None = param(None, "CRS of gcp_list.txt; empty = the survey's CRS when projected, "
                                         "else the GCPs' UTM zone")
    sensor_width_mm: float | None = param(None, "camera sensor width (long side, mm); empty = from the "
                                                "built-in table of drone cameras by EXIF model", min=0.1)
    focal_length_mm: float | None = param(None, "focal length (mm); empty = EXIF FocalLength", min=0.1)
    yaw_source: str = param("auto", "image heading: 'xmp' (DJI gimbal/flight yaw), 'track' (direction of "
                                    "flight between images), 'fixed' (yaw_deg); 'auto' = xmp, else track",
                            choices=("auto", "xmp", "track", "fixed"))
    yaw_deg: float = param(0.0, "heading of the image top (degrees clockwise from north) for yaw_source "
                                "'fixed', added to the flight direction for 'track'", min=-360, max=360)
    height_source: str = param("auto", "camera height above a GCP: 'gps' (EXIF altitude - GCP z), 'relative' "
                                       "(DJI relative altitude), 'fixed' (flight_height_m); 'auto' = relative "
                                       "when the images have it, else gps", choices=("auto", "gps", "relative", "fixed"))
    altitude_offset_m: float = param(0.0, "added to the EXIF GPS altitude to put it in the survey's height "
                                          "datum (e.g. the geoid height when GPS is ellipsoidal)")
    flight_height_m: float | None = param(None, "flight height above ground (m) for height_source 'fixed'", min=1)
    max_center_distance: float = param(0.8, "candidate only when the predicted GCP is within this distance "
                                            "of the image centre (0 = centre, 1 = a corner)", min=0.0, max=1.0)
    edge_margin_px: int = param(10, "ignore predictions closer than this to the image edge (pixels)", min=0)
    max_images_per_gcp: int = param(0, "keep only the best-ranked candidates per GCP (0 = all)", min=0)
    auto: bool = param(False, "find each target in its candidate images and write gcp_list.txt without the GUI")
    search_radius_px: int = param(0, "auto: half-size of the search window around a prediction (0 = the "
                                     "larger of 6 % of the image width and 3/4 of the target)", min=0)
    target_size_m: float = param(0.5, "auto: side of the square GCP target (m)", min=0.01)
    target_pattern: str = param("checker", "auto: the target's look: 'checker' (2x2 black and white quadrants) "
                                           "or 'square' (a plain square on a contrasting background)",
                                choices=("checker", "square"))
    zoom_px: int = param(150, "GUI: half-size of the view around a predicted position (pixels)", min=10)
    gcp_list: Path | None = param(None, "existing gcp_list.txt to continue (empty = output_dir/gcp_list.txt "
                                        "if it exists)")


@dataclass
class Finder:
    """Everything the GUI and auto mode need: GCPs, image metadata and ranked candidates."""

    gcps: dict[str, GCP]
    crs: object
    images: dict[str, ImageInfo]
    candidates: dict[str, list[Candidate]]      # per GCP, best first
    ratio: dict[str, float]
    yaw: dict[str, float]
    pitch: dict[str, float]
    height: dict[tuple[str, str], float]        # (gcp, image) -> camera height above the GCP

    def gsd(self, gcp: str, image: str) -> float:
        info = self.images[image]
        return self.height[(gcp, image)] / (self.ratio[image] * max(info.width, info.height))


def _camera_positions(infos: list[ImageInfo], crs) -> None:
    from pyproj import CRS, Transformer

    t = Transformer.from_crs(CRS.from_epsg(4326), crs, always_xy=True)
    for info in infos:
        x, y = t.transform(info.lon, info.lat)
        info.xyz = np.array([x, y, info.alt if info.alt is not None else np.nan])


def _image_yaw(info: ImageInfo, cfg: GcpFinderConfig, track: float) -> float:
    """The heading of the image top: DJI XMP, the flight line's direction, or the configured value."""
    src = cfg.yaw_source
    if src == "auto":
        src = "xmp" if info.yaw is not None else "track"
    if src == "xmp":
        if info.yaw is None:
            raise InputError("the image has no DJI yaw in its XMP", path=info.path,
                             fix="set 'yaw_source' to 'track' or 'fixed'")
        return info.yaw
    if src == "track":
        return (track + cfg.yaw_deg) % 360.0
    return cfg.yaw_deg


def _camera_heights(info: ImageInfo, cfg: GcpFinderConfig, pts: np.ndarray, ground: float
                    ) -> tuple[np.ndarray, str]:
    """The camera's height (z in the survey's datum) used for each GCP, and which source gave it."""
    hs = cfg.height_source
    if hs == "auto":
        # DJI's relative altitude is robust; EXIF altitudes are often in another height datum than the survey
        hs = "relative" if info.relative_alt is not None else "gps" if info.alt is not None else "fixed"
    if hs == "gps":
        if info.alt is None:
            raise InputError("the image has no GPS altitude", path=info.path,
                             fix="set 'height_source' to 'relative' or 'fixed' (with flight_height_m)")
        return np.full(len(pts), info.alt + cfg.altitude_offset_m), hs
    if hs == "relative":
        if info.relative_alt is None:
            raise InputError("the image has no DJI relative altitude", path=info.path,
                             fix="set 'height_source' to 'gps' or 'fixed' (with flight_height_m)")
        return np.full(len(pts), ground + info.relative_alt), hs  # take-off taken at the GCPs' median height
    if cfg.flight_height_m is None:
        raise ConfigError("the images have no altitude; set the flight height",
                          fix="set 'flight_height_m' (metres above ground)")
    return pts[:, 2] + cfg.flight_height_m, hs


def find_candidates(cfg: GcpFinderConfig) -> Finder:
    """Read the survey and every image's metadata; predict each GCP's pixel in each image; rank."""
    gcps, crs = read_survey(cfg.survey, cfg.survey_crs, cfg.output_crs)
    infos, skipped = [], []
    for p in progress(list_images(cfg.images), desc="reading EXIF", unit="img"):
        info = read_image_info(p)
        (infos if info.lat is not None else skipped).append(info)
    if skipped:
        log.warning("%d images have no GPS position in EXIF and are skipped (e.g. %s); module 0 writes it",
                    len(skipped), skipped[0].name)
    if not infos:
        raise InputError("no image has a GPS position in its EXIF", path=cfg.images,
                         fix="write the positions with module 0 (gps_embed) first")
    _camera_positions(infos, crs)
    infos.sort(key=lambda i: (i.time if i.time is not None else 0.0, i.name))
    track = track_yaw(np.array([i.xyz[:2] for i in infos]))
    pts = np.array([[g.x, g.y, g.z] for g in gcps])
    ground = float(np.median(pts[:, 2]))
    cands: dict[str, list[Candidate]] = {g.id: [] for g in gcps}
    ratio, yaw, pitch, height = {}, {}, {}, {}
    for k, info in enumerate(infos):
        ratio[info.name] = focal_ratio(info, cfg.sensor_width_mm, cfg.focal_length_mm)
        yaw[info.name] = _image_yaw(info, cfg, track[k])
        pitch[info.name] = info.pitch if info.pitch is not None else -90.0
        cam_z, hs = _camera_heights(info, cfg, pts, ground)
        for g, z in zip(gcps, cam_z):
            height[(g.id, info.name)] = float(z - g.z)
        if not 0 < float(np.median(cam_z - pts[:, 2])) < 2000:
            log.warning("%s: the camera is %.0f m above the GCPs (%s height); check 'height_source' and "
                        "'altitude_offset_m'", info.name, float(np.median(cam_z - pts[:, 2])), hs)
        uv = predict_pixels(info, ratio[info.name], yaw[info.name], pitch[info.name], cam_z, pts)
        m = cfg.edge_margin_px
        cx, cy = (info.width - 1) / 2.0, (info.height - 1) / 2.0
        dist = np.hypot(uv[:, 0] - cx, uv[:, 1] - cy) / math.hypot(cx, cy)
        ok = ((uv[:, 0] >= m) & (uv[:, 0] <= info.width - 1 - m) & (uv[:, 1] >= m) &
              (uv[:, 1] <= info.height - 1 - m) & (dist <= cfg.max_center_distance) & (cam_z - pts[:, 2] > 0))
        for gi in np.flatnonzero(ok):
            cands[gcps[gi].id].append(Candidate(gcps[gi].id, info.name, float(uv[gi, 0]), float(uv[gi, 1]),
                                                float(dist[gi])))
    for gid, lst in cands.items():
        lst.sort(key=lambda c: c.center_distance)
        if cfg.max_images_per_gcp:
            del lst[cfg.max_images_per_gcp:]
        for r, c in enumerate(lst, start=1):
            c.rank = r
    unseen = [gid for gid, lst in cands.items() if not lst]
    if len(unseen) == len(gcps):
        raise InputError(f"none of the {len(gcps)} GCPs falls inside any of the {len(infos)} images", path=cfg.survey,
                         fix="check 'survey_crs' (x = easting/longitude, y = northing/latitude) and that the survey "
                             "belongs to this flight; or raise 'max_center_distance'")
    if unseen:
        log.warning("GCPs outside every image (check their coordinates): %s", ", ".join(unseen))
    return Finder({g.id: g for g in gcps}, crs, {i.name: i for i in infos}, cands, ratio, yaw, pitch, height)


def write_candidates(path: Path, finder: Finder) -> Path:
    with atomic_open(path, "w") as fh:
        w = csv.writer(fh)
        w.writerow(["gcp", "rank", "image", "u_pred", "v_pred", "center_distance"])
        for lst in finder.candidates.values():
            for c in lst:
                w.writerow([c.gcp, c.rank, c.image, f"{c.u:.1f}", f"{c.v:.1f}", f"{c.center_distance:.3f}"])
    return path


def plot_candidates(path: Path, finder: Finder) -> Path:
    """Overview figure: image footprints, camera track and GCPs with their number of candidate images."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon

    from matchplant.core.io import atomic_path

    fig = Figure(figsize=(8, 7), dpi=100)
    ax = fig.add_subplot()
    ground = float(np.median([g.z for g in finder.gcps.values()]))
    for name, info in finder.images.items():
        h = (info.alt if info.alt is not None else ground) - ground
        if h > 0:
            fp = footprint(info, finder.ratio[name], finder.yaw[name], finder.pitch[name], h)
            ax.add_patch(Polygon(fp, closed=True, fill=False, lw=0.5, color="0.6"))
    cams = np.array([i.xyz[:2] for i in finder.images.values()])
    ax.plot(cams[:, 0], cams[:, 1], ".-", color="tab:blue", lw=0.6, ms=3, label="camera positions")
    for gid, g in finder.gcps.items():
        n = len(finder.candidates[gid])
        ax.plot(g.x, g.y, "s", color="tab:green" if n >= MIN_IMAGES_PER_GCP else "tab:red", ms=7)
        ax.annotate(f"{gid} ({n})", (g.x, g.y), xytext=(4, 4), textcoords="offset points", fontsize=8)
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("GCPs (number of candidate images) and image footprints")
    ax.legend(loc="best", fontsize=8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


class MarkStore:
    """The marks of one session: set, move, delete, undo; every change is saved to gcp_list.txt."""

    def __init__(self, finder: Finder, path: Path, autosave: bool = True):
        self.finder = finder
        self.path = Path(path)
        self.autosave = autosave
        self.marks: dict[tuple[str, str], tuple[float, float]] = {}
        self.undo_stack: list[tuple[tuple[str, str], tuple[float, float] | None]] = []

    def load(self, path: Path) -> int:
        """Continue from an existing gcp_list.txt; returns the number of marks taken over."""
        from pyproj import Transformer

        _, crs, marks = read_gcp_list(path)
        t = None if crs.equals(self.finder.crs) else Transformer.from_crs(crs, self.finder.crs, always_xy=True)
        ids = list(self.finder.gcps)
        xy = np.array([[g.x, g.y] for g in self.finder.gcps.values()])
        n = 0
        for m in marks:
            gid = m.gcp if m.gcp in self.finder.gcps else None
            if gid is None:  # unnamed line: the surveyed GCP at its coordinates
                mx, my = t.transform(m.x, m.y) if t else (m.x, m.y)
                d = np.hypot(xy[:, 0] - mx, xy[:, 1] - my)
                if d.min() < 0.5:
                    gid = ids[int(np.argmin(d))]
            if gid is None:
                log.warning("gcp_list line for %s (%s) matches no surveyed GCP; dropped", m.image, m.gcp or "unnamed")
                continue
            self.marks[(gid, m.image)] = (m.u, m.v)
            n += 1
        return n

    def set(self, gcp: str, image: str, u: float, v: float, record: bool = True) -> None:
        if record:
            self.undo_stack.append(((gcp, image), self.marks.get((gcp, image))))
        self.marks[(gcp, image)] = (float(u), float(v))
        self._changed()

    def delete(self, gcp: str, image: str) -> bool:
        if (gcp, image) not in self.marks:
            return False
        self.undo_stack.append(((gcp, image), self.marks.pop((gcp, image))))
        self._changed()
        return True

    def undo(self) -> tuple[str, str] | None:
        if not self.undo_stack:
            return None
        key, previous = self.undo_stack.pop()
        if previous is None:
            self.marks.pop(key, None)
        else:
            self.marks[key] = previous
        self._changed()
        return key

    def count(self, gcp: str) -> int:
        return sum(1 for g, _ in self.marks if g == gcp)

    def to_marks(self) -> list[Mark]:
        order = {gid: i for i, gid in enumerate(self.finder.gcps)}
        out = []
        for (gid, image), (u, v) in sorted(self.marks.items(), key=lambda kv: (order.get(kv[0][0], 1e9), kv[0][1])):
            g = self.finder.gcps[gid]
            out.append(Mark(g.x, g.y, g.z, u, v, image, gid))
        return out

    def save(self) -> Path:
        return write_gcp_list(self.path, crs_header(self.finder.crs), self.to_marks())

    def _changed(self) -> None:
        if self.autosave:
            self.save()

    def warn_few(self) -> list[str]:
        few = [gid for gid in self.finder.gcps if 0 < self.count(gid) < MIN_IMAGES_PER_GCP]
        if few:
            log.warning("GCPs marked in fewer than %d images (ODM may ignore them): %s", MIN_IMAGES_PER_GCP,
                        ", ".join(f"{g} ({self.count(g)})" for g in few))
        return few


def auto_mark(finder: Finder, store: MarkStore, cfg: GcpFinderConfig) -> int:
    """Detect every GCP's target near its predicted pixel in each candidate image; returns the count."""
    by_image: dict[str, list[Candidate]] = {}
    for lst in finder.candidates.values():
        for c in lst:
            by_image.setdefault(c.image, []).append(c)
    found = 0
    for image, cs in progress(sorted(by_image.items()), desc="finding targets", unit="img"):
        info = finder.images[image]
        gray = load_gray(info.path)
        for c in cs:
            uv = locate_target(gray, c.u, c.v, cfg.target_size_m / finder.gsd(c.gcp, image), cfg.search_radius_px,
                               cfg.target_pattern)
            if uv is None:
                log.info("%s: no target found near (%.0f, %.0f) in %s", c.gcp, c.u, c.v, image)
                continue
            store.set(c.gcp, image, uv[0], uv[1], record=False)
            found += 1
    return found


def store_for(cfg: GcpFinderConfig, finder: Finder, autosave: bool) -> MarkStore:
    out = Path(cfg.output_dir)
    store = MarkStore(finder, out / "gcp_list.txt", autosave=autosave)
    existing = cfg.gcp_list or (out / "gcp_list.txt")
    if Path(existing).is_file():
        n = store.load(Path(existing))
        log.info("continuing from %s (%d marks)", existing, n)
    return store


def run(cfg: GcpFinderConfig) -> Finder:
    """Candidates (CSV and figure); with ``auto`` also the marks and gcp_list.txt."""
    out = Path(cfg.output_dir)
    finder = find_candidates(cfg)
    write_candidates(out / "candidates.csv", finder)
    plot_candidates(out / "candidates.png", finder)
    for gid, lst in finder.candidates.items():
        log.info("%s: %d candidate images%s", gid, len(lst), f" (best: {lst[0].image})" if lst else "")
    log.info("candidates: %s", out / "candidates.csv")
    if cfg.auto:
        store = store_for(cfg, finder, autosave=False)
        n = auto_mark(finder, store, cfg)
        store.save()
        store.warn_few()
        log.info("found %d targets; wrote %s (review it with --gui)", n, store.path)
    else:
        log.info("mark the GCPs with --gui (or run with --set auto=true)")
    return finder
