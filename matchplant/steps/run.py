"""``matchplant run pipeline.yaml``: run several steps in order, chaining their outputs."""

from matchplant.pipeline import PipelineConfig, run_pipeline
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="run",
    config=PipelineConfig,
    run=run_pipeline,
    positional_key="pipeline",
    flags={"--from": ("from_step", "re-run from this step on")},
)
