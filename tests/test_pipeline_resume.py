"""``matchplant run`` continues a step's interrupted run (issue 40, point 3): a step that can resume (its StepSpec
names a resume key and its checkpoint, as module 6 does) is re-run with that key set when its previous run stopped
unfinished with the same settings and inputs and left a checkpoint; otherwise it starts anew. A stand-in step
counts to ``iterations`` writing a checkpoint after each, so where it started is exact."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

import matchplant.pipeline.plan as pipeline_plan
from matchplant.core.runtime.config import param
from matchplant.pipeline import PipelineConfig, run_pipeline
from matchplant.steps import StepSpec

STARTS: list[tuple[bool, int]] = []  # (resume, first iteration) of every run of the step
STOP_AT: list[int] = []  # Ctrl-C before this iteration (once)


@dataclass
class CountToConfig:
    source: Path | None = param(None, "input file", path="file", required=True)
    output_dir: Path = param("out", "output folder", path="out")
    iterations: int = param(6, "how far to count")
    resume: bool = param(False, "continue from the checkpoint")


def _checkpoint(cfg) -> Path:
    return Path(cfg.output_dir) / "last.txt"


def count_to(cfg: CountToConfig) -> None:
    start = int(_checkpoint(cfg).read_text()) if cfg.resume else 0
    STARTS.append((cfg.resume, start + 1))
    for i in range(start + 1, cfg.iterations + 1):
        if STOP_AT and i == STOP_AT[0]:
            STOP_AT.clear()
            raise KeyboardInterrupt
        _checkpoint(cfg).write_text(str(i))


SPEC = StepSpec("count_to", CountToConfig, count_to, resume_key="resume", resume_file=_checkpoint)


@pytest.fixture
def pipe(tmp_path, monkeypatch) -> Path:
    real = pipeline_plan.resolve_step
    monkeypatch.setattr(pipeline_plan, "resolve_step", lambda name: SPEC if name == "count_to" else real(name))
    STARTS.clear()
    STOP_AT.clear()
    (tmp_path / "input.txt").write_text("x")
    path = tmp_path / "pipeline.yaml"
    path.write_text("output_dir: out\nsteps:\n  - name: train\n    module: count_to\n    config: {source: input.txt}\n")
    return path


def _run(path: Path, **kw):
    return run_pipeline(PipelineConfig(pipeline=path, **kw))


def test_an_interrupted_step_continues_where_it_stopped_then_counts_as_finished(pipe):
    STOP_AT.append(4)
    with pytest.raises(KeyboardInterrupt):
        _run(pipe)
    assert _run(pipe) == {"train": "ran"}
    assert STARTS == [(False, 1), (True, 4)]  # the re-run continued at the interrupted iteration
    assert _run(pipe) == {"train": "up to date"}  # its stamp holds its own settings (resume not among them)
    assert len(STARTS) == 2


def test_changed_settings_or_no_checkpoint_start_anew(pipe):
    STOP_AT.append(3)
    with pytest.raises(KeyboardInterrupt):
        _run(pipe)
    pipe.write_text(pipe.read_text().replace("source: input.txt", "source: input.txt, iterations: 7"))
    _run(pipe)
    assert STARTS == [(False, 1), (False, 1)]
    STARTS.clear()
    STOP_AT.append(1)  # stopped before its first checkpoint: the earlier run's last.txt is not this run's
    pipe.write_text(pipe.read_text().replace("iterations: 7", "iterations: 8"))
    with pytest.raises(KeyboardInterrupt):
        _run(pipe)
    _run(pipe)
    assert STARTS == [(False, 1), (False, 1)]


def test_from_step_starts_anew_and_its_interruption_is_continued(pipe):
    STOP_AT.append(4)
    with pytest.raises(KeyboardInterrupt):
        _run(pipe)
    assert _run(pipe, from_step="train") == {"train": "ran"}
    STOP_AT.append(3)  # a finished step re-run with --from and interrupted: no longer up to date
    with pytest.raises(KeyboardInterrupt):
        _run(pipe, from_step="train")
    assert _run(pipe) == {"train": "ran"}
    assert STARTS == [(False, 1), (False, 1), (False, 1), (True, 3)]
