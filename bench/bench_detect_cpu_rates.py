"""Seconds per megapixel of one detection pass on a CPU core, per architecture, with its spread (issue 40).

    taskset -c 1 python bench/bench_detect_cpu_rates.py                 # every measured architecture, 5 rounds
    taskset -c 1 python bench/bench_detect_cpu_rates.py --rounds 3 fasterrcnn_resnet18_fpn_lite

The rates kept in ``matchplant/detection/architectures.py`` (``cpu_seconds_per_megapixel``: docs/performance.md's
"How long will it take?" rows and ``bench_detect_cover.py``'s hours; module 7's own estimate times the real model
instead). One thread, random weights, one 1024 px tile per pass (module 7's default tile, resized by each model
to its ``min_size``): :func:`matchplant.detection.device.measure_cpu_rates`, one pass after a warm-up per
measurement. The architectures alternate within each round (their order rotated round by round) so that a
change in the machine's load reaches all of them alike; the median, the range and the load average before and
after are printed as JSON. Pin it to one core and leave the others idle: the rates stated before this bench
(2.5 to 4x these) were measured while other jobs shared the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics

import torch

from matchplant.detection.architectures import ARCHITECTURES
from matchplant.detection.device import measure_cpu_rates


def main(argv: list[str] | None = None) -> dict:
    """Parse the options, time detection passes per architecture on one core in rounds; the s/MP and their spread."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("architectures", nargs="*", help="default: every architecture with a measured rate")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--tile", type=int, default=1024)
    args = ap.parse_args(argv)
    names = args.architectures or [a.name for a in ARCHITECTURES.values() if a.cpu_seconds_per_megapixel is not None]
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    runs: dict[str, list[float]] = {n: [] for n in names}
    for r in range(args.rounds):
        order = names[r % len(names) :] + names[: r % len(names)]
        for name in order:
            runs[name].append(measure_cpu_rates([name], tile=args.tile, repeats=1)[name])
            print(f"round {r + 1}/{args.rounds} {name}: {runs[name][-1]:.2f} s/MP", flush=True)
    result = {
        "affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_before": [round(v, 2) for v in load_before],
        "load_after": [round(v, 2) for v in os.getloadavg()],
        "tile": args.tile,
        "threads": torch.get_num_threads(),
        "seconds_per_megapixel": {
            n: {
                "median": round(statistics.median(v), 2),
                "min": round(min(v), 2),
                "max": round(max(v), 2),
                "runs": [round(x, 2) for x in v],
                "kept_in_code": ARCHITECTURES[n].cpu_seconds_per_megapixel,
            }
            for n, v in runs.items()
        },
    }
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
