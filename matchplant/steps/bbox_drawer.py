"""Step 4 (4_bbox_drawer): draw plant boxes in a GUI; import and export COCO and YOLO."""

from pathlib import Path

from matchplant.bbox_drawer.annotate import AnnotateConfig, run
from matchplant.bbox_drawer.gui import launch
from matchplant.steps import StepSpec


def gui(cfg: AnnotateConfig, config_path: Path | None = None) -> None:
    launch(cfg)


SPEC = StepSpec(name="bbox_drawer", config=AnnotateConfig, run=run, gui=gui,
                flags={"--images": ("images", "folder of images to annotate"),
                       "--output": ("output_dir", "folder for the session and the exports")})
