"""Benchmark of modules 6 and 7: training and detection speed, and what a short training reaches.

Measures, on synthetic plant tiles (matchplant.detection.synth):
- training images/s of MatchPlant's loop (``train``: augmentation, per-part SGD, warm-up, AMP on CUDA,
  validation and checkpoints excluded from the timing) against a bare torchvision loop (same model,
  same data, plain forward/backward/step): the overhead of our loop;
- detection tiles/s of module 7's tiled detection on a large photo (tiling, batching, merging)
  against calling the bare model on the same tiles;
- the validation AP50 the run reaches on its held-out tiles (a learning check; random initial weights,
  since no pretrained weights are downloaded here).

    python -m bench.bench_model_train --quick            # a minute or two on a CPU
    python -m bench.bench_model_train                    # the stated CPU run (README of 6_model_train)
    python -m bench.bench_model_train --device cuda --arch fasterrcnn_resnet50_fpn --size 512 --tiles 200

The alternating, pinned comparisons (docs/benchmarks.md's rows) are ``python -m bench --only train`` and
``--only detect`` (:func:`comparison`; ``--device cuda`` for the GPU figures).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from bench.gpu_figures import GpuMonitor
from matchplant.core.formats.images import read_rgb8
from matchplant.core.runtime.config import load_config
from matchplant.detection.architectures import get_architecture
from matchplant.detection.checkpoint import load_detector
from matchplant.detection.data import CocoDetection, collate
from matchplant.detection.device import select_device
from matchplant.detection.model import build_detector
from matchplant.detection.synth import make_photo, make_tiles
from matchplant.model_test.tiles import detect_image, model_predictor, tile_starts
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.gpu import amp_dtype
from matchplant.model_train.run import train

os.environ.setdefault("MATCHPLANT_QUIET", "1")


def gpu_rates(batch: int, iters: int) -> list[str]:
    """On a GPU: the torchvision reference's 0.02 for 16 images scaled linearly to ``batch`` (0.02 at batch 2
    made ResNet-50 FPN's loss nan), warmed up over half the run (at most 50 iterations) so that it fits."""
    lr = 0.02 * batch / 16
    return [
        *(f"lr.{part}={lr:g}" for part in ("backbone", "fpn", "rpn", "roi_heads")),
        f"warmup_iters={gpu_warmup(iters)}",
    ]


def gpu_warmup(iters: int) -> int:
    """Warm-up iterations of a GPU run: half the timed iterations, 1 to 50."""
    return max(1, min(50, iters // 2))


DISTINCT_TILES = 32  # drawn; the rest are copies under other names (drawing a 1024 px tile takes most of a second)


def copied_tiles(folder: Path, size: int, n: int, radius: tuple[float, float]) -> Path:
    """``n`` PNG tiles of ``size`` px with their COCO JSON (``train.json``): :data:`DISTINCT_TILES` drawn, copied
    under new names (each file is read and decoded as its own tile: the loader's work is that of ``n`` tiles)."""
    path = make_tiles(folder, n_images=min(n, DISTINCT_TILES), size=size, radius=radius, negatives=1, seed=0,
                      name="train.json")  # fmt: skip
    data = json.loads(path.read_text())
    images, anns = list(data["images"]), list(data["annotations"])
    for k in range(len(images), n):
        src = images[k % len(images)]
        name = f"images/copy_{k:05d}.png"
        shutil.copyfile(path.parent / src["file_name"], path.parent / name)
        data["images"].append({**src, "id": k + 1, "file_name": name})
        copies = [a for a in anns if a["image_id"] == src["id"]]
        start = len(data["annotations"])
        data["annotations"] += [{**a, "id": start + j + 1, "image_id": k + 1} for j, a in enumerate(copies)]
    path.write_text(json.dumps(data))
    return path


def train_settings(
    work: Path, train_json: Path, arch: str, size: int, net: int, epochs: int, batch: int, device: str
) -> list[str]:
    """The benchmark's training settings (small anchors for small synthetic plants, no checkpoints kept)."""
    anchors = [int(net / 8), int(net / 4), int(net / 2)]
    levels = get_architecture(arch).anchors.levels
    return [
        f"train_json={train_json}",
        f"output_dir={work / 'run'}",
        f"model.architecture={arch}",
        "model.pretrained=none",
        f"model.min_size={net}",
        f"model.max_size={net}",
        f"model.anchor_sizes={json.dumps([anchors] * levels)}",
        "model.roi.batch_size_per_image=128",
        "model.rpn.pre_nms_top_n_train=500",
        "model.rpn.post_nms_top_n_train=500",
        "model.rpn.pre_nms_top_n_test=500",
        "model.rpn.post_nms_top_n_test=500",
        f"epochs={epochs}",
        f"batch_size={batch}",
        "num_workers=0",
        "warmup_iters=20",
        "lr.backbone=0.02",
        "lr.fpn=0.02",
        "lr.rpn=0.02",
        "lr.roi_heads=0.02",
        "save_every=0",
        f"device={device}",
    ]


def bare_step(model, opt, images, targets, device, dtype=None, scaler=None) -> int:
    """One step of the bare torchvision training loop (module 6's peer); returns the images it used. ``dtype``:
    autocast at that precision (on a GPU the peer runs at ours: bf16, or fp16 with ``scaler``)."""
    images = [im.to(device) for im in images]
    targets = [{"boxes": t["boxes"].to(device), "labels": t["labels"].to(device)} for t in targets]
    with torch.autocast(device_type=device.type, enabled=dtype is not None, dtype=dtype):
        loss = sum(model(images, targets).values())
    opt.zero_grad()
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
    else:
        loss.backward()
        opt.step()
    return len(images)


def bare_loop(cfg, train_json: Path, device, epochs: int) -> float:
    """The plain torchvision loop on the same model and data: forward, backward, step (on a GPU at our precision,
    learning rate and warm-up; its DataLoader as torchvision's reference sets it: 4 workers, pinned). Returns the
    seconds of its epoch loop (data loading included, model building excluded, as ours)."""
    torch.manual_seed(cfg.seed)
    ds = CocoDetection(train_json)
    gpu = device.type == "cuda"
    feed = {"num_workers": 4, "pin_memory": True} if gpu else {}
    loader = torch.utils.data.DataLoader(ds, batch_size=cfg.batch_size, shuffle=True, collate_fn=collate, **feed)
    model = build_detector(cfg.model, 2).to(device).train()
    opt = torch.optim.SGD(model.parameters(), lr=cfg.lr.backbone if gpu else 0.01, momentum=0.9, weight_decay=5e-4)
    warm = torch.optim.lr_scheduler.LambdaLR(opt, lambda it: min(1.0, (it + 1) / max(cfg.warmup_iters or 1, 1)))
    dtype = amp_dtype(device, cfg.amp)
    scaler = torch.amp.GradScaler("cuda") if dtype == torch.float16 else None
    t0 = time.perf_counter()
    for _ in range(epochs):
        for images, targets in loader:
            bare_step(model, opt, images, targets, device, dtype, scaler)
            if gpu:
                warm.step()
    if gpu:
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def comparison(name: str, work: Path, quick: bool, device: str):
    """For ``python -m bench``: ``train`` (our training loop vs :func:`bare_loop`, same model, data
    and steps) or ``detect`` (module 7's tiled detection vs the bare model on the same tiles).

    CPU: MobileNetV3-FPN, 48 tiles of 128 px seen at 320 px, batch 4, 1 epoch (quick: 24 of 96 px).
    CUDA: ResNet-50 FPN at 800 px (the torchvision reference recipe's size), batch 2; detection on a
    20 MP photo."""
    import shutil

    from bench.harness import Comparison

    dev = select_device(device)
    if dev.type == "cuda":
        arch, s, scale, n_tiles, batch = "fasterrcnn_resnet50_fpn", 800, 1.0, (16 if quick else 64), 2
        photo_w, photo_h = (2736, 1824) if quick else (5472, 3648)
    else:
        arch, s, scale, batch = "fasterrcnn_mobilenet_v3_large_fpn", (96 if quick else 128), 2.5, 4
        n_tiles = 24 if quick else 48
        photo_w, photo_h = (4 * s, 3 * s) if quick else (8 * s, 6 * s)
    radius = (s / 16, s / 8)
    if dev.type == "cuda":  # drawing 800 px tiles takes most of a second each: a few drawn, the rest copies
        train_json = copied_tiles(work / "data", s, n_tiles, radius)
    else:
        train_json = make_tiles(
            work / "data",
            n_images=n_tiles,
            size=s,
            radius=radius,
            negatives=max(1, n_tiles // 12),
            seed=0,
            name="train.json",
        )
    net = int(round(s * scale))
    settings = train_settings(work, train_json, arch, s, net, 1, batch, device)
    if dev.type == "cuda":
        settings += gpu_rates(batch, -(-n_tiles // batch))
    cfg = load_config(ModelTrainConfig, None, settings)
    notes = {
        "architecture": arch,
        "tile": s,
        "network_input": net,
        "tiles": n_tiles,
        "batch": batch,
        "device": str(dev),
        "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
        "precision": str(amp_dtype(dev, cfg.amp) or "fp32"),
        "lr": cfg.lr.backbone,
        "warmup_iters": cfg.warmup_iters,
    }
    if name == "train":

        def reset(side: str):
            shutil.rmtree(work / "run", ignore_errors=True)

        def ours() -> float:
            with GpuMonitor(dev) as m:
                summary = train(cfg)
            notes["ours_gpu"] = m.figures()
            return float(sum(h["train_time_s"] for h in summary["history"]))

        def peer() -> float:
            with GpuMonitor(dev) as m:
                seconds = bare_loop(cfg, train_json, dev, 1)
            notes["peer_gpu"] = m.figures()
            return seconds

        return Comparison(
            name,
            f"1 epoch, {n_tiles} tiles of {s} px at {net} px, {arch}, batch {batch}, {notes['precision']}",
            "matchplant train",
            "bare torchvision loop",
            ours,
            peer,
            reset=reset,
            items=n_tiles,
            unit="images",
            notes=notes,
        )
    train(cfg)  # a model that has seen the plants, for realistic detections
    det_model, _ = load_detector(work / "run" / "checkpoints" / "last.pt", dev)
    det_model.roi_heads.score_thresh = 0.5
    photo = work / "photo.png"
    make_photo(photo, photo_w, photo_h, n_plants=photo_w * photo_h // (s * s) * 3, radius=radius, seed=2)
    img = read_rgb8(photo)
    overlap = s // 4
    starts = [(x, y) for y in tile_starts(photo_h, s, overlap) for x in tile_starts(photo_w, s, overlap)]
    predictor = model_predictor(det_model, dev, amp=True)

    def ours():
        with GpuMonitor(dev) as m:
            detect_image(img, predictor, tile_size=s, overlap=overlap, batch_size=batch)
        notes["ours_gpu"] = m.figures()

    def bare():
        with GpuMonitor(dev) as m, torch.inference_mode():
            for i in range(0, len(starts), batch):
                b = [
                    torch.from_numpy(img[y : y + s, x : x + s]).to(dev).permute(2, 0, 1).float().div(255)
                    for x, y in starts[i : i + batch]
                ]
                out = det_model(b)
            if dev.type == "cuda":
                torch.cuda.synchronize()
        notes["peer_gpu"] = m.figures()
        return out

    return Comparison(
        name,
        f"{photo_w} x {photo_h} photo, {len(starts)} tiles of {s} px, batch {batch}, {arch}",
        "matchplant detect_image",
        "bare model on the tiles",
        ours,
        bare,
        items=len(starts),
        unit="tiles",
        notes=notes,
    )


def main() -> None:
    """Parse the options, time module 6's training and module 7's detection against bare torchvision loops; print."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, a short run")
    ap.add_argument("--arch", default="fasterrcnn_mobilenet_v3_large_fpn")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--tiles", type=int, default=48, help="training tiles (a quarter as many for validation)")
    ap.add_argument("--size", type=int, default=128, help="tile side in pixels")
    ap.add_argument("--epochs", type=int, default=15)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument(
        "--scale",
        type=float,
        default=2.5,
        help="tiles are enlarged this much for the network "
        "(MobileNetV3-FPN sees at stride 16 and 32: small plants need it; model.min_size = scale x size)",
    )
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch's default)")
    ap.add_argument("--out", type=Path, default=None, help="keep the run here (default: a temporary folder)")
    args = ap.parse_args()
    if args.quick:
        args.tiles, args.size, args.epochs = 16, 96, 2

    if args.threads:
        torch.set_num_threads(args.threads)

    device = select_device(args.device)
    tmp = tempfile.TemporaryDirectory()
    work = args.out or Path(tmp.name)
    s = args.size
    radius = (s / 16, s / 8)
    train_json = make_tiles(
        work / "data",
        n_images=args.tiles,
        size=s,
        radius=radius,
        negatives=max(1, args.tiles // 12),
        seed=0,
        name="train.json",
    )
    val_json = make_tiles(
        work / "data", n_images=max(4, args.tiles // 4), size=s, radius=radius, negatives=1, seed=1, name="val.json"
    )
    net = int(round(s * args.scale))  # anchors are in the network's (resized) pixels
    settings = [
        *train_settings(work, train_json, args.arch, s, net, args.epochs, args.batch, args.device),
        f"val_json={val_json}",
        f"step_size={max(args.epochs - 3, 1)}",
    ]
    cfg = load_config(ModelTrainConfig, None, settings)
    t0 = time.perf_counter()
    summary = train(cfg)
    wall = time.perf_counter() - t0
    ours_ips = float(np.median([h["train_images_per_s"] for h in summary["history"]]))
    best = summary["best"]

    # the bare torchvision loop: same model settings and data, no augmentation, no extras
    ds = CocoDetection(train_json)
    loader = torch.utils.data.DataLoader(ds, batch_size=args.batch, shuffle=True, collate_fn=collate)
    model = build_detector(cfg.model, 2).to(device).train()
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9, weight_decay=5e-4)
    n, t0 = 0, time.perf_counter()
    for images, targets in loader:
        n += bare_step(model, opt, images, targets, device)
    if device.type == "cuda":
        torch.cuda.synchronize()
    bare_ips = n / (time.perf_counter() - t0)

    # detection: module 7's tiled detection on a large photo against the bare model on the same tiles
    photo_w, photo_h = (4 * s, 3 * s) if args.quick else (8 * s, 6 * s)
    photo = work / "photo.png"
    make_photo(photo, photo_w, photo_h, n_plants=photo_w * photo_h // (s * s) * 3, radius=radius, seed=2)
    img = read_rgb8(photo)
    det_model, _ = load_detector(work / "run" / "checkpoints" / "best.pt", device)
    det_model.roi_heads.score_thresh = 0.5
    overlap = s // 4
    n_tiles = len(tile_starts(photo_w, s, overlap)) * len(tile_starts(photo_h, s, overlap))
    predictor = model_predictor(det_model, device, amp=True)
    detect_image(img, predictor, tile_size=s, overlap=overlap, batch_size=args.batch)  # warm-up
    t0 = time.perf_counter()
    boxes, _, _ = detect_image(img, predictor, tile_size=s, overlap=overlap, batch_size=args.batch)
    ours_tps = n_tiles / (time.perf_counter() - t0)
    tiles = [
        img[y : y + s, x : x + s] for y in tile_starts(photo_h, s, overlap) for x in tile_starts(photo_w, s, overlap)
    ]
    batches = [
        [torch.from_numpy(t).permute(2, 0, 1).float().div(255).to(device) for t in tiles[i : i + args.batch]]
        for i in range(0, len(tiles), args.batch)
    ]
    t0 = time.perf_counter()
    with torch.inference_mode():
        for b in batches:
            det_model(b)
    if device.type == "cuda":
        torch.cuda.synchronize()
    bare_tps = n_tiles / (time.perf_counter() - t0)

    result = {
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "architecture": args.arch,
        "tiles": {"train": args.tiles, "val": max(4, args.tiles // 4), "size": s},
        "epochs": args.epochs,
        "batch": args.batch,
        "train_wall_s": round(wall, 1),
        "best_val": {"epoch": best["epoch"], best.get("metric", "AP50"): best["value"]},
        "final_val": summary["history"][-1].get("val"),
        "train_images_per_s": {
            "matchplant": round(ours_ips, 2),
            "bare_torchvision": round(bare_ips, 2),
            "ratio": round(ours_ips / bare_ips, 3),
        },
        "detect_tiles_per_s": {
            "matchplant_tiled": round(ours_tps, 2),
            "bare_model": round(bare_tps, 2),
            "ratio": round(ours_tps / bare_tps, 3),
            "photo": [photo_w, photo_h],
            "tiles": n_tiles,
            "boxes_found": int(len(boxes)),
        },
        "settings": settings[3:],
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
