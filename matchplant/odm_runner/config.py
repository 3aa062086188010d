"""Step 2's settings: the ODM options, the Docker and NodeODM backends, and the project folder.

The defaults are the paper's (DSM, DTM, 0.5 cm orthophoto, undistorted images kept); options that
would remove an output later steps need are refused here, before hours of processing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from matchplant.core.runtime.config import param, section
from matchplant.core.runtime.errors import ConfigError, MatchPlantError

# options that would remove or skip an output later modules need
FORBIDDEN_OPTIONS = {
    "optimize-disk-space": "it deletes opensfm/undistorted, which modules 3 and 8 need",
    "skip-orthophoto": "modules 3 and 9 need odm_orthophoto/odm_orthophoto.tif",
    "project-path": "the runner sets it; set project_dir instead",
    "gcp": "set gcp_file instead",
}


class ODMRunError(MatchPlantError):
    """ODM itself failed (non-zero exit, failed task)."""


@dataclass
class ODMOptions:
    """OpenDroneMap options (the paper's defaults: DSM, DTM, 0.5 cm orthophoto, undistorted images kept)."""

    dsm: bool = param(True, "build odm_dem/dsm.tif (--dsm); modules 3 and 8 need it")
    dtm: bool = param(True, "build odm_dem/dtm.tif (--dtm); plant height in module 9 needs it")
    orthophoto_resolution: float = param(
        0.5,
        "orthophoto resolution in cm/pixel (--orthophoto-resolution); "
        "ODM never goes finer than the images' ground sampling distance",
        min=0.01,
    )
    dem_resolution: float | None = param(
        None, "DSM/DTM resolution in cm/pixel (--dem-resolution); empty: ODM's default", min=0.01
    )
    extra: dict = param(
        {},
        "more ODM options as 'name: value' (true for a flag), e.g. "
        "{feature-quality: high, pc-quality: medium}; see docs.opendronemap.org/arguments",
    )


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
class OdmRunnerConfig:
    """Run OpenDroneMap (Docker or NodeODM) on a project folder and check its outputs."""

    writes_into_inputs = ("output_dir",)  # a user may still keep the manifest in the project folder, as before

    project_dir: Path = param(
        None, "ODM project folder; the images go in its images/ subfolder", path="dir", required=True
    )
    images_dir: Path | None = param(
        None,
        "folder of the images if not <project_dir>/images (mounted or uploaded as the project's images)",
        path="dir",
    )
    gcp_file: Path | None = param(
        None,
        "gcp_list.txt to use; empty: gcp_list.txt in the images folder or the project folder when present",
        path="file",
    )
    use_gcp: bool = param(True, "use the GCP file (false: georeference from the images' GPS only)")
    backend: Literal["docker", "nodeodm"] = param("docker", "where ODM runs", choices=["docker", "nodeodm"])
    check_only: bool = param(False, "do not run ODM; only check an existing project and write the manifest")
    odm: ODMOptions = section(ODMOptions)
    docker: DockerSettings = section(DockerSettings)
    nodeodm: NodeODMSettings = section(NodeODMSettings)
    # ODM's own outputs always land in project_dir (that is what ODM does); MatchPlant's files go here, like
    # every other step's, so that the ODM project holds only ODM's files
    output_dir: Path = param(
        Path("runs/odm_runner"),
        "where the manifest, logs and NodeODM task state go (ODM's own outputs are written into project_dir)",
        path="out",
    )

    def check(self) -> None:
        """Reject ODM options in ``odm.extra`` that MatchPlant sets itself or that break later steps."""
        for name in self.odm.extra:
            key = str(name).lstrip("-")
            if key in FORBIDDEN_OPTIONS:
                raise ConfigError(
                    f"config key 'odm.extra' must not set '{key}': {FORBIDDEN_OPTIONS[key]}",
                    fix=f"remove '{key}' from odm.extra",
                )
