"""The synthetic field generator as a command: an ODM-shaped project with exact ground truth."""

from matchplant.simfield import PRESETS, SimFieldConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="simfield",
    config=SimFieldConfig,
    run=run,
    flags={
        "--preset": ("preset", f"field size: {', '.join(PRESETS)}"),
        "--seed": ("seed", "random seed (the same seed gives the same field)"),
    },
)
