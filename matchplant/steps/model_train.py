"""Step 6 (6_model_train): train a plant detector, with transfer learning, from YAML."""

from pathlib import Path

from matchplant.model_train import ModelTrainConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="model_train",
    config=ModelTrainConfig,
    run=run,
    flags={
        "--resume": ("resume", "continue the run in output_dir from its last checkpoint", "true"),
        "--fresh": (
            "resume",
            "start a new run in output_dir, replacing an earlier run's "
            "checkpoints (e.g. after changing model.architecture)",
            "fresh",
        ),
        "--epochs": ("epochs", "number of epochs (shortcut for --set epochs=N)"),
    },
    resume_key="resume",
    resume_file=lambda cfg: Path(cfg.output_dir) / "checkpoints" / "last.pt",
)
