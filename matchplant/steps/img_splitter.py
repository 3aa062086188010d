"""Step 5 (5_img_splitter): tile annotated images and split them into train/val/test; GUI (setup screen, preview)."""

from matchplant.img_splitter import ImgSplitterConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="img_splitter",
    config=ImgSplitterConfig,
    run=run,
    gui="matchplant.img_splitter.gui:launch",
    flags={
        "--images": ("images", "folder of the annotated source images"),
        "--annotations": ("annotations", "COCO JSON (or YOLO labels folder) of the boxes"),
    },
)
