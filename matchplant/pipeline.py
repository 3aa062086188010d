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

A step is skipped when it finished before with the same settings and its inputs have not changed since
(a fingerprint in ``<output_dir>/.pipeline/<step>.json``); ``--from STEP`` re-runs from that step on. A
failure names the step and stops; the outputs of earlier steps stay as they were.
"""

from __future__ import annotations

import hashlib
import json
import re
import time
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

from matchplant.core.config import load_config, param, read_yaml_mapping, set_value, to_dict, validate
from matchplant.core.errors import ConfigError, MatchPlantError
from matchplant.core.io import write_json
from matchplant.core.log import get_logger
from matchplant.steps import resolve_step

log = get_logger("pipeline")
_REF = re.compile(r"\$\{([A-Za-z0-9_.\-]+)\}")


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


def read_pipeline(path: Path) -> tuple[dict, list[Step]]:
    data = read_yaml_mapping(path)
    base = path.resolve().parent
    steps_data = data.get("steps")
    if not isinstance(steps_data, list) or not steps_data:
        raise ConfigError("the pipeline has no 'steps' list", path=path,
                          fix="add 'steps:' with one '- module: NAME' entry per step (see the README)")
    top = {k: v for k, v in data.items() if k != "steps"}
    top.setdefault("output_dir", "pipeline_output")
    top["output_dir"] = str((base / str(top["output_dir"])).resolve())
    steps: list[Step] = []
    seen: set[str] = set()
    for i, sd in enumerate(steps_data):
        if not isinstance(sd, dict) or "module" not in sd:
            raise ConfigError(f"step {i + 1} has no 'module'", path=path, fix="write '- module: NAME' for each step")
        unknown = set(sd) - {"name", "module", "config", "config_file"}
        if unknown:
            raise ConfigError(f"step {i + 1} has unknown key(s) {sorted(unknown)}", path=path,
                              fix="a step takes name, module, config and config_file")
        name = str(sd.get("name") or sd["module"])
        if name in seen:
            raise ConfigError(f"two steps are named '{name}'", path=path, fix="give each step a unique 'name'")
        seen.add(name)
        cfile = sd.get("config_file")
        steps.append(Step(name=name, module=str(sd["module"]),
                          config_file=(base / cfile) if cfile else None, settings=dict(sd.get("config") or {})))
    return top, steps


def _substitute(value: Any, scope: dict, where: str) -> Any:
    if isinstance(value, str):
        def repl(m: re.Match) -> str:
            key = m.group(1)
            if key not in scope:
                raise ConfigError(f"{where}: '${{{key}}}' refers to nothing known",
                                  fix=f"known names: {', '.join(sorted(scope)) or 'none'}")
            return str(scope[key])
        return _REF.sub(repl, value)
    if isinstance(value, list):
        return [_substitute(v, scope, where) for v in value]
    if isinstance(value, dict):
        return {k: _substitute(v, scope, where) for k, v in value.items()}
    return value


def _flatten(prefix: str, d: dict) -> list[tuple[str, Any]]:
    out = []
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out += _flatten(key, v)
        else:
            out.append((key, v))
    return out


def build_step_config(step: Step, spec, scope: dict, base: Path) -> Any:
    cfg = load_config(spec.config, step.config_file, check_paths=False, strict=False)
    settings = _substitute(step.settings, scope, f"step '{step.name}'")
    if spec.output_key and spec.output_key not in settings:
        settings[spec.output_key] = str(Path(scope["output_dir"]) / step.name)
    # pipeline values are relative to the pipeline file, like any YAML config
    for key, value in _flatten("", settings):
        set_value(cfg, key, value, source=f"step '{step.name}'", base=base)
    return cfg


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


def run_pipeline(cfg: PipelineConfig) -> dict[str, str]:
    """Run the steps; returns ``{step: "ran" | "up to date" | "skipped"}``."""
    path = Path(cfg.pipeline)
    top, steps = read_pipeline(path)
    names = [s.name for s in steps]
    for key, label in ((cfg.from_step, "from_step"), *((n, "only") for n in cfg.only)):
        if key and key not in names:
            raise ConfigError(f"{label}: no step named '{key}'", path=path, fix=f"steps are: {', '.join(names)}")
    out_root = Path(top["output_dir"])
    state_dir = out_root / ".pipeline"
    scope: dict[str, Any] = {k: v for k, v in top.items() if not isinstance(v, (dict, list))}
    forced = False
    results: dict[str, str] = {}
    base = path.resolve().parent
    for step in steps:
        forced = forced or (cfg.from_step == step.name) or cfg.force
        spec = resolve_step(step.module)
        step_cfg = build_step_config(step, spec, scope, base)
        try:
            validate(step_cfg, source=f"step '{step.name}' of {path.name}")
        except MatchPlantError as exc:
            raise type(exc)(f"step '{step.name}' ({step.module}): {exc.problem}", path=exc.path, fix=exc.fix) from exc
        out = getattr(step_cfg, spec.output_key, None) if spec.output_key else None
        for f in fields(step_cfg):
            v = getattr(step_cfg, f.name)
            if not is_dataclass(v) and not isinstance(v, (list, dict)):
                scope[f"{step.name}.{f.name}"] = v
        if cfg.only and step.name not in cfg.only:
            results[step.name] = "skipped"
            continue
        stamp = state_dir / f"{step.name}.json"
        fp = _fingerprint(step_cfg)
        if not forced and stamp.is_file() and json.loads(stamp.read_text()).get("fingerprint") == fp:
            log.info("[%s] up to date, skipped", step.name)
            results[step.name] = "up to date"
            continue
        log.info("[%s] running %s ...", step.name, step.module)
        t0 = time.time()
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
