"""``matchplant cameras PROJECT``: what an ODM, Metashape or Pix4D project holds; map points found in its photos."""

from matchplant.core.formats.camera_report import CamerasConfig, run_cameras
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="cameras",
    config=CamerasConfig,
    run=run_cameras,
    output_key=None,
    positional_key="project",
    flags={
        "--points": ("points", "a CSV of map points (x, y, z) to find in the original photos"),
        "--points-crs": ("points_crs", "the points' CRS (default: the project's)"),
        "--output": ("output", "where the points' photo pixels go as CSV ('-': standard output)"),
        "--project-type": ("project_type", "auto, odm, metashape or pix4d"),
    },
)
