"""Module 7's ``detect.cover``: the fewest photos seeing every point k times, checked against brute force and
against the synthetic field's true plant visibility; its estimate logged beside every photo's."""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
import pytest
from scipy import sparse
from small_detector import save_small, small_detector

from matchplant.core.formats.coco import read_dataset
from matchplant.core.formats.predictions import read_predictions
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError
from matchplant.detection.synth import make_photo
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.cover import choose, multi_cover
from matchplant.model_test.inputs import list_images
from matchplant.model_test.run import run
from tests.log_records import log_records, messages


def _demand_met(A: np.ndarray, rows: list[int], k: int) -> bool:
    return bool((A[rows].sum(axis=0) >= np.minimum(k, A.sum(axis=0))).all())


@pytest.mark.parametrize("k", [1, 2, 3])
def test_multi_cover_meets_every_demand_and_is_near_the_brute_force_optimum(k):
    """Random incidences of 9 photos over 40 points: every point held min(k, n) times, no photo removable, and
    at most one photo more than the fewest found by trying every subset (seeded: the same instances each run)."""
    for seed in range(12):
        rng = np.random.default_rng(seed)
        A = rng.random((9, 40)) < 0.35
        A = A[:, A.any(axis=0)]
        chosen = multi_cover(sparse.csr_matrix(A), k)
        assert _demand_met(A, chosen, k)
        for i in chosen:  # irredundant
            assert not _demand_met(A, [j for j in chosen if j != i], k)
        best = next(
            n
            for n in range(1, 10)
            if any(_demand_met(A, list(rows), k) for rows in itertools.combinations(range(9), n))
        )
        assert best <= len(chosen) <= best + 1, (seed, k, best, len(chosen))


@pytest.mark.slow
def test_cover_sees_every_true_plant_k_times(tiny_field):
    """On the tiny field, with its true boxes (which photo sees which plant, from the renderer, independent of the
    footprints): every plant is in min(k, n) of the chosen photos, n the photos that see it at all, for >= 97 %
    of the plants (the rest: plants cut by a photo's border, whose centre point is inside); fewer photos for
    k = 1 than for k = 2."""
    truth = read_dataset(tiny_field.boxes_undistorted, validate=False)
    name_of = {im["id"]: im["file_name"] for im in truth["images"]}
    seen_by: dict[int, set[str]] = {}
    for a in truth["annotations"]:
        seen_by.setdefault(a["plant_id"], set()).add(name_of[a["image_id"]])
    files = list_images(tiny_field.root)
    counts = []
    for k in (1, 2):
        chosen = {p.name for p in choose(files, k, tiny_field.root).files}
        ok = [len(names & chosen) >= min(k, len(names)) for names in seen_by.values()]
        assert np.mean(ok) >= 0.97, (k, np.mean(ok))
        counts.append(len(chosen))
    assert counts[0] < counts[1] <= len(files)  # tiny: 3 x 3 photos, k = 2 needs every one


def test_cover_needs_a_project(tmp_path):
    make_photo(tmp_path / "imgs" / "a.png", 64, 64, n_plants=1, seed=0)
    (tmp_path / "ck.pt").write_bytes(b"")
    with pytest.raises(ConfigError, match="detect.project_dir") as e:
        load_config(
            ModelTestConfig,
            None,
            [f"checkpoint={tmp_path / 'ck.pt'}", f"detect.images={tmp_path / 'imgs'}", "detect.cover=2"],
        )
    assert "detect.cover: 0" in e.value.fix


@pytest.mark.slow
def test_detection_on_the_cover_logs_both_estimates(tiny_field, tmp_path):
    """detect.cover: 1 on the tiny field's project: predictions for the cover's photos only, and the estimate for
    the cover and for every photo logged before detection."""
    ck = save_small(tmp_path / "model.pt", *small_detector())
    cfg = load_config(
        ModelTestConfig,
        None,
        [
            f"checkpoint={ck}",
            f"detect.images={tiny_field.root}",
            f"output_dir={tmp_path / 'out'}",
            "detect.cover=1",
            "detect.tile_size=200",
            "detect.overlap=40",
            "detect.score_threshold=0",
            "detect.drawn_images=0",
            "device=cpu",
        ],
    )
    every = list_images(tiny_field.root)
    cover = choose(every, 1, tiny_field.root)
    with log_records("matchplant.model_test", logging.INFO) as records:
        run(cfg)
    preds = read_predictions(tmp_path / "out" / "predictions.json")
    assert sorted(Path(im["file_name"]).name for im in preds["images"]) == sorted(p.name for p in cover.files)
    assert preds["info"]["cover"] == 1
    line = next(m for m in messages(records) if "the cover's" in m)
    assert f"the cover's {len(cover.files)} photo(s)" in line and f"every one of the {len(every)} photos" in line
