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

    images: Path | None = param(
        None, "folder of images to annotate (e.g. module 3's selected undistorted images)", path="dir", required=True
    )
    output_dir: Path = param(
        Path("runs/bbox_drawer"),
        "folder for the session (session.json, saved after every edit) and exports",
        path="out",
    )
    categories: list[str] = param(["plant"], "category names (1 to 5); keys 1-5 choose them in the GUI")
    owned_areas: Path | None = param(
        None,
        "optional JSON {image_name: [[u, v], ...]}: the area each image owns (module 3), drawn as a dashed outline",
        path="file",
    )
    import_coco: Path | None = param(None, "optional COCO dataset whose boxes are loaded for correction", path="file")
    import_yolo: Path | None = param(
        None, "optional folder of YOLO labels (<image stem>.txt + classes.txt) loaded for correction", path="dir"
    )
    import_predictions: Path | None = param(
        None, "optional module 7 predictions JSON loaded for correction (model-assisted labelling)", path="file"
    )
    import_masks: Path | None = param(
        None,
        "optional folder of masks (label images named like their photo, "
        "<stem>.png, any image format incl. GIF): instance ids or one colour "
        "per plant, or a binary mask split into connected components; each "
        "object becomes a box",
        path="dir",
    )
    mask_min_area: int = param(
        20, "mask objects with fewer pixels are not imported (specks; counted in the log)", min=1
    )
    mask_mode: Literal["auto", "binary", "instance"] = param(
        "auto",
        "how masks are read: 'auto' decides from each mask's pixels (objects whose interiors each hold a "
        "value of their own are instances, whatever the values; a mask whose objects all peak at one "
        "value is binary, however many grey levels its anti-aliased edges hold; said in the log), "
        "'binary' (objects = connected components above mask_threshold), 'instance' (one object per "
        "value or colour)",
        choices=["auto", "binary", "instance"],
    )
    mask_threshold: float | None = param(
        None,
        "binary masks: pixel values at or above this are plant (empty = half "
        "the mask's top value); setting it reads the masks as binary",
        min=0.0,
    )
    import_deepforest: Path | None = param(
        None, "optional DeepForest CSV (image_path,xmin,ymin,xmax,ymax,label)", path="file"
    )
    import_voc: Path | None = param(
        None, "optional Pascal VOC XML file or folder of them (LabelImg, CVAT)", path="exists"
    )
    import_cvat: Path | None = param(
        None,
        "optional 'CVAT for images 1.1' XML export (CVAT's and Label Studio's COCO exports go to import_coco)",
        path="file",
    )
    label_map: dict[str, str] = param(
        {},
        "imported labels -> categories, for imports whose labels are not "
        "the category names, e.g. {Tree: plant} (DeepForest) or {'0': plant}; "
        "a label that is neither a category nor mapped is an error",
    )
    min_score: float = param(0.5, "imported predictions below this score are left out", min=0.0, max=1.0)
    min_box_size: float = param(
        2.0,
        "smaller boxes (px, after clipping to the image) are not created; a click without drag selects instead",
        min=0.0,
    )
    annotated_region: Literal["auto", "owned", "image"] = param(
        "auto",
        "the part of each image whose plants are ALL boxed, recorded in annotations.json for module 5 "
        "(which then masks the rest of each tile, so no unboxed plant is taught as background): "
        "'owned' = its owned area (box every plant that touches it), 'image' = the whole image, "
        "'auto' = owned when owned_areas is given",
        choices=["auto", "owned", "image"],
    )
    export_yolo: bool = param(True, "also write YOLO labels and classes.txt to <output_dir>/yolo")
    include_unseen: bool = param(False, "export images never opened and without boxes too (as negatives)")

    def check(self) -> None:
        """Reject settings that contradict each other: mask options, owned areas, the category list and label_map."""
        if self.mask_mode == "instance" and self.mask_threshold is not None:
            raise ConfigError(
                "mask_threshold applies to binary masks, but mask_mode is 'instance'",
                fix="remove mask_threshold, or set mask_mode: binary (or auto)",
            )
        if self.annotated_region == "owned" and self.owned_areas is None:
            raise ConfigError(
                "annotated_region: owned needs the owned areas",
                fix="set owned_areas to module 3's owned_areas.json, or annotated_region: image",
            )
        if not 1 <= len(self.categories) <= MAX_CATEGORIES:
            raise ConfigError(
                f"'categories' must list 1 to {MAX_CATEGORIES} names, got {self.categories}",
                fix="for example: categories: [plant, weed]",
            )
        self.label_map = {str(k): str(v) for k, v in (self.label_map or {}).items()}
        wrong = {k: v for k, v in self.label_map.items() if v not in self.categories}
        if wrong:
            k, v = next(iter(wrong.items()))
            raise ConfigError(
                f"label_map maps '{k}' to '{v}', which is not one of the categories {self.categories}",
                fix=f"map onto a category (label_map: {{{k}: {self.categories[0]}}}) or add '{v}' to 'categories'",
            )
        if len(set(self.categories)) != len(self.categories):
            raise ConfigError(f"'categories' has a repeated name: {self.categories}", fix="make the names unique")
