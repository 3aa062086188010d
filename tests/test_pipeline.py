"""The pipeline runner: order, chaining by ${step.key}, skipping up-to-date steps, --from, failure and resume.

The stand-in modules below copy and transform text files so that every output can be checked exactly;
the runner on the real modules is tested end to end in test_end_to_end.py.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import pytest
from log_records import log_records, messages

import matchplant.demo as demo
import matchplant.pipeline.plan as pipeline_plan
from matchplant.cli import run_module
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError, InputError, MatchPlantError
from matchplant.core.runtime.io import write_text
from matchplant.pipeline import PipelineConfig, run_pipeline
from matchplant.steps import StepSpec

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
    real = pipeline_plan.resolve_step
    monkeypatch.setattr(pipeline_plan, "resolve_step", lambda name: SPECS[name] if name in SPECS else real(name))
    CALLS.clear()
    (tmp_path / "words.txt").write_text("one two three")
    pipe = tmp_path / "pipeline.yaml"
    pipe.write_text(
        "output_dir: results\n"
        "text: words.txt\n"
        "steps:\n"
        "  - name: shout\n    module: upper\n    config: {source: '${text}'}\n"
        "  - name: tally\n    module: count\n    config: {source: '${shout.output_dir}/upper.txt'}\n"
    )
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
    # the missing file is one the first step should have written: found when its step runs
    pipe.write_text(text.replace("${shout.output_dir}/upper.txt", "${shout.output_dir}/missing.txt"))
    with pytest.raises(MatchPlantError) as info:
        run_pipeline(PipelineConfig(pipeline=pipe))
    assert "step 'tally'" in str(info.value) and "missing.txt" in str(info.value)
    assert (tmp / "results" / "shout" / "upper.txt").read_text() == "ONE TWO THREE"
    pipe.write_text(text)  # fixed: the finished step is skipped, the failed one runs
    CALLS.clear()
    assert run_pipeline(PipelineConfig(pipeline=pipe)) == {"shout": "up to date", "tally": "ran"}
    assert CALLS == ["count"]


def test_a_missing_input_of_a_later_step_is_found_before_any_step_runs(setup):
    tmp, pipe = setup
    pipe.write_text(pipe.read_text().replace("source: '${shout.output_dir}/upper.txt'", "source: missing.txt"))
    with pytest.raises(ConfigError) as info:
        run_pipeline(PipelineConfig(pipeline=pipe))
    assert "step 2 'tally'" in str(info.value) and "missing.txt" in str(info.value)
    assert CALLS == [] and not (tmp / "results" / "shout").exists()


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


# -- every step checked before any runs -----------------------------------------------------------------------


def write(pipe: Path, text: str) -> Path:
    pipe.write_text("output_dir: results\ntext: words.txt\nsteps:\n" + text)
    return pipe


def failure(pipe: Path, exc: type = ConfigError) -> str:
    with pytest.raises(exc) as info:
        run_pipeline(PipelineConfig(pipeline=pipe))
    assert CALLS == [], "a step ran although the pipeline has a problem"
    return str(info.value)


SHOUT = "  - name: shout\n    module: upper\n    config: {source: '${text}'}\n"


@pytest.mark.parametrize(
    "step2, expected",
    [
        ("  - name: tally\n    module: img_spliter\n", "did you mean 'img_splitter'"),
        ("  - name: tally\n    module: frobnicate\n", "set 'module' to one of: gps_embeder, gcp_finder"),
        (
            "  - name: tally\n    module: count\n    config: {sorce: '${shout.output_dir}/upper.txt'}\n",
            "did you mean 'source'",
        ),
        (
            "  - name: tally\n    module: count\n    config: {source: '${shuot.output_dir}/upper.txt'}\n",
            "did you mean 'shout.output_dir'",
        ),
        (
            "  - name: tally\n    module: count\n    config: {source: '${shout.output_folder}/upper.txt'}\n",
            "did you mean 'output_dir'",
        ),
        (
            "  - name: tally\n    module: count\n    config: {source: '${tally.output_dir}/upper.txt'}\n",
            "refers to this step itself",
        ),
        ("  - name: tally\n    module: count\n    config: {source: '${shout}/upper.txt'}\n", "names a step but no key"),
        ("  - name: tally\n    module: count\n    config: {source: '${shout.output_dir/upper.txt'}\n", "malformed"),
        ("  - name: shout\n    module: count\n", "two steps are named 'shout'"),
        ("  - count\n", "write it as '- module: count'"),
        ("  - name: tally\n    modul: count\n", "did you mean 'module'"),
        ("  - name: tally\n    module: count\n    config: [a, b]\n", "'config' must be 'key: value' lines"),
        (
            "  - name: tally\n    module: upper\n    config: {source: '${text}', fail: maybe}\n",
            "'fail' must be true or false",
        ),
    ],
)
def test_problems_of_step_2_are_found_before_step_1_runs(setup, step2, expected):
    tmp, pipe = setup
    message = failure(write(pipe, SHOUT + step2))
    assert expected in message and "pipeline.yaml" in message and "fix:" in message
    assert not (tmp / "results" / "shout").exists()


def test_forward_reference_and_cycle(setup):
    tmp, pipe = setup
    message = failure(
        write(
            pipe,
            "  - name: a\n    module: count\n    config: {source: '${b.output_dir}/upper.txt'}\n"
            "  - name: b\n    module: upper\n    config: {source: '${text}'}\n",
        )
    )
    assert "refers to step 'b', which runs later (step 2)" in message and "move 'b' before 'a'" in message
    message = failure(
        write(
            pipe,
            "  - name: a\n    module: count\n    config: {source: '${b.output_dir}/upper.txt'}\n"
            "  - name: b\n    module: upper\n    config: {source: '${a.output_dir}/x.txt'}\n",
        )
    )
    assert "a cycle: 'b' also refers to 'a'" in message


def test_every_problem_is_listed_with_its_step_and_line(setup):
    tmp, pipe = setup
    message = failure(
        write(
            pipe,
            "  - name: shout\n    module: gps_embedr\n"
            "  - name: tally\n    module: count\n    config: {source: nothing.txt}\n"
            "  - name: third\n    module: count\n    config: {source: '${nope}'}\n",
        )
    )
    assert message.startswith("3 problems in pipeline.yaml (no step has run)")
    assert "step 1 'shout' (gps_embedr), line 4" in message and "did you mean 'gps_embeder'" in message
    assert "step 2 'tally' (count), line 6" in message and "nothing.txt" in message
    assert "step 3 'third' (count), line 9" in message and "'${nope}' refers to nothing known" in message


def test_a_reference_to_a_broken_step_is_not_reported_twice(setup):
    tmp, pipe = setup
    message = failure(
        write(
            pipe,
            "  - name: shout\n    module: upper\n    config: {source: '${text}', fail: 3}\n"
            "  - name: tally\n    module: count\n    config: {source: '${shout.output_dir}/u'}\n",
        )
    )
    assert "'fail' must be true or false" in message and "tally" not in message


@pytest.mark.parametrize(
    "text, expected",
    [
        ("", "pipeline file is empty"),
        ("output_dir: results\nstep:\n  - module: upper\n", "it has 'step': did you mean 'steps'"),
        ("steps:\n  module: upper\n", "'steps' must be a list"),
        ("steps:\n  - module: upper\n    config: {source: [x\n", "not valid YAML at line"),
        ("steps:\n\t- module: upper\n", "line 2 is indented with a tab"),
        ("steps:\n  - module: upper\n    config: {source: a.txt}\n    config: {source: b.txt}\n", "given twice"),
        ("- module: upper\n", "expected an object"),
    ],
)
def test_bad_pipeline_file_structure(setup, text, expected):
    tmp, pipe = setup
    pipe.write_text(text)
    assert expected in failure(pipe)


def test_bom_crlf_pipeline_and_typed_whole_references(setup):
    tmp, pipe = setup
    text = pipe.read_text().replace("text: words.txt\n", "text: words.txt\nflag: false\n")
    text = text.replace("config: {source: '${text}'}", "config: {source: '${text}', fail: '${flag}'}")
    pipe.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    assert run_pipeline(PipelineConfig(pipeline=pipe)) == {"shout": "ran", "tally": "ran"}
    assert (tmp / "results" / "tally" / "count.txt").read_text() == "3"


def test_a_literal_path_to_an_earlier_output_says_how_to_refer_to_it(setup):
    tmp, pipe = setup
    message = failure(
        write(pipe, SHOUT + "  - name: tally\n    module: count\n    config: {source: results/shout/upper.txt}\n")
    )
    assert "refer to it as '${shout.output_dir}/upper.txt'" in message


def test_outputs_over_inputs_are_refused_before_any_step_runs(setup):
    tmp, pipe = setup
    (tmp / "data").mkdir()
    (tmp / "data" / "words.txt").write_text("a b")
    # the step's own output folder holds its input
    message = failure(
        write(pipe, "  - name: shout\n    module: upper\n    config: {source: data/words.txt, output_dir: data}\n")
    )
    assert "output folder 'output_dir'" in message and "contains the input 'source'" in message
    # a later step writes into the folder of an earlier step's input
    message = failure(
        write(
            pipe,
            "  - name: shout\n    module: upper\n    config: {source: data/words.txt}\n"
            "  - name: tally\n    module: count\n"
            "    config: {source: '${shout.output_dir}/upper.txt', output_dir: data}\n",
        )
    )
    assert "tally.output_dir" in message and "shout.source" in message
    assert (tmp / "data" / "words.txt").read_text() == "a b"


def test_unknown_from_step_has_did_you_mean(setup):
    tmp, pipe = setup
    with pytest.raises(ConfigError, match="did you mean 'tally'"):
        run_pipeline(PipelineConfig(pipeline=pipe, from_step="taly"))


def test_every_bad_key_of_one_step_is_reported(setup):
    tmp, pipe = setup
    message = failure(
        write(
            pipe,
            SHOUT + "  - name: tally\n    module: count\n"
            "    config: {sorce: '${shout.output_dir}/u', output_dir: '${nope}'}\n",
        )
    )
    assert "2 problems" in message and "did you mean 'source'" in message and "'${nope}'" in message


def test_the_demo_lists_each_step_once_over_its_two_parts(setup, monkeypatch):
    """The demo runs its first steps, holds photos out, then the rest: a finished step of the first part is not
    listed again as "up to date, skipped" by the second (seen: steps 0-5 twice in the console)."""
    tmp, pipe = setup
    monkeypatch.setattr(demo, "FIRST_STEPS", 1)
    between = []
    with log_records("matchplant.pipeline", logging.INFO) as records:
        results = demo.run_in_two_parts(pipe, "", lambda: between.append(list(CALLS)))
    assert results == {"shout": "ran", "tally": "ran"} and between == [["upper:words.txt"]]
    lines = messages(records)
    for name in ("shout", "tally"):
        assert sum(ln.startswith(f"[{name}] running") for ln in lines) == 1
        assert not any(ln.startswith(f"[{name}]") and "skipped" in ln for ln in lines), lines
    with log_records("matchplant.pipeline", logging.INFO) as records:  # again: each up to date, listed once
        assert demo.run_in_two_parts(pipe, "", lambda: None) == {"shout": "up to date", "tally": "up to date"}
    assert messages(records) == ["[shout] up to date, skipped", "[tally] up to date, skipped"]
