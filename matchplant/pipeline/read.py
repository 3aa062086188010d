"""Reading a pipeline file: its top-level keys and its steps (name, module, config file, settings), each with
its line for the messages."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.validate import did_you_mean, read_text, read_yaml

_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")
STEP_KEYS = ("name", "module", "config", "config_file")


@dataclass
class Step:
    """One step of a pipeline file: its name, module, optional config file and settings, and where it is written."""

    name: str
    module: str
    config_file: Path | None
    settings: dict
    number: int = 0  # 1-based position in the file
    line: int | None = None

    @property
    def label(self) -> str:
        """How messages name the step: number, name, module and line."""
        return f"step {self.number} '{self.name}' ({self.module})" + (f", line {self.line}" if self.line else "")


# --------------------------------------------------------------------------------------------------
# reading the file


class Problems:
    """Every problem found in a pipeline file, raised as one error naming the file and each step."""

    def __init__(self, path: Path):
        self.path = path
        self.items: list[tuple[str, MatchPlantError]] = []

    def add(self, where: str, exc: MatchPlantError) -> None:
        """Record a problem found at ``where`` (a step's label)."""
        self.items.append((where, exc))

    def raise_if_any(self) -> None:
        """Raise one error listing every problem recorded (the problem itself when there is one); nothing when none."""
        if not self.items:
            return
        if len(self.items) == 1:
            where, exc = self.items[0]
            raise type(exc)(
                f"{self.path.name}, {where}: {exc.problem}", path=exc.path or self.path, fix=exc.fix
            ) from exc
        lines = [f"{len(self.items)} problems in {self.path.name} (no step has run):"]
        for where, exc in self.items:
            lines.append(f"  - {where}: {exc.problem}")
            if exc.path is not None and exc.path != self.path:
                lines.append(f"      file: {exc.path}")
            if exc.fix:
                lines.append(f"      fix:  {exc.fix}")
        raise ConfigError("\n".join(lines), path=self.path, fix="correct them, then run the pipeline again")


# --------------------------------------------------------------------------------------------------
# checking every step before running any


def _step_lines(text: str) -> list[int]:
    """The line of each item of the top-level 'steps' list (for messages); empty when it cannot be told."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return []
    if not isinstance(node, yaml.MappingNode):
        return []
    for key, value in node.value:
        if key.value == "steps" and isinstance(value, yaml.SequenceNode):
            return [item.start_mark.line + 1 for item in value.value]
    return []


def read_pipeline(path: Path) -> tuple[dict, list[Step]]:
    """The top-level keys (``output_dir`` made absolute) and the steps, with every structural problem."""
    data = read_yaml(path, what="pipeline file")
    base = path.resolve().parent
    if "steps" not in data:
        close = [k for k in data if did_you_mean(str(k), ["steps"])]
        hint = f"; it has '{close[0]}': did you mean 'steps'?" if close else ""
        raise ConfigError(
            f"the pipeline has no 'steps' list{hint}",
            path=path,
            fix="add 'steps:' with one '- module: NAME' entry per step (see docs/tutorials/season-odm.md)",
        )
    steps_data = data["steps"]
    if not isinstance(steps_data, list) or not steps_data:
        raise ConfigError(
            "the pipeline has no 'steps' list"
            if not steps_data
            else f"'steps' must be a list ('- module: NAME' lines), not a {type(steps_data).__name__}",
            path=path,
            fix="write each step as '- module: NAME' under 'steps:', indented the same",
        )
    top = {str(k): v for k, v in data.items() if k != "steps"}
    top.setdefault("output_dir", "pipeline_output")
    dash = str(top["output_dir"]).strip() == "-"
    if dash or not isinstance(top["output_dir"], (str, Path)) or not str(top["output_dir"]).strip():
        raise ConfigError(
            "'output_dir' must be a folder, got '-' (standard output, which is for a file)"
            if dash
            else f"'output_dir' must be a folder, got {top['output_dir']!r}",
            path=path,
            fix="set output_dir: FOLDER (relative to the pipeline file)",
        )
    top["output_dir"] = str((base / str(top["output_dir"])).resolve())
    lines = _step_lines(read_text(path))
    problems = Problems(path)
    steps: list[Step] = []
    seen: dict[str, int] = {}
    for i, sd in enumerate(steps_data):
        line = lines[i] if i < len(lines) else None
        where = f"step {i + 1}" + (f", line {line}" if line else "")
        try:
            step = _read_step(sd, i + 1, line, base)
        except ConfigError as exc:
            problems.add(where, exc)
            continue
        if step.name in seen:
            problems.add(
                where,
                ConfigError(
                    f"two steps are named '{step.name}' (steps {seen[step.name]} and {i + 1})",
                    fix="give each step a unique 'name'",
                ),
            )
        seen.setdefault(step.name, i + 1)
        steps.append(step)
    problems.raise_if_any()
    return top, steps


def _read_step(sd: Any, number: int, line: int | None, base: Path) -> Step:
    if isinstance(sd, str):
        raise ConfigError(
            f"the step is the text '{sd}', not a mapping",
            fix=f"write it as '- module: {sd}' (with 'name:' and 'config:' below it)",
        )
    if not isinstance(sd, dict):
        raise ConfigError(f"the step is {sd!r}, not a mapping", fix="write '- module: NAME' for each step")
    unknown = [str(k) for k in sd if k not in STEP_KEYS]
    if unknown:
        hint = did_you_mean(unknown[0], STEP_KEYS)
        raise ConfigError(
            f"unknown key(s) {unknown}{'; ' + hint if hint else ''}",
            fix="a step takes name, module, config and config_file; module settings go under 'config:'",
        )
    if "module" not in sd:
        raise ConfigError("the step has no 'module'", fix="write '- module: NAME' for each step")
    name = sd.get("name", sd["module"])
    if not isinstance(name, (str, int)) or not _NAME.match(str(name)):
        raise ConfigError(
            f"step name {name!r} must be letters, digits, '_' or '-'",
            fix="rename the step (it is used in ${name.key} references and folder names)",
        )
    if not isinstance(sd["module"], str):
        raise ConfigError(
            f"'module' must be a module name, got {sd['module']!r}", fix="run 'matchplant --help' for the list"
        )
    settings = sd.get("config") or {}
    if not isinstance(settings, dict):
        raise ConfigError(
            f"'config' must be 'key: value' lines, got {settings!r}", fix="indent the module's settings under 'config:'"
        )
    cfile = sd.get("config_file")
    if cfile is not None and not isinstance(cfile, str):
        raise ConfigError(f"'config_file' must be a path, got {cfile!r}", fix="set config_file: FILE.yaml")
    return Step(
        name=str(name),
        module=sd["module"],
        config_file=(base / cfile) if cfile else None,
        settings=dict(settings),
        number=number,
        line=line,
    )
