"""``matchplant run pipeline.yaml``: several modules in order, headless, each step's outputs feeding the next.

A pipeline file names its steps; each step is a module with its settings (inline, or a config file plus
overrides). Values may refer to earlier steps and to the pipeline's own keys::

    output_dir: season2024          # each step writes to <output_dir>/<step name> unless it says otherwise
    project: /data/odm/field3       # any extra top-level key can be used as ${project}
    steps:
      - name: projection
        module: project_boxes
        config:
          project_dir: ${project}
          predictions: ${detect.output_dir}/predictions.json

Before any step runs, every step is checked: its module and keys, the types and ranges of its values, every
``${...}`` reference (an earlier step and one of its keys; a later step, the step itself or an unknown name
is an error), the input paths that do not come from an earlier step (those are checked when their step
runs), and its outputs (not an input, writable: :mod:`matchplant.core.runtime.guard`). All problems are reported
together, so a typo in the last step costs seconds, not the hours of the steps before it.

A step is skipped when it finished before with the same settings and its inputs have not changed since
(a fingerprint in ``<output_dir>/.pipeline/<step>.json``); ``--from STEP`` re-runs from that step on. A
failure names the step and stops; the outputs of earlier steps stay as they were.
"""

from matchplant.pipeline.read import read_pipeline
from matchplant.pipeline.run import PipelineConfig, run_pipeline

__all__ = ["PipelineConfig", "read_pipeline", "run_pipeline"]
