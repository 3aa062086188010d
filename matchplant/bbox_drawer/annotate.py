"""Module 4: plant boxes on a folder of images - the configuration and the run without a window.

The pieces: :mod:`matchplant.bbox_drawer.store` holds the session (every box, its edits, undo, the
exports), :mod:`matchplant.bbox_drawer.importers` reads boxes to correct (a COCO dataset, YOLO labels
with ``classes.txt``, or module 7's predictions, tiles put back in source-image pixels), and
:mod:`matchplant.bbox_drawer.gui` is the window. Exports: one COCO dataset (``annotations.json``) and
YOLO labels plus ``classes.txt`` (:mod:`matchplant.core.yolo`).

The area each image "owns" (module 3) can be shown: a JSON file ``{image_name: [[u, v], ...]}``, one
polygon in pixels of that image per image name (:mod:`matchplant.core.owned_areas`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.bbox_drawer.importers import read_coco_boxes, read_prediction_boxes, read_yolo_boxes
from matchplant.bbox_drawer.store import MAX_CATEGORIES, AnnotationStore
from matchplant.core.config import param
from matchplant.core.errors import ConfigError
from matchplant.core.io import read_json
from matchplant.core.log import get_logger

log = get_logger("annotate")


@dataclass
class AnnotateConfig:
    """Module 4 - draw plant boxes on images; import COCO, YOLO or predictions; export COCO and YOLO."""

    images: Path | None = param(None, "folder of images to annotate (e.g. module 3's selected undistorted images)",
                         path="dir", required=True)
    output_dir: Path | None = param(None, "folder for the session (session.json, saved after every edit) and exports",
                             path="out", required=True)
    categories: list[str] = param(["plant"], "category names (1 to 5); keys 1-5 choose them in the GUI")
    owned_areas: Path | None = param(None, "optional JSON {image_name: [[u, v], ...]}: the area each image "
                                           "owns (module 3), drawn as a dashed outline", path="file")
    import_coco: Path | None = param(None, "optional COCO dataset whose boxes are loaded for correction",
                                     path="file")
    import_yolo: Path | None = param(None, "optional folder of YOLO labels (<image stem>.txt + classes.txt) "
                                           "loaded for correction", path="dir")
    import_predictions: Path | None = param(None, "optional module 7 predictions JSON loaded for correction "
                                                  "(model-assisted labelling)", path="file")
    min_score: float = param(0.5, "imported predictions below this score are left out", min=0.0, max=1.0)
    min_box_size: float = param(2.0, "smaller boxes (px, after clipping to the image) are not created; "
                                     "a click without drag selects instead", min=0.0)
    export_yolo: bool = param(True, "also write YOLO labels and classes.txt to <output_dir>/yolo")
    include_unseen: bool = param(False, "export images never opened and without boxes too (as negatives)")

    def check(self) -> None:
        if not 1 <= len(self.categories) <= MAX_CATEGORIES:
            raise ConfigError(f"'categories' must list 1 to {MAX_CATEGORIES} names, got {self.categories}",
                              fix="for example: categories: [plant, weed]")
        if len(set(self.categories)) != len(self.categories):
            raise ConfigError(f"'categories' has a repeated name: {self.categories}", fix="make the names unique")


def open_session(cfg: AnnotateConfig) -> AnnotationStore:
    """Open or resume the session and apply the imports named in the config (each once)."""
    store = AnnotationStore(cfg.images, cfg.output_dir, cfg.categories, min_box_size=cfg.min_box_size)
    if cfg.import_coco is not None:
        store.import_boxes(read_coco_boxes(cfg.import_coco), str(cfg.import_coco))
    if cfg.import_yolo is not None:
        store.import_boxes(read_yolo_boxes(cfg.import_yolo, {n: store.size(n) for n in store.images}),
                           str(cfg.import_yolo))
    if cfg.import_predictions is not None:
        store.import_boxes(read_prediction_boxes(cfg.import_predictions, cfg.min_score), str(cfg.import_predictions))
    return store


def run(cfg: AnnotateConfig) -> dict[str, Path]:
    """Without the GUI: open or resume the session, apply imports, write the exports."""
    store = open_session(cfg)
    out = store.export(coco=True, yolo=cfg.export_yolo, include_unseen=cfg.include_unseen)
    n_images = len(read_json(out["coco"])["images"])
    log.info("%d box(es) on %d image(s) -> %s", store.count(), n_images, out["coco"])
    if "yolo" in out:
        log.info("YOLO labels and classes.txt -> %s", out["yolo"])
    return out


__all__ = ["AnnotateConfig", "open_session", "run"]
