"""The ``docker`` backend: the ``opendronemap/odm`` image on this computer.

:func:`docker_command` builds the ``docker run`` argument list (a pure function: no TTY, the project
mounted at ``/datasets/code``, files owned by the user on Linux and macOS, paths with spaces, Windows
paths); :func:`run_docker` runs it with the log streamed to the console and to
``<output>/odm_docker.log`` and checks the exit code.
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
import subprocess
import sys
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path, PurePath, PurePosixPath, PureWindowsPath

from matchplant.core.runtime.errors import ConfigError, DependencyError
from matchplant.core.runtime.log import get_logger
from matchplant.odm_runner.config import ODMRunError, OdmRunnerConfig
from matchplant.odm_runner.inputs import find_gcp_file, odm_arguments, odm_images

log = get_logger("odm_runner")

CONTAINER_ROOT = "/datasets"  # ODM's --project-path inside the container
CONTAINER_PROJECT = "/datasets/code"  # the project folder as ODM sees it ("code" is ODM's default name)


def docker_command(
    cfg: OdmRunnerConfig,
    *,
    platform: str | None = None,
    uid: int | None = None,
    gid: int | None = None,
    gcp_file: str | PurePath | None = None,
) -> list[str]:
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
            raise ConfigError(f"Docker cannot mount a path containing ':': {text}", fix="rename the folder without ':'")
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
        raise DependencyError(
            f"Docker was not found ('{command}' is not on PATH)",
            fix="install Docker Desktop (Windows, macOS) or Docker Engine (Linux), "
            "or use backend: nodeodm with a NodeODM server",
        )
    try:
        res = subprocess.run(
            [exe, "info", "--format", "{{.ServerVersion}}"], capture_output=True, text=True, timeout=60
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise DependencyError(f"cannot run '{exe} info': {exc}", fix="check the Docker installation") from exc
    if res.returncode != 0:
        detail = (res.stderr or res.stdout).strip().splitlines()
        raise DependencyError(
            "Docker is installed but its engine is not running" + (f" ({detail[-1]})" if detail else ""),
            fix="start Docker Desktop, or on Linux 'sudo systemctl start docker' "
            "(and add yourself to the 'docker' group)",
        )
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
            proc = subprocess.Popen(
                list(argv),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                text=True,
                errors="replace",
                bufsize=1,
            )
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


def run_docker(cfg: OdmRunnerConfig) -> dict:
    """Run ODM in Docker; raise ODMRunError with the end of the log if it fails."""
    exe = check_docker(cfg.docker.command)
    odm_images(cfg)
    gcp = find_gcp_file(cfg)
    argv = docker_command(cfg, gcp_file=gcp)
    argv[0] = exe
    log.info("running OpenDroneMap in Docker (this takes minutes to hours):\n  %s", subprocess.list2cmdline(argv))
    log_path = Path(cfg.output_dir) / "odm_docker.log"
    start = time.time()
    code, last = run_streaming(argv, log_path)
    if code != 0:
        tail = "\n".join("    " + ln for ln in last[-15:])
        raise ODMRunError(
            f"OpenDroneMap stopped with exit code {code}; the end of its log:\n{tail}",
            path=log_path,
            fix="read the log above; common causes: too little memory "
            "(give Docker more), too few matching images, a bad gcp_list.txt",
        )
    return {
        "backend": "docker",
        "command": argv,
        "exit_code": code,
        "gcp_file": str(gcp) if gcp else None,
        "seconds": round(time.time() - start, 1),
        "log": str(log_path),
    }
