"""Step 2 (2_odm_runner): run OpenDroneMap (Docker, NodeODM) and check its outputs."""

from matchplant.odm_runner import OdmRunnerConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="odm_runner",
    config=OdmRunnerConfig,
    run=run,
    flags={
        "--project": ("project_dir", "ODM project folder (holds images/)"),
        "--backend": ("backend", "docker or nodeodm"),
    },
)
