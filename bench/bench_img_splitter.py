"""Tiling throughput of module 5 against SAHI's ``slice_coco`` on the same images and settings.

    python bench/bench_img_splitter.py            # 50 photos of 4000 x 3000 (JPEG), tile 1024, overlap 100
    python bench/bench_img_splitter.py --quick    # 6 photos of 2000 x 1500

Both write lossless PNG tiles and keep every tile (negatives included) with the same box threshold
(0.3 of a box's area). SAHI (``pip install sahi``) is a benchmark-only dependency; without it only
MatchPlant is timed. Prints tiles per second for MatchPlant with one process (as SAHI), with all
cores, and SAHI, and the ratios. ``python -m bench --only tiling`` is the alternating, pinned
comparison (one process each; :func:`comparison`).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset
from matchplant.core.runtime.config import load_config
from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.run import run


def make_photos(folder: Path, n: int, width: int, height: int, boxes_per_image: int = 150) -> Path:
    """Field-like JPEGs (soil texture and green plants) and a COCO file of their plant boxes."""
    folder.mkdir(parents=True, exist_ok=True)
    ds = new_dataset(["plant"])
    rng = np.random.default_rng(0)
    aid = 1
    for i in range(n):
        low = cv2.resize(rng.uniform(0, 1, (height // 40, width // 40)).astype(np.float32), (width, height))
        soil = (
            (np.stack([90 + 40 * low, 70 + 30 * low, 50 + 20 * low], axis=2) + rng.normal(0, 6, (height, width, 1)))
            .clip(0, 255)
            .astype(np.uint8)
        )
        ds["images"].append({"id": i + 1, "file_name": f"photo_{i:03d}.jpg", "width": width, "height": height})
        for _ in range(boxes_per_image):
            w, h = rng.uniform(40, 160, 2)
            x, y = rng.uniform(0, width - w), rng.uniform(0, height - h)
            cv2.ellipse(
                soil,
                (int(x + w / 2), int(y + h / 2)),
                (int(w / 2), int(h / 2)),
                0,
                0,
                360,
                (40, int(rng.uniform(110, 170)), 40),
                -1,
            )
            ds["annotations"].append(make_annotation(aid, i + 1, [x, y, w, h]))
            aid += 1
        cv2.imwrite(str(folder / f"photo_{i:03d}.jpg"), soil, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return write_dataset(folder.parent / "annotations.json", ds)


def time_matchplant(images: Path, ann: Path, out: Path, tile: int, overlap: int, workers: int) -> tuple[float, int]:
    """Time module 5 on the images and annotations; the seconds and the tiles written."""
    cfg = load_config(
        ImgSplitterConfig,
        None,
        [
            f"images={images}",
            f"annotations={ann}",
            f"output_dir={out}",
            f"tile_size={tile}",
            f"overlap={overlap}",
            "min_visible=0.3",
            "min_box_side=0",
            "negative_share=1",
            "tile_format=png",
            f"workers={workers}",
            "split=[1, 0, 0]",
        ],
    )
    t0 = time.perf_counter()
    summary = run(cfg)
    return time.perf_counter() - t0, summary["tiles"]


def time_sahi(images: Path, ann: Path, out: Path, tile: int, overlap: int) -> tuple[float, int] | None:
    """Time SAHI's ``slice_coco`` on the same images and settings; the seconds and the tiles, None without SAHI."""
    try:
        from sahi.slicing import slice_coco
    except ImportError:
        return None
    t0 = time.perf_counter()
    coco, _ = slice_coco(
        coco_annotation_file_path=str(ann),
        image_dir=str(images),
        output_coco_annotation_file_name="sliced",
        output_dir=str(out),
        ignore_negative_samples=False,
        slice_height=tile,
        slice_width=tile,
        overlap_height_ratio=overlap / tile,
        overlap_width_ratio=overlap / tile,
        min_area_ratio=0.3,
        out_ext=".png",
        verbose=False,
    )
    return time.perf_counter() - t0, len(coco["images"])


def comparison(name: str, work: Path, quick: bool, device: str):
    """For ``python -m bench``: module 5 with one process against SAHI's ``slice_coco`` on the same
    photos and settings (50 JPEGs of 4000 x 3000, tile 1024, overlap 100; quick: 6 of 2000 x 1500)."""
    from bench.harness import Comparison

    n, w, h = (6, 2000, 1500) if quick else (50, 4000, 3000)
    tile, overlap = 1024, 100
    ann = make_photos(work / "images", n, w, h)
    counts: dict[str, int] = {}

    def reset(side: str):
        shutil.rmtree(work / side, ignore_errors=True)

    def ours():
        counts["ours"] = time_matchplant(work / "images", ann, work / "ours", tile, overlap, workers=1)[1]

    def peer():
        counts["peer"] = time_sahi(work / "images", ann, work / "peer", tile, overlap)[1]

    def check() -> dict:
        size = {s: sum(p.stat().st_size for p in (work / s).rglob("*.png")) for s in ("ours", "peer")}
        return {
            "tiles_ours": counts["ours"],
            "tiles_sahi": counts["peer"],
            "png_bytes_ours_over_sahi": size["ours"] / max(size["peer"], 1),
        }

    try:
        import sahi  # noqa: F401 - only to know whether the peer can run

        skip = None
    except ImportError:
        skip = "SAHI is not installed (pip install sahi)"
    return Comparison(
        name,
        f"{n} JPEG photos of {w} x {h}, tile {tile}, overlap {overlap}, PNG tiles",
        "matchplant tiling (1 process)",
        "sahi slice_coco",
        ours,
        None if skip else peer,
        reset=reset,
        check=None if skip else check,
        items=0,
        unit="tiles",
        skip=skip,
    )


def main(argv=None) -> int:
    """Parse the options, time module 5 and SAHI on generated photos and print both."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="6 photos of 2000 x 1500 instead of 50 of 4000 x 3000")
    p.add_argument("--tile", type=int, default=1024)
    p.add_argument("--overlap", type=int, default=100)
    p.add_argument("--keep", action="store_true", help="keep the generated data (printed path)")
    args = p.parse_args(argv)
    n, w, h = (6, 2000, 1500) if args.quick else (50, 4000, 3000)
    os.environ.setdefault("MATCHPLANT_QUIET", "1")
    root = Path(tempfile.mkdtemp(prefix="bench_tiling_"))
    try:
        t0 = time.perf_counter()
        ann = make_photos(root / "images", n, w, h)
        print(
            f"data: {n} JPEG photos {w}x{h}, tile {args.tile}, overlap {args.overlap} "
            f"(generated in {time.perf_counter() - t0:.1f} s); {os.cpu_count()} CPU cores"
        )
        results = {}
        for label, workers in (("matchplant, 1 process", 1), ("matchplant, all cores", 0)):
            sec, tiles = time_matchplant(root / "images", ann, root / "mp", args.tile, args.overlap, workers)
            results[label] = (sec, tiles)
            shutil.rmtree(root / "mp")
        sahi = time_sahi(root / "images", ann, root / "sahi", args.tile, args.overlap)
        if sahi is not None:
            results["sahi slice_coco"] = sahi
        for label, (sec, tiles) in results.items():
            print(f"{label:<24} {tiles:5d} tiles in {sec:7.2f} s = {tiles / sec:7.2f} tiles/s")
        if sahi is not None:
            base = sahi[1] / sahi[0]
            for label in ("matchplant, 1 process", "matchplant, all cores"):
                sec, tiles = results[label]
                print(f"ratio {label} / sahi: {tiles / sec / base:.2f}x")
        else:
            print("SAHI is not installed (pip install sahi): no comparison")
    finally:
        if args.keep:
            print(f"data kept in {root}")
        else:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
