"""Image files: listing a folder and reading pixels, one way for every step.

Listing skips hidden files and the junk that operating systems leave in photo folders (``Thumbs.db``,
macOS ``._*`` resource forks, ``.DS_Store``): they are not images, whatever their extension says.
Reading goes through ``np.fromfile`` + ``cv2.imdecode`` so that non-ASCII paths work on Windows too.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate import check_jpeg

# The image suffixes, in one table: every raster photo format a step may meet, and the named subsets of
# the steps that take fewer (their order is the order a "no image" message lists them in).
JPEG_SUFFIXES = (".jpg", ".jpeg")
TIFF_SUFFIXES = (".tif", ".tiff")
IMAGE_SUFFIXES = JPEG_SUFFIXES + (".png",) + TIFF_SUFFIXES + (".bmp",)
EXIF_SUFFIXES = JPEG_SUFFIXES + TIFF_SUFFIXES  # photos a camera writes EXIF into (step 1 reads it)
ODM_SUFFIXES = EXIF_SUFFIXES + (".png", ".dng")  # what ODM takes as input photos


def is_image_name(path: Path, suffixes: Iterable[str] = IMAGE_SUFFIXES) -> bool:
    """True for a visible file named like an image (``._IMG_1.JPG`` and ``Thumbs.db`` are not)."""
    return path.suffix.lower() in tuple(suffixes) and not path.name.startswith(".")


def match_name(name: str, known: Iterable[str]) -> str | None:
    """The image of ``known`` that ``name`` refers to: same file name, or the same up to ODM's ``.tif``."""
    known = set(known)
    base = Path(str(name).replace("\\", "/")).name
    for candidate in (base, base + ".tif", base[:-4] if base.lower().endswith(".tif") else None):
        if candidate in known:
            return candidate
    return None


def list_images(
    folder: str | Path,
    suffixes: Iterable[str] = IMAGE_SUFFIXES,
    *,
    key: str = "images",
    fix: str | None = None,
    min_count: int = 1,
) -> list[Path]:
    """The image files of ``folder``, sorted by name.

    ``key`` names the config key that points at the folder, for the messages; fewer than ``min_count``
    images is an error that says what the folder holds instead.
    """
    folder = Path(folder)
    suffixes = tuple(s.lower() for s in suffixes)
    fix = fix or f"set '{key}' to the folder of your photos"
    if not folder.is_dir():
        raise InputError("image folder not found" if not folder.exists() else "not a folder", path=folder, fix=fix)
    files = sorted(p for p in folder.iterdir() if p.is_file() and is_image_name(p, suffixes))
    if len(files) < min_count:
        others = sorted({p.suffix.lower() or p.name for p in folder.iterdir() if p.is_file()})
        kinds = "/".join(s.lstrip(".").upper() for s in suffixes)
        found = f"; found {', '.join(others)}" if others else ""
        raise InputError(
            f"{len(files)} image(s) ({kinds}) in the folder, at least {min_count} needed{found}", path=folder, fix=fix
        )
    return files


def read_image(path: str | Path) -> np.ndarray:
    """Pixels exactly as stored (any bit depth; colour as RGB(A))."""
    path = Path(path)
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"cannot read the image: {exc}", path=path, fix="check that the file exists") from exc
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError("not a readable image", path=path, fix="remove the file or convert it to PNG, JPEG or TIFF")
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return img


def read_rgb8(path: str | Path) -> np.ndarray:
    """An image as RGB uint8 (H, W, 3), what the detector sees: 16-bit and float images are scaled to
    8 bits, grey is repeated into three bands, a fourth band is dropped."""
    img = read_image(path)
    if img.dtype != np.uint8:
        scale = 255.0 / 65535.0 if img.dtype == np.uint16 else 255.0 / max(float(np.nanmax(img)), 1e-9)
        img = np.clip(np.nan_to_num(img.astype(np.float32)) * scale, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] < 3:
        img = np.repeat(img[:, :, :1], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def display_rgb(img: np.ndarray) -> np.ndarray:
    """8-bit RGB for showing an image of any bit depth (16-bit and float images are stretched)."""
    if img.ndim == 3 and img.shape[2] > 3:
        img = img[..., :3]
    if img.dtype == np.uint8:
        return img
    a = img.astype(np.float32)
    finite = a[np.isfinite(a)]
    lo, hi = np.percentile(finite, [0.5, 99.5]) if finite.size else (0.0, 1.0)
    return (np.clip((np.nan_to_num(a, nan=lo) - lo) / max(hi - lo, 1e-9), 0, 1) * 255).astype(np.uint8)


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) read from the file header only."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except Exception:  # noqa: BLE001 - PIL cannot read every GeoTIFF layout; GDAL can
        try:
            import rasterio  # lazy: GDAL only for the GeoTIFFs PIL cannot read (training and detection run without it)

            with rasterio.open(path) as src:
                return int(src.width), int(src.height)
        except Exception as exc:  # noqa: BLE001
            raise InputError(
                f"cannot read the image size: {exc}", path=path, fix="check that the file is a complete image"
            ) from exc


def whole_image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image that must be whole: its header readable, a JPEG with its end marker, a PNG
    with its end chunk (a truncated copy is named, not tiled or annotated half grey)."""
    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # PIL's "Corrupt EXIF data": said below, with the file's name
            size = image_size(path)
    except InputError as exc:
        raise InputError(
            "not a readable image (broken, truncated or another kind of file)",
            path=path,
            fix="copy the photo again, or move it out of the image folder",
        ) from exc
    if path.suffix.lower() in JPEG_SUFFIXES:
        check_jpeg(path)
    elif path.suffix.lower() == ".png":
        with open(path, "rb") as fh:
            fh.seek(max(0, path.stat().st_size - 64))
            if b"IEND" not in fh.read():
                raise InputError(
                    "the PNG is truncated (no end chunk)",
                    path=path,
                    fix="copy the image again, or move it out of the image folder",
                )
    return size
