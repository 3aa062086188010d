"""Module 7: evaluate a trained detector on test tiles, and detect plants on whole new images.

This file is the step's entry (:func:`run`): every input read and checked, the device and its runtime chosen once
(:func:`~matchplant.detection.gpu.choose_runtime`), the outputs staged, then the evaluation
(:mod:`~matchplant.model_test.evaluation`, the ``evaluate`` section) and/or the detection
(:mod:`~matchplant.model_test.engine`, the ``detect`` section). One photo's tiles, predictor and merge are in
:mod:`~matchplant.model_test.tiles`; the CUDA feed in :mod:`~matchplant.model_test.gpu_feed`.
"""

from __future__ import annotations

from pathlib import Path

from matchplant.core.runtime.guard import staged_outputs
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.manifest import previous_files, remove_stale, write_manifest
from matchplant.detection.device import configure_threads, select_device
from matchplant.detection.distributed import join
from matchplant.detection.gpu import choose_runtime
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.cover import images_to_detect
from matchplant.model_test.engine import detect
from matchplant.model_test.evaluation import evaluate, test_tiles
from matchplant.model_test.inputs import read_model
from matchplant.model_test.scale import with_detect_settings

# tests/test_gpu_paths.py (kept unchanged by issue 44) imports these two from here; they live in tiles.py
from matchplant.model_test.tiles import detect_image, model_predictor

__all__ = ["detect_image", "model_predictor", "run"]

log = get_logger("model_test")


def run(cfg: ModelTestConfig) -> dict:
    """Evaluation and/or detection; every output appears at the end, together (a failed run leaves none).

    Parameters
    ----------
    cfg : ModelTestConfig
        The step's settings (``config.yaml``): ``evaluate.dataset_json`` evaluates, ``detect.images`` detects.

    Returns
    -------
    dict
        ``metrics`` (the evaluation's, as in ``metrics.json``) and/or ``predictions`` (the path of
        ``predictions.json``).
    """
    shard, device = join(select_device(cfg.device))  # under torchrun: this process's share and GPU
    runtime = choose_runtime(device, cfg.amp)  # the device's kind is tested here, once
    if runtime.on_cpu:
        configure_threads(cfg.threads or None)  # the cores free for this process, not every core (issue 29)
    # every input read and checked before the first (slow) model pass
    ck = read_model(cfg)
    cfg = with_detect_settings(cfg, ck)  # a null detect.tile_size / overlap: the checkpoint's training tiles'
    evaluating = cfg.evaluate.dataset_json is not None and shard.main  # under torchrun: evaluated once
    ds = test_tiles(cfg, ck) if evaluating else None
    files, every = images_to_detect(cfg.detect) if cfg.detect.images is not None else (None, None)
    if shard.world > 1:  # every process stages its own files: the folder they move into must exist first
        Path(cfg.output_dir).mkdir(parents=True, exist_ok=True)
    result: dict = {}
    before = previous_files(cfg.output_dir)
    with staged_outputs(cfg.output_dir) as out:
        if evaluating:
            result["metrics"] = evaluate(cfg, runtime, out, ck=ck, ds=ds)
        drawn: list[str] = []  # every process's drawn images
        if files is not None:
            result["predictions"] = detect(cfg, runtime, shard, out, ck=ck, files=files, every=every, listed=drawn)
        now = write_manifest(out, drawn) if shard.main else []
    if shard.main:  # only once the new outputs are in place; the other processes' drawn images are in `now`
        remove_stale(Path(cfg.output_dir), before, now)
    shard.leave()
    return result
