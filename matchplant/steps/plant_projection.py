"""Step 8 (8_plant_projection): put detected boxes on the map through the camera poses and the DSM."""

from matchplant.plant_projection import PlantProjectionConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="plant_projection",
    config=PlantProjectionConfig,
    run=run,
    flags={
        "--mode": ("mode", "project, evaluate or both"),
        "--project": ("project", "ODM project folder"),
        "--predictions": ("predictions", "detections JSON (module 7)"),
        "--reference": ("evaluate.reference", "reference boxes for mode evaluate"),
    },
)
