"""Step 5 (5_img_splitter): tile annotated images and split them into train/val/test; GUI (setup screen, preview)."""

from matchplant.img_splitter.gui import launch
from matchplant.img_splitter.tiling import TilingConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(name="img_splitter", config=TilingConfig, run=run, gui=launch,
                flags={"--images": ("images", "folder of the annotated source images"),
                       "--annotations": ("annotations", "COCO JSON (or YOLO labels folder) of the boxes"),
                       "--output": ("output_dir", "folder for the tiles and the split datasets")})
