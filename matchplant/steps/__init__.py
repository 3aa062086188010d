"""The command layer: one small file per step, naming its config class, its run function and its GUI.

``matchplant.cli`` and ``matchplant.pipeline`` find a step here by its one name, the word of its numbered
folder (``8_plant_projection`` -> ``plant_projection``: the command, this layer's file and the step's
subpackage). Each file exposes ``SPEC``, a :class:`StepSpec`. Step files are imported by name on demand
(:func:`resolve_step`) so that ``matchplant --help`` and the pipeline's checks do not load PyTorch, and a step's
window only for ``--gui`` (:meth:`StepSpec.load_gui`).
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from matchplant.core.runtime.errors import ConfigError

# name -> (numbered folder, one-line summary); the numbered steps first, in order
STEPS: dict[str, tuple[str, str]] = {
    "gps_embeder": ("0_gps_embeder", "write GNSS positions into image EXIF"),
    "gcp_finder": ("1_gcp_finder", "find and mark GCPs, write gcp_list.txt"),
    "odm_runner": ("2_odm_runner", "run OpenDroneMap and check its outputs"),
    "min_img_finder": ("3_min_img_finder", "fewest undistorted images covering the field"),
    "bbox_drawer": ("4_bbox_drawer", "draw plant boxes; COCO and YOLO"),
    "img_splitter": ("5_img_splitter", "tile annotated images, split train/val/test"),
    "model_train": ("6_model_train", "train a plant detector"),
    "model_test": ("7_model_test", "COCO evaluation and detection on new images"),
    "plant_projection": ("8_plant_projection", "put detected plants on the map"),
    "spatial_stat_extractor": ("9_spatial_stat_extractor", "plant polygons and per-plant statistics"),
    "simfield": ("", "generate a synthetic ODM project with exact ground truth"),
    "inspect": ("", "object sizes of a COCO file; recommended tile size, overlap, min_size, anchors"),
    "init": ("", "write a commented pipeline.yaml for a season from an ODM, Metashape or Pix4D project"),
    "cameras": ("", "what an ODM, Metashape or Pix4D project holds; map points found in its photos"),
    "run": ("", "run several steps in order from one pipeline.yaml"),
}

# every other name a step answers to, in this one table: older command names, and the number of its folder
# (``8_plant_projection`` -> ``8``)
ALIASES: dict[str, str] = {
    "gps_embed": "gps_embeder",
    "train": "model_train",
    "project_boxes": "plant_projection",
    "stat_extractor": "spatial_stat_extractor",
    **{folder.split("_", 1)[0]: name for name, (folder, _) in STEPS.items() if folder},
}


@dataclass
class StepSpec:
    """How the command line and the pipeline drive one step."""

    name: str
    config: type
    run: Callable[[Any], Any]
    # the window as "module:function" (``launch(cfg, config_path)``), imported only for --gui (load_gui): a
    # plain run then loads none of matplotlib's widgets and GUI code (seconds of CPU at every start)
    gui: str | None = None
    # extra flags as shortcuts for --set: "--preset" -> ("preset", "help text"); a third item makes it a
    # switch without a value: "--resume" -> ("resume", "help", "true") means --set resume=true
    flags: dict[str, tuple[str, ...]] = field(default_factory=dict)
    output_key: str = "output_dir"
    # when set, the positional argument fills this key instead of naming a config file
    # (``matchplant run pipeline.yaml``)
    positional_key: str | None = None
    # a step that continues an interrupted run (module 6): the key that asks for it (``resume``) and what says
    # there is one to continue (its checkpoint, given the config); ``matchplant run`` sets the key when the
    # step's previous run stopped unfinished with the same settings (matchplant/pipeline/run.py)
    resume_key: str | None = None
    resume_file: Callable[[Any], Path] | None = None

    def load_gui(self) -> Callable[[Any, Path | None], Any]:
        """The step's window function, imported now."""
        module, _, function = self.gui.partition(":")
        return getattr(importlib.import_module(module), function)


def canonical_name(name: str) -> str:
    """The step's one name for ``name`` (an alias, a folder number, dashes for underscores)."""
    name = name.replace("-", "_")
    name = ALIASES.get(name, name)
    if name not in STEPS:
        close = difflib.get_close_matches(name, list(STEPS) + list(ALIASES), n=1)
        hint = f"did you mean '{ALIASES.get(close[0], close[0])}'?" if close else "run 'matchplant --help' for the list"
        raise ConfigError(f"unknown module '{name}'; {hint}")
    return name


def resolve_step(name: str) -> StepSpec:
    """The :class:`StepSpec` of step ``name`` (aliases accepted)."""
    return importlib.import_module(f"matchplant.steps.{canonical_name(name)}").SPEC
