"""Run logging: the console and a log file in the output folder, with the configuration and versions.

Every run leaves ``<output>/logs/<module>_<time>.log`` so that a result can always be traced to the
settings and package versions that made it.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import os
import platform
import sys
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

import yaml

from matchplant.core.runtime.config import to_dict

LOGGER_NAME = "matchplant"
VERSIONED = (
    "matchplant",
    "numpy",
    "scipy",
    "opencv-python-headless",
    "rasterio",
    "pyproj",
    "shapely",
    "geopandas",
    "torch",
    "torchvision",
    "pycocotools",
    "matplotlib",
    "piexif",
    "rasterstats",
)


def get_logger(name: str | None = None) -> logging.Logger:
    """The package's logger, or its child ``name``."""
    return logging.getLogger(LOGGER_NAME if not name else f"{LOGGER_NAME}.{name}")


def package_versions() -> dict[str, str]:
    """Versions of Python, the platform and the main packages, for the run log."""
    # not platform.platform(): it runs 'uname -p' in a child process, a fork of this one, whose resident memory
    # (the parent's at the fork) module 9 would report as its worker processes' peak
    out = {
        "python": platform.python_version(),
        "platform": f"{platform.system()}-{platform.release()}-{platform.machine()}",
    }
    for pkg in VERSIONED:
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (test runners and GUIs replace it)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


def setup_console(level: int | None = logging.INFO) -> logging.Logger:
    """Attach the console handler once; ``level=None`` keeps the level already chosen (e.g. --quiet)."""
    logger = get_logger()
    logger.setLevel(logging.DEBUG)
    if not any(getattr(h, "_matchplant_console", False) for h in logger.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        handler._matchplant_console = True  # type: ignore[attr-defined]
        handler.setLevel(logging.INFO if level is None else level)
        logger.addHandler(handler)
    for h in logger.handlers:
        if getattr(h, "_matchplant_console", False) and level is not None:
            h.setLevel(level)
    logger.propagate = False
    return logger


def start_run_log(output_dir: str | Path, module: str, config: Any = None) -> Path:
    """Attach a file handler for this run and record the configuration and package versions."""
    logger = setup_console(level=None)
    for h in list(logger.handlers):
        if getattr(h, "_matchplant_run", False):
            logger.removeHandler(h)
            h.close()
    log_dir = Path(output_dir) / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    rank = os.environ.get("RANK", "0")  # torchrun: one log per process, not one overwritten by all
    path = log_dir / (f"{module}_{stamp}.log" if rank == "0" else f"{module}_{stamp}_rank{rank}.log")
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.setLevel(logging.DEBUG)
    handler._matchplant_run = True  # type: ignore[attr-defined]
    logger.addHandler(handler)
    logger.debug("command: %s", " ".join(sys.argv))
    logger.debug("versions:\n%s", yaml.safe_dump(package_versions(), sort_keys=False))
    if config is not None:
        logger.debug("configuration:\n%s", yaml.safe_dump(to_dict(config), sort_keys=False))
    return path


def stop_run_log() -> None:
    """Detach and close the run log's file handler."""
    logger = get_logger()
    for h in list(logger.handlers):
        if getattr(h, "_matchplant_run", False):
            logger.removeHandler(h)
            h.close()


class _FinalPaths(logging.Filter):
    """Rewrites a staged output folder's path into the folder it becomes (see ``naming_final``)."""

    def __init__(self, staged: Path, final: Path):
        super().__init__()
        self.pairs = [(str(staged.resolve()), str(final.resolve())), (str(staged), str(final))]

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        new = msg
        for staged, final in self.pairs:
            new = new.replace(staged, final)
        if new != msg:
            record.msg, record.args = new, None
        return True


@contextlib.contextmanager
def naming_final(staged: str | Path, final: str | Path) -> Iterator[None]:
    """While a step writes into a staged folder that is renamed when it succeeds, messages name the final
    folder: a path printed to the user must still exist after the run (a ``.partial-...`` path would not)."""
    f = _FinalPaths(Path(staged), Path(final))
    handlers = list(get_logger().handlers) + list(logging.getLogger().handlers)
    for h in handlers:
        h.addFilter(f)
    try:
        yield
    finally:
        for h in handlers:
            h.removeFilter(f)
