"""Module 7's input checks: the checkpoint (:func:`read_model`), the images to detect on (listed, whole, their
size against the tile), and why a run found nothing (the score threshold, the scale, the model) instead of an empty
predictions file."""

from __future__ import annotations

from pathlib import Path

from matchplant.core.formats.images import is_image_name
from matchplant.core.formats.images import list_images as list_image_files
from matchplant.core.formats.odm import SUBMODELS_DIR, ODMProject
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.detection.dataset_checks import check_image_files, image_size
from matchplant.detection.device import DEVICE_CHOICES
from matchplant.detection.foreign import read_any_checkpoint

log = get_logger("model_test")

SYSTEM_JUNK = ("thumbs.db", "desktop.ini", ".ds_store")
CHECKPOINT_FIX = "use the trained checkpoint (module 6's checkpoints/best.pt, not an untrained or early one)"


def read_model(cfg) -> dict:
    """The checkpoint of ``cfg`` (a :class:`~matchplant.model_test.config.ModelTestConfig`): module 6's, the
    paper's layout or bare torchvision weights (their classes from ``class_names``)."""
    ck = read_any_checkpoint(cfg.checkpoint, class_names=list(cfg.class_names) or None)
    if cfg.class_names and "foreign" not in ck and list(cfg.class_names) != ck["class_names"]:
        log.warning(
            "class_names %s ignored: the module 6 checkpoint %s holds its own classes %s",
            list(cfg.class_names),
            cfg.checkpoint,
            ck["class_names"],
        )
    return ck


def list_images(path: Path) -> list[Path]:
    """``detect.images``: one image file, every image of a folder, or an ODM project folder's undistorted images
    (of every submodel of a split-merge project, each image once)."""
    if path.is_file():
        if not is_image_name(path):
            raise InputError(
                f"detect.images is a {path.suffix or 'extension-less'} file, not an image (JPEG, PNG, TIFF)",
                path=path,
                fix="point detect.images at an image or a folder of images",
            )
        return [path]
    if (path / "opensfm").is_dir() or (path / SUBMODELS_DIR).is_dir():
        project = ODMProject(path)
        project.require("undistorted_images")
        files = list(project.undistorted_images().values())
        log.info(
            "%d undistorted images in the ODM project %s%s",
            len(files),
            path,
            f" ({len(project.submodels)} submodels)" if project.is_split else "",
        )
        return files
    fix = "point detect.images at the undistorted images (opensfm/undistorted/images)"
    files = list_image_files(path, key="detect.images", fix=fix, min_count=0)
    if not files:
        raise _no_images(path, fix)
    return files


def _no_images(path: Path, fix: str) -> InputError:
    """What the folder holds instead of images, and a subfolder with images if there is one."""
    entries = sorted(path.iterdir())
    names = [p.name for p in entries if p.is_file()]
    junk = [n for n in names if n.startswith(".") or n.lower() in SYSTEM_JUNK]
    other = [n for n in names if n not in junk]
    parts = [f"{len(other)} other file(s): {', '.join(other[:5])}"] if other else []
    if junk:
        parts.append(f"{len(junk)} system or hidden file(s), skipped: {', '.join(junk[:5])}")
    held = f"; it holds {' and '.join(parts)}" if parts else "; the folder is empty"
    sub = next((d for d in entries if d.is_dir() and any(is_image_name(p) for p in d.iterdir() if p.is_file())), None)
    hint = f"; did you mean its subfolder '{sub.name}' ({sub})?" if sub is not None else ""
    return InputError(f"no images (JPEG, PNG, TIFF) in this folder{held}{hint}", path=path, fix=fix)


def check_images(files: list[Path], tile_size: int) -> list[tuple[int, int]]:
    """Every image whole and readable (an error naming the broken ones, before hours of detection); a warning
    for images smaller than the tile (each is then detected whole). Returns ``(width, height)`` per image."""
    sizes = check_image_files(files, "detect.images")
    small = [(f, wh) for f, wh in zip(files, sizes) if wh[0] < tile_size or wh[1] < tile_size]
    if small:
        f, (w, h) = small[0]
        log.warning(
            "detect.tile_size = %d px is larger than %d of the %d image(s) (e.g. %s: %dx%d px): each of those "
            "is detected whole, as one tile of its own size",
            tile_size,
            len(small),
            len(files),
            f.name,
            w,
            h,
        )
    return sizes


def check_device(device: str) -> None:
    """A clear error for a ``device`` key that is none of auto, cpu, cuda, cuda:N, mps."""
    if str(device).lower().split(":")[0] not in DEVICE_CHOICES:
        raise ConfigError(f"device '{device}' is not one of auto, cpu, cuda, cuda:N, mps", fix="set device: auto")


def nothing_found(
    n_images: int,
    probe: Path,
    best: float | None,
    threshold: float,
    tile_size: int,
    model_config: dict,
    checkpoint: Path,
) -> InputError:
    """The error for a detection run without a single box: the best score the model gives on ``probe`` (at any
    score), and the scale it sees the plants at."""
    w, h = image_size(probe)
    tw, th = min(tile_size, w), min(tile_size, h)
    lo, hi = float(model_config.get("min_size", 800)), float(model_config.get("max_size", 1333))
    scale = min(lo / min(tw, th), hi / max(tw, th))
    seen = f"its {tw}x{th}-px tiles are resized by {scale:.2f} for the model (model.min_size {lo:g})"
    if best is None:
        why = f"the model finds no box at all on {probe.name}, even at score 0; {seen}"
        fix = (
            f"{CHECKPOINT_FIX}, and set detect.tile_size to the size of the training tiles so that plants look "
            "as large as the model learned them"
        )
    else:
        why = f"the best box on {probe.name} scores {best:.3f}; {seen}"
        fix = (
            f"lower detect.score_threshold below {best:.2f} and check the drawn boxes; if they are not plants, "
            f"{CHECKPOINT_FIX} and set detect.tile_size to the size of the training tiles"
        )
    return InputError(
        f"no plant found on any of the {n_images} image(s) at detect.score_threshold = {threshold:g}: "
        f"{why} (checkpoint {checkpoint.name})",
        path=probe,
        fix=fix,
    )


def nothing_in_test(n_tiles: int, dataset_json: Path, checkpoint: Path) -> InputError:
    """The error for an evaluation in which the model gives no box at all (every box is kept, at any score)."""
    return InputError(
        f"the model finds no box at all on the {n_tiles} test tile(s), even at score 0: its metrics "
        f"would all be 0 (checkpoint {checkpoint})",
        path=dataset_json,
        fix=f"{CHECKPOINT_FIX}; test on tiles cut like the training tiles (module 5, same tile size)",
    )
