"""Benchmark of module 8 through a Metashape project against the ODM path (the same field, the same boxes).

    python -m bench.bench_plant_projection_cameras            # the small synthetic field (generated once)
    NUMBA_NUM_THREADS=1 taskset -c 1 python -m bench.bench_plant_projection_cameras --pairs 5

Writes the field's ODM poses as a Metashape camera export and a Pix4D params folder (our writers), projects the
ground-truth boxes of every original photo through each, alternating runs, and prints the CPU seconds of each
path (median and range) and its ratio to ODM's within each round (median and quartiles).
"""

from __future__ import annotations

import argparse
import gc
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from bench.bench_plant_projection import field  # noqa: E402
from matchplant.core.formats.coco import read_dataset  # noqa: E402
from matchplant.core.formats.metashape_writer import write_metashape  # noqa: E402
from matchplant.core.formats.odm import ODMProject  # noqa: E402
from matchplant.core.formats.pix4d import write_pix4d  # noqa: E402
from matchplant.core.formats.projects import open_project  # noqa: E402
from matchplant.plant_projection.merge import merge_views  # noqa: E402
from matchplant.plant_projection.views import project_predictions  # noqa: E402


def main() -> None:
    """Time module 8 through ODM, Metashape and Pix4D projects of one field."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="small", help="the synthetic field's preset (generated once)")
    ap.add_argument("--pairs", type=int, default=5, help="alternating runs of each path")
    args = ap.parse_args()
    f = field(args.preset, None)
    ds = read_dataset(f.boxes_raw, validate=False)
    preds = {"images": ds["images"], "categories": ds["categories"]}
    preds["predictions"] = [dict(a, score=1.0) for a in ds["annotations"]]
    odm = ODMProject(f.root)
    out = Path(tempfile.mkdtemp(prefix="matchplant_cameras_bench_"))
    shots = odm.reconstruction().shots
    (out / "meta").mkdir()
    write_metashape(out / "meta" / "cameras.xml", shots, odm.frame())
    write_pix4d(out / "p4d", "field", shots, odm.frame())
    dsm = f.root / "odm_dem" / "dsm.tif"
    paths = {
        "odm": lambda: ODMProject(f.root),
        "metashape": lambda: open_project(out / "meta" / "cameras.xml", dsm=dsm),
        "pix4d": lambda: open_project(out / "p4d", dsm=dsm),
    }
    times: dict[str, list[float]] = {k: [] for k in paths}
    for make in paths.values():  # warm-up: numba compilation, PROJ's database
        merge_views(project_predictions(make(), preds)[0])
    order = list(paths)
    for i in range(args.pairs):  # each round in another order: no path always runs right after another
        for k in order[i % len(order) :] + order[: i % len(order)]:
            gc.collect()
            c0 = time.process_time()
            merge_views(project_predictions(paths[k](), preds)[0])
            times[k].append(time.process_time() - c0)
    n = len(preds["predictions"])
    base = np.array(times["odm"])
    print(f"{n} boxes on {len(ds['images'])} original photos, {args.pairs} runs each (CPU seconds, reading included)")
    for k, t in times.items():
        med = float(np.median(t))
        q1, mid, q3 = np.percentile(np.array(t) / base, [25, 50, 75])  # the ratio within each round
        print(
            f"  {k:10s} median {med:.3f} s ({min(t):.3f}-{max(t):.3f}), {n / med:,.0f} boxes/s, "
            f"x{mid:.3f} ODM (round by round; quartiles {q1:.3f}-{q3:.3f})"
        )


if __name__ == "__main__":
    main()
