"""Step 4 (4_bbox_drawer): draw plant boxes in a GUI (after a setup screen); import and export COCO and YOLO."""

from matchplant.bbox_drawer import BboxDrawerConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="bbox_drawer",
    config=BboxDrawerConfig,
    run=run,
    gui="matchplant.bbox_drawer.gui:launch",
    flags={"--images": ("images", "folder of images to annotate")},
)
