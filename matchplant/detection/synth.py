"""Small synthetic detection data: green plants on soil, with exact boxes (tests, benchmarks, demos).

Not a substitute for the synthetic field (``matchplant.simfield``): a quick way to make COCO tiles or a
large "photo" with known plants, in any number and size, without rendering a whole field.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from matchplant.core.formats.coco import make_annotation, new_dataset, write_dataset


def soil(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A brown, noisy soil background (RGB uint8)."""
    base = np.array([120, 92, 64], dtype=np.float32)
    noise = rng.normal(0, 10, size=(height, width, 1)).astype(np.float32)
    return np.clip(base + noise + rng.normal(0, 4, size=(height, width, 3)), 0, 255).astype(np.uint8)


def draw_plants(img: np.ndarray, centers: np.ndarray, radii: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Draw elliptical green plants; returns their boxes ``[x1, y1, x2, y2]`` clipped to the image."""
    h, w = img.shape[:2]
    boxes = []
    for (cx, cy), r in zip(centers, radii):
        rx, ry = r * rng.uniform(0.8, 1.2), r * rng.uniform(0.8, 1.2)
        green = tuple(int(v) for v in (rng.uniform(30, 70), rng.uniform(140, 200), rng.uniform(30, 70)))
        # sub-pixel ellipse (shift=4) so the box is exact
        cv2.ellipse(
            img,
            (int(round(cx * 16)), int(round(cy * 16))),
            (int(round(rx * 16)), int(round(ry * 16))),
            0,
            0,
            360,
            green,
            -1,
            cv2.LINE_AA,
            shift=4,
        )
        boxes.append([max(cx - rx, 0), max(cy - ry, 0), min(cx + rx, w), min(cy + ry, h)])
    return np.asarray(boxes, dtype=float).reshape(-1, 4)


def place_plants(
    rng: np.random.Generator, n: int, height: int, width: int, radius: tuple[float, float], margin: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` plant centres and radii that do not touch each other."""
    centers, radii = [], []
    for _ in range(n * 20):
        if len(centers) == n:
            break
        r = rng.uniform(*radius)
        c = rng.uniform([margin, margin], [width - margin, height - margin])
        if all(np.hypot(*(c - c2)) > 1.3 * (r + r2) + 2 for c2, r2 in zip(centers, radii)):
            centers.append(c)
            radii.append(r)
    return np.asarray(centers).reshape(-1, 2), np.asarray(radii)


def make_tiles(
    out: str | Path,
    n_images: int = 16,
    size: int = 128,
    plants: tuple[int, int] = (2, 6),
    radius: tuple[float, float] = (6, 12),
    negatives: int = 2,
    seed: int = 0,
    name: str = "tiles.json",
    source: str = "synthetic.tif",
) -> Path:
    """``n_images`` PNG tiles (the last ``negatives`` without plants) and their COCO JSON in ``out``.

    Tiles record a made-up source image and offset, like module 5's, so provenance can be checked.
    """
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    ds = new_dataset(["plant"])
    ann_id = 1
    for i in range(n_images):
        img = soil(rng, size, size)
        n = 0 if i >= n_images - negatives else int(rng.integers(plants[0], plants[1] + 1))
        centers, radii = place_plants(rng, n, size, size, radius)
        boxes = draw_plants(img, centers, radii, rng)
        file_name = f"images/{Path(name).stem}_{i:04d}.png"
        cv2.imwrite(str(out / file_name), img[:, :, ::-1])
        ds["images"].append(
            {
                "id": i + 1,
                "file_name": file_name,
                "width": size,
                "height": size,
                "source_image": source,
                "x0": i * size,
                "y0": 0,
            }
        )
        for b in boxes:
            ds["annotations"].append(make_annotation(ann_id, i + 1, [b[0], b[1], b[2] - b[0], b[3] - b[1]]))
            ann_id += 1
    return write_dataset(out / name, ds)


def make_photo(
    path: str | Path, width: int, height: int, n_plants: int, radius: tuple[float, float] = (8, 14), seed: int = 0
) -> np.ndarray:
    """A large synthetic photo with plants written to ``path``; returns the true boxes ``[x1, y1, x2, y2]``."""
    rng = np.random.default_rng(seed)
    img = soil(rng, height, width)
    centers, radii = place_plants(rng, n_plants, height, width, radius, margin=radius[1])
    boxes = draw_plants(img, centers, radii, rng)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img[:, :, ::-1])
    return boxes
