"""Step 4 (4_bbox_drawer): draw plant boxes in a GUI (after a setup screen); import and export COCO and YOLO."""

from matchplant.bbox_drawer.annotate import AnnotateConfig, run
from matchplant.bbox_drawer.gui import launch
from matchplant.steps import StepSpec

SPEC = StepSpec(name="bbox_drawer", config=AnnotateConfig, run=run, gui=launch,
                flags={"--images": ("images", "folder of images to annotate"),
                       "--output": ("output_dir", "folder for the session and the exports")})
