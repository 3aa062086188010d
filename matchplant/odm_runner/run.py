"""Module 2: run OpenDroneMap on a project folder, then check that every output later modules need is there.

Two backends, one configuration:

* ``docker`` - the ``opendronemap/odm`` image on this computer, run with the log streamed to the console
  and to ``<output>/odm_docker.log``; the exit code is checked.
* ``nodeodm`` - a NodeODM server (or ClusterODM in front of several) through pyodm: upload with a progress
  bar, processing progress, download into the project. The task id is saved in
  ``<output>/nodeodm_task.json`` so an interrupted run resumes the same task instead of starting over.

After a run (or alone, with ``check_only``) :func:`~matchplant.odm_runner.outputs.check_outputs` verifies
the files of docs/DESIGN.md §2 with :class:`~matchplant.core.formats.odm.ODMProject`, names the ODM option that
produces each missing one, and :func:`~matchplant.odm_runner.outputs.write_manifest` records what was run
and what came out in ``<output>/odm_manifest.json``.

The settings are :mod:`.config`, the inputs given to ODM :mod:`.inputs`, the backends :mod:`.docker`
and :mod:`.nodeodm`, the check :mod:`.outputs`; this module runs them in order.
"""

from __future__ import annotations

from pathlib import Path

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.odm_runner.config import OdmRunnerConfig
from matchplant.odm_runner.docker import run_docker
from matchplant.odm_runner.nodeodm import run_nodeodm
from matchplant.odm_runner.outputs import OutputReport, check_outputs, write_manifest

log = get_logger("odm_runner")


def run(cfg: OdmRunnerConfig) -> OutputReport:
    """Run ODM with the chosen backend (unless ``check_only``), check its outputs, write the manifest.

    A project that modules 3, 8 and 9 cannot use is an error listing every problem (a missing output names
    the ODM option that makes it).

    Parameters
    ----------
    cfg : OdmRunnerConfig
        The step's settings, as loaded from its YAML config (``2_odm_runner/config.yaml``) or built in Python.

    Returns
    -------
    OutputReport
        What the ODM project holds (no problems: every step after can use it).
    """
    Path(cfg.output_dir).mkdir(parents=True, exist_ok=True)
    run_info = None
    if not cfg.check_only:
        run_info = run_docker(cfg) if cfg.backend == "docker" else run_nodeodm(cfg)
    report = check_outputs(cfg.project_dir)
    if report.ok or run_info is not None:  # after a run, the manifest records it even when outputs are lacking
        manifest = write_manifest(Path(cfg.output_dir) / "odm_manifest.json", cfg, report, run_info)
        log.info("manifest: %s", manifest)
    if not report.ok:
        see = " (see odm_manifest.json)" if run_info is not None else ""
        raise InputError(
            f"the ODM project cannot be used by modules 3, 8 and 9 ({len(report.problems)} "
            "problem(s)):\n" + "\n".join(f"  - {p}" for p in report.problems),
            path=cfg.project_dir,
            fix="re-run ODM with the options named above, or restore the files named" + see,
        )
    log.info("all outputs needed by modules 3, 8 and 9 are present in %s", cfg.project_dir)
    return report
