"""Module 4's settings (the folder's config.yaml is generated from them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.bbox_drawer.store import MAX_CATEGORIES
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError


@dataclass
class BboxDrawerConfig:
    """Module 4 - draw plant boxes on images; import COCO (CVAT, Label Studio), YOLO, predictions, masks,
    DeepForest CSV, Pascal VOC or CVAT XML; export COCO and YOLO."""

    images: Path | None = param(None, "folder of images to annotate (e.g. module 3's selected undistorted images)",
                         path="dir", required=True)
    output_dir: Path = param(Path("runs/bbox_drawer"), "folder for the session (session.json, saved after every "
                                                       "edit) and exports", path="out")
    categories: list[str] = param(["plant"], "category names (1 to 5); keys 1-5 choose them in the GUI")
    owned_areas: Path | None = param(None, "optional JSON {image_name: [[u, v], ...]}: the area each image "
                                           "owns (module 3), drawn as a dashed outline", path="file")
    import_coco: Path | None = param(None, "optional COCO dataset whose boxes are loaded for correction",
                                     path="file")
    import_yolo: Path | None = param(None, "optional folder of YOLO labels (<image stem>.txt + classes.txt) "
                                           "loaded for correction", path="dir")
    import_predictions: Path | None = param(None, "optional module 7 predictions JSON loaded for correction "
                                                  "(model-assisted labelling)", path="file")
    import_masks: Path | None = param(None, "optional folder of masks (label images named like their photo, "
                                            "<stem>.png): instance ids, or a binary mask split into connected "
                                            "components; each object becomes a box", path="dir")
    mask_min_area: int = param(20, "mask objects with fewer pixels are not imported (specks)", min=1)
    import_deepforest: Path | None = param(None, "optional DeepForest CSV (image_path,xmin,ymin,xmax,ymax,label)",
                                           path="file")
    import_voc: Path | None = param(None, "optional Pascal VOC XML file or folder of them (LabelImg, CVAT)",
                                    path="exists")
    import_cvat: Path | None = param(None, "optional 'CVAT for images 1.1' XML export (CVAT's and Label Studio's "
                                           "COCO exports go to import_coco)", path="file")
    min_score: float = param(0.5, "imported predictions below this score are left out", min=0.0, max=1.0)
    min_box_size: float = param(2.0, "smaller boxes (px, after clipping to the image) are not created; "
                                     "a click without drag selects instead", min=0.0)
    annotated_region: Literal["auto", "owned", "image"] = param(
        "auto", "the part of each image whose plants are ALL boxed, recorded in annotations.json for module 5 "
                "(which then masks the rest of each tile, so no unboxed plant is taught as background): "
                "'owned' = its owned area (box every plant that touches it), 'image' = the whole image, "
                "'auto' = owned when owned_areas is given", choices=["auto", "owned", "image"])
    export_yolo: bool = param(True, "also write YOLO labels and classes.txt to <output_dir>/yolo")
    include_unseen: bool = param(False, "export images never opened and without boxes too (as negatives)")

    def check(self) -> None:
        if self.annotated_region == "owned" and self.owned_areas is None:
            raise ConfigError("annotated_region: owned needs the owned areas",
                              fix="set owned_areas to module 3's owned_areas.json, or annotated_region: image")
        if not 1 <= len(self.categories) <= MAX_CATEGORIES:
            raise ConfigError(f"'categories' must list 1 to {MAX_CATEGORIES} names, got {self.categories}",
                              fix="for example: categories: [plant, weed]")
        if len(set(self.categories)) != len(self.categories):
            raise ConfigError(f"'categories' has a repeated name: {self.categories}", fix="make the names unique")
