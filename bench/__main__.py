"""``python -m bench``: MatchPlant against its peers, timed in turn on one pinned core (see bench/harness.py).

python -m bench                       # every comparison, full size (tens of minutes)
python -m bench --quick               # small sizes (a few minutes)
python -m bench --only zonal-coverage --only gps-embed
python -m bench --device cuda         # training and tiled detection on the GPU
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bench.runner import GPU_NAMES, REGISTRY, run_all, run_child


def main(argv: list[str] | None = None) -> int:
    """``python -m bench``: run the chosen comparisons and print each one's speed ratio; the exit status."""
    ap = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes: a short run")
    ap.add_argument(
        "--only",
        action="append",
        choices=sorted(REGISTRY),
        metavar="NAME",
        help=f"run only this comparison (repeatable): {', '.join(REGISTRY)}",
    )
    ap.add_argument(
        "--device",
        default="cpu",
        choices=["cpu", "cuda"],
        help="cuda: GPU figures for training and tiled detection (needs a CUDA GPU)",
    )
    ap.add_argument("--pairs", type=int, default=3, help="timed ours/peer pairs after the warm-up (at least 3)")
    ap.add_argument(
        "--runs",
        type=int,
        default=None,
        help="runs of each comparison, each in a fresh process; the row's spread is the range of the runs' medians "
        "(default 3 on the CPU; 1 with --device cuda, whose rows must fit a short GPU session)",
    )
    ap.add_argument("--no-save", action="store_true", help="do not write the JSON record in bench/results/")
    ap.add_argument("--child", metavar="NAME", help=argparse.SUPPRESS)
    ap.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return run_child(args.child, args.quick, args.device, args.pairs, args.result)
    if args.pairs < 3:
        ap.error("--pairs must be at least 3 (a min-max needs several pairs)")
    names = args.only or (list(GPU_NAMES) if args.device == "cuda" else list(REGISTRY))
    if args.device == "cuda":
        import torch  # only for this check

        if not torch.cuda.is_available():
            print(
                "python -m bench --device cuda: no CUDA GPU is visible to PyTorch "
                f"(torch {torch.__version__}, CUDA build {torch.version.cuda}); run it on a machine with an "
                "NVIDIA GPU and a CUDA build of PyTorch, or leave out --device cuda",
                file=sys.stderr,
            )
            return 2
        names = [n for n in names if n in GPU_NAMES]
    if args.runs is None:
        args.runs = 1 if args.device == "cuda" else 3
    if args.runs < 1:
        ap.error("--runs must be at least 1")
    return run_all(names, args.quick, args.device, args.pairs, save=not args.no_save, runs=args.runs)


if __name__ == "__main__":
    raise SystemExit(main())
