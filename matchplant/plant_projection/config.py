"""Step 8's settings: what to project, how rays meet the surface, how views merge, what to evaluate.

The folder's ``config.yaml`` is generated from these classes; the help texts are what users read there.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.formats.vectors import VECTOR_FORMATS
from matchplant.core.runtime.config import param, section
from matchplant.core.runtime.errors import ConfigError


@dataclass
class EvaluateConfig:
    """Evaluation against boxes drawn on the orthophoto (mode: evaluate or both)."""

    reference: Path | None = param(
        None,
        "reference plant boxes: COCO JSON over the orthophoto, a vector file "
        "(GeoPackage, shapefile, GeoJSON) or a CSV with xmin,ymin,xmax,ymax "
        "in the map CRS",
        path="file",
    )
    plants: Path | None = param(
        None,
        "projected plants to evaluate (GeoPackage, shapefile or CSV); null: plants.gpkg in output_dir",
        path="file",
    )
    orthophoto: Path | None = param(
        None, "orthophoto for COCO references and the figure; null: the ODM project's odm_orthophoto.tif", path="file"
    )
    iou_threshold: float = param(
        0.5, "a reference box counts as well projected above this IoU (paper: 0.5)", min=0.0, max=1.0
    )
    figure_pixels: int = param(1600, "longest side of the orthophoto in the figure, pixels", min=200, max=10000)


@dataclass
class PlantProjectionConfig:
    """Project detected plant boxes from the photos onto the map through the camera poses and the DSM."""

    outputs_inside_inputs = ("project",)  # the project is read by fixed names: <project>/plants is fine
    renamed_keys = {"write_shapefile": ("vector_formats", "[gpkg, shp] for write_shapefile: true, [gpkg] for false")}
    key_aliases = {"project_dir": "project"}  # the name of the same folder in modules 2 and 3

    mode: Literal["project", "evaluate", "both"] = param(
        "project",
        "project: boxes to map plants; evaluate: compare plants with reference boxes; both: one then the other",
        choices=("project", "evaluate", "both"),
    )
    project: Path | None = param(
        None,
        "the project: an ODM folder (opensfm/, odm_dem/, odm_orthophoto/), a Metashape camera export (.xml) or "
        "project (.psx), or a Pix4D project folder (these pose the original photos: image_type original)",
        path="exists",
    )
    project_type: Literal["auto", "odm", "metashape", "pix4d"] = param(
        "auto",
        "which program made the project (auto: from its files, named in the log)",
        choices=("auto", "odm", "metashape", "pix4d"),
    )
    predictions: Path | None = param(
        None, "detections: module 7's predictions JSON, or a COCO results list (then also set images_from)", path="file"
    )
    images_from: Path | None = param(None, "COCO dataset giving the image entries of a plain results list", path="file")
    image_type: Literal["auto", "undistorted", "original"] = param(
        "auto",
        "which photos the boxes are on: undistorted (<name>.tif, ODM's undistorted images), original "
        "(the raw photos, brown/fisheye camera) or auto (from the file names)",
        choices=("auto", "undistorted", "original"),
    )
    dsm: Path | None = param(
        None,
        "surface to intersect the rays with (any CRS); null: the project's odm_dem/dsm.tif, or the DEM GeoTIFF "
        "beside a Metashape export, or Pix4D's 3_dsm_ortho/1_dsm/",
        path="file",
    )
    min_score: float = param(
        0.5, "ignore detections scoring below this (they are counted in the summary)", min=0.0, max=1.0
    )
    edge_points: int = param(
        4, "rays along each box edge besides the corners (more follow the relief better)", min=0, max=50
    )
    silhouette_clearance: float = param(
        0.02,
        "metres: a ray stops when it comes this close above the DSM. The far edge of a photo box is the image "
        "of the plant's top (relief); its ray only grazes the top and would land on the soil behind the plant, "
        "making the map box too long. A few cm keeps it on the plant; too much stops rays over leaves "
        "(0 = plain intersection)",
        min=0.0,
        max=1.0,
    )
    hidden_height: float = param(
        0.05,
        "metres: a box side whose grazing hit stands this much above the ground lay behind the plant's top (or "
        "behind another plant); it is taken from views that saw that side, else mirrored about the plant's top",
        min=0.0,
    )
    ground_window: float = param(
        1.5,
        "metres: the ground under the plants is estimated from the DSM by removing every bump narrower than "
        "this; set it above the widest plant (or row, once the canopy closes)",
        min=0.05,
    )
    fill_holes: float = param(
        0.1,
        "metres: DSM nodata holes no wider than this are filled from their rims before rays are cast (a ray "
        "meeting a hole loses its box); larger holes stay holes and their boxes are listed (0 = fill none)",
        min=0.0,
    )
    map_box: Literal["inscribed", "outline"] = param(
        "inscribed",
        "the plant's map box: inscribed = box of the ellipse inscribed in the projected outline "
        "(right for roundish plants whatever the flight direction); outline = box around the outline",
        choices=("inscribed", "outline"),
    )
    merge: Literal["nadir", "fuse", "none"] = param(
        "nadir",
        "one plant in several views: nadir = keep the view closest to nadir; fuse = robust "
        "intersection of the views' boxes (trims relief displacement of tall plants); none = keep every "
        "view as its own record",
        choices=("nadir", "fuse", "none"),
    )
    merge_iou: float = param(
        0.25,
        "views whose map boxes overlap this much (IoU) are the same plant (half of it when one box lies "
        "inside the other)",
        min=0.01,
        max=0.99,
    )
    border_pixels: float = param(
        2.0, "a box this close to the image (or tile) border is cut; a whole view is preferred to a cut one", min=0.0
    )
    geometry: Literal["outline", "box"] = param(
        "outline",
        "the plants' geometry: the projected outline (follows the relief) or the axis-aligned box",
        choices=("outline", "box"),
    )
    layer: str = param("plants", "layer name in the GeoPackage")
    vector_formats: list[str] = param(
        ["gpkg"],
        "vector files of the plants: gpkg (plants.gpkg, what module 9 "
        "reads), shp (plants.shp, for older GIS tools, short column "
        "names), geojson; plants.csv is always written",
        choices=VECTOR_FORMATS,
    )
    write_views: bool = param(True, "also write views.csv: every projected box with the plant it was merged into")
    output_dir: Path = param(Path("runs/plant_projection"), "folder for the outputs and the run log", path="out")
    evaluate: EvaluateConfig = section(EvaluateConfig)

    def unused_keys(self) -> set[str]:
        """Mode evaluate compares plants already projected with the reference: it reads no detections."""
        return {"predictions", "images_from"} if self.mode == "evaluate" else set()

    def check(self) -> None:
        """Require the inputs ``mode`` needs: the project and predictions, the reference boxes, the plants."""
        if self.mode in ("project", "both"):
            for key in ("project", "predictions"):
                if getattr(self, key) is None:
                    raise ConfigError(
                        f"config key '{key}' is required for mode '{self.mode}'",
                        fix=f"set '{key}: ...' in the config or pass --set {key}=PATH",
                    )
        if self.mode in ("evaluate", "both") and self.evaluate.reference is None:
            raise ConfigError(
                f"config key 'evaluate.reference' is required for mode '{self.mode}'",
                fix="set it to the boxes drawn on the orthophoto (COCO JSON, vector file or CSV)",
            )
        if self.mode == "evaluate" and self.evaluate.plants is None and not (self.output_dir / "plants.gpkg").is_file():
            raise ConfigError(
                "mode 'evaluate' needs projected plants: set 'evaluate.plants', or run mode 'project' first",
                path=self.output_dir / "plants.gpkg",
                fix="set evaluate.plants to the plants.gpkg written by the projection",
            )
