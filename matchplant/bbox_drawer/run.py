"""Module 4: plant boxes on a folder of images - the configuration and the run without a window.

The pieces: :mod:`matchplant.bbox_drawer.store` holds the session (every box, its edits, undo, the
exports), :mod:`matchplant.bbox_drawer.importers` reads boxes to correct (a COCO dataset, YOLO labels
with ``classes.txt``, or module 7's predictions, tiles put back in source-image pixels), and
:mod:`matchplant.bbox_drawer.gui` is the window. Exports: one COCO dataset (``annotations.json``) and
YOLO labels plus ``classes.txt`` (:mod:`matchplant.core.formats.yolo`).

The area each image "owns" (module 3) can be shown: a JSON file ``{image_name: [[u, v], ...]}``, one
polygon in pixels of that image per image name (:mod:`matchplant.core.formats.owned_areas`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from matchplant.bbox_drawer.config import BboxDrawerConfig
from matchplant.bbox_drawer.importers import (
    read_coco_boxes,
    read_cvat_boxes,
    read_deepforest_boxes,
    read_mask_boxes,
    read_prediction_boxes,
    read_voc_boxes,
    read_yolo_boxes,
)
from matchplant.bbox_drawer.store import (
    NOT_A_FAULT,
    NOT_IN_FOLDER,
    STATE_NAME,
    AnnotationStore,
)
from matchplant.core.formats.box_files import resolve_image_names
from matchplant.core.formats.coco import DropLog
from matchplant.core.formats.images import is_image_name, match_name
from matchplant.core.formats.owned_areas import read_owned_areas
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.guard import check_outputs, staged_outputs
from matchplant.core.runtime.io import read_json
from matchplant.core.runtime.log import get_logger

log = get_logger("bbox_drawer")

DROPPED_NAME = "import_dropped.csv"  # every imported box left out, where it came from and why
NOT_SELECTED = "photo not in module 3's selection"  # expected: an import made for the whole flight
IMPORT_KEYS = (
    "import_coco",
    "import_yolo",
    "import_predictions",
    "import_masks",
    "import_deepforest",
    "import_voc",
    "import_cvat",
)


def open_session(cfg: BboxDrawerConfig, output_dir: Path | None = None) -> AnnotationStore:
    """Open or resume the session and apply the imports named in the config (each once).

    ``output_dir``: where the session is written (a run's staging folder), resumed from ``cfg.output_dir``.
    Boxes an import leaves out are counted in a warning and listed in ``<output_dir>/import_dropped.csv``;
    an import file of which no box can be used is an error (the CSV then goes to ``cfg.output_dir``).
    """
    out = Path(output_dir or cfg.output_dir)
    store = AnnotationStore(
        cfg.images,
        out,
        cfg.categories,
        min_box_size=cfg.min_box_size,
        resume_from=Path(cfg.output_dir) / STATE_NAME,
        label_map=cfg.label_map,
    )
    drops = DropLog()
    for key in IMPORT_KEYS:
        path = getattr(cfg, key)
        if path is None:
            continue
        if str(Path(path).resolve()) in store.state["imports"]:
            log.info("%s was already imported into this session; skipped", path)
            continue
        boxes = _read_import(cfg, key, path, store)
        before = len(drops)
        drops.rows += boxes.drops.rows
        added = store.import_boxes(boxes, str(path), drops)
        faults = [r for r in drops.rows[before:] if r["reason"] != NOT_A_FAULT]
        if added == 0 and (faults or not any(boxes.values())):
            _fail_import(cfg, key, path, drops, faults, before)
    if len(drops):
        unselected = _not_selected(cfg, drops)
        drops.write_csv(out / DROPPED_NAME)
        listed = Path(cfg.output_dir) / DROPPED_NAME
        if unselected:
            photos = len({r["image"] for r in unselected})
            log.info(
                "%d imported box(es) on %d photo(s) module 3 did not select were not added: those photos are "
                "not in the selection (%s; e.g. %s); listed in %s",
                len(unselected),
                photos,
                cfg.images,
                unselected[0]["image"],
                listed,
            )
        others = DropLog([r for r in drops.rows if r["reason"] != NOT_SELECTED])
        if len(others):
            log.warning(
                "%d imported box(es) were not added (%s); each one, where it came from and why: %s",
                len(others),
                others.summary(),
                listed,
            )
    return store


def _selection(images: Path) -> dict | None:
    """Module 3's selection.json when ``images`` is its folder of selected images (``<output_dir>/images``)."""
    for folder in (images, images.parent):
        path = folder / "selection.json"
        if path.is_file() and (folder / "selected_images.csv").is_file():
            try:
                data = read_json(path)
            except InputError:
                return None
            return data if isinstance(data, dict) else None
    return None


def _not_selected(cfg: BboxDrawerConfig, drops: DropLog) -> list[dict]:
    """The boxes left out because their photo is one module 3 did not select (expected when an import covers the
    whole flight and ``images`` is module 3's selection): their reason becomes NOT_SELECTED."""
    selection = _selection(Path(cfg.images))
    rows = [r for r in drops.rows if r["reason"] == NOT_IN_FOLDER]
    if selection is None or not rows:
        return []
    flight = _flight_images(selection.get("project_dir"))
    names = sorted({r["image"] for r in rows})
    if flight:  # the project is at hand: only names of its photos are expected
        matched, _ = resolve_image_names(names, flight)
        names = [n for n in names if n in matched]
    out = []
    for r in rows:
        if r["image"] in names:
            r["reason"], r["detail"] = NOT_SELECTED, f"module 3 did not select it ({Path(cfg.images).parent})"
            out.append(r)
    return out


def _flight_images(project_dir) -> list[str]:
    """The photo names of module 3's ODM project (its undistorted images, every submodel's), [] if not at hand."""
    if not project_dir or not Path(project_dir).is_dir():
        return []
    root = Path(project_dir)
    folders = [root / "opensfm/undistorted/images", root / "images"] + sorted(
        root.glob("submodels/submodel_*/opensfm/undistorted/images")
    )
    return sorted({p.name for f in folders if f.is_dir() for p in f.iterdir() if is_image_name(p)})


def _read_import(cfg: BboxDrawerConfig, key: str, path: Path, store: AnnotationStore):
    if key == "import_coco":
        return read_coco_boxes(path)
    if key == "import_yolo":
        return read_yolo_boxes(path, {n: store.size(n) for n in store.images})
    if key == "import_predictions":
        return read_prediction_boxes(path, cfg.min_score)
    if key == "import_masks":
        return read_mask_boxes(
            path,
            store.images,
            cfg.mask_min_area,
            store.categories[0],
            {n: store.size(n) for n in store.images},
            cfg.mask_mode,
            cfg.mask_threshold,
        )
    return {"import_deepforest": read_deepforest_boxes, "import_voc": read_voc_boxes, "import_cvat": read_cvat_boxes}[
        key
    ](path)


def _fail_import(cfg: BboxDrawerConfig, key: str, path: Path, drops: DropLog, faults: list[dict], before: int):
    """No box of an import file could be used: an error that says why (the list of boxes beside the log)."""
    if not faults:
        raise InputError(
            "the file holds no boxes",
            path=path,
            fix=f"check that this is the right file, or remove '{key}' from the config",
        )
    csv_path = DropLog(drops.rows[before:]).write_csv(Path(cfg.output_dir) / DROPPED_NAME)
    first = faults[0]
    hint = f" ({first['detail']})" if first["detail"] else ""
    raise InputError(
        f"none of the {len(faults)} box(es) could be imported: {DropLog(faults).summary()}; first: "
        f"{first['where'] or 'a box'} for '{first['image']}': {first['reason']}{hint}; every box and "
        f"why: {csv_path}",
        path=path,
        fix=f"check that '{key}' was made on the photos in 'images' ({cfg.images}) and that its "
        "boxes and categories are valid",
    )


def annotated_regions(cfg: BboxDrawerConfig, store: AnnotationStore) -> dict[str, np.ndarray]:
    """Image name -> the polygon whose plants are all boxed (the owned area); ``{}`` = whole images."""
    if cfg.annotated_region == "image" or cfg.owned_areas is None:
        return {}
    out = {}
    for key, poly in read_owned_areas(cfg.owned_areas).items():
        name = match_name(key, store.files)  # module 3 may name the shot, not the .tif
        if name is not None:
            out[name] = poly
    missing = [n for n in store.images if n not in out]
    if missing:
        log.warning("%d image(s) have no owned area (e.g. %s): recorded as annotated whole", len(missing), missing[0])
    return out


def run(cfg: BboxDrawerConfig) -> dict[str, Path]:
    """Module 4 without the GUI: open or resume the session, apply imports, write the exports.

    Everything is written into a staging folder moved into ``output_dir`` only at the end: a failed run
    leaves ``output_dir`` as it was (apart from its log and, when an import failed, import_dropped.csv).

    Parameters
    ----------
    cfg : BboxDrawerConfig
        The step's settings, as loaded from its YAML config (``4_bbox_drawer/config.yaml``) or built in Python.

    Returns
    -------
    dict
        ``"coco"`` -> the annotations.json written, and ``"yolo"`` -> the YOLO folder with ``export_yolo``.
    """
    check_outputs(cfg)
    final = Path(cfg.output_dir)
    with staged_outputs(final) as stage:
        store = open_session(cfg, stage)
        if store.count() == 0:
            imports = [k for k in IMPORT_KEYS if getattr(cfg, k) is not None]
            raise InputError(
                "there are no boxes to export: "
                + (
                    f"the session has none and {', '.join(imports)} added none"
                    if imports
                    else "the session has none and nothing is imported"
                ),
                path=final / STATE_NAME,
                fix="draw boxes with --gui, or import them (import_coco, import_yolo, import_predictions, ...)",
            )
        out = store.export(
            coco=True, yolo=cfg.export_yolo, include_unseen=cfg.include_unseen, regions=annotated_regions(cfg, store)
        )
        n_images = len(read_json(out["coco"])["images"])
    out = {k: final / Path(v).relative_to(stage) for k, v in out.items()}
    log.info("%d box(es) on %d image(s) -> %s", store.count(), n_images, out["coco"])
    if "yolo" in out:
        log.info("YOLO labels and classes.txt -> %s", out["yolo"])
    return out


__all__ = ["BboxDrawerConfig", "annotated_regions", "open_session", "run"]
