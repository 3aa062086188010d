"""References between steps: ``${step.key}`` and ``${key}`` resolved from the pipeline's own keys and the earlier
steps' settings; a step's config built from its file, its settings and those references."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from matchplant.core.runtime.config import load_config, set_value
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.validate import did_you_mean
from matchplant.pipeline.read import Step
from matchplant.steps import StepSpec

_REF = re.compile(r"\$\{([A-Za-z0-9_.\-]+)\}")


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


class Unresolved(Exception):
    """A reference to an earlier step whose own config failed (its problem is already reported)."""


@dataclass
class Scope:
    """What ``${...}`` references can name: the file's top-level keys and each step's config keys and values."""

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
                raise ConfigError(
                    f"'${{{ref}}}' refers to this step itself",
                    fix="refer to an earlier step's key or to a top-level key",
                )
            if other.number > step.number:
                cycle = any(
                    m.group(1).split(".")[0] == step.name
                    for m in _REF.finditer(json.dumps(other.settings, default=str))
                )
                raise ConfigError(
                    f"'${{{ref}}}' refers to step '{head}', which runs later (step {other.number})"
                    + (f"; a cycle: '{head}' also refers to '{step.name}'" if cycle else ""),
                    fix=f"a step can use only earlier steps' keys: move '{head}' before "
                    f"'{step.name}'" + (" and remove one of the two references" if cycle else ""),
                )
            if not rest:
                raise ConfigError(
                    f"'${{{ref}}}' names a step but no key",
                    fix=f"write '${{{head}.output_dir}}' or another key of step '{head}'",
                )
            if rest not in self.keys.get(head, ()):
                if head not in self.keys:
                    raise Unresolved
                hint = did_you_mean(rest, self.keys[head])
                raise ConfigError(
                    f"'${{{ref}}}': step '{head}' ({other.module}) has no key '{rest}'{'; ' + hint if hint else ''}",
                    fix=f"use one of that module's keys (matchplant {other.module} --write-config FILE lists them)",
                )
            if head not in self.values:
                raise Unresolved
            if self.values[head][rest] is None:
                raise ConfigError(
                    f"'${{{ref}}}' is not set (null) in step '{head}'",
                    fix=f"set '{rest}' in step '{head}', or refer to another key",
                )
            return self._plain(ref, self.values[head][rest]), True
        names = [*self.top, *(s.name for s in self.steps), *(f"{s.name}.output_dir" for s in self.steps)]
        hint = did_you_mean(ref, names)
        raise ConfigError(
            f"'${{{ref}}}' refers to nothing known{'; ' + hint if hint else ''}",
            fix=f"top-level keys: {', '.join(sorted(self.top))}; earlier steps' keys as ${{step.key}}",
        )

    @staticmethod
    def _plain(ref: str, value: Any) -> Any:
        if value is None:
            raise ConfigError(f"'${{{ref}}}' is empty (null)", fix=f"give '{ref}' a value")
        if isinstance(value, (dict, list, tuple)) or is_dataclass(value):
            raise ConfigError(
                f"'${{{ref}}}' is a list or section, not a single value",
                fix="refer to a single value (a path, a number, a name)",
            )
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
                raise ConfigError(
                    f"'{key}: {value}' has a malformed reference",
                    fix="write references as ${name} or ${step.key} (letters, digits, _ - .)",
                )
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
        except Unresolved:
            unresolved = True
        except MatchPlantError as exc:
            errors.append(exc)
    if errors:
        raise StepProblems(errors)
    if unresolved:
        raise Unresolved
    return cfg, pending


class StepProblems(Exception):
    """The problems of several keys of one step."""

    def __init__(self, errors: list[MatchPlantError]):
        super().__init__(str(errors[0]))
        self.errors = errors
