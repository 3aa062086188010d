"""Step 1's settings, in one place so that every part of the step (and its GUI) reads the same ones."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from matchplant.core.formats.gcp_marks import FORMATS
from matchplant.core.runtime.config import param

MIN_IMAGES_PER_GCP = 3  # ODM ignores a GCP marked in fewer images


@dataclass
class GcpFinderConfig:
    """Module 1: find the images that see each GCP, mark the GCPs (GUI or auto), write gcp_list.txt."""

    images: Path | None = param(
        None, "folder of the flight's images (JPEG or TIFF, with EXIF GPS)", path="dir", required=True
    )
    survey: Path | None = param(None, "GCP survey table: CSV with the header id,x,y,z", path="file", required=True)
    survey_crs: str | None = param(
        None,
        "CRS of the survey: EPSG code (EPSG:32614, EPSG:4326 = lon/lat), 'WGS84 UTM 14N' or a PROJ string",
        required=True,
    )
    output_dir: Path = param(
        Path("runs/gcp_finder"),
        "output folder: gcp_list.txt (and the files of formats), candidates.csv, candidates.png",
        path="out",
    )
    output_crs: str | None = param(
        None, "CRS of gcp_list.txt; empty = the survey's CRS when projected, else the GCPs' UTM zone"
    )
    sensor_width_mm: float | None = param(
        None,
        "camera sensor width (long side, mm); empty = from the built-in table of drone cameras by EXIF model",
        min=0.1,
    )
    focal_length_mm: float | None = param(None, "focal length (mm); empty = EXIF FocalLength", min=0.1)
    yaw_source: str = param(
        "auto",
        "image heading: 'xmp' (DJI gimbal/flight yaw), 'track' (direction of "
        "flight between images), 'fixed' (yaw_deg); 'auto' = xmp, else track",
        choices=("auto", "xmp", "track", "fixed"),
    )
    yaw_deg: float = param(
        0.0,
        "heading of the image top (degrees clockwise from north) for yaw_source "
        "'fixed', added to the flight direction for 'track'",
        min=-360,
        max=360,
    )
    height_source: str = param(
        "auto",
        "camera height above a GCP: 'gps' (EXIF altitude - GCP z), 'relative' "
        "(DJI relative altitude), 'fixed' (flight_height_m); 'auto' = relative "
        "when the images have it, else gps",
        choices=("auto", "gps", "relative", "fixed"),
    )
    altitude_offset_m: float = param(
        0.0,
        "added to the EXIF GPS altitude to put it in the survey's height "
        "datum (e.g. the geoid height when GPS is ellipsoidal)",
    )
    flight_height_m: float | None = param(None, "flight height above ground (m) for height_source 'fixed'", min=1)
    max_center_distance: float = param(
        0.8,
        "candidate only when the predicted GCP is within this distance of the image centre (0 = centre, 1 = a corner)",
        min=0.0,
        max=1.0,
    )
    edge_margin_px: int = param(10, "ignore predictions closer than this to the image edge (pixels)", min=0)
    max_images_per_gcp: int = param(0, "keep only the best-ranked candidates per GCP (0 = all)", min=0)
    auto: bool = param(False, "find each target in its candidate images and write gcp_list.txt without the GUI")
    search_radius_px: int = param(
        0,
        "auto: half-size of the search window around a prediction (0 = the "
        "larger of 6 % of the image width and 3/4 of the target)",
        min=0,
    )
    target_size_m: float = param(0.5, "auto: side of the square GCP target (m)", min=0.01)
    target_pattern: str = param(
        "checker",
        "auto: the target's look: 'checker' (2x2 black and white quadrants) "
        "or 'square' (a plain square on a contrasting background)",
        choices=("checker", "square"),
    )
    zoom_px: int = param(150, "GUI: half-size of the view around a predicted position (pixels)", min=10)
    gcp_list: Path | None = param(
        None, "existing gcp_list.txt to continue (empty = output_dir/gcp_list.txt if it exists)", path="file"
    )
    formats: list[str] = param(
        ["odm"],
        "programs to write the marks for: odm (gcp_list.txt), pix4d (pix4d_gcps.csv, pix4d_marks.csv), "
        "metashape (metashape_reference.csv; metashape_markers.xml too with metashape_cameras); "
        "gcp_list.txt is always written, sessions continue from it",
        choices=FORMATS,
    )
    metashape_cameras: Path | None = param(
        None,
        "Metashape's camera ids for metashape_markers.xml: the chunk's File > Export > Export Cameras... "
        "XML (empty = the reference CSV only)",
        path="file",
    )
