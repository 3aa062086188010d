"""Module 5's split of the source photos into train / val / test: at random with a seed, or spatially (photos
ordered along the field's long axis, so that val and test are separate parts of the field)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from matchplant.core.formats.box_files import resolve_image_names
from matchplant.core.formats.exif import image_gps
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.validate import read_csv

SPLITS = ("train", "val", "test")


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


def split_images(
    names: list[str], ratios: list[float], seed: int = 0, positions: dict[str, tuple[float, float]] | None = None
) -> dict[str, str]:
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
        table = read_csv(path, required=["image"], numeric=["x", "y"], what="positions CSV")
        matched, _ = resolve_image_names(table.column("image"), files)
        for i, row in enumerate(table.rows):
            name = matched.get(row["image"])
            if name:
                out[name] = (float(table.numbers["x"][i]), float(table.numbers["y"][i]))
    else:
        for name, p in files.items():
            gps = image_gps(p)
            if gps:
                lat, lon, _ = gps
                out[name] = (lon * 111320.0 * np.cos(np.radians(lat)), lat * 110540.0)  # metres, for ordering
    missing = sorted(set(files) - set(out))
    if missing:
        raise InputError(
            f"no position for {len(missing)} image(s) (e.g. {missing[0]}) for the spatial split",
            path=path,
            fix="give 'positions' (a CSV image,x,y) or use split_mode: random",
        )
    return out


__all__ = ["SPLITS", "split_counts", "split_images", "read_positions"]
