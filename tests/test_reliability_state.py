"""Issue 47, the project's own state: a season folder that is moved or renamed keeps its finished steps and its
interrupted training (fingerprints relative to the season), and a file is deleted only when this run or an earlier
run's recorded setting created it for deletion (``save_every: auto`` removed an ``epoch_001.pt`` that a
``save_every: 1`` session had kept)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest

import matchplant.model_train.checkpoint as ck
from matchplant.pipeline import PipelineConfig, run_pipeline
from matchplant.pipeline.plan import plan_pipeline
from matchplant.pipeline.read import read_pipeline
from matchplant.pipeline.run import _fingerprint


def season(root: Path) -> Path:
    """A season folder: a pipeline of one quick step (module inspect) and its annotations, all inside it."""
    root.mkdir(parents=True)
    (root / "boxes.json").write_text(
        json.dumps(
            {
                "images": [{"id": 1, "file_name": "a.jpg", "width": 400, "height": 400}],
                "annotations": [
                    {"id": i, "image_id": 1, "category_id": 1, "bbox": [10 * i, 10, 20, 20]} for i in range(1, 6)
                ],
                "categories": [{"id": 1, "name": "plant"}],
            }
        )
    )
    path = root / "pipeline.yaml"
    path.write_text(
        "output_dir: out\nsteps:\n  - name: sizes\n    module: inspect\n    config: {annotations: boxes.json}\n",
        encoding="utf-8",
    )
    return path


@pytest.mark.parametrize("how", ["renamed", "moved"])
def test_a_moved_or_renamed_season_keeps_its_finished_steps(how, tmp_path):
    path = season(tmp_path / "2026")
    assert run_pipeline(PipelineConfig(pipeline=path)) == {"sizes": "ran"}
    dst = tmp_path / "2026-maize" if how == "renamed" else tmp_path / "archive" / "seasons" / "2026"
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(path.parent), str(dst))
    assert run_pipeline(PipelineConfig(pipeline=dst / "pipeline.yaml")) == {"sizes": "up to date"}


def test_the_fingerprint_still_changes_with_the_settings_and_the_inputs(tmp_path):
    path = season(tmp_path / "s")
    first = _fingerprints(path)
    (path.parent / "boxes.json").write_text((path.parent / "boxes.json").read_text() + " ")
    assert _fingerprints(path) != first


def _fingerprints(path: Path) -> list[str]:
    top, steps = read_pipeline(path)
    return [_fingerprint(p.cfg, path.parent.resolve()) for p in plan_pipeline(path, top, steps)]


# --------------------------------------------------------------------------------------------------
# deleting only what was created for deletion


@pytest.fixture
def fake_save(monkeypatch):
    """The real save writes a detector; the names of the files are what is checked here."""

    def save(job, state, name, epoch_done, record, partial):
        (job.ck_dir / name).write_bytes(b"x" * 100)

    monkeypatch.setattr(ck, "save", save)


def session(ck_dir: Path, save_every, minutes: float) -> SimpleNamespace:
    ck_dir.mkdir(parents=True, exist_ok=True)
    return SimpleNamespace(
        cfg=SimpleNamespace(save_every=save_every),
        budget=SimpleNamespace(limited=bool(minutes)),
        ck_dir=ck_dir,
        extras={},
    )


def epochs(job, first: int, last: int) -> list[str]:
    for epoch in range(first, last + 1):
        ck.save_numbered(job, None, epoch, {})
    return sorted(p.name for p in job.ck_dir.iterdir() if p.suffix == ".pt")


def test_auto_on_resume_keeps_what_an_earlier_session_kept(tmp_path, fake_save):
    """The issue's case: a first session with save_every: 1, resumed with a budget and save_every: auto."""
    folder = tmp_path / "checkpoints"
    assert epochs(session(folder, 1, 15), 1, 2) == ["epoch_001.pt", "epoch_002.pt"]
    kept = epochs(session(folder, "auto", 15), 3, 30)
    assert kept == ["epoch_001.pt", "epoch_002.pt", "epoch_020.pt", "epoch_025.pt", "epoch_030.pt"]


def test_auto_deletes_what_an_earlier_auto_session_wrote(tmp_path, fake_save):
    folder = tmp_path / "checkpoints"
    epochs(session(folder, "auto", 15), 1, 12)  # epoch_005, epoch_010: auto's, recorded
    kept = epochs(session(folder, "auto", 15), 13, 25)
    assert kept == ["epoch_015.pt", "epoch_020.pt", "epoch_025.pt"]


def test_a_users_file_of_the_same_name_pattern_is_never_deleted(tmp_path, fake_save):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    (folder / "epoch_000.pt").write_bytes(b"mine")
    assert "epoch_000.pt" in epochs(session(folder, "auto", 15), 1, 40)


def test_a_damaged_record_of_deletable_files_is_named(tmp_path, fake_save):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    (folder / ck.AUTO_RECORD).write_text('{"files": ["epoch_0')
    with pytest.raises(Exception) as info:
        epochs(session(folder, "auto", 15), 1, 5)
    assert ck.AUTO_RECORD in str(info.value) and "delete it" in str(info.value)
