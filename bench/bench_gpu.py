"""GPU rows of ``python -m bench --device cuda`` (issue 38), each a whole run printed with its acceptance figures:

- ``train-ceiling``: ResNet-50 FPN's own training speed at the paper's 1024 px on tensors already on the GPU, at
  the batch (8, 16 or 32) that runs fastest, fp32 and at module 6's precision (the model's ceiling), beside module
  6's loop (``train``) at that batch on 1024 px PNG tiles read from disk: the loop's share of the ceiling;
- ``detect-photos``: module 7 (``matchplant model_test`` as a user runs it) on a folder of 20 MP JPEG photos:
  photos/s from the disk to ``predictions.json``, and what 1,000 photos take.

Each records the GPU's utilisation and peak memory (:mod:`bench.gpu_figures`). On a CPU they run at toy sizes (a
check that the code runs; the figures mean nothing there).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import torch

from bench.bench_model_train import copied_tiles, gpu_rates, train_settings
from bench.gpu_figures import GpuMonitor, figures_of
from matchplant.core.runtime.config import load_config
from matchplant.detection.checkpoint import save_checkpoint
from matchplant.detection.data import CocoDetection, collate
from matchplant.detection.device import select_device
from matchplant.detection.model import build_detector
from matchplant.detection.synth import make_photo
from matchplant.model_test.config import ModelTestConfig
from matchplant.model_test.run import run as run_model_test
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.gpu import amp_dtype
from matchplant.model_train.run import train

PAPER = "fasterrcnn_resnet50_fpn"


def sizes(device, quick: bool) -> dict:
    """Tile and photo sizes, batches and counts: the issue's on a GPU, toy ones on a CPU (a check that it runs)."""
    if device.type == "cuda":
        return {"tile": 1024, "tiles": 96 if quick else 256, "batches": (8, 16, 32), "steps": 12, "photo": (5472, 3648),
                "photos": 16 if quick else 48, "detect_tile": 1024, "detect_batch": 0}  # fmt: skip
    return {"tile": 64, "tiles": 8, "batches": (2, 4), "steps": 2, "photo": (320, 240), "photos": 2,
            "detect_tile": 128, "detect_batch": 4}  # fmt: skip


def tile_set(work: Path, size: int, n: int) -> Path:
    """A folder of ``n`` synthetic PNG training tiles of ``size`` px with their train.json."""
    return copied_tiles(work / "tiles", size, n, (size / 32, size / 12))


def on_device_batch(ds: CocoDetection, batch: int, device) -> tuple[list, list]:
    """One batch of the dataset (cycled) moved to the device: images and targets."""
    images, targets = collate([ds[i % len(ds)] for i in range(batch)])
    return (
        [im.to(device) for im in images],
        [{"boxes": t["boxes"].to(device), "labels": t["labels"].to(device)} for t in targets],
    )


def model_alone(cfg, ds: CocoDetection, batch: int, steps: int, device, dtype) -> dict:
    """Images/s of forward + backward + SGD step on one batch already on the device (no loader, no copies)."""
    torch.manual_seed(0)
    model = build_detector(cfg.model, 2).to(device).train()
    opt = torch.optim.SGD(model.parameters(), lr=cfg.lr.backbone, momentum=0.9, weight_decay=5e-4)
    scaler = torch.amp.GradScaler("cuda") if dtype == torch.float16 else None
    images, targets = on_device_batch(ds, batch, device)

    def step():
        with torch.autocast(device_type=device.type, enabled=dtype is not None, dtype=dtype):
            loss = sum(model(images, targets).values())
        opt.zero_grad(set_to_none=True)
        (scaler.scale(loss) if scaler else loss).backward()
        if scaler:
            scaler.step(opt)
            scaler.update()
        else:
            opt.step()

    for _ in range(3):  # warm-up: cuDNN's choices, the allocator
        step()
    with GpuMonitor(device) as m:
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - t0
    return {"batch": batch, "images_per_s": round(batch * steps / seconds, 1), **m.figures()}


def ceiling(cfg, ds: CocoDetection, batches, steps: int, device, dtype) -> dict:
    """The fastest of ``batches`` (one that does not fit the GPU's memory is skipped)."""
    best = None
    for batch in batches:
        try:
            r = model_alone(cfg, ds, batch, steps, device, dtype)
        except torch.OutOfMemoryError:
            break
        finally:
            if device.type == "cuda":
                torch.cuda.empty_cache()
        if best is None or r["images_per_s"] > best["images_per_s"]:
            best = r
    return best


# the settings module 6's loop is timed with, one after another (model_train/gpu.py's MATCHPLANT_GPU): what each of
# the GPU options gives on the same tiles
VARIANTS = (
    ("default (bf16 where supported, fused step)", ""),
    ("fp16 autocast + GradScaler", "bf16=0"),
    ("unfused optimizer step", "fused=0"),
    ("channels_last", "channels_last=1"),
)


def our_loop(work: Path, train_json: Path, batch: int, n_tiles: int, tile: int, device, env: str) -> dict:
    """Module 6's ``train`` for two epochs on the tiles on disk, with ``MATCHPLANT_GPU=env``: images/s of its loop in
    the second (the first pays for cuDNN's choices and the workers' start, once per run)."""
    settings = train_settings(work, train_json, PAPER, tile, tile, 2, batch, device.type)
    settings += gpu_rates(batch, -(-n_tiles // batch))
    cfg = load_config(ModelTrainConfig, None, settings)
    before = os.environ.get("MATCHPLANT_GPU")
    os.environ["MATCHPLANT_GPU"] = env
    try:
        with GpuMonitor(device) as m:
            summary = train(cfg)
    finally:
        os.environ.pop("MATCHPLANT_GPU") if before is None else os.environ.__setitem__("MATCHPLANT_GPU", before)
    return {"images_per_s": summary["history"][-1]["train_images_per_s"], **m.figures()}


def train_ceiling_row(name: str, work: Path, quick: bool, device) -> dict:
    """The ``train-ceiling`` row: the model's fastest training speed beside module 6's loop on files, and its share."""
    z = sizes(device, quick)
    train_json = tile_set(work, z["tile"], z["tiles"])
    probe_batch = z["batches"][0]
    base = train_settings(work, train_json, PAPER, z["tile"], z["tile"], 1, probe_batch, device.type)
    cfg = load_config(ModelTrainConfig, None, [*base, *gpu_rates(probe_batch, 50)])
    ds = CocoDetection(train_json)
    dtype = amp_dtype(device, True)
    top = ceiling(cfg, ds, z["batches"], z["steps"], device, dtype)
    fp32 = model_alone(cfg, ds, top["batch"], z["steps"], device, None)
    loops = {
        label: our_loop(work, train_json, top["batch"], z["tiles"], z["tile"], device, env) for label, env in VARIANTS
    }
    ours = loops[VARIANTS[0][0]]
    share = ours["images_per_s"] / top["images_per_s"]
    row = (
        f"{PAPER} at {z['tile']} px, batch {top['batch']}: the model alone {top['images_per_s']} img/s "
        f"({dtype or 'fp32'}; fp32 {fp32['images_per_s']}), module 6's loop on files {ours['images_per_s']} img/s "
        f"= {100 * share:.0f} % | " + "; ".join(f"{k}: {v['images_per_s']}" for k, v in loops.items())
    )
    return {
        "name": name,
        "row": row,
        "result": {"ceiling": top, "ceiling_fp32": fp32, "ours": loops, "precision": str(dtype or "fp32")},
        "acceptance": figures_of(name, [round(share, 3), top["images_per_s"]]),
    }


def photo_folder(work: Path, size: tuple[int, int], n: int) -> Path:
    """``n`` JPEG photos of ``size`` with synthetic plants (one drawn, copied under new names: writing 20 MP
    photos takes longer than detecting them)."""
    folder = work / "photos"
    folder.mkdir(parents=True, exist_ok=True)
    first = folder / "photo_000.png"
    make_photo(first, size[0], size[1], n_plants=size[0] * size[1] // 40000, radius=(15, 40), seed=2)
    jpeg = cv2.imencode(".jpg", cv2.imread(str(first)), [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()
    first.unlink()
    for i in range(n):
        (folder / f"photo_{i:03d}.jpg").write_bytes(jpeg)
    return folder


def random_checkpoint(work: Path, tile: int) -> Path:
    """ResNet-50 FPN from random weights saved as a module 6 checkpoint (no COCO weights offline), seeing ``tile`` px
    tiles at their own size: every box scores about 0.5, so each tile keeps its 100 best boxes (a dense field: the
    merge's worst case)."""
    settings = ["train_json=x", f"model.architecture={PAPER}", "model.pretrained=none", f"model.min_size={tile}",
                f"model.max_size={tile}"]  # fmt: skip
    cfg = load_config(ModelTrainConfig, None, settings, check_paths=False, strict=False)
    torch.manual_seed(0)
    return save_checkpoint(work / "model.pt", build_detector(cfg.model, 2), cfg.model, ["plant"], [1], epoch=1)


def detect_photos_row(name: str, work: Path, quick: bool, device) -> dict:
    """The ``detect-photos`` row: module 7 on a folder of 20 MP photos, photos per second and the time of 1,000."""
    z = sizes(device, quick)
    folder = photo_folder(work, z["photo"], z["photos"])
    settings = [
        f"checkpoint={random_checkpoint(work, z['detect_tile'])}",
        f"detect.images={folder}",
        f"output_dir={work / 'out'}",
        f"detect.tile_size={z['detect_tile']}",
        f"detect.overlap={z['detect_tile'] // 8}",
        "detect.score_threshold=0.3",
        "detect.drawn_images=0",
        f"device={device.type}",
    ]
    if z["detect_batch"]:
        settings.append(f"batch_size={z['detect_batch']}")
    cfg = load_config(ModelTestConfig, None, settings)
    with GpuMonitor(device) as m:
        t0 = time.perf_counter()
        run_model_test(cfg)
        seconds = time.perf_counter() - t0
    rate = z["photos"] / seconds
    row = (
        f"{z['photos']} JPEG photos of {z['photo'][0]} x {z['photo'][1]} px, {PAPER}, tiles of {z['detect_tile']} "
        f"px: {rate:.2f} photos/s ({seconds:.1f} s with the model's loading), 1,000 photos in "
        f"{1000 / rate / 60:.1f} min"
    )
    return {
        "name": name,
        "row": row,
        "result": {"photos": z["photos"], "seconds": round(seconds, 2), "photos_per_s": round(rate, 2), **m.figures()},
        "acceptance": figures_of(name, [round(rate, 2), round(1000 / rate / 60, 2)]),
    }


def run_row(name: str, work: Path, quick: bool, device: str) -> dict:
    """``python -m bench``'s rows ``train-ceiling`` and ``detect-photos`` (bench/runner.py)."""
    dev = select_device(device)
    row = train_ceiling_row if name == "train-ceiling" else detect_photos_row
    return {**row(name, work, quick, dev), "command": f"python -m bench --device {device} --only {name}"}
