"""Step 3's settings, in one class: the folder's ``config.yaml``, the CLI flags and the GUI all read it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.formats.vectors import VECTOR_FORMATS
from matchplant.core.runtime.config import param


@dataclass
class MinImgFinderConfig:
    """Choose the fewest undistorted images covering the field, and the part of the field each one owns."""

    outputs_inside_inputs = ("project_dir",)  # the project is read by fixed names: <project>/min_images is fine

    project_dir: Path = param(
        None,
        "the project: an ODM folder (opensfm/, odm_dem/dsm.tif, odm_orthophoto/), a Metashape camera export (.xml) "
        "or project (.psx) with its DEM and orthomosaic GeoTIFFs beside it, or a Pix4D project folder",
        path="exists",
        required=True,
    )
    project_type: Literal["auto", "odm", "metashape", "pix4d"] = param(
        "auto",
        "which program made the project (auto: from its files, named in the log)",
        choices=("auto", "odm", "metashape", "pix4d"),
    )
    aoi_file: Path | None = param(
        None,
        "polygon file of the area to cover (GeoPackage, Shapefile, GeoJSON); empty: the orthophoto's valid-data area",
        path="file",
    )
    uncovered_threshold: float = param(
        5.0,
        "share of the area allowed to stay uncovered, percent (the paper's uncovered-area threshold)",
        min=0.0,
        max=90.0,
    )
    max_overlap: float = param(
        30.0,
        "largest overlap between two selected images, percent of the smaller "
        "footprint (the paper's overlap limit; relaxed with a warning if the "
        "coverage cannot be reached)",
        min=0.0,
        max=100.0,
    )
    overlap_penalty: float = param(0.2, "greedy score = new area - penalty x area covered twice", min=0.0, max=10.0)
    method: Literal["greedy", "milp"] = param(
        "greedy",
        "greedy set cover (fast, any size) or milp (exact integer program, small flights)",
        choices=["greedy", "milp"],
    )
    milp_time_limit: float = param(60.0, "seconds the integer program may run (method: milp)", min=1.0)
    cell_size: float = param(0.0, "coverage grid cell size in metres; 0: automatic (about 40,000 cells)", min=0.0)
    border_samples: int = param(16, "rays cast along each side of an image for its footprint", min=2, max=500)
    dsm_resolution: float = param(
        0.05, "DSM resolution used for footprints, metres (coarser is faster); 0: the file's own", min=0.0
    )
    preview_size: int = param(
        1500, "longest side, in pixels, of the orthophoto read for the AOI and the figure", min=100, max=20000
    )
    copy_images: Literal["copy", "link", "none"] = param(
        "copy",
        "put the selected images in output_dir/images: "
        "copy, link (hard link, no extra space), or none "
        "(only list them)",
        choices=["copy", "link", "none"],
    )
    vector_formats: list[str] = param(
        ["gpkg"],
        "GIS files of the footprints, owned areas, AOI and uncovered "
        "parts: gpkg (footprints.gpkg, a layer each), shp or geojson "
        "(footprints.<ext> and footprints_<layer>.<ext>)",
        choices=VECTOR_FORMATS,
    )
    output_dir: Path = param(Path("runs/min_img_finder"), "folder for the outputs", path="out")
