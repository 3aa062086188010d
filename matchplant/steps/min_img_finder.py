"""Step 3 (3_min_img_finder): the fewest undistorted images that cover the field; GUI."""

from matchplant.min_img_finder.config import MinImagesConfig
from matchplant.min_img_finder.finder import run
from matchplant.min_img_finder.gui import open_gui
from matchplant.steps import StepSpec

SPEC = StepSpec(name="min_img_finder", config=MinImagesConfig, run=run, gui=open_gui,
                flags={"--project": ("project_dir", "ODM project folder"),
                       "--uncovered": ("uncovered_threshold", "percent of the area allowed uncovered")})
