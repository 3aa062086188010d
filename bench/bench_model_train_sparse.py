"""Training crops on sparse plants (issue 28): where a 256 px window placed anywhere would mostly hold no plant,
does placing it on a plant (``augment.crop_on_plant``) help? Synthetic photos (:mod:`matchplant.detection.synth`)
of ``--size`` px with a few plants each (the issue's hidden data: ~20 panicles in a 1024 px photo, one per ~50,000
px^2), trained as :mod:`bench.bench_model_train_real` trains (``inspect``'s advice, ``model.architecture: auto``
from random weights, one core), for a fixed number of epochs, once per ``crop_on_plant`` value given.

    taskset -c 0 python -m bench.bench_model_train_sparse --epochs 20 --on-plant 1 0   # 1024 px photos, 6-12 plants
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from bench.bench_model_train_real import run_on
from matchplant.core.runtime.log import setup_console
from matchplant.detection.synth import make_tiles


def main() -> None:
    """Parse the options, train at each ``crop_on_plant`` setting on sparse photos; print cost and test AP50."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=1024, help="photo side in pixels")
    ap.add_argument(
        "--radius",
        type=float,
        nargs=2,
        default=(20, 45),
        help="plant radius in pixels, least and most (large enough that inspect advises no tiling)",
    )
    ap.add_argument("--photos", type=int, default=24, help="training photos (a quarter as many for val and test)")
    ap.add_argument("--plants", type=int, nargs=2, default=(6, 12), help="plants per photo, least and most")
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--on-plant", type=float, nargs="+", default=[1.0, 0.0], help="augment.crop_on_plant values")
    args = ap.parse_args()
    setup_console()
    work = Path(tempfile.mkdtemp(prefix="bench_train_sparse_"))
    n_eval = max(args.photos // 4, 2)
    splits = [
        make_tiles(
            work / name,
            n_images=n,
            size=args.size,
            plants=tuple(args.plants),
            radius=tuple(args.radius),
            negatives=0,
            seed=seed,
            name=f"{name}.json",
        )
        for name, n, seed in (("train", args.photos, 0), ("val", n_eval, 1), ("test", n_eval, 2))
    ]
    for on_plant in args.on_plant:
        r = run_on(
            *splits,
            0.0,
            work,
            "cpu",
            [f"epochs={args.epochs}", f"val_every={args.epochs}", f"augment.crop_on_plant={on_plant:g}"],
        )
        print(
            json.dumps(
                {
                    "crop_on_plant": on_plant,
                    "size": args.size,
                    "plants": args.plants,
                    "radius": args.radius,
                    "advice": r["inspect_advice"],
                    **{
                        k: r[k]
                        for k in ("iterations_done", "cpu_s_per_iteration", "best_val", "test_AP50", "load_before")
                    },
                },
                default=str,
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
