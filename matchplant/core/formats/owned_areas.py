"""``owned_areas.json``: the part of the field each selected image owns, in that image's pixels.

Written by module 3 (one polygon per selected image), read by module 4 to show and limit annotation.
Format: ``{image file name: [[u, v], ...]}``, at least three points per polygon, pixels of that image.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import read_json, write_json

FIX = "use the owned_areas.json written by module 3 (3_min_img_finder)"


def write_owned_areas(path: str | Path, polygons: Mapping[str, np.ndarray]) -> Path:
    """Write ``{image file name: (N, 2) pixel polygon}``, rounded to 0.01 px."""
    return write_json(
        path,
        {
            name: [[round(float(u), 2), round(float(v), 2)] for u, v in np.asarray(poly)]
            for name, poly in polygons.items()
        },
    )


def read_owned_areas(path: str | Path | None) -> dict[str, np.ndarray]:
    """``{image file name: (N, 2) float array}``; ``{}`` when ``path`` is None."""
    if path is None:
        return {}
    data = read_json(path)
    if not isinstance(data, dict):
        raise InputError("owned-area file must be a JSON object {image_name: [[u, v], ...]}", path=path, fix=FIX)
    out = {}
    for name, poly in data.items():
        try:
            arr = np.asarray(poly, dtype=float)
        except (TypeError, ValueError):
            arr = np.zeros((0,))
        if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 3 or not np.isfinite(arr).all():
            raise InputError(
                f"the polygon of '{name}' is not a list of at least 3 finite [u, v] points", path=path, fix=FIX
            )
        out[name] = arr
    return out
