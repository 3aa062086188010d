"""``matchplant init``: a season's ``pipeline.yaml`` written from an ODM project folder, so that nobody has to write
one by hand. What it finds fills the steps: the project's photos and rasters (module 9 reads the DSM, DTM and
orthophoto that exist), the tile size, overlap and detector input the annotations' plant sizes call for
(``matchplant inspect``'s advice), and the detector recipe ``auto`` picks on the machine that trains (module 6).

- with annotations (plant boxes on the project's photos, a COCO file): modules 2 to 9, training a detector;
- with a checkpoint (a trained detector): modules 2, 3 and 7 to 9, detecting with it;
- with neither: modules 2 and 3 (the photos to annotate), and the comment that says how to go on.

Paths are written relative to the pipeline file's folder; each step has a comment that says what it does and
which keys one typically changes (:mod:`matchplant.pipeline.write`)."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from matchplant.core.formats.odm import ODMProject
from matchplant.core.formats.projects import PhotoProject, open_project
from matchplant.core.runtime.config import param
from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.io import STDOUT
from matchplant.core.runtime.log import get_logger
from matchplant.pipeline.chain import season_chain
from matchplant.pipeline.season_inputs import check_season_inputs
from matchplant.pipeline.write import write_pipeline

log = get_logger("init")

NOTES = {
    "2_odm": "module 2: checks that OpenDroneMap's outputs are all there (check_only: true); set it to false to run "
    "ODM in Docker on the project's images.",
    "3_select": "module 3: the fewest photos that cover the field: the ones to annotate with `matchplant bbox_drawer "
    "--gui`. Change area (a polygon of the plots) or uncovered_threshold.",
    "4_annotate": "module 4: the plant boxes (import_coco) checked and written as annotations.json. Change "
    "min_box_size, label_map.",
    "5_tiles": "module 5: the annotated photos cut into tiles and split into train, val and test. tile_size and "
    "overlap come from the plants' sizes (matchplant inspect); change split.",
    "6_train": "module 6: trains the detector. pretrained: auto takes COCO weights when they are cached or "
    "downloadable, else none; architecture: auto then picks on the machine that trains: on a GPU the paper's "
    "Faster R-CNN ResNet-50 FPN, on a CPU from random weights the light ResNet-18 FPN with its from-scratch "
    "recipe (module 6's README), each logged with the reason. Change max_minutes (the time budget). A re-run "
    "after Ctrl-C continues the training.",
    "7_detect": "module 7: the test tiles' AP (evaluate) and the plants on every photo of the project "
    "(detect.images). Change detect.score_threshold (0.5) after looking at the drawn boxes.",
    "8_plants": "module 8: every detected plant put on the map from all the photos that see it (plants.gpkg). "
    "Change min_score, mode.",
    "9_stats": "module 9: per-plant height (CHM = DSM - DTM), vegetation indices and statistics. Add "
    "rasters.multispectral with red_band and nir_band for NDVI, and a plots section for stand counts.",
}


@dataclass
class InitConfig:
    """Write a commented pipeline.yaml for a season from an ODM, Metashape or Pix4D project (matchplant run runs it)."""

    project: Path | None = param(
        None,
        "the project: an ODM folder (opensfm/, odm_dem/, odm_orthophoto/), a Metashape camera export (.xml) or "
        "project (.psx), or a Pix4D project folder",
        path="exists",
        required=True,
    )
    project_type: str = param(
        "auto", "which program made the project (auto: from its files)", choices=("auto", "odm", "metashape", "pix4d")
    )
    annotations: Path | None = param(
        None,
        "plant boxes on the project's photos (a COCO JSON: module 4's annotations.json, CVAT's COCO export): "
        "the pipeline tiles them and trains a detector",
        path="file",
    )
    checkpoint: Path | None = param(
        None, "a trained detector (module 6's checkpoints/best.pt): the pipeline detects with it", path="file"
    )
    output: Path = param(
        Path("pipeline.yaml"),
        'the pipeline file to write (its folder is created; "-": standard output, paths then relative to the '
        "current folder)",
        path="out_file",
    )
    max_minutes: float = param(
        60.0, "module 6's time budget for training, in minutes (0 = none: module 6's 30 epochs)", min=0
    )
    force: bool = param(False, "replace an existing pipeline file")

    def check(self) -> None:
        """An existing pipeline file is kept unless ``force``; the output is a .yaml file (or standard output)."""
        if self.output is not None and str(self.output) == STDOUT:
            return
        if self.output is not None and Path(self.output).is_dir():
            raise ConfigError(
                "output is a folder: init writes one pipeline file",
                path=self.output,
                fix=f"give a file in it, e.g. --output {Path(self.output) / 'pipeline.yaml'}",
            )
        if self.output is not None and Path(self.output).exists() and not self.force:
            raise ConfigError(
                "the pipeline file exists already (it may hold your edits)",
                path=self.output,
                fix="give another output, or set force: true (--set force=true) to replace it",
            )
        if self.output is not None and Path(self.output).suffix.lower() not in (".yaml", ".yml"):
            raise ConfigError("output must be a .yaml file", path=self.output, fix="e.g. --set output=pipeline.yaml")


def _rel(path: Path, base: Path) -> str:
    return Path(os.path.relpath(Path(path).resolve(), base)).as_posix()


def season_spec(cfg: InitConfig, advice: dict) -> dict:
    """The pipeline's content: the top-level keys and the steps that the inputs allow."""
    base = Path(cfg.output).resolve().parent
    project = open_project(cfg.project, cfg.project_type)
    odm = isinstance(project, ODMProject)
    top = {"output_dir": ".", "project": _rel(project.root if odm else Path(cfg.project), base)}
    photos = (
        "${project}/" + _rel(project.path("undistorted_images"), project.root.resolve())
        if odm
        else _rel(photo_folder(project, cfg.project), base)
    )
    tile = {k: advice[k] for k in ("tile_size", "overlap") if k in advice}
    chain: dict = {}
    if cfg.annotations is not None:
        top["annotations"] = _rel(cfg.annotations, base)
        model = {"architecture": "auto", "pretrained": "auto"}
        if cfg.checkpoint is not None:  # annotations and a detector: training starts from the detector
            top["checkpoint"] = _rel(cfg.checkpoint, base)
            model = {"checkpoint": "${checkpoint}"}
        if "min_size" in advice:  # the detector input that keeps the median plant >= 24 px (matchplant inspect)
            model.update(min_size=advice["min_size"], max_size=advice["max_size"], anchor_sizes="auto")
        chain = {
            "annotations": "${annotations}",
            "tiles": tile,
            "train": {"model": model, "max_minutes": cfg.max_minutes},
        }
        evaluate = {"dataset_json": "${5_tiles.output_dir}/test.json"}  # module 5's test split
    elif cfg.checkpoint is not None:
        top["checkpoint"] = _rel(cfg.checkpoint, base)
        chain, evaluate = {"checkpoint": "${checkpoint}"}, {}
    if chain:  # module 7 on every photo of the project, then modules 8 and 9
        chain["detect"] = {"detect": {"images": photos, **tile}, "evaluate": evaluate}
        rasters = {
            key: "${project}/" + _rel(project.path(name), project.root.resolve())
            if odm
            else _rel(project.path(name), base)
            for key, name in (("dsm", "dsm"), ("dtm", "dtm"), ("rgb", "orthophoto"))
            if project.has(name)
        }
        if "dtm" not in rasters:  # module 9's heights need both (a CHM); init warned of the missing DTM
            rasters.pop("dsm", None)
        chain["stats"] = {"rasters": rasters}
    if not odm:  # Metashape, Pix4D: the program named; they pose the original photos
        chain["select"] = {"project_type": project.program}
        chain["plants"] = {"project_type": project.program, "image_type": "original"}
    return {**top, "steps": season_chain("${project}", photos, odm=odm, **chain)}


def photo_folder(project: PhotoProject, source: Path) -> Path:
    """The one folder of a Metashape or Pix4D project's original photos (every posed photo on disk)."""
    folders = sorted({p.parent for p in project.image_paths().values()})
    if len(folders) != 1:
        raise InputError(
            f"the {project.program} project's photos lie in {len(folders)} folders; the pipeline needs one",
            path=source,
            fix="put the photos in one folder (modules 3 and 7 read it)",
        )
    return folders[0]


def header(cfg: InitConfig, spec: dict) -> str:
    """The file's first comment: how it was made, how to run it, what is missing."""
    lines = [
        "A season's pipeline, written by `matchplant init` from the project "
        f"{spec['project']}; run it with: matchplant run "
        f"{'<this file>' if str(cfg.output) == STDOUT else Path(cfg.output).name}",
        "Relative paths are relative to this file's folder; ${name} is a top-level key or an earlier step's key.",
        "Each step writes to <output_dir>/<step name>; a finished step with unchanged settings is skipped.",
        "Before ODM (GPS into the photos, ground control points): modules 0 and 1 (`matchplant --help`).",
    ]
    if cfg.annotations is None and cfg.checkpoint is None:
        lines.append(
            "No annotations or detector given: annotate module 3's photos with `matchplant bbox_drawer --gui`, "
            "then run `matchplant init` again with --set annotations=<their annotations.json>."
        )
    return "\n".join(lines)


def init_pipeline(
    cfg: InitConfig, advise: Callable[[Path], dict], check_checkpoint: Callable[[Path], None] | None = None
) -> Path:
    """Check what init is given (:mod:`matchplant.pipeline.season_inputs`: an error writes nothing), then write the
    pipeline file. ``advise(annotations)``: the tiling and detector input the plants call for;
    ``check_checkpoint(path)``: raises when the checkpoint is no detector MatchPlant reads."""
    check_season_inputs(cfg.project, cfg.annotations, cfg.checkpoint, check_checkpoint, cfg.project_type)
    advice = advise(cfg.annotations) if cfg.annotations is not None else {}
    spec = season_spec(cfg, advice)
    path = write_pipeline(Path(cfg.output), spec, NOTES, header(cfg, spec))
    log.info("wrote %s (%d steps: %s)", path, len(spec["steps"]), ", ".join(s["name"] for s in spec["steps"]))
    log.info("run it with: matchplant run %s", path)
    return path
