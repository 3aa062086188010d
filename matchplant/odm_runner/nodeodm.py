"""The ``nodeodm`` backend: a NodeODM server (or ClusterODM in front of several) through pyodm.

Upload with a progress bar, processing progress, download into the project. The task id is saved in
``<output>/nodeodm_task.json`` so that an interrupted run resumes the same task instead of starting over
(uploading a flight and processing it take hours).
"""

from __future__ import annotations

import datetime as _dt
import shutil
import time
from pathlib import Path

from pyodm import Node
from pyodm.exceptions import NodeConnectionError, NodeResponseError, OdmError
from pyodm.types import TaskStatus

from matchplant.core.runtime.errors import ConfigError, DependencyError, MatchPlantError
from matchplant.core.runtime.io import place, read_json, write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.odm_runner.config import NodeODMSettings, ODMRunError, OdmRunnerConfig
from matchplant.odm_runner.inputs import find_gcp_file, odm_images, odm_option_dict

log = get_logger("odm_runner")

# what NodeODM must put in all.zip (its default leaves out opensfm/, which modules 3 and 8 need)
NODEODM_OUTPUTS = [
    "opensfm/reconstruction.json",
    "opensfm/reconstruction.topocentric.json",
    "opensfm/undistorted/reconstruction.json",
    "opensfm/undistorted/images",
    "odm_dem",
    "odm_orthophoto",
    "odm_georeferencing",
    "odm_report",
    "images.json",
]


def _node(settings: NodeODMSettings):
    try:
        node = Node.from_url(settings.url, timeout=settings.timeout)
    except Exception as exc:  # noqa: BLE001 - pyodm raises plain exceptions for bad URLs
        raise ConfigError(
            f"config key 'nodeodm.url' is not a valid address: {settings.url!r} ({exc})",
            fix="write it as http://HOST:PORT, e.g. http://localhost:3000",
        ) from exc
    node.token = settings.token or ""
    return node


def _node_error(exc: Exception, settings: NodeODMSettings) -> MatchPlantError:
    if isinstance(exc, NodeConnectionError):
        return DependencyError(
            f"cannot reach the NodeODM server at {settings.url} ({exc})",
            fix="start it (docker run -p 3000:3000 opendronemap/nodeodm) or correct nodeodm.url",
        )
    if isinstance(exc, NodeResponseError):
        return ODMRunError(
            f"the NodeODM server refused the request: {exc}", fix="check nodeodm.token and the ODM options"
        )
    return ODMRunError(f"NodeODM error: {type(exc).__name__}: {exc}", fix="check the server's log")


def percent_bar(desc: str):
    """A 0-100 % progress bar and the callback pyodm calls with the percentage done."""
    bar = progress(range(100), desc=desc, total=100, unit="%")
    done = [0]

    def update(pct: float) -> None:
        step = int(pct) - done[0]
        if step > 0:
            bar.update(step)
            done[0] += step

    return bar, update


def run_nodeodm(cfg: OdmRunnerConfig) -> dict:
    """Upload, process and download through NodeODM; resume the task saved in the state file."""
    settings = cfg.nodeodm
    node = _node(settings)
    state_path = Path(cfg.output_dir) / "nodeodm_task.json"
    options = odm_option_dict(cfg.odm)
    start = time.time()
    try:
        info = node.info()
        log.info(
            "NodeODM %s at %s (engine %s %s, %s tasks queued)",
            info.version,
            settings.url,
            info.engine,
            info.engine_version,
            info.task_queue_count,
        )
        task = None
        if settings.resume and state_path.is_file():
            state = read_json(state_path)
            try:
                task = node.get_task(state["uuid"])
                status = task.info().status
                log.info("resuming NodeODM task %s (%s)", task.uuid, status.name.lower())
                if status in (TaskStatus.FAILED, TaskStatus.CANCELED):
                    log.warning("the saved task %s; starting a new one", status.name.lower())
                    task = None
            except (NodeResponseError, KeyError):
                log.warning("the saved task is unknown to this server; starting a new one")
                task = None
        if task is None:
            images = odm_images(cfg)
            gcp = find_gcp_file(cfg)
            files = [str(p) for p in images] + ([str(gcp)] if gcp else [])
            bar, uploaded = percent_bar("upload")
            task = node.create_task(
                files,
                options,
                name=Path(cfg.project_dir).name,
                progress_callback=uploaded,
                outputs=NODEODM_OUTPUTS,
                parallel_uploads=settings.parallel_uploads,
            )
            bar.close()
            write_json(
                state_path,
                {
                    "uuid": task.uuid,
                    "url": settings.url,
                    "options": options,
                    "images": len(images),
                    "gcp_file": str(gcp) if gcp else None,
                    "created": _dt.datetime.now().isoformat(timespec="seconds"),
                },
            )
            log.info(
                "NodeODM task %s created with %d images; its id is saved in %s", task.uuid, len(images), state_path
            )
        _wait(task, settings.poll_seconds)
        log.info("downloading the results into %s", cfg.project_dir)
        _download(task, Path(cfg.project_dir))
    except KeyboardInterrupt:
        log.warning("interrupted: the task keeps running on the server; run again to resume it")
        raise
    except MatchPlantError:
        raise
    except OdmError as exc:
        raise _node_error(exc, settings) from exc
    except OSError as exc:
        raise _node_error(exc, settings) from exc
    return {
        "backend": "nodeodm",
        "url": settings.url,
        "task": task.uuid,
        "options": options,
        "seconds": round(time.time() - start, 1),
        "state_file": str(state_path),
    }


def _wait(task, poll_seconds: float) -> None:
    bar = progress(range(100), desc="ODM processing", total=100, unit="%")
    shown = 0
    while True:
        info = task.info()
        pct = int(max(0.0, min(100.0, float(info.progress or 0))))
        if pct > shown:
            bar.update(pct - shown)
            shown = pct
        if info.status == TaskStatus.COMPLETED:
            break
        if info.status in (TaskStatus.FAILED, TaskStatus.CANCELED):
            bar.close()
            try:
                tail = "\n".join("    " + ln for ln in (task.output(-15) or []))
            except Exception:  # noqa: BLE001 - the log is a courtesy; the failure is what matters
                tail = ""
            raise ODMRunError(
                f"the NodeODM task {task.uuid} {info.status.name.lower()}: {info.last_error}\n{tail}",
                fix="read the task's log in NodeODM/WebODM; fix the cause and run again (a failed task is not resumed)",
            )
        time.sleep(poll_seconds)
    bar.close()


def _download(task, project: Path) -> None:
    """Download all.zip next to the project, then move its folders into the project (replacing old ones)."""
    tmp = project / ".nodeodm_download"
    if tmp.exists():
        shutil.rmtree(tmp)
    bar, cb = percent_bar("download")
    try:
        task.download_assets(str(tmp), progress_callback=cb)
        bar.close()
        for item in sorted(tmp.rglob("*")):
            if item.is_file():
                target = project / item.relative_to(tmp)
                target.parent.mkdir(parents=True, exist_ok=True)
                place(item, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
