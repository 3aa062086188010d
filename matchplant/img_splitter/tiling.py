"""Module 5: cut annotated images into tiles for training and split them into train / val / test.

Each source image is covered by a grid of ``tile_size`` squares overlapping by ``overlap`` pixels; the
last row and column are moved back to end at the image edge, so every tile is full size (an image
smaller than a tile gives one tile, the whole image). A box is kept in a tile when at least
``min_visible`` of its area lies inside the tile (the paper calls this threshold "IoU") and the part
inside is at least ``min_box_side`` pixels on both sides; it is then clipped to the tile and shifted by
the tile's offset. Tiles with no kept box are negatives; ``negative_share`` of them are kept.

Splits are made by source image (every tile of one photo lands in the same split), at random with a
seed, or spatially (photos ordered along the field's long axis, so val and test are separate parts of
the field). Output (``output_dir``)::

    train.json  val.json  test.json         COCO; each image entry has source_image, x0, y0
    train/images/<photo stem>_<x0>_<y0>.png  tiles, lossless (PNG, or TIFF for TIFF sources)
    train/labels/*.txt  classes.txt  data.yaml   with ``yolo: true``
    summary.json                             counts per split, boxes kept and lost, skipped images
"""

from __future__ import annotations

import concurrent.futures as cf
import csv
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from PIL import Image

from matchplant.core.coco import make_annotation, new_dataset, read_dataset, write_dataset
from matchplant.core.config import param
from matchplant.core.errors import ConfigError, InputError
from matchplant.core.images import list_images, match_name
from matchplant.core.io import atomic_path, read_json, write_json, write_text
from matchplant.core.log import get_logger
from matchplant.core.odm import image_size
from matchplant.core.progress import progress
from matchplant.core.yolo import coco_to_yolo, yolo_to_coco

log = get_logger("tiling")

SPLITS = ("train", "val", "test")
LOSSLESS = {".png": ".png", ".tif": ".tif", ".tiff": ".tif"}  # source suffix -> tile suffix kept as is


@dataclass
class TilingConfig:
    """Module 5 - tile annotated images, recompute their boxes and split the tiles into train/val/test."""

    images: Path | None = param(None, "folder of the annotated source images", path="dir", required=True)
    annotations: Path | None = param(None, "the boxes: module 4's COCO JSON (annotations.json), or a folder of YOLO "
                                    "labels with classes.txt", path="exists", required=True)
    output_dir: Path | None = param(None, "folder for the tiles, one COCO JSON per split and summary.json",
                             path="out", required=True)
    tile_size: int = param(1024, "tile side in pixels", min=32)
    overlap: int = param(100, "pixels shared by neighbouring tiles (so a plant cut by one tile is whole in "
                              "the next)", min=0)
    min_visible: float = param(0.3, "smallest fraction of a box's area inside a tile for the box to be kept "
                                    "in that tile (the paper's 'IoU')", min=0.0, max=1.0)
    iou: float | None = param(None, "the paper's name for min_visible; when set, it is used instead",
                              min=0.0, max=1.0)
    min_box_side: float = param(10.0, "boxes whose part inside a tile is narrower or lower than this (px) "
                                      "are dropped from that tile", min=0.0)
    split: list[float] = param([0.7, 0.15, 0.15], "shares of source images for train, val, test", min=0.0)
    seed: int = param(0, "random seed of the split and of the choice of negative tiles")
    split_mode: Literal["random", "spatial"] = param("random", "'random' split of the photos, or 'spatial': "
                                                     "photos ordered along the field, val and test at its end "
                                                     "(needs positions or GPS in EXIF)",
                                                     choices=["random", "spatial"])
    positions: Path | None = param(None, "CSV image,x,y of each photo for the spatial split (default: the "
                                         "images' EXIF GPS)", path="file")
    negative_share: float = param(0.1, "share of the tiles without any plant that are kept as negative "
                                       "examples (0 = none, 1 = all)", min=0.0, max=1.0)
    tile_format: Literal["auto", "png", "tif"] = param("auto", "tile files: 'auto' keeps a PNG or TIFF "
                                                       "source's format and writes PNG otherwise (always lossless)",
                                                       choices=["auto", "png", "tif"])
    yolo: bool = param(False, "also write YOLO labels, classes.txt and data.yaml")
    workers: int = param(0, "parallel processes (0 = one per CPU core, up to 8)", min=0)

    def check(self) -> None:
        if self.overlap >= self.tile_size:
            raise ConfigError(f"'overlap' ({self.overlap}) must be smaller than 'tile_size' ({self.tile_size})",
                              fix="for example tile_size: 1024 with overlap: 100")
        if len(self.split) != 3 or sum(self.split) <= 0:
            raise ConfigError(f"'split' must be three shares (train, val, test), got {self.split}",
                              fix="for example split: [0.7, 0.15, 0.15]")

    @property
    def threshold(self) -> float:
        return self.min_visible if self.iou is None else self.iou


# -- geometry -------------------------------------------------------------------------------------------


def tile_origins(length: int, tile: int, overlap: int) -> np.ndarray:
    """Start offsets along one axis: every ``tile - overlap`` px, the last one ending at the edge."""
    if length <= tile:
        return np.zeros(1, dtype=int)
    stride = tile - overlap
    starts = np.arange(0, length - tile, stride)
    return np.append(starts, length - tile).astype(int)


def tile_grid(width: int, height: int, tile: int, overlap: int) -> np.ndarray:
    """(T, 4) tiles ``[x0, y0, x1, y1]`` covering the image, row by row."""
    xs, ys = tile_origins(width, tile, overlap), tile_origins(height, tile, overlap)
    x0, y0 = np.meshgrid(xs, ys)
    x0, y0 = x0.ravel(), y0.ravel()
    return np.stack([x0, y0, np.minimum(x0 + tile, width), np.minimum(y0 + tile, height)], axis=1)


@dataclass
class ImagePlan:
    """Which box goes into which tile, for one source image."""

    tiles: np.ndarray      # (T, 4) x0 y0 x1 y1
    boxes: np.ndarray      # (N, 4) source boxes x1 y1 x2 y2
    keep: np.ndarray       # (T, N) bool: box n kept in tile t
    clipped: np.ndarray    # (T, N, 4) box n clipped to tile t, in tile pixels
    visible: np.ndarray    # (T, N) fraction of box n's area inside tile t

    @property
    def kept_anywhere(self) -> np.ndarray:
        return self.keep.any(axis=0) if self.keep.size else np.zeros(len(self.boxes), bool)

    @property
    def positive(self) -> np.ndarray:
        return self.keep.any(axis=1) if self.keep.size else np.zeros(len(self.tiles), bool)


def plan_image(boxes_xyxy: np.ndarray, width: int, height: int, tile: int, overlap: int,
               min_visible: float, min_box_side: float) -> ImagePlan:
    """Tile one image and decide, for every tile and box at once, what is kept (vectorised)."""
    tiles = tile_grid(width, height, tile, overlap)
    b = np.asarray(boxes_xyxy, dtype=float).reshape(-1, 4)
    t = tiles[:, None, :].astype(float)
    lo = np.maximum(b[None, :, :2], t[..., :2])
    hi = np.minimum(b[None, :, 2:], t[..., 2:])
    wh = np.clip(hi - lo, 0, None)
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    visible = wh[..., 0] * wh[..., 1] / np.where(area > 0, area, np.inf)[None, :]
    keep = (visible >= min_visible) & (visible > 0) & (wh >= min_box_side).all(axis=2)
    clipped = np.concatenate([lo, hi], axis=2) - np.tile(t[..., :2], 2)
    return ImagePlan(tiles, b, keep, clipped, visible)


# -- splitting ------------------------------------------------------------------------------------------


def split_counts(n: int, ratios: list[float]) -> list[int]:
    """Whole numbers of images per split (largest remainder); a split with a share gets one if it can."""
    r = np.asarray(ratios, float) / np.sum(ratios)
    raw = r * n
    counts = np.floor(raw).astype(int)
    for i in np.argsort(-(raw - counts), kind="stable")[: n - counts.sum()]:
        counts[i] += 1
    for i in np.flatnonzero((counts == 0) & (r > 0)):
        donor = int(np.argmax(counts))
        if counts[donor] > 1:
            counts[donor] -= 1
            counts[i] += 1
    return counts.tolist()


def split_images(names: list[str], ratios: list[float], seed: int = 0,
                 positions: dict[str, tuple[float, float]] | None = None) -> dict[str, str]:
    """``{image: split}``; random with ``seed``, or with ``positions`` in blocks along the main axis."""
    names = sorted(names)
    if positions is not None:
        xy = np.array([positions[n] for n in names], float)
        xy -= xy.mean(axis=0)
        axis = np.linalg.svd(xy, full_matrices=False)[2][0] if len(names) > 1 else np.array([1.0, 0.0])
        order = np.argsort(xy @ axis, kind="stable")
    else:
        order = np.random.default_rng(seed).permutation(len(names))
    counts = split_counts(len(names), ratios)
    labels = np.repeat(np.array(SPLITS), counts)
    return {names[i]: str(labels[k]) for k, i in enumerate(order)}


def read_positions(path: Path | None, files: dict[str, Path]) -> dict[str, tuple[float, float]]:
    """Photo positions for the spatial split: a CSV ``image,x,y`` or the images' EXIF GPS."""
    out: dict[str, tuple[float, float]] = {}
    if path is not None:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            if not reader.fieldnames or not {"image", "x", "y"} <= set(reader.fieldnames):
                raise InputError("the positions CSV needs the columns image,x,y", path=path,
                                 fix="write a header line 'image,x,y' and one line per photo")
            for row in reader:
                name = match_name(row["image"], files)
                if name:
                    out[name] = (float(row["x"]), float(row["y"]))
    else:
        for name, p in files.items():
            gps = _exif_lonlat(p)
            if gps:
                lon, lat = gps
                out[name] = (lon * 111320.0 * np.cos(np.radians(lat)), lat * 110540.0)  # metres, for ordering
    missing = sorted(set(files) - set(out))
    if missing:
        raise InputError(f"no position for {len(missing)} image(s) (e.g. {missing[0]}) for the spatial split",
                         path=path, fix="give 'positions' (a CSV image,x,y) or use split_mode: random")
    return out


def _exif_lonlat(path: Path) -> tuple[float, float] | None:
    try:
        with Image.open(path) as im:
            gps = im.getexif().get_ifd(0x8825)
        if not gps or 2 not in gps or 4 not in gps:
            return None
        def deg(v, ref):
            d = float(v[0]) + float(v[1]) / 60 + float(v[2]) / 3600
            return -d if ref in ("S", "W") else d
        return deg(gps[4], gps.get(3, "E")), deg(gps[2], gps.get(1, "N"))
    except Exception:  # noqa: BLE001 - a file without readable EXIF has no position
        return None


# -- image files --------------------------------------------------------------------------------------


def read_raw(path: str | Path) -> np.ndarray:
    """Pixels exactly as stored (OpenCV channel order, any bit depth), for lossless cropping."""
    img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError("not a readable image", path=path, fix="remove it from the annotations or re-export it")
    return img


def write_lossless(path: Path, pixels: np.ndarray) -> None:
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1] if path.suffix == ".png" else []
    ok, buf = cv2.imencode(path.suffix, np.ascontiguousarray(pixels), params)
    if not ok:
        raise InputError(f"could not encode a {path.suffix} tile of type {pixels.dtype}", path=path,
                         fix="use tile_format: tif")
    with atomic_path(path) as tmp:
        buf.tofile(tmp)


def _cut(job: tuple[str, list[tuple[int, int, int, int, str]]]) -> int:
    """Worker: read one source image and write its chosen tiles."""
    src, tiles = job
    img = read_raw(src)
    for x0, y0, x1, y1, out in tiles:
        write_lossless(Path(out), img[y0:y1, x0:x1])
    return len(tiles)


# -- the run ----------------------------------------------------------------------------------------------


@dataclass
class Source:
    name: str
    path: Path
    width: int
    height: int
    boxes: np.ndarray                # (N, 4) xyxy
    categories: np.ndarray           # (N,)
    plan: ImagePlan | None = None
    split: str = ""
    negatives: list[int] = field(default_factory=list)  # indices of negative tiles kept


def load_sources(cfg: TilingConfig) -> tuple[list[Source], list[dict], list[str]]:
    """The annotated images found on disk, the categories, and the annotated names missing on disk."""
    files = {p.name: p for p in list_images(cfg.images, min_count=0)}
    if cfg.annotations.is_dir():
        ds = yolo_to_coco(cfg.annotations, {n: image_size(p) for n, p in files.items()})
    else:
        ds = read_dataset(cfg.annotations)
    by_image: dict[int, list[dict]] = {im["id"]: [] for im in ds["images"]}
    for a in ds["annotations"]:
        by_image[a["image_id"]].append(a)
    sources, missing = [], []
    for im in ds["images"]:
        name = match_name(im["file_name"], files)
        if name is None:
            missing.append(im["file_name"])
            continue
        w, h = image_size(files[name])
        if (w, h) != (im["width"], im["height"]):
            raise InputError(f"'{name}' is {w}x{h} px on disk but {im['width']}x{im['height']} in the annotations",
                             path=cfg.annotations, fix="annotate the same (unresized) images that you tile")
        anns = by_image[im["id"]]
        b = np.array([a["bbox"] for a in anns], float).reshape(-1, 4)
        b[:, 2:] += b[:, :2]
        sources.append(Source(name, files[name], w, h, b, np.array([a["category_id"] for a in anns], int)))
    if missing:
        log.warning("%d annotated image(s) not found in %s and skipped (e.g. %s)", len(missing), cfg.images,
                    missing[0])
    if not sources:
        raise InputError("none of the annotated images is in the image folder", path=cfg.images,
                         fix="set 'images' to the folder the annotations were made on")
    stems = [Path(s.name).stem for s in sources]
    if len(set(stems)) != len(stems):
        raise InputError("two annotated images differ only in their extension; tile names would clash",
                         path=cfg.images, fix="rename one of them")
    return sources, ds["categories"], missing


def plan_all(cfg: TilingConfig, sources: list[Source]) -> None:
    """Tile plans, the split, and the (seeded) choice of negatives kept - all before any pixel is read."""
    positions = read_positions(cfg.positions, {s.name: s.path for s in sources}) \
        if cfg.split_mode == "spatial" else None
    splits = split_images([s.name for s in sources], cfg.split, cfg.seed, positions)
    empty = [k for k, share in zip(SPLITS, cfg.split) if share > 0 and k not in splits.values()]
    if empty:
        log.warning("only %d annotated image(s): the %s split is empty; annotate more images for a fair "
                    "evaluation", len(sources), " and ".join(empty))
    negatives = []
    for s in sources:
        s.plan = plan_image(s.boxes, s.width, s.height, cfg.tile_size, cfg.overlap, cfg.threshold, cfg.min_box_side)
        s.split = splits[s.name]
        negatives += [(s, int(t)) for t in np.flatnonzero(~s.plan.positive)]
    n_keep = int(round(cfg.negative_share * len(negatives)))
    for i in sorted(np.random.default_rng(cfg.seed).choice(len(negatives), n_keep, replace=False)):
        s, t = negatives[i]
        s.negatives.append(t)


def tile_suffix(cfg: TilingConfig, source: Path) -> str:
    if cfg.tile_format != "auto":
        return "." + cfg.tile_format
    return LOSSLESS.get(source.suffix.lower(), ".png")


def _remove_previous(out: Path) -> None:
    """Delete the tiles a previous run listed, so that no stale tile is mistaken for a new one."""
    for split in SPLITS:
        old = out / f"{split}.json"
        if not old.is_file():
            continue
        for im in read_json(old).get("images", []):
            for p in (out / split / "images" / im["file_name"], out / split / "labels" / (Path(im["file_name"]).stem + ".txt")):
                if p.is_file():
                    p.unlink()
        old.unlink()


def run(cfg: TilingConfig) -> dict:
    """Tile, split and write everything; returns the summary (also written to summary.json)."""
    sources, categories, missing = load_sources(cfg)
    plan_all(cfg, sources)
    out = Path(cfg.output_dir)
    _remove_previous(out)
    datasets = {k: new_dataset([c["name"] for c in sorted(categories, key=lambda c: c["id"])],
                               info={"description": f"MatchPlant tiles ({k})", "images_dir": f"{k}/images",
                                     "tile_size": cfg.tile_size, "overlap": cfg.overlap}) for k in SPLITS}
    cat_map = {c["id"]: i + 1 for i, c in enumerate(sorted(categories, key=lambda c: c["id"]))}
    jobs = []
    ann_id = {k: 1 for k in SPLITS}
    for s in sources:
        ds = datasets[s.split]
        chosen = sorted(set(np.flatnonzero(s.plan.positive).tolist()) | set(s.negatives))
        tiles = []
        for t in chosen:
            x0, y0, x1, y1 = (int(v) for v in s.plan.tiles[t])
            file_name = f"{Path(s.name).stem}_{x0}_{y0}{tile_suffix(cfg, s.path)}"
            image_id = len(ds["images"]) + 1
            ds["images"].append({"id": image_id, "file_name": file_name, "width": x1 - x0, "height": y1 - y0,
                                 "source_image": s.name, "x0": x0, "y0": y0})
            for n in np.flatnonzero(s.plan.keep[t]):
                cx1, cy1, cx2, cy2 = s.plan.clipped[t, n]
                ds["annotations"].append(make_annotation(ann_id[s.split], image_id, [cx1, cy1, cx2 - cx1, cy2 - cy1],
                                                         cat_map[int(s.categories[n])]))
                ann_id[s.split] += 1
            tiles.append((x0, y0, x1, y1, str(out / s.split / "images" / file_name)))
        jobs.append((str(s.path), tiles))
    _run_jobs(jobs, cfg.workers)
    summary = _summary(cfg, sources, datasets, missing)
    for split, ds in datasets.items():
        if ds["images"] or cfg.split[SPLITS.index(split)] > 0:
            write_dataset(out / f"{split}.json", ds)
            if cfg.yolo:
                coco_to_yolo(ds, out / split, labels_subdir="labels")
    if cfg.yolo:
        names = [c["name"] for c in datasets["train"]["categories"]]
        write_text(out / "classes.txt", "".join(n + "\n" for n in names))
        write_text(out / "data.yaml", f"path: {out.resolve().as_posix()}\ntrain: train/images\nval: val/images\n"
                                      f"test: test/images\nnames: {names}\n")
    write_json(out / "summary.json", summary)
    log.info("%d tiles from %d images: %s; %d of %d boxes kept in at least one tile -> %s",
             summary["tiles"], len(sources), ", ".join(f"{k} {v['tiles']}" for k, v in summary["splits"].items()),
             summary["boxes_kept"], summary["boxes"], out)
    return summary


def _run_jobs(jobs: list, workers: int) -> None:
    workers = workers or min(8, os.cpu_count() or 1)
    total = sum(len(t) for _, t in jobs)
    bar = progress(None, desc="tiles", total=total, unit="tile")
    if workers == 1 or len(jobs) == 1:
        for job in jobs:
            bar.update(_cut(job))
    else:
        with cf.ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
            for done in cf.as_completed([pool.submit(_cut, job) for job in jobs]):
                bar.update(done.result())
    bar.close()


def _summary(cfg: TilingConfig, sources: list[Source], datasets: dict, missing: list[str]) -> dict:
    splits = {}
    for k in SPLITS:
        mine = [s for s in sources if s.split == k]
        splits[k] = {"images": len(mine), "tiles": len(datasets[k]["images"]),
                     "boxes": len(datasets[k]["annotations"]), "negative_tiles": sum(len(s.negatives) for s in mine),
                     "source_images": sorted(s.name for s in mine)}
    lost = {s.name: int((~s.plan.kept_anywhere).sum()) for s in sources if (~s.plan.kept_anywhere).any()}
    return {"tiles": sum(v["tiles"] for v in splits.values()), "boxes": int(sum(len(s.boxes) for s in sources)),
            "boxes_kept": int(sum(s.plan.kept_anywhere.sum() for s in sources)), "boxes_lost_by_image": lost,
            "negative_tiles_available": int(sum((~s.plan.positive).sum() for s in sources)),
            "missing_images": missing, "splits": splits,
            "settings": {"tile_size": cfg.tile_size, "overlap": cfg.overlap, "min_visible": cfg.threshold,
                         "min_box_side": cfg.min_box_side, "split": list(cfg.split), "seed": cfg.seed,
                         "split_mode": cfg.split_mode, "negative_share": cfg.negative_share}}


__all__ = ["TilingConfig", "tile_origins", "tile_grid", "plan_image", "ImagePlan", "split_counts", "split_images",
           "load_sources", "plan_all", "run"]
