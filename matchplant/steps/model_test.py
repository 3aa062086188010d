"""Step 7 (7_model_test): COCO evaluation of a checkpoint, and detection on new images."""

from matchplant.model_test import ModelTestConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(name="model_test", config=ModelTestConfig, run=run)
