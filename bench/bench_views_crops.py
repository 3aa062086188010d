"""Plant crops from raw photos (issue 46): the whole command against decoding every photo once.

    python -m bench.bench_views_crops                       # 1,000 photos of 4000x3000, 20,000 plants, best 3
    python -m bench.bench_views_crops --photos 200 --plants 4000 --runs 1     # a quick look
    taskset -c 1 python -m bench.bench_views_crops --runs 3  # pinned to one core

Builds a synthetic ODM project (no photo content to speak of: the decoder's time depends on the size and the
JPEG's detail, so each photo is one of 8 distinct noisy 12 MP JPEGs, hard-linked): a field of plants in rows
(domes on a flat DSM, 2 cm cells), a nadir flight over it on a grid (about 40 photos see each point), and the
plants' polygons. The floor is every photo decoded once with the same decoder (OpenCV); the ratio is
``cut_crops`` (draping, planning, decoding, cutting, writing, the index) over the floor, per run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import geopandas as gpd
import numpy as np
import rasterio
import shapely
from affine import Affine

from matchplant.views import CropSettings, cut_crops, survey_cameras

ROW, STEP = 0.76, 0.2  # metres between rows, between plants in a row
RADIUS, HEIGHT = 0.09, 0.3  # each plant: a dome
CELL = 0.02  # DSM cell, metres
OFFSET = (702309.0, 4524878.0)
DISTINCT = 8  # distinct JPEGs, hard-linked to make the flight


def build(root: Path, photos: int, plants: int, width: int, height: int) -> gpd.GeoDataFrame:
    """Write the project into ``root``; return the plants' polygons (map CRS)."""
    rows = max(1, int(round(np.sqrt(plants * STEP / ROW))))
    per_row = int(np.ceil(plants / rows))
    gx, gy = np.meshgrid(np.arange(rows) * ROW + 1.0, np.arange(per_row) * STEP + 1.0, indexing="ij")
    xy = np.column_stack([gx.ravel(), gy.ravel()])[:plants]
    field_w, field_l = rows * ROW + 2.0, per_row * STEP + 2.0
    # DSM: domes H (1 - (r/R)^2) on flat ground at 0 (plants on a regular grid: the nearest is arithmetic)
    nx, ny = int(np.ceil(field_w / CELL)), int(np.ceil(field_l / CELL))
    cx = (np.arange(nx) + 0.5) * CELL
    cy = field_l - (np.arange(ny) + 0.5) * CELL
    dx = (cx - 1.0) - np.clip(np.round((cx - 1.0) / ROW), 0, rows - 1) * ROW
    dy = (cy - 1.0) - np.clip(np.round((cy - 1.0) / STEP), 0, per_row - 1) * STEP
    rho2 = (dy[:, None] ** 2 + dx[None, :] ** 2) / RADIUS**2
    dsm = np.where(rho2 < 1, HEIGHT * (1 - rho2), 0.0).astype(np.float32)
    (root / "odm_dem").mkdir(parents=True)
    transform = Affine(CELL, 0, OFFSET[0], 0, -CELL, OFFSET[1] + field_l)
    with rasterio.open(
        root / "odm_dem" / "dsm.tif", "w", driver="GTiff", width=nx, height=ny, count=1, dtype="float32",
        crs="EPSG:32614", transform=transform, nodata=-9999, tiled=True,
    ) as dst:  # fmt: skip
        dst.write(dsm, 1)
    (root / "odm_georeferencing").mkdir()
    (root / "odm_georeferencing" / "coords.txt").write_text(f"WGS84 UTM 14N\n{OFFSET[0]:.0f} {OFFSET[1]:.0f}\n")
    # the flight: a grid of nadir photos over the field, about 40 seeing each point
    footprint = np.sqrt(40 * field_w * field_l / photos / (width / height)) * np.array([width / height, 1.0])
    altitude = 12.0
    focal = altitude / footprint[0]  # normalised by the image's larger side (OpenSfM)
    n_across = max(1, int(round(np.sqrt(photos * field_w / field_l))))
    n_along = int(np.ceil(photos / n_across))
    px, py = np.meshgrid(np.linspace(0, field_w, n_across), np.linspace(0, field_l, n_along), indexing="ij")
    centres = np.column_stack([px.ravel(), py.ravel(), np.full(px.size, altitude)])[:photos]
    R = np.diag([1.0, -1.0, -1.0])  # x east, y south (down the image), z down
    camera = {"projection_type": "brown", "width": width, "height": height, "focal_x": focal, "focal_y": focal,
              "c_x": 0.0, "c_y": 0.0, "k1": -0.02, "k2": 0.005, "k3": 0.0, "p1": 0.0, "p2": 0.0}  # fmt: skip
    names = [f"IMG_{k:05d}.JPG" for k in range(photos)]
    shots = {
        n: {"rotation": [np.pi, 0.0, 0.0], "translation": (-R @ c).tolist(), "camera": "cam"}
        for n, c in zip(names, centres)
    }
    (root / "opensfm").mkdir()
    (root / "opensfm" / "reconstruction.json").write_text(json.dumps([{"cameras": {"cam": camera}, "shots": shots}]))
    (root / "images").mkdir()
    rng = np.random.default_rng(0)
    sources = []
    for k in range(DISTINCT):
        img = cv2.GaussianBlur(rng.integers(0, 255, (height, width, 3), dtype=np.uint8), (0, 0), 1.2)
        sources.append(root / f"source_{k}.jpg")
        cv2.imwrite(str(sources[-1]), img, [cv2.IMWRITE_JPEG_QUALITY, 92])
    for k, n in enumerate(names):
        os.link(sources[k % DISTINCT], root / "images" / n)
    polys = shapely.buffer(shapely.points(xy[:, 0] + OFFSET[0], xy[:, 1] + OFFSET[1]), RADIUS, quad_segs=6)
    return gpd.GeoDataFrame({"plant_id": np.arange(1, plants + 1)}, geometry=polys, crs="EPSG:32614")


def decode_all(folder: Path) -> float:
    """Seconds to decode every photo once (the floor)."""
    t = time.perf_counter()
    for p in sorted(folder.iterdir()):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        assert img is not None
    return time.perf_counter() - t


def main() -> None:
    """Build the survey, then time the floor and the crops ``--runs`` times, alternating."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--photos", type=int, default=1000)
    ap.add_argument("--plants", type=int, default=20000)
    ap.add_argument("--width", type=int, default=4000, help="photo width in pixels (height 3/4)")
    ap.add_argument("--best", type=int, default=3, help="best N views per plant (0: every whole view)")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--work", type=Path, default=None, help="folder for the survey (default: a temporary one)")
    args = ap.parse_args()
    os.environ.setdefault("MATCHPLANT_QUIET", "1")
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_views_"))
    root = work / "project"
    shutil.rmtree(root, ignore_errors=True)
    t = time.perf_counter()
    plants = build(root, args.photos, args.plants, args.width, args.width * 3 // 4)
    print(f"survey: {args.photos} photos of {args.width}x{args.width * 3 // 4}, {args.plants} plants "
          f"(built in {time.perf_counter() - t:.0f} s)")  # fmt: skip
    survey = survey_cameras(root)
    ratios = []
    for run in range(args.runs):
        floor = decode_all(root / "images")
        out = work / f"crops_{run}"
        shutil.rmtree(out, ignore_errors=True)
        t = time.perf_counter()
        result = cut_crops(plants, survey, out, CropSettings(best=args.best))
        took = time.perf_counter() - t
        ratios.append(took / floor)
        print(f"run {run + 1}: decode floor {floor:.1f} s, crops {took:.1f} s, ratio {took / floor:.2f} "
              f"({result.crops} crops of {result.plants_seen} plants from {result.photos} photos)")  # fmt: skip
        shutil.rmtree(out, ignore_errors=True)
    spread = f" (min {min(ratios):.2f}, max {max(ratios):.2f})" if len(ratios) > 1 else ""
    print(f"ratio median {statistics.median(ratios):.2f}{spread}; "
          f"peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")  # fmt: skip
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
