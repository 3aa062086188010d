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

from __future__ import annotations

import hashlib
import json
import re
import time
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import yaml

from matchplant.core.runtime.config import load_config, param, set_value, to_dict, validate
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.guard import (
    INPUT_KINDS,
    check_no_overlap,
    check_outputs_are_not_inputs,
    check_outputs_writable,
    inputs_and_outputs,
)
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import check_path, did_you_mean, read_text, read_yaml
from matchplant.steps import STEPS, StepSpec, resolve_step

log = get_logger("pipeline")
_REF = re.compile(r"\$\{([A-Za-z0-9_.\-]+)\}")
_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")
STEP_KEYS = ("name", "module", "config", "config_file")


@dataclass
class PipelineConfig:
    """Run several MatchPlant modules in order from one file (see matchplant/pipeline.py)."""

    pipeline: Path | None = param(None, "the pipeline YAML file (steps and their settings)", path="file",
                                  required=True)
    output_dir: Path | None = param(None, "where the run log goes (default: the pipeline's output_dir)")
    from_step: str = param("", "re-run from this step on, even if earlier results are up to date")
    only: list[str] = param([], "run only these steps (names); empty = all")
    force: bool = param(False, "re-run every step, even when up to date")

    def check(self) -> None:
        if self.output_dir is None and self.pipeline is not None and Path(self.pipeline).is_file():
            self.output_dir = Path(read_pipeline(Path(self.pipeline))[0]["output_dir"])


@dataclass
class Step:
    name: str
    module: str
    config_file: Path | None
    settings: dict
    number: int = 0  # 1-based position in the file
    line: int | None = None

    @property
    def label(self) -> str:
        return f"step {self.number} '{self.name}' ({self.module})" + (f", line {self.line}" if self.line else "")


@dataclass
class Planned:
    """A step with its checked config; ``pending`` keys take their value from an earlier step's outputs."""

    step: Step
    spec: StepSpec
    cfg: Any
    pending: set[str] = field(default_factory=set)


class Problems:
    """Every problem found in a pipeline file, raised as one error naming the file and each step."""

    def __init__(self, path: Path):
        self.path = path
        self.items: list[tuple[str, MatchPlantError]] = []

    def add(self, where: str, exc: MatchPlantError) -> None:
        self.items.append((where, exc))

    def raise_if_any(self) -> None:
        if not self.items:
            return
        if len(self.items) == 1:
            where, exc = self.items[0]
            raise type(exc)(f"{self.path.name}, {where}: {exc.problem}", path=exc.path or self.path,
                            fix=exc.fix) from exc
        lines = [f"{len(self.items)} problems in {self.path.name} (no step has run):"]
        for where, exc in self.items:
            lines.append(f"  - {where}: {exc.problem}")
            if exc.path is not None and exc.path != self.path:
                lines.append(f"      file: {exc.path}")
            if exc.fix:
                lines.append(f"      fix:  {exc.fix}")
        raise ConfigError("\n".join(lines), path=self.path, fix="correct them, then run the pipeline again")


# --------------------------------------------------------------------------------------------------
# reading the file


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
        raise ConfigError(f"the pipeline has no 'steps' list{hint}", path=path,
                          fix="add 'steps:' with one '- module: NAME' entry per step (see the README)")
    steps_data = data["steps"]
    if not isinstance(steps_data, list) or not steps_data:
        raise ConfigError("the pipeline has no 'steps' list" if not steps_data else
                          f"'steps' must be a list ('- module: NAME' lines), not a {type(steps_data).__name__}",
                          path=path, fix="write each step as '- module: NAME' under 'steps:', indented the same")
    top = {str(k): v for k, v in data.items() if k != "steps"}
    top.setdefault("output_dir", "pipeline_output")
    if not isinstance(top["output_dir"], (str, Path)) or not str(top["output_dir"]).strip():
        raise ConfigError(f"'output_dir' must be a folder, got {top['output_dir']!r}", path=path,
                          fix="set output_dir: FOLDER (relative to the pipeline file)")
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
            problems.add(where, ConfigError(f"two steps are named '{step.name}' (steps {seen[step.name]} and "
                                            f"{i + 1})", fix="give each step a unique 'name'"))
        seen.setdefault(step.name, i + 1)
        steps.append(step)
    problems.raise_if_any()
    return top, steps


def _read_step(sd: Any, number: int, line: int | None, base: Path) -> Step:
    if isinstance(sd, str):
        raise ConfigError(f"the step is the text '{sd}', not a mapping",
                          fix=f"write it as '- module: {sd}' (with 'name:' and 'config:' below it)")
    if not isinstance(sd, dict):
        raise ConfigError(f"the step is {sd!r}, not a mapping", fix="write '- module: NAME' for each step")
    unknown = [str(k) for k in sd if k not in STEP_KEYS]
    if unknown:
        hint = did_you_mean(unknown[0], STEP_KEYS)
        raise ConfigError(f"unknown key(s) {unknown}{'; ' + hint if hint else ''}",
                          fix="a step takes name, module, config and config_file; module settings go under "
                              "'config:'")
    if "module" not in sd:
        raise ConfigError("the step has no 'module'", fix="write '- module: NAME' for each step")
    name = sd.get("name", sd["module"])
    if not isinstance(name, (str, int)) or not _NAME.match(str(name)):
        raise ConfigError(f"step name {name!r} must be letters, digits, '_' or '-'",
                          fix="rename the step (it is used in ${name.key} references and folder names)")
    if not isinstance(sd["module"], str):
        raise ConfigError(f"'module' must be a module name, got {sd['module']!r}",
                          fix="run 'matchplant --help' for the list")
    settings = sd.get("config") or {}
    if not isinstance(settings, dict):
        raise ConfigError(f"'config' must be 'key: value' lines, got {settings!r}",
                          fix="indent the module's settings under 'config:'")
    cfile = sd.get("config_file")
    if cfile is not None and not isinstance(cfile, str):
        raise ConfigError(f"'config_file' must be a path, got {cfile!r}", fix="set config_file: FILE.yaml")
    return Step(name=str(name), module=sd["module"], config_file=(base / cfile) if cfile else None,
                settings=dict(settings), number=number, line=line)


# --------------------------------------------------------------------------------------------------
# references


def flat_values(cfg: Any, prefix: str = "") -> dict[str, Any]:
    """``{dotted.key: value}`` of a config, sections included (their keys are ``section.key``)."""
    out: dict[str, Any] = {}
    for f in fields(cfg):
        v = getattr(cfg, f.name)
        if is_dataclass(v):
            out.update(flat_values(v, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = v
    return out


class _Unresolved(Exception):
    """A reference to an earlier step whose own config failed (its problem is already reported)."""


@dataclass
class Scope:
    top: dict
    steps: list[Step]
    keys: dict[str, set[str]]  # step name -> its config's keys
    values: dict[str, dict] = field(default_factory=dict)  # step name -> its built config's values

    def lookup(self, ref: str, step: Step) -> tuple[Any, bool]:
        """The value ``${ref}`` stands for in ``step``, and whether it comes from an earlier step."""
        if ref in self.top:
            return self._plain(ref, self.top[ref]), False
        head, _, rest = ref.partition(".")
        order = {s.name: s for s in self.steps}
        if head in order:
            other = order[head]
            if other.number == step.number:
                raise ConfigError(f"'${{{ref}}}' refers to this step itself",
                                  fix="refer to an earlier step's key or to a top-level key")
            if other.number > step.number:
                cycle = any(m.group(1).split(".")[0] == step.name for m in _REF.finditer(json.dumps(other.settings, default=str)))
                raise ConfigError(f"'${{{ref}}}' refers to step '{head}', which runs later (step {other.number})"
                                  + (f"; a cycle: '{head}' also refers to '{step.name}'" if cycle else ""),
                                  fix=f"a step can use only earlier steps' keys: move '{head}' before "
                                      f"'{step.name}'" + (" and remove one of the two references" if cycle else ""))
            if not rest:
                raise ConfigError(f"'${{{ref}}}' names a step but no key",
                                  fix=f"write '${{{head}.output_dir}}' or another key of step '{head}'")
            if rest not in self.keys.get(head, ()):
                if head not in self.keys:
                    raise _Unresolved
                hint = did_you_mean(rest, self.keys[head])
                raise ConfigError(f"'${{{ref}}}': step '{head}' ({other.module}) has no key '{rest}'"
                                  f"{'; ' + hint if hint else ''}",
                                  fix=f"use one of that module's keys (matchplant {other.module} --write-config "
                                      "FILE lists them)")
            if head not in self.values:
                raise _Unresolved
            if self.values[head][rest] is None:
                raise ConfigError(f"'${{{ref}}}' is not set (null) in step '{head}'",
                                  fix=f"set '{rest}' in step '{head}', or refer to another key")
            return self._plain(ref, self.values[head][rest]), True
        names = [*self.top, *(s.name for s in self.steps), *(f"{s.name}.output_dir" for s in self.steps)]
        hint = did_you_mean(ref, names)
        raise ConfigError(f"'${{{ref}}}' refers to nothing known{'; ' + hint if hint else ''}",
                          fix=f"top-level keys: {', '.join(sorted(self.top))}; earlier steps' keys as "
                              "${step.key}")

    @staticmethod
    def _plain(ref: str, value: Any) -> Any:
        if value is None:
            raise ConfigError(f"'${{{ref}}}' is empty (null)", fix=f"give '{ref}' a value")
        if isinstance(value, (dict, list, tuple)) or is_dataclass(value):
            raise ConfigError(f"'${{{ref}}}' is a list or section, not a single value",
                              fix="refer to a single value (a path, a number, a name)")
        return value

    def substitute(self, value: Any, step: Step, key: str) -> tuple[Any, bool]:
        """``value`` with its references replaced; True when one of them comes from an earlier step."""
        if isinstance(value, str):
            from_step = False
            whole = _REF.fullmatch(value.strip())
            if whole:  # "${x}" alone keeps the value's type (a number stays a number)
                return self.lookup(whole.group(1), step)

            def repl(m: re.Match) -> str:
                nonlocal from_step
                v, s = self.lookup(m.group(1), step)
                from_step = from_step or s
                return str(v)

            text = _REF.sub(repl, value)
            if "${" in _REF.sub("", value):
                raise ConfigError(f"'{key}: {value}' has a malformed reference",
                                  fix="write references as ${name} or ${step.key} (letters, digits, _ - .)")
            return text, from_step
        if isinstance(value, (list, tuple)):
            pairs = [self.substitute(v, step, key) for v in value]
            return [v for v, _ in pairs], any(s for _, s in pairs)
        if isinstance(value, dict):
            pairs = {k: self.substitute(v, step, f"{key}.{k}") for k, v in value.items()}
            return {k: v for k, (v, _) in pairs.items()}, any(s for _, s in pairs.values())
        return value, False


def _flatten(cfg: Any, prefix: str, d: dict) -> list[tuple[str, Any]]:
    """Dotted keys of nested settings, descending only into the config's sections (a dict-valued key stays whole)."""
    out = []
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        sub = getattr(cfg, str(k), None) if cfg is not None and hasattr(cfg, "__dataclass_fields__") else None
        if isinstance(v, dict) and is_dataclass(sub):
            out += _flatten(sub, key, v)
        else:
            out.append((key, v))
    return out


def build_step_config(step: Step, spec: StepSpec, scope: Scope, base: Path) -> tuple[Any, set[str]]:
    """The step's config (file, then settings with references resolved) and its keys set from earlier steps.

    Every key is tried: the problems of all of them are raised together (:class:`StepProblems`)."""
    cfg = load_config(spec.config, step.config_file, check_paths=False, strict=False)
    settings = dict(step.settings)
    if spec.output_key and spec.output_key not in settings:
        settings[spec.output_key] = str(Path(scope.top["output_dir"]) / step.name)
    pending: set[str] = set()
    errors: list[MatchPlantError] = []
    unresolved = False
    # pipeline values are relative to the pipeline file, like any YAML config
    for key, raw in _flatten(cfg, "", settings):
        try:
            value, from_step = scope.substitute(raw, step, key)
            if from_step:
                pending.add(key)
            set_value(cfg, key, value, source=f"step '{step.name}'", base=base)
        except _Unresolved:
            unresolved = True
        except MatchPlantError as exc:
            errors.append(exc)
    if errors:
        raise StepProblems(errors)
    if unresolved:
        raise _Unresolved
    return cfg, pending


class StepProblems(Exception):
    """The problems of several keys of one step."""

    def __init__(self, errors: list[MatchPlantError]):
        super().__init__(str(errors[0]))
        self.errors = errors


# --------------------------------------------------------------------------------------------------
# checking every step before running any


def _is_pending(key: str, pending: set[str]) -> bool:
    return key.split("[")[0] in pending


def _pending_paths(cfg: Any, pending: set[str]) -> list[Path]:
    values = flat_values(cfg)
    out = []
    for key in pending:
        v = values.get(key)
        for item in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(item, (str, Path)) and str(item):
                out.append(Path(item))
    return out


def _within(p: Path, roots: list[Path]) -> bool:
    p = Path(p).resolve()
    return any(p == r.resolve() or r.resolve() in p.parents for r in roots)


def check_step(planned: Planned, earlier_outputs: dict[str, Path], source: str) -> None:
    """Ranges, choices and the class's own checks; input paths not made by earlier steps; outputs."""
    cfg, pending = planned.cfg, planned.pending
    try:
        validate(cfg, source=source, check_paths=False)
    except MatchPlantError as exc:
        # a class check about a file that an earlier step will write waits until this step runs
        if exc.path is None or not _within(exc.path, _pending_paths(cfg, pending)):
            raise
    for key, p, kind in inputs_and_outputs(cfg)[0]:
        if _is_pending(key, pending):
            continue
        try:
            check_path(p, kind, key=key, source=source)
        except ConfigError as exc:
            maker = next((name for name, out in earlier_outputs.items() if _within(p, [out])), None)
            if maker is None:
                raise
            rest = Path(p).resolve().relative_to(earlier_outputs[maker].resolve()).as_posix()
            raise ConfigError(exc.problem, path=p, fix=f"if step '{maker}' writes it, refer to it as "
                                                       f"'${{{maker}.output_dir}}/{rest}' so that it is checked "
                                                       "after that step has run") from exc
    check_outputs_are_not_inputs(cfg, source=source)
    check_outputs_writable(cfg)


def plan_pipeline(path: Path, top: dict, steps: list[Step]) -> list[Planned]:
    """Build and check every step's config; raise one error listing every problem (no step has run)."""
    problems = Problems(path)
    base = path.resolve().parent
    specs: dict[str, StepSpec] = {}
    for step in steps:
        try:
            spec = resolve_step(step.module)
            if spec.name == "run":
                raise ConfigError("a pipeline step cannot run a pipeline", fix="list the pipeline's steps here")
            specs[step.name] = spec
        except MatchPlantError as exc:
            problems.add(step.label, ConfigError(exc.problem, path=path, fix=exc.fix or (
                f"set 'module' to one of: {', '.join(n for n in STEPS if n != 'run')}")))
    scalars = {k: v for k, v in top.items()}
    scope = Scope(scalars, steps, {n: set(flat_values(s.config())) for n, s in specs.items()})
    planned: list[Planned] = []
    earlier_outputs: dict[str, Path] = {}
    for step in steps:
        if step.name not in specs:
            continue
        spec = specs[step.name]
        try:
            cfg, pending = build_step_config(step, spec, scope, base)
            p = Planned(step, spec, cfg, pending)
            check_step(p, earlier_outputs, f"step '{step.name}'")
        except _Unresolved:
            continue
        except StepProblems as exc:
            for e in exc.errors:
                problems.add(step.label, e)
            continue
        except MatchPlantError as exc:
            problems.add(step.label, exc)
            continue
        scope.values[step.name] = flat_values(cfg)
        out = getattr(cfg, spec.output_key, None) if spec.output_key else None
        if out is not None:
            earlier_outputs[step.name] = Path(out)
        planned.append(p)
    problems.raise_if_any()
    _check_across_steps(planned, problems)
    problems.raise_if_any()
    return planned


def _check_across_steps(planned: list[Planned], problems: Problems) -> None:
    """No step writes over, into or around an input that another step reads (other than earlier outputs)."""
    outputs = []
    for p in planned:
        exempt = set(getattr(type(p.cfg), "writes_into_inputs", ()))
        outputs += [(p, k, path) for k, path in inputs_and_outputs(p.cfg)[1] if k not in exempt]
    for reader in planned:
        made_before = [path for w, _, path in outputs if w.step.number < reader.step.number]
        inputs = [(f"{reader.step.name}.{k}", path, kind) for k, path, kind in inputs_and_outputs(reader.cfg)[0]
                  if kind in INPUT_KINDS and not _is_pending(k, reader.pending) and not _within(path, made_before)]
        for writer, key, path in outputs:
            if writer is reader:
                continue  # checked with the step itself
            inside_ok = [f"{reader.step.name}.{k}" for k in getattr(type(reader.cfg), "outputs_inside_inputs", ())]
            try:
                check_no_overlap([(f"{writer.step.name}.{key}", path)], inputs, inside_ok=inside_ok,
                                 source=f"steps '{writer.step.name}' and '{reader.step.name}'")
            except ConfigError as exc:
                problems.add(writer.step.label, exc)
                return


# --------------------------------------------------------------------------------------------------
# running


def _fingerprint(cfg: Any) -> str:
    """The settings plus size and modification time of every existing input path they name."""
    h = hashlib.sha256(json.dumps(to_dict(cfg), sort_keys=True, default=str).encode())

    def paths(obj: Any):
        if is_dataclass(obj):
            for f in fields(obj):
                if f.metadata.get("path") == "out":
                    continue
                yield from paths(getattr(obj, f.name))
        elif isinstance(obj, Path):
            yield obj
        elif isinstance(obj, (list, tuple)):
            for v in obj:
                yield from paths(v)

    for p in paths(cfg):
        if p.is_file():
            st = p.stat()
            h.update(f"{p}:{st.st_size}:{st.st_mtime_ns}".encode())
        elif p.is_dir():
            for q in sorted(p.rglob("*")):
                if q.is_file():
                    st = q.stat()
                    h.update(f"{q}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()


def _check_names(cfg: PipelineConfig, steps: list[Step], path: Path) -> None:
    names = [s.name for s in steps]
    for key, label in ((cfg.from_step, "from_step"), *((n, "only") for n in cfg.only)):
        if key and key not in names:
            hint = did_you_mean(key, names)
            raise ConfigError(f"{label}: no step named '{key}'{'; ' + hint if hint else ''}", path=path,
                              fix=f"steps are: {', '.join(names)}")


def run_pipeline(cfg: PipelineConfig) -> dict[str, str]:
    """Check every step, then run them; returns ``{step: "ran" | "up to date" | "skipped"}``."""
    path = Path(cfg.pipeline)
    top, steps = read_pipeline(path)
    _check_names(cfg, steps, path)
    planned = plan_pipeline(path, top, steps)
    state_dir = Path(top["output_dir"]) / ".pipeline"
    forced = False
    results: dict[str, str] = {}
    for p in planned:
        step, spec, step_cfg = p.step, p.spec, p.cfg
        forced = forced or (cfg.from_step == step.name) or cfg.force
        if cfg.only and step.name not in cfg.only:
            results[step.name] = "skipped"
            continue
        try:  # now the inputs from earlier steps exist: check them too
            validate(step_cfg, source=f"step '{step.name}' of {path.name}")
        except MatchPlantError as exc:
            raise type(exc)(f"step '{step.name}' ({step.module}): {exc.problem}", path=exc.path, fix=exc.fix) from exc
        stamp = state_dir / f"{step.name}.json"
        fp = _fingerprint(step_cfg)
        if not forced and stamp.is_file() and json.loads(stamp.read_text()).get("fingerprint") == fp:
            log.info("[%s] up to date, skipped", step.name)
            results[step.name] = "up to date"
            continue
        log.info("[%s] running %s ...", step.name, step.module)
        t0 = time.time()
        out = getattr(step_cfg, spec.output_key, None) if spec.output_key else None
        if out is not None:
            Path(out).mkdir(parents=True, exist_ok=True)
        try:
            spec.run(step_cfg)
        except MatchPlantError as exc:
            raise type(exc)(f"step '{step.name}' ({step.module}) failed: {exc.problem}", path=exc.path,
                            fix=(exc.fix or "") + f"; then re-run: matchplant run {path} (finished steps are skipped)"
                            ) from exc
        except Exception as exc:
            raise MatchPlantError(f"step '{step.name}' ({step.module}) failed: {type(exc).__name__}: {exc}",
                                  fix=f"see the log; earlier steps' outputs are kept; re-run with --debug "
                                      f"for the traceback, or with --set from_step={step.name}") from exc
        # a step that finished after a later input changed must not count as up to date: fingerprint again
        write_json(stamp, {"fingerprint": _fingerprint(step_cfg), "module": step.module,
                           "seconds": round(time.time() - t0, 2), "finished": time.strftime("%Y-%m-%d %H:%M:%S")})
        log.info("[%s] done in %.1f s", step.name, time.time() - t0)
        results[step.name] = "ran"  # later steps see its new files: their fingerprints change by mtime
    return results
