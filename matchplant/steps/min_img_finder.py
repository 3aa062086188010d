"""Step 3 (3_min_img_finder): the fewest undistorted images that cover the field; GUI."""

from matchplant.min_img_finder import MinImgFinderConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="min_img_finder",
    config=MinImgFinderConfig,
    run=run,
    gui="matchplant.min_img_finder.gui:launch",
    flags={
        "--project": ("project_dir", "ODM project folder"),
        "--uncovered": ("uncovered_threshold", "percent of the area allowed uncovered"),
    },
)
