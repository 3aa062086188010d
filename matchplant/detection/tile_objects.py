"""Distinct plants behind the boxes of overlapping tiles (module 5's tiles, module 7's metrics).

Module 5 writes a plant once per tile that holds enough of it, clipped to the tile: a plant in the
overlap of two tiles is two boxes. Counting plants (and the plants found) must count it once. The
tile images carry ``source_image``, ``x0`` and ``y0``; in source pixels, two boxes ``A`` (tile ``Ta``)
and ``B`` (tile ``Tb``) of the same class are copies of one plant ``O`` exactly when
``A ∩ Tb == B ∩ Ta`` (both are ``O ∩ Ta ∩ Tb``) and that part is not empty, within ``tol`` pixels of
rounding. Copies are joined transitively (a plant in four tiles is one).
"""

from __future__ import annotations

import numpy as np

CHUNK = 256


def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def distinct_objects(dataset: dict, tol: float = 1.0) -> tuple[dict[int, int], int]:
    """``({annotation id: object number}, number of distinct objects)`` of a COCO dataset of tiles.
    Images without ``source_image`` are their own source (each box is then its own object)."""
    images = {im["id"]: im for im in dataset.get("images", [])}
    anns = [a for a in dataset.get("annotations", []) if a.get("image_id") in images]
    if not anns:
        return {}, 0
    n = len(anns)
    parent = np.arange(n)
    src, box, tile = [], np.zeros((n, 4)), np.zeros((n, 4))
    for k, a in enumerate(anns):
        im = images[a["image_id"]]
        x0, y0 = float(im.get("x0", 0)), float(im.get("y0", 0))
        x, y, w, h = (float(v) for v in a["bbox"])
        box[k] = [x0 + x, y0 + y, x0 + x + w, y0 + y + h]
        tile[k] = [x0, y0, x0 + float(im["width"]), y0 + float(im["height"])]
        src.append((im.get("source_image", f"\0image {im['id']}"), a.get("category_id")))
    groups: dict[tuple, list[int]] = {}
    for k, key in enumerate(src):
        groups.setdefault(key, []).append(k)
    image_of = np.array([a["image_id"] for a in anns])
    for members in groups.values():
        idx = np.asarray(members)
        if len(idx) < 2 or len(set(image_of[idx].tolist())) < 2:
            continue
        for start in range(0, len(idx), CHUNK):
            i = idx[start : start + CHUNK]
            # A ∩ Tb and B ∩ Ta for every pair (i in rows, j in columns)
            a_in_tb = np.concatenate(
                [np.maximum(box[i, None, :2], tile[None, idx, :2]), np.minimum(box[i, None, 2:], tile[None, idx, 2:])],
                axis=2,
            )
            b_in_ta = np.concatenate(
                [np.maximum(box[None, idx, :2], tile[i, None, :2]), np.minimum(box[None, idx, 2:], tile[i, None, 2:])],
                axis=2,
            )
            same = (np.abs(a_in_tb - b_in_ta) <= tol).all(axis=2)
            nonempty = ((a_in_tb[..., 2] - a_in_tb[..., 0]) > 0) & ((a_in_tb[..., 3] - a_in_tb[..., 1]) > 0)
            pairs = np.argwhere(same & nonempty & (image_of[i][:, None] != image_of[idx][None, :]))
            for r, c in pairs:
                ra, rb = _find(parent, int(i[r])), _find(parent, int(idx[c]))
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([_find(parent, k) for k in range(n)])
    _, number = np.unique(roots, return_inverse=True)
    return {int(a["id"]): int(number[k]) for k, a in enumerate(anns)}, int(number.max()) + 1


def found_objects(ev, object_of: dict[int, int], threshold: float) -> int:
    """How many distinct objects have at least one tile box matched at IoU 0.5 by a detection scoring at
    least ``threshold`` (COCOeval's own greedy matches, as :func:`matchplant.detection.evaluate.operating_point`
    counts them)."""
    all_area = list(ev.params.areaRng[0])
    max_det = ev.params.maxDets[-1]
    found: set[int] = set()
    for e in ev.evalImgs:
        if e is None or list(e["aRng"]) != all_area or e["maxDet"] != max_det:
            continue
        score_of = dict(zip(e["dtIds"], e["dtScores"]))
        for gt_id, dt_id in zip(e["gtIds"], np.asarray(e["gtMatches"][0])):
            if dt_id > 0 and score_of.get(int(dt_id), -1.0) >= threshold and int(gt_id) in object_of:
                found.add(object_of[int(gt_id)])
    return len(found)
