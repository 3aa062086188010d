"""``matchplant inspect <coco.json>``: object sizes in pixels and the tiling and detector settings they call for."""

from matchplant.detection.objects import InspectConfig, inspect_dataset
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="inspect",
    config=InspectConfig,
    run=inspect_dataset,
    output_key=None,
    positional_key="annotations",
    flags={"--report": ("report", "also write the statistics and advice to this JSON file")},
)
