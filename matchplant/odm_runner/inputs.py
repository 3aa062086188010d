"""What ODM is given: the images folder, the GCP file, and the configured options as ODM arguments.

The same options go to both backends, as command-line flags (Docker) or as pyodm's dictionary (NodeODM).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matchplant.core.formats.images import ODM_SUFFIXES, list_images
from matchplant.odm_runner.config import ODMOptions, OdmRunnerConfig


def images_folder(cfg: OdmRunnerConfig) -> Path:
    """Where the images are: ``images_dir`` when set, else ODM's own place, ``<project_dir>/images``."""
    return Path(cfg.images_dir) if cfg.images_dir is not None else Path(cfg.project_dir) / "images"


def odm_images(cfg: OdmRunnerConfig) -> list[Path]:
    """The images ODM will get; fewer than 2 is an error now rather than after ODM has started."""
    return list_images(
        images_folder(cfg),
        ODM_SUFFIXES,
        key="images_dir",
        min_count=2,
        fix="put the flight's overlapping images (JPG/TIF) in <project_dir>/images, or set images_dir",
    )


def find_gcp_file(cfg: OdmRunnerConfig) -> Path | None:
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
