"""The pipeline runner: order, chaining by ${step.key}, skipping up-to-date steps, --from, failure and resume.

The stand-in modules below copy and transform text files so that every output can be checked exactly;
the runner on the real modules is tested end to end in test_end_to_end.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

import matchplant.pipeline as pipeline
from matchplant.cli import run_module
from matchplant.steps import StepSpec
from matchplant.core.config import param
from matchplant.core.errors import ConfigError, InputError, MatchPlantError
from matchplant.core.io import write_text
from matchplant.pipeline import PipelineConfig, run_pipeline

CALLS: list[str] = []


@dataclass
class UpperConfig:
    source: Path | None = param(None, "input text file", path="file", required=True)
    output_dir: Path = param("out", "output folder", path="out")
    fail: bool = param(False, "raise an error (to test failures)")


def upper(cfg: UpperConfig) -> None:
    CALLS.append(f"upper:{cfg.source.name}")
    if cfg.fail:
        raise InputError("this step was told to fail", path=cfg.source, fix="set fail: false")
    write_text(Path(cfg.output_dir) / "upper.txt", cfg.source.read_text().upper())


@dataclass
class CountConfig:
    source: Path | None = param(None, "input text file", path="file", required=True)
    output_dir: Path = param("out", "output folder", path="out")


def count(cfg: CountConfig) -> None:
    CALLS.append("count")
    write_text(Path(cfg.output_dir) / "count.txt", str(len(cfg.source.read_text().split())))


SPECS = {"upper": StepSpec("upper", UpperConfig, upper), "count": StepSpec("count", CountConfig, count)}


@pytest.fixture
def setup(tmp_path, monkeypatch):
    real = pipeline.resolve_step
    monkeypatch.setattr(pipeline, "resolve_step", lambda name: SPECS[name] if name in SPECS else real(name))
    CALLS.clear()
    (tmp_path / "words.txt").write_text("one two three")
    pipe = tmp_path / "pipeline.yaml"
    pipe.write_text(
        "output_dir: results\n"
        "text: words.txt\n"
        "steps:\n"
        "  - name: shout\n    module: upper\n    config: {source: '${text}'}\n"
        "  - name: tally\n    module: count\n    config: {source: '${shout.output_dir}/upper.txt'}\n")
    return tmp_path, pipe


def test_runs_in_order_and_chains_outputs(setup):
    tmp, pipe = setup
    assert run_pipeline(PipelineConfig(pipeline=pipe)) == {"shout": "ran", "tally": "ran"}
    assert (tmp / "results" / "shout" / "upper.txt").read_text() == "ONE TWO THREE"
    assert (tmp / "results" / "tally" / "count.txt").read_text() == "3"
    assert CALLS == ["upper:words.txt", "count"]


def test_up_to_date_steps_are_skipped_and_changes_rerun(setup):
    tmp, pipe = setup
    run_pipeline(PipelineConfig(pipeline=pipe))
    CALLS.clear()
    assert run_pipeline(PipelineConfig(pipeline=pipe)) == {"shout": "up to date", "tally": "up to date"}
    assert CALLS == []
    (tmp / "words.txt").write_text("four five")  # changed input: both steps must run again
    assert run_pipeline(PipelineConfig(pipeline=pipe)) == {"shout": "ran", "tally": "ran"}
    assert (tmp / "results" / "tally" / "count.txt").read_text() == "2"


def test_from_step_reruns_that_step_and_later(setup):
    tmp, pipe = setup
    run_pipeline(PipelineConfig(pipeline=pipe))
    CALLS.clear()
    assert run_pipeline(PipelineConfig(pipeline=pipe, from_step="tally")) == {"shout": "up to date", "tally": "ran"}
    with pytest.raises(ConfigError, match="no step named 'nope'"):
        run_pipeline(PipelineConfig(pipeline=pipe, from_step="nope"))


def test_failure_names_the_step_keeps_earlier_results_and_resumes(setup):
    tmp, pipe = setup
    text = pipe.read_text()
    pipe.write_text(text.replace("source: '${shout.output_dir}/upper.txt'", "source: missing.txt"))
    with pytest.raises(MatchPlantError) as info:
        run_pipeline(PipelineConfig(pipeline=pipe))
    assert "step 'tally'" in str(info.value) and "missing.txt" in str(info.value)
    assert (tmp / "results" / "shout" / "upper.txt").read_text() == "ONE TWO THREE"
    pipe.write_text(text)  # fixed: the finished step is skipped, the failed one runs
    CALLS.clear()
    assert run_pipeline(PipelineConfig(pipeline=pipe)) == {"shout": "up to date", "tally": "ran"}
    assert CALLS == ["count"]


def test_failing_module_is_reported_with_step_name(setup):
    tmp, pipe = setup
    pipe.write_text(pipe.read_text().replace("config: {source: '${text}'}", "config: {source: '${text}', fail: true}"))
    with pytest.raises(InputError, match="step 'shout' \\(upper\\) failed: this step was told to fail"):
        run_pipeline(PipelineConfig(pipeline=pipe))
    assert not (tmp / "results" / "tally").exists()


def test_bad_pipeline_files(setup):
    tmp, pipe = setup
    pipe.write_text("steps:\n  - module: upper\n    config: {source: '${nothing}'}\n")
    with pytest.raises(ConfigError, match="nothing"):
        run_pipeline(PipelineConfig(pipeline=pipe))
    pipe.write_text("steps: []\n")
    with pytest.raises(ConfigError, match="no 'steps'"):
        run_pipeline(PipelineConfig(pipeline=pipe))
    pipe.write_text("steps:\n  - module: upper\n    confg: {}\n")
    with pytest.raises(ConfigError, match="confg"):
        run_pipeline(PipelineConfig(pipeline=pipe))


def test_command_line_run_and_from(setup, capsys):
    tmp, pipe = setup
    assert run_module("run", [str(pipe)]) == 0
    assert (tmp / "results" / "tally" / "count.txt").read_text() == "3"
    assert list((tmp / "results" / "logs").glob("run_*.log"))
    assert run_module("run", [str(pipe), "--from", "tally"]) == 0
    assert run_module("run", [str(pipe), "--from", "nope"]) == 2
    assert "no step named 'nope'" in capsys.readouterr().err
