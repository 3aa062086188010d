"""Issue 47's classes of mistakes, as a new user makes them: a key given twice in a ``--config`` file, ``-`` for
standard output, a full disk, a damaged state file of the pipeline, a number that is not finite, a checkpoint
deleted that the run did not create, and ``init`` given what it cannot use (raw photos, no DTM, another flight's
annotations, a YOLO model). The table-driven tests (tests/test_reliability_*.py) run each class over every flag,
key and reader; these cases run one of each end to end through the harness (inputs unchanged, no partial output)."""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

import pytest
import yaml
from cases_model_train import args, splits
from harness import Case, Work

LINUX_ONLY = (pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/dev/full is Linux's"),)


def config(w: Work, text: str, name: str = "config.yaml") -> Path:
    path = w.inputs / name
    path.write_text(text, encoding="utf-8")
    return path


def m6_duplicate_key(w: Work) -> list[str]:
    tr, _, val, _ = splits(w, n_train=2, n_val=1)
    cfg = config(w, "model:\n  architecture: fasterrcnn_resnet18_fpn_lite\n  min_size: 64\n  architecture: auto\n")
    return ["--config", str(cfg), *args(w, tr, val)]


def m9_duplicate_key(w: Work) -> list[str]:
    plants = w.copy("plants")
    return [
        "--config",
        str(config(w, f"polygons: {plants / 'plants.gpkg'}\npolygons: last_season.gpkg\n")),
        "--set",
        f"output_dir={w.out}",
    ]


def init_duplicate_key(w: Work) -> list[str]:
    field = w.artifacts / "field"
    return ["--config", str(config(w, f"project: {field}\noutput: {w.out / 'p.yaml'}\nproject: elsewhere\n"))]


def init_to_stdout(w: Work) -> list[str]:
    return [str(w.artifacts / "field"), "--output", "-"]


def inspect_to_stdout(w: Work) -> list[str]:
    return [str(w.copy("field/truth/boxes_undistorted.json")), "--report", "-"]


def output_folder_dash(w: Work) -> list[str]:
    return ["--set", f"images={w.artifacts / 'field' / 'opensfm/undistorted/images'}", "--output", "-"]


def write_config_full_disk(w: Work) -> list[str]:
    return ["--write-config", "/dev/full"]


def init_link_to_full_disk(w: Work) -> list[str]:
    w.out.mkdir(parents=True, exist_ok=True)
    link = w.out / "pipeline.yaml"
    link.symlink_to("/dev/full")
    return [str(w.artifacts / "field"), "--output", str(link), "--set", "force=true"]


def pipeline_with_damaged_record(w: Work) -> list[str]:
    boxes = w.copy("field/truth/boxes_undistorted.json")
    path = w.inputs / "pipeline.yaml"
    path.write_text(
        f"output_dir: {json.dumps(str(w.out))}\nsteps:\n  - name: sizes\n    module: inspect\n"
        f"    config: {{annotations: {json.dumps(str(boxes))}}}\n",
        encoding="utf-8",
    )
    record = w.out / ".pipeline" / "sizes.json"
    record.parent.mkdir(parents=True)
    record.write_text('{"fingerprint": "ab')
    return [str(path)]


def max_minutes_inf(w: Work) -> list[str]:
    tr, _, val, _ = splits(w, n_train=2, n_val=1)
    return args(w, tr, val, "max_minutes=inf")


def init_raw_photos(w: Work) -> list[str]:
    return [str(w.copy("field/images", "photos")), "--output", str(w.out / "pipeline.yaml")]


def linked_field(w: Work, *without: str) -> Path:
    dst = w.inputs / "project"
    shutil.copytree(w.artifacts / "field", dst, copy_function=os.symlink)
    for rel in without:
        (dst / rel).unlink()
    return dst


def init_without_dtm(w: Work) -> list[str]:
    return [str(linked_field(w, "odm_dem/dtm.tif")), "--output", str(w.out / "pipeline.yaml")]


def heights_left_out(w: Work) -> None:
    steps = {s["name"]: s["config"] for s in yaml.safe_load((w.out / "pipeline.yaml").read_text())["steps"]}
    assert [s for s in steps] == ["2_odm", "3_select"]


def init_other_flight(w: Work) -> list[str]:
    ds = json.loads((w.artifacts / "field/truth/boxes_undistorted.json").read_text())
    for im in ds["images"]:
        im["file_name"] = "2019_" + im["file_name"]
    other = w.inputs / "annotations.json"
    other.write_text(json.dumps(ds))
    return [str(w.artifacts / "field"), "--annotations", str(other), "--output", str(w.out / "pipeline.yaml")]


def init_text_as_checkpoint(w: Work) -> list[str]:
    best = w.inputs / "best.pt"
    best.write_text("a YOLO model's training log, saved as best.pt by mistake\n")
    return [str(w.artifacts / "field"), "--checkpoint", str(best), "--output", str(w.out / "pipeline.yaml")]


def init_output_folder(w: Work) -> list[str]:
    w.out.mkdir(parents=True, exist_ok=True)
    return [str(w.artifacts / "field"), "--output", str(w.out)]


def config_from_stdin(w: Work) -> list[str]:
    return ["--config", "-"]


def set_input_to_dash(w: Work) -> list[str]:
    return ["--set", "images=-", "--set", f"output_dir={w.out}"]


CASES = [
    Case("r-m6-duplicate-config-key", "model_train", m6_duplicate_key, mentions=("'architecture'", "twice", "line")),
    Case("r-m9-duplicate-config-key", "spatial_stat_extractor", m9_duplicate_key, mentions=("'polygons'", "twice")),
    Case("r-init-duplicate-config-key", "init", init_duplicate_key, mentions=("'project'", "twice")),
    Case("r-init-output-to-stdout", "init", init_to_stdout, "ok"),
    Case("r-inspect-report-to-stdout", "inspect", inspect_to_stdout, "ok"),
    Case("r-output-folder-dash", "img_splitter", output_folder_dash, mentions=("output_dir", "standard output")),
    Case("r-input-dash", "gps_embeder", set_input_to_dash, mentions=("images", "standard output")),
    Case("r-config-dash", "img_splitter", config_from_stdin, mentions=("standard input",)),
    Case("r-init-output-folder", "init", init_output_folder, mentions=("folder", "pipeline.yaml")),
    Case("r-write-config-full-disk", "model_train", write_config_full_disk, mentions=("/dev/full",), marks=LINUX_ONLY),
    Case("r-init-link-to-full-disk", "init", init_link_to_full_disk, mentions=("pipeline.yaml",), marks=LINUX_ONLY),
    Case("r-pipeline-damaged-record", "run", pipeline_with_damaged_record, mentions=("sizes.json", "delete")),
    Case("r-m6-max-minutes-inf", "model_train", max_minutes_inf, mentions=("max_minutes", "finite")),
    Case("r-init-raw-photos", "init", init_raw_photos, mentions=("no photogrammetry outputs", "odm_runner")),
    Case("r-init-without-dtm", "init", init_without_dtm, "ok", check=heights_left_out),
    Case("r-init-annotations-of-another-flight", "init", init_other_flight, mentions=("other photos", "2019_")),
    Case("r-init-text-as-checkpoint", "init", init_text_as_checkpoint, mentions=("best.pt", "checkpoint")),
]
