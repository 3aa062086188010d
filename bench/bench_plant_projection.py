"""Benchmark of module 8: boxes projected onto the DSM per second (one core), merge included.

    python bench/bench_plant_projection.py            # the large synthetic field (generated once into the temp folder)
    python bench/bench_plant_projection.py --quick    # the small field
    python bench/bench_plant_projection.py --field DIR  # an existing synthetic field
    python bench/bench_plant_projection.py --preset tiny --seed 1 --tilt 20 --slope 10   # another generated field
    python bench/bench_plant_projection.py --quick --noise realistic   # the small field with a photogrammetric DSM
    NUMBA_NUM_THREADS=1 taskset -c 0 python bench/bench_plant_projection.py   # really one core

Projects the ground-truth boxes of every undistorted image (score 1) and prints boxes/s for the ray/DSM
intersection and for the whole run (reading, projection, merge), and the accuracy against the truth.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core, as the issue asks
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from matchplant.core.formats.coco import read_dataset  # noqa: E402
from matchplant.core.formats.odm import ODMProject  # noqa: E402
from matchplant.core.geometry.surface import Surface  # noqa: E402
from matchplant.plant_projection.config import PlantProjectionConfig  # noqa: E402
from matchplant.plant_projection.evaluation import evaluate_boxes  # noqa: E402
from matchplant.plant_projection.geometry import box_outline  # noqa: E402
from matchplant.plant_projection.merge import merge_views  # noqa: E402
from matchplant.plant_projection.settings import ProjectionSettings  # noqa: E402
from matchplant.plant_projection.views import project_predictions  # noqa: E402
from matchplant.simfield.layout import FieldPaths  # noqa: E402


def field(
    preset: str, given: str | None, seed: int = 0, tilt: float = 0.0, slope: float = 0.0, noise: str = "exact"
) -> FieldPaths:
    """The given field, else the preset's field (with tilt, slope or noise), generated once in the temp folder."""
    if given:
        return FieldPaths(Path(given))
    extra = {"tilt_deg": tilt, "slope_pct": slope} if tilt or slope else {}
    name = f"{preset}_seed{seed}" + "".join(f"_{k}{v:g}" for k, v in extra.items())
    if noise != "exact":
        extra["noise"] = noise
        name += f"_{noise}"
    root = Path(tempfile.gettempdir()) / "matchplant_bench_fields" / name
    if not (root / "truth" / "map_boxes.csv").is_file():
        from matchplant.simfield import generate_field

        print(f"generating the {preset} synthetic field in {root} (once) ...", flush=True)
        generate_field(preset=preset, seed=seed, out=root, **extra)
    return FieldPaths(root)


def bare_kernel(project: ODMProject, ds: dict, edge_points: int) -> tuple[float, int]:
    """CPU seconds of the bare ray/DSM intersection (Surface.intersect, no clearance) of every box outline ray,
    and the number of boxes: the kernel's own speed, beside the whole path's."""
    surface = Surface.open(project.path("dsm"))
    by_image: dict = {}
    for a in ds["annotations"]:
        by_image.setdefault(a["image_id"], []).append(a["bbox"])
    cpu, n = 0.0, 0
    for im in ds["images"]:
        if im["id"] not in by_image:
            continue
        sid = im["file_name"][:-4]
        shot, frame = project.nominal_shot(sid), project.frame_of(sid)
        b = np.array(by_image[im["id"]], dtype=float)
        uv = box_outline(np.column_stack([b[:, :2], b[:, :2] + b[:, 2:]]), edge_points).reshape(-1, 2)
        dirs = shot.ray_directions(uv)
        origin = frame.to_map(shot.center[None, :])
        c0 = time.process_time()
        surface.intersect(origin, dirs)
        cpu += time.process_time() - c0
        n += len(b)
    return cpu, n


def main() -> None:
    """Parse the options, time module 8's projection and merge of the field's true boxes, print boxes/s and accuracy."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="use the small field instead of the large one")
    ap.add_argument("--field", help="an existing synthetic field folder")
    ap.add_argument(
        "--preset", help="generate this preset instead (tiny, small, large, split; once, in the temp folder)"
    )
    ap.add_argument("--seed", type=int, default=0, help="with --preset: the field's seed")
    ap.add_argument("--tilt", type=float, default=0.0, help="with --preset: forward camera tilt, degrees")
    ap.add_argument("--slope", type=float, default=0.0, help="with --preset: terrain slope, percent")
    ap.add_argument(
        "--noise",
        default="exact",
        choices=("exact", "realistic"),
        help="with --preset/--quick: the field's DSM exact or photogrammetric (simfield's noise)",
    )
    ap.add_argument("--edge-points", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3, help="runs; their median and range are reported")
    args = ap.parse_args()
    f = field(
        args.preset or ("small" if args.quick else "large"), args.field, args.seed, args.tilt, args.slope, args.noise
    )
    ds = read_dataset(f.boxes_undistorted, validate=False)
    preds = {
        "images": ds["images"],
        "categories": ds["categories"],
        "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
    }
    n = len(preds["predictions"])
    project = ODMProject(f.root)
    settings = ProjectionSettings.from_config(PlantProjectionConfig(edge_points=args.edge_points))

    # the core: ray/DSM intersection of every box outline, image by image, several runs: the figure is their
    # median and the spread their range (one run, or the best of a few, claimed more than a later run gives)
    runs = []
    for _ in range(args.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        views, rejected = project_predictions(project, preds, settings)
        t1 = time.perf_counter()
        plants = merge_views(views)
        t2, c2 = time.perf_counter(), time.process_time()
        runs.append((t0, t1, t2, c2 - c0))
    t0, t1, t2, cpu = sorted(runs, key=lambda r: r[3])[len(runs) // 2]  # the median run by CPU time
    per_run = sorted(n / r[3] for r in runs)
    truth = pd.read_csv(f.map_boxes)[["xmin", "ymin", "xmax", "ymax"]].to_numpy()
    m = evaluate_boxes(truth, plants[["xmin", "ymin", "xmax", "ymax"]].to_numpy())
    rays = n * 4 * (args.edge_points + 1)
    print(f"field: {f.root} ({len(ds['images'])} images, {len(truth)} plants)")
    print(f"boxes: {n} ({rays} rays), not projected: {len(rejected)}")
    print(f"projection (read + rays/DSM): {t1 - t0:.2f} s = {n / (t1 - t0):,.0f} boxes/s")
    print(f"merge into plants:            {t2 - t1:.2f} s = {n / max(t2 - t1, 1e-9):,.0f} boxes/s")
    print(f"total:                        {t2 - t0:.2f} s = {n / (t2 - t0):,.0f} boxes/s")
    print(
        f"total CPU time (one thread):  {cpu:.2f} s = {n / cpu:,.0f} boxes/s, median of {args.repeat} runs "
        f"(range {per_run[0]:,.0f}-{per_run[-1]:,.0f}; the wall-clock figures include waiting for a shared core); "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    if not project.is_split and project.frame().is_affine:
        k_cpu, k_n = bare_kernel(project, ds, args.edge_points)
        print(
            f"bare ray kernel (Surface.intersect, CPU): {k_cpu:.2f} s = {k_n / k_cpu:,.0f} boxes/s "
            f"(whole path: {n / cpu:,.0f} boxes/s)"
        )
    try:
        import resource  # POSIX only

        print(f"peak memory (max RSS): {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:,.0f} MB")
    except ImportError:
        pass
    if len(rejected):
        print("not projected, by reason:", rejected["reason"].value_counts().to_dict())
    print(
        f"plants: {len(plants)} (truth {len(truth)}), median views {np.median(plants['views']):.0f}; "
        f"matched {m['share_matched']:.1%}, IoU>0.5 {m['share_iou_above_0.5']:.1%}, "
        f"median IoU {m['iou_median']:.3f}"
    )


if __name__ == "__main__":
    main()
