"""Module 2: run OpenDroneMap on a project folder, then check that every output later modules need is there.

Two backends, one configuration:

* ``docker`` - the ``opendronemap/odm`` image on this computer. :func:`docker_command` builds the
  ``docker run`` argument list (a pure function: no TTY, the project mounted at ``/datasets/code``, files
  owned by the user on Linux and macOS, paths with spaces, Windows paths); :func:`run_docker` runs it with
  the log streamed to the console and to ``<output>/odm_docker.log`` and checks the exit code.
* ``nodeodm`` - a NodeODM server (or ClusterODM in front of several) through pyodm: upload with a progress
  bar, processing progress, download into the project. The task id is saved in
  ``<output>/nodeodm_task.json`` so an interrupted run resumes the same task instead of starting over.

After a run (or alone, with ``check_only``) :func:`check_outputs` verifies the files of DESIGN §2 with
:class:`~matchplant.core.odm.ODMProject`, names the ODM option that produces each missing one, and
:func:`write_manifest` records what was run and what came out in ``<output>/odm_manifest.json``.
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path, PurePath, PurePosixPath, PureWindowsPath
from typing import Any, Literal, Sequence

from matchplant.core.config import param, section
from matchplant.core.errors import ConfigError, DependencyError, InputError, MatchPlantError
from matchplant.core.io import read_json, write_json
from matchplant.core.log import get_logger
from matchplant.core.odm import OUTPUTS, ODMProject

log = get_logger("odm_runner")

CONTAINER_ROOT = "/datasets"           # ODM's --project-path inside the container
CONTAINER_PROJECT = "/datasets/code"   # the project folder as ODM sees it ("code" is ODM's default name)
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".png", ".dng")
# outputs modules 3, 8 and 9 read (DESIGN §2); the topocentric copy is optional
REQUIRED_OUTPUTS = ("reconstruction", "undistorted_reconstruction", "undistorted_images", "dsm", "dtm",
                    "orthophoto", "coords")
# options that would remove or skip an output later modules need
FORBIDDEN_OPTIONS = {
    "optimize-disk-space": "it deletes opensfm/undistorted, which modules 3 and 8 need",
    "skip-orthophoto": "modules 3 and 9 need odm_orthophoto/odm_orthophoto.tif",
    "project-path": "the runner sets it; set project_dir instead",
    "gcp": "set gcp_file instead",
}
# what NodeODM must put in all.zip (its default leaves out opensfm/, which modules 3 and 8 need)
NODEODM_OUTPUTS = ["opensfm/reconstruction.json", "opensfm/reconstruction.topocentric.json",
                   "opensfm/undistorted/reconstruction.json", "opensfm/undistorted/images",
                   "odm_dem", "odm_orthophoto", "odm_georeferencing", "odm_report", "images.json"]


class ODMRunError(MatchPlantError):
    """ODM itself failed (non-zero exit, failed task)."""


# --------------------------------------------------------------------------------------------------
# configuration


@dataclass
class ODMOptions:
    """OpenDroneMap options (the paper's defaults: DSM, DTM, 0.5 cm orthophoto, undistorted images kept)."""

    dsm: bool = param(True, "build odm_dem/dsm.tif (--dsm); modules 3 and 8 need it")
    dtm: bool = param(True, "build odm_dem/dtm.tif (--dtm); plant height in module 9 needs it")
    orthophoto_resolution: float = param(0.5, "orthophoto resolution in cm/pixel (--orthophoto-resolution); "
                                              "ODM never goes finer than the images' ground sampling distance",
                                         min=0.01)
    dem_resolution: float | None = param(None, "DSM/DTM resolution in cm/pixel (--dem-resolution); "
                                               "empty: ODM's default", min=0.01)
    extra: dict = param({}, "more ODM options as 'name: value' (true for a flag), e.g. "
                            "{feature-quality: high, pc-quality: medium}; see docs.opendronemap.org/arguments")


@dataclass
class DockerSettings:
    """Local Docker backend."""

    image: str = param("opendronemap/odm", "Docker image to run (opendronemap/odm:gpu with gpus: true)")
    command: str = param("docker", "the docker program (a name on PATH or a full path)")
    gpus: bool = param(False, "pass --gpus all (needs the NVIDIA container toolkit and the :gpu image)")
    run_as_user: bool = param(True, "on Linux/macOS run as your user id so the outputs belong to you")
    extra_args: list[str] = param([], "more 'docker run' arguments, e.g. ['--memory', '16g']")


@dataclass
class NodeODMSettings:
    """NodeODM (or ClusterODM) backend."""

    url: str = param("http://localhost:3000", "address of the NodeODM or ClusterODM server")
    token: str = param("", "access token, if the server requires one")
    poll_seconds: float = param(10.0, "seconds between progress checks", min=0.05)
    resume: bool = param(True, "resume the task saved in nodeodm_task.json instead of uploading again")
    parallel_uploads: int = param(4, "images uploaded at once", min=1, max=64)
    timeout: float = param(60.0, "seconds to wait for one server reply", min=1)


@dataclass
class ODMRunnerConfig:
    """Run OpenDroneMap (Docker or NodeODM) on a project folder and check its outputs."""

    project_dir: Path = param(None, "ODM project folder; the images go in its images/ subfolder",
                              path="dir", required=True)
    images_dir: Path | None = param(None, "folder of the images if not <project_dir>/images "
                                          "(mounted or uploaded as the project's images)", path="dir")
    gcp_file: Path | None = param(None, "gcp_list.txt to use; empty: gcp_list.txt in the images folder or "
                                        "the project folder when present", path="file")
    use_gcp: bool = param(True, "use the GCP file (false: georeference from the images' GPS only)")
    backend: Literal["docker", "nodeodm"] = param("docker", "where ODM runs",
                                                  choices=["docker", "nodeodm"])
    check_only: bool = param(False, "do not run ODM; only check an existing project and write the manifest")
    odm: ODMOptions = section(ODMOptions)
    docker: DockerSettings = section(DockerSettings)
    nodeodm: NodeODMSettings = section(NodeODMSettings)
    output_dir: Path | None = param(None, "where the manifest, logs and NodeODM state go; empty: project_dir",
                                    path="out")

    def check(self) -> None:
        if self.output_dir is None and self.project_dir is not None:
            self.output_dir = self.project_dir
        for name in self.odm.extra:
            key = str(name).lstrip("-")
            if key in FORBIDDEN_OPTIONS:
                raise ConfigError(f"config key 'odm.extra' must not set '{key}': {FORBIDDEN_OPTIONS[key]}",
                                  fix=f"remove '{key}' from odm.extra")


# --------------------------------------------------------------------------------------------------
# inputs


def images_folder(cfg: ODMRunnerConfig) -> Path:
    return Path(cfg.images_dir) if cfg.images_dir is not None else Path(cfg.project_dir) / "images"


def list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise InputError("the images folder does not exist", path=folder,
                         fix="put the drone images in <project_dir>/images, or set images_dir")
    images = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                    and not p.name.startswith("."))
    if len(images) < 2:
        raise InputError(f"the images folder holds {len(images)} image(s); ODM needs at least 2 overlapping images",
                         path=folder, fix="copy the flight's images (JPG/TIF) into this folder")
    return images


def find_gcp_file(cfg: ODMRunnerConfig) -> Path | None:
    """The GCP file to use: the configured one, else ``gcp_list.txt`` in the images or project folder."""
    if not cfg.use_gcp:
        return None
    if cfg.gcp_file is not None:
        return Path(cfg.gcp_file)
    for candidate in (images_folder(cfg) / "gcp_list.txt", Path(cfg.project_dir) / "gcp_list.txt"):
        if candidate.is_file():
            return candidate
    return None


def odm_arguments(options: ODMOptions) -> list[str]:
    """ODM command-line options (without the project and GCP arguments)."""
    args: list[str] = []
    if options.dsm:
        args.append("--dsm")
    if options.dtm:
        args.append("--dtm")
    args += ["--orthophoto-resolution", _num(options.orthophoto_resolution)]
    if options.dem_resolution is not None:
        args += ["--dem-resolution", _num(options.dem_resolution)]
    for name, value in options.extra.items():
        flag = "--" + str(name).lstrip("-")
        if value is True:
            args.append(flag)
        elif value is False or value is None:
            continue
        else:
            args += [flag, _num(value) if isinstance(value, float) else str(value)]
    return args


def odm_option_dict(options: ODMOptions) -> dict[str, Any]:
    """The same options as pyodm wants them: ``{'dsm': True, 'orthophoto-resolution': 0.5, ...}``."""
    out: dict[str, Any] = {}
    if options.dsm:
        out["dsm"] = True
    if options.dtm:
        out["dtm"] = True
    out["orthophoto-resolution"] = options.orthophoto_resolution
    if options.dem_resolution is not None:
        out["dem-resolution"] = options.dem_resolution
    for name, value in options.extra.items():
        if value is not None and value is not False:
            out[str(name).lstrip("-")] = value
    return out


def _num(v: float) -> str:
    return f"{v:g}"


# --------------------------------------------------------------------------------------------------
# Docker backend


def docker_command(cfg: ODMRunnerConfig, *, platform: str | None = None, uid: int | None = None,
                   gid: int | None = None, gcp_file: str | PurePath | None = None) -> list[str]:
    """The ``docker run`` argument list for this configuration (pure: no file or process is touched).

    ``platform`` is ``sys.platform`` by default (``win32`` formats Windows host paths); ``uid``/``gid``
    default to the current user's on Linux and macOS. ``gcp_file`` is the GCP file to pass (as found by
    :func:`find_gcp_file`). Every argument is one list item, so paths with spaces need no quoting.
    """
    platform = platform or sys.platform
    windows = platform.startswith("win")
    host = PureWindowsPath if windows else PurePosixPath

    def host_path(p: str | PurePath) -> str:
        text = str(host(str(p)))
        if not windows and ":" in text:
            raise ConfigError(f"Docker cannot mount a path containing ':': {text}",
                              fix="rename the folder without ':'")
        return text

    def inside(p: str | PurePath, root: str | PurePath) -> str | None:
        try:
            rel = host(str(p)).relative_to(host(str(root)))
        except ValueError:
            return None
        return str(PurePosixPath(CONTAINER_PROJECT, *rel.parts))

    project = cfg.project_dir
    argv = [cfg.docker.command, "run", "--rm", "-i"]  # -i without -t: works with no terminal (CI, cron, GUIs)
    if cfg.docker.run_as_user and not windows:
        if uid is None:
            uid, gid = os.getuid(), os.getgid()  # type: ignore[attr-defined]
        argv += ["--user", f"{uid}:{gid if gid is not None else uid}"]
    if cfg.docker.gpus:
        argv += ["--gpus", "all"]
    argv += ["-v", f"{host_path(project)}:{CONTAINER_PROJECT}"]
    if cfg.images_dir is not None and inside(cfg.images_dir, project) != f"{CONTAINER_PROJECT}/images":
        argv += ["-v", f"{host_path(cfg.images_dir)}:{CONTAINER_PROJECT}/images:ro"]
    gcp_arg: list[str] = []
    if gcp_file is not None:
        target = inside(gcp_file, project)
        if target is None:  # outside the project: mount the file itself
            target = f"{CONTAINER_ROOT}/gcp/{host(str(gcp_file)).name}"
            argv += ["-v", f"{host_path(gcp_file)}:{target}:ro"]
        gcp_arg = ["--gcp", target]
    argv += list(cfg.docker.extra_args)
    argv.append(cfg.docker.image)
    argv += ["--project-path", CONTAINER_ROOT, *gcp_arg, *odm_arguments(cfg.odm)]
    return argv


def check_docker(command: str = "docker") -> str:
    """Raise DependencyError unless Docker is installed and its engine answers; return the program path."""
    exe = shutil.which(command)
    if exe is None:
        raise DependencyError(f"Docker was not found ('{command}' is not on PATH)",
                              fix="install Docker Desktop (Windows, macOS) or Docker Engine (Linux), "
                                  "or use backend: nodeodm with a NodeODM server")
    try:
        res = subprocess.run([exe, "info", "--format", "{{.ServerVersion}}"], capture_output=True, text=True,
                             timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise DependencyError(f"cannot run '{exe} info': {exc}", fix="check the Docker installation") from exc
    if res.returncode != 0:
        detail = (res.stderr or res.stdout).strip().splitlines()
        raise DependencyError("Docker is installed but its engine is not running"
                              + (f" ({detail[-1]})" if detail else ""),
                              fix="start Docker Desktop, or on Linux 'sudo systemctl start docker' "
                                  "(and add yourself to the 'docker' group)")
    return exe


def run_streaming(argv: Sequence[str], log_path: Path, *, tail: int = 30) -> tuple[int, list[str]]:
    """Run ``argv``, copying its output line by line to the logger and to ``log_path``.

    Returns the exit code and the last ``tail`` lines.
    The log file is appended (not written atomically) on purpose: it must survive a crash half-way.
    """
    log_path.parent.mkdir(parents=True, exist_ok=True)
    last: deque[str] = deque(maxlen=tail)
    with open(log_path, "a", encoding="utf-8") as fh:
        fh.write(f"# {_dt.datetime.now().isoformat(timespec='seconds')} {subprocess.list2cmdline(argv)}\n")
        try:
            proc = subprocess.Popen(list(argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, text=True, errors="replace", bufsize=1)
        except OSError as exc:
            raise DependencyError(f"cannot start '{argv[0]}': {exc}", fix="check the docker.command setting") from exc
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                line = line.rstrip("\n")
                fh.write(line + "\n")
                last.append(line)
                log.info("  %s", line)
            code = proc.wait()
        except KeyboardInterrupt:
            proc.terminate()
            proc.wait()
            raise
    return code, list(last)


def run_docker(cfg: ODMRunnerConfig) -> dict:
    """Run ODM in Docker; raise ODMRunError with the end of the log if it fails."""
    exe = check_docker(cfg.docker.command)
    list_images(images_folder(cfg))
    gcp = find_gcp_file(cfg)
    argv = docker_command(cfg, gcp_file=gcp)
    argv[0] = exe
    log.info("running OpenDroneMap in Docker (this takes minutes to hours):\n  %s", subprocess.list2cmdline(argv))
    log_path = Path(cfg.output_dir) / "odm_docker.log"
    start = time.time()
    code, last = run_streaming(argv, log_path)
    if code != 0:
        tail = "\n".join("    " + ln for ln in last[-15:])
        raise ODMRunError(f"OpenDroneMap stopped with exit code {code}; the end of its log:\n{tail}",
                          path=log_path, fix="read the log above; common causes: too little memory "
                                             "(give Docker more), too few matching images, a bad gcp_list.txt")
    return {"backend": "docker", "command": argv, "exit_code": code, "gcp_file": str(gcp) if gcp else None,
            "seconds": round(time.time() - start, 1), "log": str(log_path)}


# --------------------------------------------------------------------------------------------------
# NodeODM backend


def _node(settings: NodeODMSettings):
    try:
        from pyodm import Node
    except ImportError as exc:  # pragma: no cover - pyodm is a dependency
        raise DependencyError("pyodm is not installed", fix="pip install pyodm") from exc
    try:
        node = Node.from_url(settings.url, timeout=settings.timeout)
    except Exception as exc:  # noqa: BLE001 - pyodm raises plain exceptions for bad URLs
        raise ConfigError(f"config key 'nodeodm.url' is not a valid address: {settings.url!r} ({exc})",
                          fix="write it as http://HOST:PORT, e.g. http://localhost:3000") from exc
    node.token = settings.token or ""
    return node


def _node_error(exc: Exception, settings: NodeODMSettings) -> MatchPlantError:
    from pyodm.exceptions import NodeConnectionError, NodeResponseError

    if isinstance(exc, NodeConnectionError):
        return DependencyError(f"cannot reach the NodeODM server at {settings.url} ({exc})",
                               fix="start it (docker run -p 3000:3000 opendronemap/nodeodm) or correct nodeodm.url")
    if isinstance(exc, NodeResponseError):
        return ODMRunError(f"the NodeODM server refused the request: {exc}",
                           fix="check nodeodm.token and the ODM options")
    return ODMRunError(f"NodeODM error: {type(exc).__name__}: {exc}", fix="check the server's log")


def percent_bar(desc: str):
    """A 0-100 % progress bar and the callback pyodm calls with the percentage done."""
    from matchplant.core.progress import progress

    bar = progress(range(100), desc=desc, total=100, unit="%")
    done = [0]

    def update(pct: float) -> None:
        step = int(pct) - done[0]
        if step > 0:
            bar.update(step)
            done[0] += step

    return bar, update


def run_nodeodm(cfg: ODMRunnerConfig) -> dict:
    """Upload, process and download through NodeODM; resume the task saved in the state file."""
    from pyodm.exceptions import NodeResponseError, OdmError
    from pyodm.types import TaskStatus

    from matchplant.core.progress import progress

    settings = cfg.nodeodm
    node = _node(settings)
    state_path = Path(cfg.output_dir) / "nodeodm_task.json"
    options = odm_option_dict(cfg.odm)
    start = time.time()
    try:
        info = node.info()
        log.info("NodeODM %s at %s (engine %s %s, %s tasks queued)", info.version, settings.url, info.engine,
                 info.engine_version, info.task_queue_count)
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
            images = list_images(images_folder(cfg))
            gcp = find_gcp_file(cfg)
            files = [str(p) for p in images] + ([str(gcp)] if gcp else [])
            bar, uploaded = percent_bar("upload")
            task = node.create_task(files, options, name=Path(cfg.project_dir).name, progress_callback=uploaded,
                                    outputs=NODEODM_OUTPUTS, parallel_uploads=settings.parallel_uploads)
            bar.close()
            write_json(state_path, {"uuid": task.uuid, "url": settings.url, "options": options,
                                    "images": len(images), "gcp_file": str(gcp) if gcp else None,
                                    "created": _dt.datetime.now().isoformat(timespec="seconds")})
            log.info("NodeODM task %s created with %d images; its id is saved in %s", task.uuid, len(images),
                     state_path)
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
    return {"backend": "nodeodm", "url": settings.url, "task": task.uuid, "options": options,
            "seconds": round(time.time() - start, 1), "state_file": str(state_path)}


def _wait(task, poll_seconds: float) -> None:
    from pyodm.types import TaskStatus

    from matchplant.core.progress import progress

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
            raise ODMRunError(f"the NodeODM task {task.uuid} {info.status.name.lower()}: {info.last_error}\n{tail}",
                              fix="read the task's log in NodeODM/WebODM; fix the cause and run again "
                                  "(a failed task is not resumed)")
        time.sleep(poll_seconds)
    bar.close()


def _download(task, project: Path) -> None:
    """Download all.zip next to the project, then move its folders into the project (replacing old ones)."""
    from matchplant.core.progress import progress

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
                os.replace(item, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# --------------------------------------------------------------------------------------------------
# output checking and manifest


@dataclass
class OutputReport:
    project: Path
    present: dict[str, bool]
    problems: list[str] = field(default_factory=list)  # missing outputs, each with the option producing it
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems


def check_outputs(project_dir: str | Path, required: Sequence[str] = REQUIRED_OUTPUTS) -> OutputReport:
    """Check the outputs modules 3, 8 and 9 need; each problem names the ODM option that fixes it."""
    project = ODMProject(project_dir)
    present = project.check()
    problems = [f"{OUTPUTS[n].relpath} ({OUTPUTS[n].what}) is missing: produced by {OUTPUTS[n].produced_by}"
                for n in required if not present[n]]
    details: dict[str, Any] = {}
    if present["undistorted_reconstruction"]:
        try:
            shots = set(project.reconstruction(undistorted=True).shots)
            images = set(project.undistorted_images())
            details["undistorted_shots"] = len(shots)
            details["undistorted_images"] = len(images)
            lacking = sorted(shots - images)
            if lacking and present["undistorted_images"]:
                problems.append(f"{len(lacking)} of {len(shots)} reconstructed images have no undistorted image "
                                f"(e.g. {lacking[0]}.tif): produced by the OpenSfM undistort step "
                                "(do not use --optimize-disk-space)")
        except MatchPlantError as exc:
            problems.append(f"opensfm/undistorted/reconstruction.json is unreadable: {exc.problem}")
    for name in ("dsm", "dtm", "orthophoto"):
        if present[name]:
            info = _raster_info(project.path(name))
            details[name] = info
            if "error" in info:
                problems.append(f"{OUTPUTS[name].relpath} is unreadable ({info['error']}): re-run ODM "
                                f"({OUTPUTS[name].produced_by})")
            elif info.get("crs") is None:
                problems.append(f"{OUTPUTS[name].relpath} has no coordinate system: give ODM GPS-tagged "
                                "images or a gcp_list.txt")
    if present["coords"]:
        try:
            crs, offset = project.coords
            details["crs"] = crs.to_string()
            details["offset"] = [float(offset[0]), float(offset[1])]
        except MatchPlantError as exc:
            problems.append(f"odm_georeferencing/coords.txt is unreadable: {exc.problem}")
    return OutputReport(project=Path(project_dir), present=present, problems=problems, details=details)


def _raster_info(path: Path) -> dict:
    import rasterio

    try:
        with rasterio.open(path) as src:
            return {"width": src.width, "height": src.height, "bands": src.count,
                    "crs": src.crs.to_string() if src.crs else None,
                    "resolution_m": [abs(src.transform.a), abs(src.transform.e)]}
    except Exception as exc:  # noqa: BLE001 - any GDAL failure means the file is unusable
        return {"error": str(exc)}


def write_manifest(path: str | Path, cfg: ODMRunnerConfig, report: OutputReport, run_info: dict | None) -> Path:
    """What was run, with which options, and every output with its size and whether it is there."""
    from matchplant.core.config import to_dict
    from matchplant.core.log import package_versions

    project = ODMProject(report.project)
    outputs = {}
    for name, out in OUTPUTS.items():
        p = project.path(name)
        entry: dict[str, Any] = {"path": out.relpath, "exists": report.present[name], "produced_by": out.produced_by}
        if report.present[name] and p.is_file():
            entry["bytes"] = p.stat().st_size
        outputs[name] = entry
    data = {
        "created": _dt.datetime.now().isoformat(timespec="seconds"),
        "project_dir": str(report.project),
        "run": run_info,
        "odm_options": odm_option_dict(cfg.odm),
        "outputs": outputs,
        "details": report.details,
        "problems": report.problems,
        "ok": report.ok,
        "config": to_dict(cfg),
        "versions": package_versions(),
    }
    return write_json(path, data)


# --------------------------------------------------------------------------------------------------
# the module


def run(cfg: ODMRunnerConfig) -> OutputReport:
    """Run ODM with the chosen backend (unless ``check_only``), check its outputs, write the manifest."""
    if cfg.output_dir is None:
        cfg.output_dir = cfg.project_dir
    Path(cfg.output_dir).mkdir(parents=True, exist_ok=True)
    run_info = None
    if not cfg.check_only:
        run_info = run_docker(cfg) if cfg.backend == "docker" else run_nodeodm(cfg)
    report = check_outputs(cfg.project_dir)
    manifest = write_manifest(Path(cfg.output_dir) / "odm_manifest.json", cfg, report, run_info)
    log.info("manifest: %s", manifest)
    if not report.ok:
        raise InputError("the ODM project lacks what later modules need:\n" +
                         "\n".join(f"  - {p}" for p in report.problems), path=cfg.project_dir,
                         fix="re-run ODM with the options named above (see odm_manifest.json)")
    log.info("all outputs needed by modules 3, 8 and 9 are present in %s", cfg.project_dir)
    return report
