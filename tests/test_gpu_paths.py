"""The GPU paths of modules 6 and 7 (issue 38), checked on a CPU: what can be decided or computed without a GPU is
compared against the CPU path or a direct computation (the speed itself needs a GPU: python -m bench --device cuda).
"""

from __future__ import annotations

import random
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from matchplant.core.runtime.errors import MatchPlantError
from matchplant.detection.gpu import GpuOptions, amp_dtype
from matchplant.model_test import gpu_feed
from matchplant.model_test.gpu_feed import DevicePredictor, decoded, detect_batch
from matchplant.model_test.run import detect_image, model_predictor
from matchplant.model_train.engine import LossTally
from matchplant.model_train.gpu import READ_EVERY, fused_ok, loader_settings

CPU = torch.device("cpu")
FAKE_CUDA = SimpleNamespace(type="cuda", index=0)


class TileModel(torch.nn.Module):
    """Stands in for a detector: one box per tile, placed and scored from the tile's pixels, so that a tile cut
    from the wrong place gives other boxes."""

    def forward(self, images):
        out = []
        for im in images:
            m = im.mean(dim=0)
            y, x = divmod(int(torch.argmax(m)), m.shape[1])
            out.append(
                {
                    "boxes": torch.tensor([[x, y, x + 5.0, y + 5.0]]),
                    "scores": torch.tensor([float(m.max())]),
                    "labels": torch.tensor([1]),
                }
            )
        return out


def test_tiles_cut_from_the_photo_on_the_device_are_the_tiles_of_the_cpu_path():
    rng = np.random.default_rng(0)
    photo = rng.integers(0, 255, (300, 410, 3), dtype=np.uint8)
    model = TileModel()
    on_device = DevicePredictor(model, CPU, amp=False, dtype=None)
    on_device.use(photo)
    kw = dict(tile_size=128, overlap=32, batch_size=3, score_threshold=0.0)
    expected = detect_image(photo, model_predictor(model, CPU), **kw)
    got = detect_image(photo, on_device, **kw)
    for a, b in zip(expected, got):
        np.testing.assert_array_equal(a, b)
    assert on_device._place(photo[64:192, 96:224]) == (64, 96)
    assert on_device._place(np.ascontiguousarray(photo[:10, :10])) is None  # a copy: sent on its own
    copy = np.ascontiguousarray(photo[5:133, 7:135])
    np.testing.assert_array_equal(on_device._tensor(copy).permute(1, 2, 0).numpy(), copy)


def test_two_photos_in_flight_give_each_photo_its_own_boxes_in_order(tmp_path):
    """The CUDA path's threads (here on the CPU): each thread's photo stays its own (the predictor keeps one per
    thread), the results come in order and equal the one-after-another path's, counts included."""
    rng = np.random.default_rng(2)
    photos = [rng.integers(0, 255, (200 + 37 * k, 260, 3), dtype=np.uint8) for k in range(7)]
    files = list(range(len(photos)))
    model = TileModel()

    def detect(img, pred, counts):
        return detect_image(img, pred, tile_size=96, overlap=16, batch_size=2, score_threshold=0.0, counts=counts)

    def run(predictor, threads):
        found = gpu_feed.detections(files, photos, CPU, predictor, detect, threads=threads, read=lambda photo: photo)
        return [(i, boxes.tolist(), scores.tolist(), counts) for i, _, (boxes, scores, _), counts in found]

    sequential = run(model_predictor(model, CPU), 0)  # the "files" are the arrays themselves
    threaded = run(DevicePredictor(model, CPU, amp=False, dtype=None), 3)
    assert [r[0] for r in threaded] == files and threaded == sequential


def test_photos_decoded_ahead_come_in_order_and_each_once():
    files = [f"photo_{i}" for i in range(11)]
    threads = set()

    def read(name):
        threads.add(threading.current_thread().name)
        time.sleep(random.uniform(0, 0.01))  # out-of-order completion
        return name.upper()

    got = list(decoded(range(len(files)), files, FAKE_CUDA, read=read))
    assert got == [(i, f.upper()) for i, f in enumerate(files)]
    assert all(t.startswith("decode") for t in threads)
    threads.clear()
    assert list(decoded([2, 5], files, CPU, read=read)) == [(2, "PHOTO_2"), (5, "PHOTO_5")]
    assert threads == {threading.current_thread().name}  # on a CPU: in order, in this thread, as before


def test_batch_from_free_memory_only_on_cuda_at_the_default(monkeypatch):
    paper = {"min_size": 1024, "max_size": 1024}
    assert gpu_feed.DEFAULT_BATCH == 4
    assert detect_batch(4, CPU, 1024, paper) == 4
    assert detect_batch(6, FAKE_CUDA, 1024, paper) == 6  # set by the user: kept
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (8 * 2**30, 80 * 2**30))
    per_tile = gpu_feed.BYTES_PER_INPUT_PIXEL * 1024 * 1024
    assert detect_batch(4, FAKE_CUDA, 1024, paper) == int(0.5 * 8 * 2**30 // per_tile)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (140 * 2**30, 140 * 2**30))
    assert detect_batch(4, FAKE_CUDA, 1024, paper) == gpu_feed.MAX_BATCH


def test_losses_summed_on_the_device_equal_the_per_step_sums_and_are_checked():
    rng = np.random.default_rng(1)
    steps = [rng.uniform(0, 2, 3) for _ in range(2 * READ_EVERY + 7)]
    names = ("a", "b", "loss")
    on_host, deferred = {}, {}
    host, dev = LossTally(on_host, "x"), LossTally(deferred, "x")
    shown = [host.add(names, list(map(float, v))) for v in steps]
    reads = [dev.add(names, torch.tensor(v, dtype=torch.float64)) for v in steps]
    dev.flush()
    assert all(shown) and sum(reads) == 2  # on the device: read every READ_EVERY steps, and at the end
    for k in names:
        assert deferred[k] == pytest.approx(on_host[k], rel=1e-12)
    bad = LossTally({}, "epoch 3/30")
    bad.add(names, torch.tensor([0.1, 0.2, 0.3]))
    bad.add(names, torch.tensor([0.1, float("nan"), float("nan")]))
    with pytest.raises(MatchPlantError, match="the training loss became nan .epoch 3/30."):
        bad.flush()


def test_workers_kept_across_epochs_augment_each_epoch_as_the_seeded_dataset(train_tiles):
    """Persistent workers (CUDA) get the epoch's seed with each index: the tiles they make equal those of the
    dataset seeded in the main process (the CPU path, and what resume repeats)."""
    from matchplant.detection.data import AugmentConfig, CocoDetection, EpochSampler

    ds = CocoDetection(train_tiles[0], augment=AugmentConfig())
    sampler = EpochSampler(len(ds), seed=3)
    for epoch in (0, 1):
        ds.set_seed(100003 * 3 + epoch)
        sampler.set_epoch(epoch)
        plain = [ds[i] for i in sampler]
        sampler.item_seed = 100003 * 3 + epoch
        ds.set_seed(None)  # as a worker forked before the epoch: only the index's seed
        carried = [ds[k] for k in sampler]
        sampler.item_seed = None
        for (a, ta), (b, tb) in zip(plain, carried):
            assert torch.equal(a, b) and torch.equal(ta["boxes"], tb["boxes"])
    # not vacuous: the augmentation does depend on the seed
    assert any(not torch.equal(ds[(i, 1)][0], ds[(i, 2)][0]) for i in range(len(ds)))


def test_gpu_settings_apply_on_cuda_only_and_follow_the_switches(monkeypatch):
    assert loader_settings(2, CPU) == {"num_workers": 2, "pin_memory": False}
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: set(range(16)), raising=False)
    feed = loader_settings(2, FAKE_CUDA)
    assert feed["num_workers"] == 8 and feed["pin_memory"] and feed["prefetch_factor"] == 4
    assert feed["persistent_workers"]
    assert amp_dtype(CPU, True) is None and not fused_ok([torch.zeros(1)], CPU)
    monkeypatch.setenv("MATCHPLANT_GPU", "bf16=0,channels_last=1,unknown=1")
    assert GpuOptions.from_env() == GpuOptions(bf16=False, fused=True, channels_last=True, compile=False)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda: True)
    assert amp_dtype(FAKE_CUDA, True) == torch.float16  # bf16 switched off
    monkeypatch.setenv("MATCHPLANT_GPU", "")
    assert amp_dtype(FAKE_CUDA, True) == torch.bfloat16 and amp_dtype(FAKE_CUDA, False) is None


class GpuLikePredictor:
    """Stands in for a GPU: a pass costs a fixed launch time plus a little per tile, and the first pass at each
    batch size costs more (memory and kernel choices); returns one box per tile."""

    def __init__(self, launch=0.05, per_tile=0.002, first=0.3):
        self.launch, self.per_tile, self.first, self.seen, self.calls = launch, per_tile, first, set(), []

    def __call__(self, tiles):
        self.calls.append(len(tiles))
        cold = self.first if len(tiles) not in self.seen else 0.0
        self.seen.add(len(tiles))
        time.sleep(cold + self.launch + self.per_tile * len(tiles))
        return [(np.zeros((1, 4)), np.ones(1), np.ones(1, int))] * len(tiles)


def test_the_detection_estimate_times_the_batch_the_gpu_will_run():
    """On a GPU the estimate's probe runs the run's batch, warm: its seconds per tile are the run's, where one cold
    tile overstated them (here 0.35 s for a tile that costs 0.0083 s in a batch of 8, 40x)."""
    from matchplant.model_test.estimate import input_pixels, probe

    image = np.zeros((600, 900, 3), np.uint8)
    config = {"min_size": 256, "max_size": 1333}
    mp = input_pixels(256, 256, 256, 1333) / 1e6
    gpu = GpuLikePredictor()
    per_tile = probe(gpu, image, 256, config, batch=8) * mp
    assert gpu.calls == [8, 8]  # an untimed pass, then the timed one
    run_s = (gpu.launch + gpu.per_tile * 8) / 8  # what each tile of the run's warm batches of 8 costs
    assert per_tile == pytest.approx(run_s, rel=0.5)
    cpu = GpuLikePredictor(first=0.0)  # a CPU: one pass of one tile, as before
    assert probe(cpu, image, 256, config) * mp == pytest.approx(cpu.launch + cpu.per_tile, rel=0.5)
    assert cpu.calls == [1]
