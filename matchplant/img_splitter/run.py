"""Module 5: cut annotated images into tiles for training and split them into train / val / test.

Each source image is covered by a grid of ``tile_size`` squares overlapping by ``overlap`` pixels; the
last row and column are moved back to end at the image edge, so every tile is full size (an image
smaller than a tile gives one tile, the whole image). A box is kept in a tile when at least
``min_visible`` of its area lies inside the tile (the paper calls this threshold "IoU") and the part
inside is at least ``min_box_side`` pixels on both sides; it is then clipped to the tile and shifted by
the tile's offset. Tiles with no kept box are negatives; ``negative_share`` of them are kept.

When module 4 recorded an ``annotated_region`` for an image (its owned area), only that region was
annotated: boxes are clipped to it, tiles mostly outside it are not written, and tile pixels outside it
are masked, so no unboxed plant becomes a negative (:mod:`matchplant.img_splitter.regions`).

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
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from matchplant.core.formats.box_files import resolve_image_names
from matchplant.core.formats.coco import (
    DropLog,
    annotated_region,
    make_annotation,
    new_dataset,
    read_dataset,
    write_dataset,
)
from matchplant.core.formats.images import list_images, whole_image_size
from matchplant.core.formats.yolo import coco_to_yolo, label_files, yolo_to_coco
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.guard import check_outputs, staged_outputs
from matchplant.core.runtime.io import atomic_path, read_json, write_json, write_text
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.progress import progress
from matchplant.img_splitter.config import ImgSplitterConfig
from matchplant.img_splitter.regions import clip_boxes, mask_outside, region_share
from matchplant.img_splitter.splits import SPLITS, read_positions, split_images

log = get_logger("img_splitter")

DROPPED_NAME = "dropped.csv"  # every box left out of the tiles (or whose image is missing), and why
LOSSLESS = {".png": ".png", ".tif": ".tif", ".tiff": ".tif"}  # source suffix -> tile suffix kept as is


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

    tiles: np.ndarray  # (T, 4) x0 y0 x1 y1
    boxes: np.ndarray  # (N, 4) source boxes x1 y1 x2 y2
    keep: np.ndarray  # (T, N) bool: box n kept in tile t
    clipped: np.ndarray  # (T, N, 4) box n clipped to tile t, in tile pixels
    visible: np.ndarray  # (T, N) fraction of box n's area inside tile t

    @property
    def kept_anywhere(self) -> np.ndarray:
        """Per box: whether at least one tile keeps it."""
        return self.keep.any(axis=0) if self.keep.size else np.zeros(len(self.boxes), bool)

    @property
    def positive(self) -> np.ndarray:
        """Per tile: whether it keeps at least one box."""
        return self.keep.any(axis=1) if self.keep.size else np.zeros(len(self.tiles), bool)


def plan_image(
    boxes_xyxy: np.ndarray, width: int, height: int, tile: int, overlap: int, min_visible: float, min_box_side: float
) -> ImagePlan:
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


def drop_reason(plan: ImagePlan, n: int, cfg: ImgSplitterConfig) -> tuple[str, str]:
    """Why box ``n`` is in no tile: a short reason naming the setting that dropped it (counted in the console's
    warning) and the details for ``dropped.csv``; only the limit that actually dropped it is named."""
    best = float(plan.visible[:, n].max()) if plan.visible.size else 0.0
    x1, y1, x2, y2 = plan.boxes[n]
    if min(x2 - x1, y2 - y1) < cfg.min_box_side:
        return (
            f"smaller than min_box_side {cfg.min_box_side:g} px",
            f"the box is {x2 - x1:.0f}x{y2 - y1:.0f} px, under min_box_side {cfg.min_box_side:g} px",
        )
    if best < cfg.threshold:
        return (
            f"cut by tile edges below min_visible {cfg.threshold:g}",
            f"at most {best:.0%} of it is visible in a tile (min_visible {cfg.threshold:g})",
        )
    return (
        f"cut by tile edges to a part under min_box_side {cfg.min_box_side:g} px",
        f"where {best:.0%} of it is visible, the part in the tile is under min_box_side {cfg.min_box_side:g} px",
    )


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
        raise InputError(
            f"could not encode a {path.suffix} tile of type {pixels.dtype}", path=path, fix="use tile_format: tif"
        )
    with atomic_path(path) as tmp:
        buf.tofile(tmp)


def _cut(job: tuple[str, list[tuple[int, int, int, int, str]], np.ndarray | None]) -> int:
    """Worker: read one source image and write its chosen tiles (masked outside the annotated region)."""
    src, tiles, region = job
    img = read_raw(src)
    for x0, y0, x1, y1, out in tiles:
        pixels = img[y0:y1, x0:x1]
        write_lossless(Path(out), pixels if region is None else mask_outside(pixels, region, x0, y0))
    return len(tiles)


# -- the run ----------------------------------------------------------------------------------------------


@dataclass
class Source:
    name: str
    path: Path
    width: int
    height: int
    boxes: np.ndarray  # (N, 4) xyxy
    categories: np.ndarray  # (N,)
    region: np.ndarray | None = None  # the annotated polygon; None = the whole image
    plan: ImagePlan | None = None
    usable: np.ndarray | None = None  # (T,) tiles enough inside the annotated region
    boxes_outside: int = 0
    ids: list = field(default_factory=list)  # annotation id of each box (for the report of boxes left out)
    split: str = ""
    negatives: list[int] = field(default_factory=list)  # indices of negative tiles kept


def load_sources(cfg: ImgSplitterConfig, drops: DropLog | None = None) -> tuple[list[Source], list[dict], list[str]]:
    """The annotated images found on disk, the categories, and the annotated names missing on disk.

    Boxes of images that are not in the folder (and YOLO lines that cannot be used) go to ``drops``; an
    annotation file without any box, an image whose size differs from the annotations and a broken image
    file are errors."""
    drops = DropLog() if drops is None else drops
    files = {p.name: p for p in list_images(cfg.images, min_count=0)}
    ds = _read_annotations(cfg, files, drops)
    by_image: dict[int, list[dict]] = {im["id"]: [] for im in ds["images"]}
    for a in ds["annotations"]:
        by_image[a["image_id"]].append(a)
    matched, unmatched = resolve_image_names([im["file_name"] for im in ds["images"]], files)
    sources, missing = [], []
    for im in ds["images"]:
        name = matched.get(im["file_name"])
        if name is None:
            missing.append(im["file_name"])
            for a in by_image[im["id"]]:
                drops.add(
                    cfg.annotations,
                    f"annotation {a.get('id')}",
                    im["file_name"],
                    a["bbox"],
                    "image not in the image folder",
                    unmatched[im["file_name"]],
                )
            continue
        sources.append(_source(cfg, im, name, files[name], by_image[im["id"]], drops))
    if missing and sources:
        example = missing[0] + (f" ({unmatched[missing[0]]})" if unmatched[missing[0]] else "")
        log.warning(
            "%d annotated image(s) not found in %s and skipped, with their boxes (e.g. %s)",
            len(missing),
            cfg.images,
            example,
        )
    if not sources:
        hint = next((v for v in unmatched.values() if v), "")
        raise InputError(
            f"none of the {len(ds['images'])} annotated images is in the image folder (e.g. "
            f"'{missing[0]}'{'; ' + hint if hint else ''})",
            path=cfg.images,
            fix="set 'images' to the folder the annotations were made on",
        )
    stems = [Path(s.name).stem for s in sources]
    if len(set(stems)) != len(stems):
        raise InputError(
            "two annotated images differ only in their extension; tile names would clash",
            path=cfg.images,
            fix="rename one of them",
        )
    return sources, ds["categories"], missing


def _read_annotations(cfg: ImgSplitterConfig, files: dict[str, Path], drops: DropLog) -> dict:
    """The annotations as a COCO dataset (a YOLO folder converted with the sizes of ``files``): at least one
    image and one box, else an error."""
    if cfg.annotations.is_dir():
        stems = {p.stem for p in label_files(cfg.annotations)}
        ds = yolo_to_coco(
            cfg.annotations, {n: whole_image_size(p) for n, p in files.items() if Path(n).stem in stems}, drops
        )
    else:
        ds = read_dataset(cfg.annotations)
    if not ds["images"]:
        raise InputError(
            "the annotations list no images",
            path=cfg.annotations,
            fix="give module 4's annotations.json (or a YOLO labels folder) of the photos in 'images'",
        )
    if not ds["annotations"]:
        what = " (this looks like module 7's predictions)" if "predictions" in ds else ""
        raise InputError(
            f"the annotations hold no box (on {len(ds['images'])} image(s)){what}: every tile would be "
            "a negative and the detector would learn nothing",
            path=cfg.annotations,
            fix="draw or import the plant boxes with module 4 first (or point 'annotations' at the "
            "file that holds them)",
        )
    return ds


def _source(cfg: ImgSplitterConfig, im: dict, name: str, path: Path, anns: list[dict], drops: DropLog) -> Source:
    """One annotated image found on disk (``name`` at ``path``): its size checked against the annotations, its
    boxes as corners, clipped to the annotated region where module 4 recorded one (the rest to ``drops``)."""
    w, h = whole_image_size(path)
    if (w, h) != (im["width"], im["height"]):
        raise InputError(
            f"'{name}' is {w}x{h} px on disk but {im['width']}x{im['height']} in the annotations",
            path=cfg.annotations,
            fix="annotate the same (unresized) images that you tile",
        )
    b = np.array([a["bbox"] for a in anns], float).reshape(-1, 4)
    b[:, 2:] += b[:, :2]
    cats = np.array([a["category_id"] for a in anns], int)
    region = annotated_region(im)
    outside = 0
    if region is not None:  # only the region was annotated: boxes clipped to it
        b, inside = clip_boxes(b, region)
        outside = int((~inside).sum())
        for i in np.flatnonzero(~inside):
            drops.add(
                cfg.annotations,
                f"annotation {anns[i].get('id')}",
                name,
                anns[i]["bbox"],
                "outside the annotated region",
                "module 4 recorded only part of this image as annotated",
            )
        b, cats = b[inside], cats[inside]
    ids = [a.get("id") for a, k in zip(anns, inside if region is not None else [True] * len(anns)) if k]
    return Source(name, path, w, h, b, cats, region, boxes_outside=outside, ids=ids)


def check_tile_size(cfg: ImgSplitterConfig, sources: list[Source]) -> None:
    """A tile at least as large as every image means no tiling: each image is one tile (what ``matchplant
    inspect`` advises when the objects are large enough at the photos' own size), said in the log. Larger than
    only some images: those are one tile each, with a warning (the others are cut)."""
    small = [s for s in sources if cfg.tile_size > s.width or cfg.tile_size > s.height]
    if not small:
        return
    if all(cfg.tile_size >= max(s.width, s.height) for s in sources):
        log.info(
            "'tile_size' (%d px) is at least the size of every image (largest %d px): no tiling, each "
            "image is one tile (set tile_size below the image size to cut them)",
            cfg.tile_size,
            max(max(s.width, s.height) for s in sources),
        )
        return
    log.warning(
        "'tile_size' (%d px) is larger than %d of %d image(s) in width or height (e.g. %s: %dx%d px): their "
        "tiles are cut to the image",
        cfg.tile_size,
        len(small),
        len(sources),
        small[0].name,
        small[0].width,
        small[0].height,
    )


def plan_all(cfg: ImgSplitterConfig, sources: list[Source]) -> None:
    """Tile plans, the split, and the (seeded) choice of negatives kept - all before any pixel is read."""
    positions = (
        read_positions(cfg.positions, {s.name: s.path for s in sources}) if cfg.split_mode == "spatial" else None
    )
    splits = split_images([s.name for s in sources], cfg.split, cfg.seed, positions)
    empty = [k for k, share in zip(SPLITS, cfg.split) if share > 0 and k not in splits.values()]
    if empty:
        log.warning(
            "only %d annotated image(s): the %s split is empty; annotate more images for a fair evaluation",
            len(sources),
            " and ".join(empty),
        )
    negatives = []
    for s in sources:
        s.plan = plan_image(s.boxes, s.width, s.height, cfg.tile_size, cfg.overlap, cfg.threshold, cfg.min_box_side)
        s.usable = (
            np.ones(len(s.plan.tiles), bool)
            if s.region is None
            else region_share(s.plan.tiles, s.region) >= max(cfg.min_region_share, 1e-9)
        )
        s.plan.keep &= s.usable[:, None]  # boxes count only in tiles that are written
        s.split = splits[s.name]
        negatives += [(s, int(t)) for t in np.flatnonzero(~s.plan.positive & s.usable)]
    n_keep = int(round(cfg.negative_share * len(negatives)))
    for i in sorted(np.random.default_rng(cfg.seed).choice(len(negatives), n_keep, replace=False)):
        s, t = negatives[i]
        s.negatives.append(t)


def tile_suffix(cfg: ImgSplitterConfig, source: Path) -> str:
    if cfg.tile_format != "auto":
        return "." + cfg.tile_format
    return LOSSLESS.get(source.suffix.lower(), ".png")


def _previous_tiles(out: Path) -> set[Path]:
    """The tiles (and YOLO labels) a previous run listed in its split files, to remove after a new run."""
    old: set[Path] = {out / DROPPED_NAME}  # a new run writes its own list, or none
    for split in SPLITS:
        path = out / f"{split}.json"
        if not path.is_file():
            continue
        try:
            images = read_json(path).get("images", [])
        except (InputError, AttributeError):
            continue
        for im in images:
            name = Path(str(im.get("file_name", ""))).name if isinstance(im, dict) else ""
            if name:
                old |= {out / split / "images" / name, out / split / "labels" / (Path(name).stem + ".txt")}
    return old


def run(cfg: ImgSplitterConfig) -> dict:
    """Tile, split and write everything; returns the summary (also written to summary.json).

    Everything is checked before a pixel is written, and the outputs are written into a staging folder moved
    into ``output_dir`` only at the end: a failed run leaves ``output_dir`` as it was (apart from its log).

    Parameters
    ----------
    cfg : ImgSplitterConfig
        The step's settings, as loaded from its YAML config (``5_img_splitter/config.yaml``) or built in Python.

    Returns
    -------
    dict
        The summary: tiles and boxes per split, boxes kept and left out.
    """
    check_outputs(cfg)
    drops = DropLog()
    sources, categories, missing = load_sources(cfg, drops)
    check_tile_size(cfg, sources)
    plan_all(cfg, sources)
    if not any(s.plan.positive.any() for s in sources):
        raise InputError(
            f"no box of the {sum(len(s.boxes) for s in sources)} is kept in any tile (each needs "
            f"min_visible {cfg.threshold:g} of its area in a tile and sides of min_box_side "
            f"{cfg.min_box_side:g} px there)",
            path=cfg.annotations,
            fix="lower min_box_side or min_visible, or check the boxes' sizes in the annotations",
        )
    out = Path(cfg.output_dir)
    old = _previous_tiles(out)
    with staged_outputs(out) as stage:
        summary = _write(cfg, sources, categories, missing, stage, out, drops)
    for path in old - {out / p for p in summary.pop("_written")} - ({out / DROPPED_NAME} if len(drops) else set()):
        path.unlink(missing_ok=True)
    if len(drops):
        log.warning(
            "%d box(es) are not in any tile: %s; each one and why: %s (to keep more, lower min_box_side or "
            "min_visible in the config, or raise the tile overlap)",
            len(drops),
            drops.summary(),
            out / DROPPED_NAME,
        )
    log.info(
        "%d tiles from %d images: %s; %d of %d boxes kept in at least one tile -> %s",
        summary["tiles"],
        len(sources),
        ", ".join(f"{k} {v['tiles']}" for k, v in summary["splits"].items()),
        summary["boxes_kept"],
        summary["boxes"],
        out,
    )
    return summary


def _write(
    cfg: ImgSplitterConfig,
    sources: list[Source],
    categories: list[dict],
    missing: list[str],
    stage: Path,
    out: Path,
    drops: DropLog,
) -> dict:
    """Write the tiles, the split datasets, YOLO files, summary.json and dropped.csv into ``stage``."""
    datasets = {
        k: new_dataset(
            [c["name"] for c in sorted(categories, key=lambda c: c["id"])],
            info={
                "description": f"MatchPlant tiles ({k})",
                "images_dir": f"{k}/images",
                "tile_size": cfg.tile_size,
                "overlap": cfg.overlap,
            },
        )
        for k in SPLITS
    }
    cat_map = {c["id"]: i + 1 for i, c in enumerate(sorted(categories, key=lambda c: c["id"]))}
    jobs = []
    ann_id = {k: 1 for k in SPLITS}
    written: list[str] = []
    for s in sources:
        ds = datasets[s.split]
        chosen = sorted(set(np.flatnonzero(s.plan.positive).tolist()) | set(s.negatives))
        tiles = []
        for t in chosen:
            x0, y0, x1, y1 = (int(v) for v in s.plan.tiles[t])
            file_name = f"{Path(s.name).stem}_{x0}_{y0}{tile_suffix(cfg, s.path)}"
            image_id = len(ds["images"]) + 1
            ds["images"].append(
                {
                    "id": image_id,
                    "file_name": file_name,
                    "width": x1 - x0,
                    "height": y1 - y0,
                    "source_image": s.name,
                    "x0": x0,
                    "y0": y0,
                    "source_width": s.width,
                    "source_height": s.height,
                    **({} if s.region is None else {"masked_outside_region": True}),
                }
            )
            for n in np.flatnonzero(s.plan.keep[t]):
                cx1, cy1, cx2, cy2 = s.plan.clipped[t, n]
                ds["annotations"].append(
                    make_annotation(
                        ann_id[s.split], image_id, [cx1, cy1, cx2 - cx1, cy2 - cy1], cat_map[int(s.categories[n])]
                    )
                )
                ann_id[s.split] += 1
            tiles.append((x0, y0, x1, y1, str(stage / s.split / "images" / file_name)))
            written += [f"{s.split}/images/{file_name}", f"{s.split}/labels/{Path(file_name).stem}.txt"]
        jobs.append((str(s.path), tiles, s.region))
        for n in np.flatnonzero(~s.plan.kept_anywhere):
            x1, y1, x2, y2 = s.boxes[n]
            drops.add(
                cfg.annotations,
                f"annotation {s.ids[n] if n < len(s.ids) else '?'}",
                s.name,
                [x1, y1, x2 - x1, y2 - y1],
                *drop_reason(s.plan, n, cfg),
            )
    _run_jobs(jobs, cfg.workers)
    summary = _summary(cfg, sources, datasets, missing)
    for split, ds in datasets.items():
        if ds["images"] or cfg.split[SPLITS.index(split)] > 0:
            write_dataset(stage / f"{split}.json", ds)
            if cfg.yolo:
                coco_to_yolo(ds, stage / split, labels_subdir="labels")
    if cfg.yolo:
        names = [c["name"] for c in datasets["train"]["categories"]]
        write_text(stage / "classes.txt", "".join(n + "\n" for n in names))
        write_text(
            stage / "data.yaml",
            f"path: {out.resolve().as_posix()}\ntrain: train/images\nval: val/images\n"
            f"test: test/images\nnames: {names}\n",
        )
    summary["dropped"] = {"boxes": len(drops), "reasons": drops.summary(), "list": DROPPED_NAME if len(drops) else None}
    if len(drops):
        drops.write_csv(stage / DROPPED_NAME)
    write_json(stage / "summary.json", summary)
    return dict(summary, _written=written)


def _run_jobs(jobs: list, workers: int) -> None:
    workers = workers or min(8, os.cpu_count() or 1)
    total = sum(len(job[1]) for job in jobs)
    bar = progress(None, desc="tiles", total=total, unit="tile")
    if workers == 1 or len(jobs) == 1:
        for job in jobs:
            bar.update(_cut(job))
    else:
        with cf.ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
            for done in cf.as_completed([pool.submit(_cut, job) for job in jobs]):
                bar.update(done.result())
    bar.close()


def _summary(cfg: ImgSplitterConfig, sources: list[Source], datasets: dict, missing: list[str]) -> dict:
    splits = {}
    for k in SPLITS:
        mine = [s for s in sources if s.split == k]
        splits[k] = {
            "images": len(mine),
            "tiles": len(datasets[k]["images"]),
            "boxes": len(datasets[k]["annotations"]),
            "negative_tiles": sum(len(s.negatives) for s in mine),
            "source_images": sorted(s.name for s in mine),
        }
    lost = {s.name: int((~s.plan.kept_anywhere).sum()) for s in sources if (~s.plan.kept_anywhere).any()}
    return {
        "tiles": sum(v["tiles"] for v in splits.values()),
        "boxes": int(sum(len(s.boxes) for s in sources)),
        "boxes_kept": int(sum(s.plan.kept_anywhere.sum() for s in sources)),
        "boxes_lost_by_image": lost,
        "negative_tiles_available": int(sum((~s.plan.positive & s.usable).sum() for s in sources)),
        "annotated_regions": {
            "images": sum(s.region is not None for s in sources),
            "boxes_outside_region": int(sum(s.boxes_outside for s in sources)),
            "tiles_outside_region": int(sum((~s.usable).sum() for s in sources)),
        },
        "missing_images": missing,
        "splits": splits,
        "settings": {
            "tile_size": cfg.tile_size,
            "overlap": cfg.overlap,
            "min_visible": cfg.threshold,
            "min_box_side": cfg.min_box_side,
            "split": list(cfg.split),
            "seed": cfg.seed,
            "split_mode": cfg.split_mode,
            "negative_share": cfg.negative_share,
            "min_region_share": cfg.min_region_share,
        },
    }


__all__ = [
    "ImgSplitterConfig",
    "tile_origins",
    "tile_grid",
    "plan_image",
    "ImagePlan",
    "split_images",
    "load_sources",
    "plan_all",
    "run",
]
