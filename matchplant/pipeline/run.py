"""Running the checked steps in order: a step finished with the same settings and unchanged inputs is skipped
(its fingerprint), a failure names the step and stops."""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

from matchplant.core.runtime.config import param, to_dict, validate
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.readers import read_record
from matchplant.core.runtime.validate import did_you_mean
from matchplant.pipeline.plan import plan_pipeline
from matchplant.pipeline.read import Step, read_pipeline

log = get_logger("pipeline")


@dataclass
class PipelineConfig:
    """Run several MatchPlant modules in order from one file (see matchplant/pipeline/)."""

    pipeline: Path | None = param(None, "the pipeline YAML file (steps and their settings)", path="file", required=True)
    output_dir: Path | None = param(None, "where the run log goes (default: the pipeline's output_dir)")
    from_step: str = param("", "re-run from this step on, even if earlier results are up to date")
    only: list[str] = param([], "run only these steps (names); empty = all")
    force: bool = param(False, "re-run every step, even when up to date")

    def check(self) -> None:
        """Take ``output_dir`` from the pipeline file when it is not set."""
        if self.output_dir is None and self.pipeline is not None and Path(self.pipeline).is_file():
            self.output_dir = Path(read_pipeline(Path(self.pipeline))[0]["output_dir"])


# --------------------------------------------------------------------------------------------------
# running


def _portable(value: Any, base: Path) -> Any:
    """Plain settings with every path under ``base`` relative to it: a season folder that is moved or renamed
    keeps its fingerprints (finished steps stay finished, an interrupted training continues)."""
    if isinstance(value, dict):
        return {k: _portable(v, base) for k, v in value.items()}
    if isinstance(value, list):
        return [_portable(v, base) for v in value]
    if isinstance(value, str) and os.path.isabs(value):
        return _relative(Path(value), base)
    return value


def _relative(path: Path, base: Path) -> str:
    """``path`` relative to ``base`` (``..`` steps allowed), as text with '/'; absolute on another drive."""
    try:
        return Path(os.path.relpath(path, base)).as_posix()
    except ValueError:  # another drive (Windows): stays absolute
        return str(path)


def _fingerprint(cfg: Any, base: Path) -> str:
    """The settings plus size and modification time of every existing input path they name, paths relative to
    ``base`` (the pipeline file's folder: the season)."""
    h = hashlib.sha256(json.dumps(_portable(to_dict(cfg), base), sort_keys=True, default=str).encode())

    def paths(obj: Any):
        if is_dataclass(obj):
            for f in fields(obj):
                if f.metadata.get("path") in ("out", "out_file"):
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
            h.update(f"{_relative(p, base)}:{st.st_size}:{st.st_mtime_ns}".encode())
        elif p.is_dir():
            for q in sorted(p.rglob("*")):
                if q.is_file():
                    st = q.stat()
                    h.update(f"{_relative(q, base)}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()


def _check_names(cfg: PipelineConfig, steps: list[Step], path: Path) -> None:
    names = [s.name for s in steps]
    for key, label in ((cfg.from_step, "from_step"), *((n, "only") for n in cfg.only)):
        if key and key not in names:
            hint = did_you_mean(key, names)
            raise ConfigError(
                f"{label}: no step named '{key}'{'; ' + hint if hint else ''}",
                path=path,
                fix=f"steps are: {', '.join(names)}",
            )


def _record_fix(path: Path, step: Step) -> str:
    return (
        f"delete {path.name} (in {path.parent}); the step then runs again from its start (or re-run with "
        f"--set force=true, or --from {step.name})"
    )


def continue_interrupted(step: Step, spec, step_cfg, started: Path, fp: str) -> bool:
    """Set the step's resume key when its previous run stopped unfinished (Ctrl-C, a crash, a time limit) with
    these settings and inputs, and left a checkpoint newer than its start: re-running the pipeline then
    continues that run instead of replacing it. A key the user set is left as it is."""
    if not spec.resume_key or getattr(step_cfg, spec.resume_key) or not started.is_file():
        return False
    record = read_record(started, what="the record of the step's interrupted run", fix=_record_fix(started, step))
    checkpoint = spec.resume_file(step_cfg)
    if record.get("fingerprint") != fp:
        log.info("[%s] its interrupted run had other settings or inputs: a new run", step.name)
        return False
    if not checkpoint.is_file() or checkpoint.stat().st_mtime < record.get("started", 0):
        return False  # stopped before its first checkpoint: nothing of it to continue
    setattr(step_cfg, spec.resume_key, True)
    log.info("[%s] continuing its interrupted run (same settings) from %s", step.name, checkpoint)
    return True


def run_pipeline(cfg: PipelineConfig) -> dict[str, str]:
    """Check every step, then run them; returns ``{step: "ran" | "up to date" | "skipped"}``."""
    path = Path(cfg.pipeline)
    season = path.resolve().parent
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
        fp = _fingerprint(step_cfg, season)
        finished = read_record(stamp, what="the record of the step's finished run", fix=_record_fix(stamp, step))
        if not forced and finished is not None and finished.get("fingerprint") == fp:
            log.info("[%s] up to date, skipped", step.name)
            results[step.name] = "up to date"
            continue
        t0 = time.time()
        out = getattr(step_cfg, spec.output_key, None) if spec.output_key else None
        if out is not None:
            Path(out).mkdir(parents=True, exist_ok=True)
        started = state_dir / f"{step.name}.started.json"
        resumed = not forced and continue_interrupted(step, spec, step_cfg, started, fp)
        if not resumed:
            log.info("[%s] running %s ...", step.name, step.module)
        write_json(started, {"fingerprint": fp, "started": t0})  # removed when it finishes
        stamp.unlink(missing_ok=True)  # an interrupted re-run (--from) is not the earlier finished one
        try:
            spec.run(step_cfg)
        except MatchPlantError as exc:
            raise type(exc)(
                f"step '{step.name}' ({step.module}) failed: {exc.problem}",
                path=exc.path,
                fix=(exc.fix or "") + f"; then re-run: matchplant run {path} (finished steps are skipped)",
            ) from exc
        except Exception as exc:
            raise MatchPlantError(
                f"step '{step.name}' ({step.module}) failed: {type(exc).__name__}: {exc}",
                fix=f"see the log; earlier steps' outputs are kept; re-run with --debug "
                f"for the traceback, or with --set from_step={step.name}",
            ) from exc
        if resumed:  # the stamp holds the step's own settings: the next run finds it up to date
            setattr(step_cfg, spec.resume_key, False)
        # a step that finished after a later input changed must not count as up to date: fingerprint again
        write_json(
            stamp,
            {
                "fingerprint": _fingerprint(step_cfg, season),
                "module": step.module,
                "seconds": round(time.time() - t0, 2),
                "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
            },
        )
        started.unlink(missing_ok=True)
        log.info("[%s] done in %.1f s", step.name, time.time() - t0)
        results[step.name] = "ran"  # later steps see its new files: their fingerprints change by mtime
    return results
