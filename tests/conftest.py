"""Shared fixtures. The synthetic fields are generated once per test session."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from matchplant.detection.synth import make_tiles

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("MATCHPLANT_QUIET", "1")

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA


@pytest.fixture(scope="session")
def tiny_field(tmp_path_factory):
    """The ``tiny`` synthetic field (seed 0): an ODM-shaped project with exact truth. Read-only: copy
    what a test changes."""
    from matchplant.simfield import generate_field
    from matchplant.simfield.layout import FieldPaths

    root = tmp_path_factory.mktemp("tiny_field")
    generate_field(preset="tiny", seed=0, out=root)
    return FieldPaths(root)


@pytest.fixture(scope="module")
def camera_exports(tiny_field, tmp_path_factory):
    """The tiny field's ODM poses written as a Metashape camera export (meta/cameras.xml) and a Pix4D params
    folder (p4d/); returns their folder."""
    from matchplant.core.formats.metashape_writer import write_metashape
    from matchplant.core.formats.odm import ODMProject
    from matchplant.core.formats.pix4d import write_pix4d

    out = tmp_path_factory.mktemp("exports")
    odm = ODMProject(tiny_field.root)
    shots = odm.reconstruction().shots
    (out / "meta").mkdir()
    write_metashape(out / "meta" / "cameras.xml", shots, odm.frame())
    write_pix4d(out / "p4d" / "1_initial" / "params", "demo", shots, odm.frame())
    return out


@pytest.fixture(scope="module")
def train_tiles(tmp_path_factory):
    """Module 6's small training set: 8 training and 4 validation tiles of 64 px with 1-3 plants each."""
    d = tmp_path_factory.mktemp("tiles")
    train_json = make_tiles(
        d, n_images=8, size=64, plants=(1, 3), radius=(5, 9), negatives=1, seed=0, name="train.json"
    )
    val_json = make_tiles(d, n_images=4, size=64, plants=(1, 3), radius=(5, 9), negatives=1, seed=1, name="val.json")
    return train_json, val_json


@pytest.fixture(scope="module")
def torch_one_thread():
    """One torch thread: on a small shared CPU, more threads make small training steps several times slower."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def xvfb_available() -> bool:
    return shutil.which("Xvfb") is not None or shutil.which("xvfb-run") is not None


def run_in_xvfb(code: str, timeout: int = 120) -> subprocess.CompletedProcess:
    """Run Python ``code`` in a real (TkAgg) window on a virtual display; the code must close itself."""
    env = dict(os.environ, MPLBACKEND="TkAgg")
    return subprocess.run(
        ["xvfb-run", "-a", sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=timeout
    )
