"""Every step checked before any runs: its module and keys, values, references, inputs and outputs, and the
outputs of one step against the inputs of another; all problems reported together."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from matchplant.core.runtime.config import validate
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.guard import (
    INPUT_KINDS,
    check_no_overlap,
    check_outputs_are_not_inputs,
    check_outputs_writable,
    inputs_and_outputs,
)
from matchplant.core.runtime.validate import check_path
from matchplant.pipeline.read import Problems, Step
from matchplant.pipeline.scope import Scope, StepProblems, Unresolved, build_step_config, flat_values
from matchplant.steps import STEPS, StepSpec, resolve_step


@dataclass
class Planned:
    """A step with its checked config; ``pending`` keys take their value from an earlier step's outputs."""

    step: Step
    spec: StepSpec
    cfg: Any
    pending: set[str] = field(default_factory=set)


def _is_pending(key: str, pending: set[str]) -> bool:
    return key.split("[")[0] in pending


def _pending_paths(cfg: Any, pending: set[str]) -> list[Path]:
    values = flat_values(cfg)
    out = []
    for key in pending:
        v = values.get(key)
        for item in v if isinstance(v, (list, tuple)) else [v]:
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
            raise ConfigError(
                exc.problem,
                path=p,
                fix=f"if step '{maker}' writes it, refer to it as "
                f"'${{{maker}.output_dir}}/{rest}' so that it is checked "
                "after that step has run",
            ) from exc
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
            problems.add(
                step.label,
                ConfigError(
                    exc.problem,
                    path=path,
                    fix=exc.fix or (f"set 'module' to one of: {', '.join(n for n in STEPS if n != 'run')}"),
                ),
            )
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
        except Unresolved:
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
        inputs = [
            (f"{reader.step.name}.{k}", path, kind)
            for k, path, kind in inputs_and_outputs(reader.cfg)[0]
            if kind in INPUT_KINDS and not _is_pending(k, reader.pending) and not _within(path, made_before)
        ]
        for writer, key, path in outputs:
            if writer is reader:
                continue  # checked with the step itself
            inside_ok = [f"{reader.step.name}.{k}" for k in getattr(type(reader.cfg), "outputs_inside_inputs", ())]
            try:
                check_no_overlap(
                    [(f"{writer.step.name}.{key}", path)],
                    inputs,
                    inside_ok=inside_ok,
                    source=f"steps '{writer.step.name}' and '{reader.step.name}'",
                )
            except ConfigError as exc:
                problems.add(writer.step.label, exc)
                return
