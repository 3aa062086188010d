"""The run guard (matchplant.core.runtime.guard): outputs never over inputs, writable before the step runs, and
outputs whole or not at all."""

from __future__ import annotations

import io
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from matchplant.core.runtime.config import param, section
from matchplant.core.runtime.errors import ConfigError, OutputError
from matchplant.core.runtime.guard import (
    check_outputs,
    check_outputs_are_not_inputs,
    check_writable,
    path_fields,
    staged_outputs,
)
from matchplant.core.runtime.log import get_logger, setup_console


@dataclass
class Band:
    path: Path | None = param(None, "band raster", path="file")


@dataclass
class Rasters:
    dsm: Path | None = param(None, "surface model", path="file")


@dataclass
class StepConfig:
    images: Path | None = param(None, "input folder", path="dir")
    polygons: Path | None = param(None, "input file", path="file")
    annotations: Path | None = param(None, "file or folder", path="exists")
    rasters: Rasters = section(Rasters)
    bands: list[Band] = field(default_factory=list)
    name: str = param("x", "not a path")
    output_dir: Path = param(Path("out"), "output folder", path="out")


@dataclass
class WritesIntoProject:
    """Like ODM: the step writes into its project folder by design."""

    writes_into_inputs = ("output_dir",)
    project_dir: Path | None = param(None, "project", path="dir")
    output_dir: Path | None = param(None, "output", path="out")


@pytest.fixture
def tree(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "a.jpg").write_bytes(b"x")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "plants.gpkg").write_bytes(b"x")
    (tmp_path / "data" / "dsm.tif").write_bytes(b"x")
    return tmp_path


def test_path_fields_walk_sections_and_lists(tree):
    cfg = StepConfig(
        images=tree / "images",
        rasters=Rasters(dsm=tree / "data" / "dsm.tif"),
        bands=[Band(tree / "b1.tif"), Band(None)],
        output_dir=tree / "out",
    )
    assert [(k, kind) for k, _, kind in path_fields(cfg)] == [
        ("images", "dir"),
        ("rasters.dsm", "file"),
        ("bands[0].path", "file"),
        ("output_dir", "out"),
    ]


@pytest.mark.parametrize(
    "settings, words",
    [
        (
            {"polygons": "data/plants.gpkg", "output_dir": "data"},
            ["output folder 'output_dir'", "contains the input 'polygons'"],
        ),
        ({"images": "images", "output_dir": "images"}, ["output 'output_dir' is the same path as input 'images'"]),
        ({"images": "images", "output_dir": "images/out"}, ["inside the input folder 'images'"]),
        ({"annotations": "images", "output_dir": "images/sub/out"}, ["inside the input folder 'annotations'"]),
        ({"rasters": Rasters(dsm="data/dsm.tif"), "output_dir": "data/"}, ["contains the input 'rasters.dsm'"]),
        ({"bands": [Band("data/dsm.tif")], "output_dir": "data/dsm.tif"}, ["same path as input 'bands[0].path'"]),
        ({"images": "images", "output_dir": "images/../images/./"}, ["same path as input 'images'"]),
    ],
)
def test_outputs_over_inputs_are_refused(tree, settings, words):
    def absolute(v):
        if isinstance(v, Rasters):
            return Rasters(dsm=tree / v.dsm)
        if isinstance(v, list):
            return [Band(tree / b.path) for b in v]
        return tree / v

    cfg = StepConfig(**{k: absolute(v) for k, v in settings.items()})
    with pytest.raises(ConfigError) as info:
        check_outputs_are_not_inputs(cfg)
    for w in words:
        assert w in str(info.value)
    assert "fix:" in str(info.value)


def test_outputs_apart_from_inputs_pass(tree):
    cfg = StepConfig(images=tree / "images", polygons=tree / "data" / "plants.gpkg", output_dir=tree / "results")
    check_outputs(cfg)
    # a sibling whose name starts like the input folder is not inside it
    check_outputs(StepConfig(images=tree / "images", output_dir=tree / "images_out"))
    # an output inside the folder of an input *file* (not a folder the step reads) is fine
    check_outputs(StepConfig(polygons=tree / "data" / "plants.gpkg", output_dir=tree / "data" / "stats"))
    # an output folder holding an input folder (gcp_list.txt beside an ODM project's images/) is fine
    check_outputs(StepConfig(images=tree / "images", output_dir=tree))


def test_a_symlink_to_an_input_is_the_input(tree):
    (tree / "link").symlink_to(tree / "images")
    with pytest.raises(ConfigError, match="same path as input 'images'"):
        check_outputs_are_not_inputs(StepConfig(images=tree / "images", output_dir=tree / "link"))


@dataclass
class ReadsAProject:
    """Like module 3: reads fixed files of an ODM project; its outputs may go in a subfolder of it."""

    outputs_inside_inputs = ("project_dir",)
    project_dir: Path | None = param(None, "project", path="dir")
    boundary: Path | None = param(None, "a file", path="file")
    output_dir: Path | None = param(None, "output", path="out")


def test_a_step_may_declare_that_it_writes_into_its_inputs(tree):
    check_outputs(WritesIntoProject(project_dir=tree / "images", output_dir=tree / "images"))
    check_outputs(ReadsAProject(project_dir=tree / "images", output_dir=tree / "images" / "min_images"))
    with pytest.raises(ConfigError, match="same path as input 'project_dir'"):
        check_outputs(ReadsAProject(project_dir=tree / "images", output_dir=tree / "images"))
    with pytest.raises(ConfigError, match="contains the input 'boundary'"):
        check_outputs(
            ReadsAProject(
                project_dir=tree / "images",
                boundary=tree / "images" / "sub" / "aoi.gpkg",
                output_dir=tree / "images" / "sub",
            )
        )


@pytest.mark.skipif(sys.platform == "win32" or os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_output_folder_is_named(tree):
    ro = tree / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="output folder 'output_dir' .* cannot be written"):
            check_outputs(StepConfig(images=tree / "images", output_dir=ro))
        with pytest.raises(OutputError, match="cannot be created in"):
            check_outputs(StepConfig(images=tree / "images", output_dir=ro / "new" / "deeper"))
    finally:
        ro.chmod(0o755)


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc, which not even root can write")
def test_unwritable_folder_is_named_even_for_root():
    with pytest.raises(OutputError) as info:
        check_writable(Path("/proc/matchplant_out/x"), key="output_dir")
    assert "output folder 'output_dir' (/proc/matchplant_out/x) cannot be created in /proc" in str(info.value)
    assert "fix:" in str(info.value)


def test_a_file_in_the_way_of_the_output_folder(tree):
    with pytest.raises(OutputError, match="is a file"):
        check_writable(tree / "data" / "plants.gpkg")
    with pytest.raises(OutputError, match="cannot be created: .*plants.gpkg is a file"):
        check_writable(tree / "data" / "plants.gpkg" / "out")
    check_writable(tree / "new" / "deeper")  # creatable: fine
    assert not (tree / "new").exists()  # and the check leaves nothing behind
    assert sorted(p.name for p in tree.iterdir()) == ["data", "images"]


# -- whole or nothing ----------------------------------------------------------------------------------------


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_staged_outputs_move_into_place_on_success_keeping_other_files(tmp_path):
    out = tmp_path / "out"
    (out / "logs").mkdir(parents=True)
    (out / "logs" / "run_1.log").write_text("old log")
    (out / "report.csv").write_text("old report")
    (out / "keep.txt").write_text("not rewritten")
    with staged_outputs(out) as stage:
        assert stage.parent == tmp_path and stage != out
        (stage / "report.csv").write_text("new report")
        (stage / "images").mkdir()
        (stage / "images" / "a.jpg").write_bytes(b"jpg")
        assert (out / "report.csv").read_text() == "old report"  # nothing visible before success
        assert not (out / "images").exists()
    assert snapshot(out) == {
        "logs/run_1.log": b"old log",
        "report.csv": b"new report",
        "keep.txt": b"not rewritten",
        "images/a.jpg": b"jpg",
    }
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporary folder left


def test_staged_outputs_create_a_new_folder_whole(tmp_path):
    out = tmp_path / "sub" / "out"
    with staged_outputs(out) as stage:
        (stage / "a.txt").write_text("a")
    assert snapshot(out) == {"a.txt": b"a"}
    if sys.platform != "win32":  # made with the usual permissions (umask), not a private temporary folder's
        umask = os.umask(0)
        os.umask(umask)
        assert out.stat().st_mode & 0o777 == 0o777 & ~umask
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["out"]


def test_a_failed_step_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.csv").write_text("old report")
    before = snapshot(out)
    with pytest.raises(RuntimeError):
        with staged_outputs(out) as stage:
            (stage / "report.csv").write_text("half")
            (stage / "new.txt").write_text("half")
            raise RuntimeError("the step failed")
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C too
        with staged_outputs(tmp_path / "fresh") as stage:
            (stage / "x.txt").write_text("half")
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_failure_while_moving_into_place_is_undone(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    for name in ("a.txt", "b.txt", "c.txt"):
        (out / name).write_text(f"old {name}")
    before = snapshot(out)
    real = os.replace
    moved = []

    def flaky(src, dst):
        if Path(dst).parent == out and Path(src).name == "c.txt" and ".partial-" in str(src):
            raise OSError(28, "No space left on device")
        moved.append(dst)
        return real(src, dst)

    monkeypatch.setattr(os, "replace", flaky)
    with pytest.raises(OSError, match="No space left"):
        with staged_outputs(out) as stage:
            for name in ("a.txt", "b.txt", "c.txt"):
                (stage / name).write_text(f"new {name}")
    assert moved  # some files had been moved before the failure: they were put back
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_staged_outputs_refuse_an_unwritable_place(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError):
        with staged_outputs(tmp_path / "file" / "out"):
            pass


def test_messages_during_a_staged_run_name_the_final_folder(tmp_path):
    """A path printed while the step writes must exist after it: the staged ``.partial-...`` folder is gone."""
    out = tmp_path / "8_plants"
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    setup_console()
    get_logger().addHandler(handler)
    try:
        with staged_outputs(out) as stage:
            (stage / "evaluation.png").write_bytes(b"png")
            get_logger("plant_projection").info("figure %s", stage / "evaluation.png")
        get_logger("plant_projection").info("after: %s", stage)  # outside the run: left as it is
    finally:
        get_logger().removeHandler(handler)
    first, second = stream.getvalue().splitlines()
    assert first == f"figure {out / 'evaluation.png'}" and (out / "evaluation.png").is_file()
    assert ".partial-" in second
