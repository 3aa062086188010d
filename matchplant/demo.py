"""``make demo``: MatchPlant end to end on a generated field, without a screen, with a report.

1. generates the ``small`` synthetic field (an ODM-shaped project with exact ground truth, each plant
   with its own vigour (NDVI), a plot layout with missing plants, and a second date with grown plants);
2. writes ``pipeline.yaml`` chaining modules 0 to 9 and runs it with ``matchplant run`` (ODM's outputs
   come from the generator; the ground-truth boxes stand in for hand annotation; a CPU-sized detector
   trains for a few minutes);
3. writes ``report.md`` with the coverage map, training curves, AP, the projected plants over the
   orthophoto, per-plant height and NDVI against the truth (over the box and over the plant's canopy
   outlined on the CHM), the outlines against the true canopies, the plots' stand counts and gaps
   against the truth, and the plants re-centred on the second date; ``report/summary.json`` holds the
   figures (``traits.height_r``, ``traits.ndvi_r``, ``traits.outline_iou_median``,
   ``plots.stand_count_exact_share``, ...).

The detections that are projected and scored come only from photos the detector never saw: every
photo of the flight outside module 5's train and val splits (module 3's unselected photos and the test
split), linked into ``heldout_images/``; ``summary.json`` lists them (``held_out``).

With ``--noise realistic`` a second field of the same scene is generated with a photogrammetric DSM/DTM,
a 5-band multispectral raster and anti-aliased masks (simfield/noise.py); its photos are the exact field's,
so modules 8 and 9 run again on it with the same detections (``noisy/``), and the report and
``summary.json`` (``noisy``) give its figures beside the exact field's.

Run ``python -m matchplant.demo --help`` for the options. Re-running skips the finished steps. Ctrl-C
stops it with one line (exit 130); the finished steps are kept.
"""

from __future__ import annotations

import signal
import sys


def _interrupted_while_starting(signum, frame):  # Ctrl-C while the libraries load: one line, no traceback
    print("interrupted (Ctrl-C) while starting; nothing was written", file=sys.stderr)
    raise SystemExit(130)


if __name__ == "__main__":  # installed before the slow imports below (several seconds on a busy machine)
    signal.signal(signal.SIGINT, _interrupted_while_starting)

import argparse  # (after the Ctrl-C handler on purpose)
import os
import shutil
import time
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
from PIL import Image

from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.gui import figure
from matchplant.core.runtime.io import atomic_path, write_text
from matchplant.core.runtime.log import get_logger, setup_console
from matchplant.core.runtime.readers import read_json
from matchplant.core.runtime.validate import did_you_mean
from matchplant.demo_pipeline import HELD_OUT, NOISY, STEP_NOTES, demo_record, noisy_spec, pipeline_spec
from matchplant.demo_report import demo_table, write_report
from matchplant.pipeline import PipelineConfig, read_pipeline, run_pipeline
from matchplant.pipeline.write import write_pipeline
from matchplant.simfield import generate_field
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.scoring import (
    TRAIT_STATS,
    growth_scores,
    match_to_truth,
    outline_ious,
    pearson,
    plot_scores,
    positions,
    trait_scores,
)
from matchplant.spatial_stat_extractor.config import SpatialStatExtractorConfig
from matchplant.spatial_stat_extractor.run import run as run_stats

log = get_logger("demo")

EPOCHS = 2  # a fixed number of epochs, not a time budget: every machine trains the same model
# ... per preset: the tiny field's 9 photos give 9 iterations an epoch, so its 2 epochs were shorter than the
# warm-up (20 iterations) and trained no detector ("no plant found"); 20 give it 180 iterations
PRESET_EPOCHS = {"tiny": 20, "small": EPOCHS, "large": EPOCHS}


def default_epochs(preset: str, epochs: int | None = None) -> int:
    """The epochs the demo trains: ``epochs`` when given (--epochs), else the preset's own."""
    return epochs if epochs is not None else PRESET_EPOCHS.get(preset, EPOCHS)


REPO = Path(__file__).resolve().parents[1]
# the demo table of docs/demo.md lies between these lines (python -m matchplant.demo --update-docs rewrites it)
DEMO_PAGE = "docs/demo.md"
TABLE_START = "<!-- demo table: written by python -m matchplant.demo --update-docs -->"
TABLE_END = "<!-- end of demo table -->"
FIRST_STEPS = 6  # steps 0-5 run first: module 5's split decides which photos are held out


def held_out_photos(tiles_summary: dict, photos: list[str]) -> tuple[list[str], dict]:
    """The photos the detector never saw (outside module 5's train and val splits) and the split itself."""
    splits = {k: sorted(v.get("source_images", [])) for k, v in tiles_summary.get("splits", {}).items()}
    seen = set(splits.get("train", [])) | set(splits.get("val", []))
    return sorted(p for p in photos if p not in seen), splits


def link_photos(src: Path, names: list[str], dst: Path) -> None:
    """``dst`` holds exactly ``names`` from ``src`` (hard links, or copies where links are impossible): files
    already there are kept as they are, so a re-run with the same split finds step 7 up to date."""
    dst.mkdir(parents=True, exist_ok=True)
    for f in dst.iterdir():
        if f.name not in names:
            f.unlink()
    for name in names:
        target = dst / name
        if target.is_file() and target.stat().st_size == (src / name).stat().st_size:
            continue
        try:
            os.link(src / name, target)
        except OSError:
            shutil.copy2(src / name, target)


def compare_with_truth(out: Path, field: Path) -> dict:
    """Per-plant traits of the projected plants against the truth (matched by position), their outlines
    against the true canopies, the plots against the true stand counts and gaps, and the growth check
    (the plants re-centred on the second date)."""
    paths = FieldPaths(field)
    table = pd.read_csv(out / "9_stats" / "stats.csv")
    traits = trait_scores(table, paths)
    outlines = gpd.read_file(out / "9_stats" / "outlines.gpkg").set_index("plant_id").reindex(table["plant_id"])
    iou = outline_ious(outlines.geometry.values, table, paths)
    traits.update(
        outline_iou_median=float(np.nanmedian(iou)),
        outline_iou_p10=float(np.nanpercentile(iou, 10)),
        plants_projected=int(len(table)),
    )
    result = {"traits": traits}
    if (out / "9_stats" / "plots.csv").is_file():
        grid = read_json(paths.plots_json)
        result["plots"] = plot_scores(
            pd.read_csv(out / "9_stats" / "plots.csv"),
            pd.read_csv(out / "9_stats" / "plot_gaps.csv"),
            paths,
            grid["plant_spacing"],
        )
    if paths.later.dsm.is_file():
        result["growth"] = growth_check(out, paths)
    _scatter(out / "report" / "traits_vs_truth.png", table, paths)
    return result


def growth_check(out: Path, paths: FieldPaths) -> dict:
    """Module 9 with the second date: the first date's boxes reused, each plant re-centred."""
    cfg = load_config(
        SpatialStatExtractorConfig,
        None,
        [
            f"polygons={out / '8_plants' / 'plants.gpkg'}",
            f"output_dir={out / 'report' / 'growth'}",
            "rasters.date=d1",
            f"rasters.dsm={paths.dsm}",
            f"rasters.dtm={paths.dtm}",
            "vector_formats=[]",
            f"more_dates=[{{date: d2, dsm: {paths.later.dsm}, dtm: {paths.later.dtm}}}]",
        ],
    )
    run_stats(cfg)
    table = pd.read_csv(out / "report" / "growth" / "stats.csv")
    d1 = table.rename(columns=lambda c: c[:-3] if c.endswith("_d1") else c)
    return growth_scores(d1, paths, ("top_x_d2", "top_y_d2"))


def _scatter(path: Path, table: pd.DataFrame, paths: FieldPaths) -> None:
    """The paper's Figure 10, box statistics and canopy statistics side by side."""
    truth = pd.read_csv(paths.traits_csv)
    m = match_to_truth(positions(table), truth[["x", "y"]].to_numpy(float))
    ok = m >= 0
    t, s = truth.iloc[m[ok]], table[ok]
    # the statistics the report's table scores (one source: TRAIT_STATS), the box's left, the canopy's right
    panels = [
        (trait, col, f"{name} over the {where}")
        for trait, (box_col, canopy_col, name) in TRAIT_STATS.items()
        for col, where in ((box_col, "box"), (canopy_col, "canopy"))
    ]
    fig = figure(headless=True, figsize=(10, 9))
    for ax, (tcol, col, name) in zip(fig.subplots(2, 2).ravel(), panels):
        x, y = t[tcol].to_numpy(float), s[col].to_numpy(float) if col in s else np.full(len(t), np.nan)
        ax.scatter(x, y, s=6, alpha=0.5)
        lo, hi = np.nanmin(np.r_[x, y]), np.nanmax(np.r_[x, y])
        ax.plot([lo, hi], [lo, hi], "k--", lw=1, label="1:1")
        ax.set_xlabel(f"true {tcol}")
        ax.set_ylabel(name)
        ax.set_title(f"{name}\nr = {pearson(x, y):.3f}, n = {int(np.isfinite(y).sum())}", fontsize=9)
        ax.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")


def run_demo(
    out: Path,
    *,
    preset: str = "small",
    seed: int = 0,
    epochs: int | None = None,
    minutes: float = 0.0,
    pretrained: str = "none",
    tile: int = 128,
    from_step: str = "",
    noise: str = "exact",
    threads: int = 0,
) -> Path:
    """Run the whole demo into ``out``: generate the field, run modules 0 to 9 on it, write the report.

    Parameters
    ----------
    out : Path
        Output folder (created; a re-run skips the finished steps).
    preset : str
        Size of the synthetic field (``tiny``, ``small``, ...).
    seed : int
        Random seed of the field.
    epochs : int
        Training epochs of the detector (a fixed number, so every machine trains the same model).
    minutes : float
        Optional time budget for training (0: none; the results then depend on the machine).
    pretrained : str
        Starting weights of the detector: ``none``, ``imagenet`` or ``coco``.
    tile : int
        Side of module 5's training tiles, in pixels.
    from_step : str
        Re-run from this pipeline step on (e.g. ``6_train``); empty: only what is not up to date.
    noise : str
        ``exact``, or ``realistic`` to run modules 8 and 9 again on a photogrammetric DSM/DTM.
    threads : int
        CPU threads for training and detection (0: the cores free now).

    Returns
    -------
    Path
        The report (``report.md``).
    """
    out = Path(out).resolve()
    epochs = default_epochs(preset, epochs)
    out.mkdir(parents=True, exist_ok=True)
    field = out / "field"
    t0 = time.time()
    _field(field, preset, seed, "exact")
    t_field = time.time() - t0
    crs = read_json(field / "truth" / "field.json")["crs"]
    pipe = out / "pipeline.yaml"
    write_pipeline(
        pipe,
        pipeline_spec(field, crs, epochs=epochs, minutes=minutes, pretrained=pretrained, tile=tile, threads=threads),
        STEP_NOTES,
        "written by `make demo` (matchplant/demo.py); run again with: matchplant run pipeline.yaml\n"
        "Relative paths are relative to this file's folder; ${name} is a top-level key or an earlier step's key.",
    )
    (out / HELD_OUT).mkdir(exist_ok=True)
    photos = sorted(p.name for p in FieldPaths(field).undistorted_images.glob("*.tif"))
    held: list[str] = []
    splits: dict = {}

    def hold_out() -> None:  # module 5's split says which photos the detector will see; the others are held out
        names, split = held_out_photos(read_json(out / "5_tiles" / "summary.json"), photos)
        held.extend(names)
        splits.update(split)
        link_photos(FieldPaths(field).undistorted_images, held, out / HELD_OUT)
        log.info(
            "%d of %d photos held out for detection and scoring (not in module 5's train or val split)",
            len(held),
            len(photos),
        )

    results = run_in_two_parts(pipe, from_step, hold_out)
    timings = {"synthetic field": ("generated" if t_field > 1 else "reused", t_field)}
    timings.update(_step_times(pipe, results))
    compare = compare_with_truth(out, field)
    extra = {"held_out": held_out_record(out, held, splits), "environment": environment(out)}
    if noise == "realistic":
        extra["noisy"] = run_noisy(out, preset, seed, crs, from_step, timings)
    report = write_report(out, field, timings, compare, extra)
    log.info("report: %s (%.1f min in all)", report, (time.time() - t0) / 60)
    return report


def run_in_two_parts(pipe: Path, from_step: str, between) -> dict[str, str]:
    """Steps 0-5, then ``between()``, then the later steps: each step run (or found up to date) and listed
    once (the second part does not list the first part's steps again as skipped)."""
    names = [st.name for st in read_pipeline(pipe)[1]]
    first, rest = names[:FIRST_STEPS], names[FIRST_STEPS:]
    early = run_pipeline(PipelineConfig(pipeline=pipe, only=first, from_step=from_step if from_step in first else ""))
    between()
    later = run_pipeline(PipelineConfig(pipeline=pipe, only=rest, from_step=from_step if from_step in rest else ""))
    return {n: (early if n in first else later)[n] for n in names}


def _field(field: Path, preset: str, seed: int, noise: str) -> None:
    """Generate the demo's field unless the folder already holds it (same preset, seed and noise)."""
    meta = field / "truth" / "field.json"
    if meta.is_file() and FieldPaths(field).later.plants_csv.is_file():
        m = read_json(meta)
        if (m.get("preset"), m.get("seed"), m.get("noise", "exact")) == (preset, seed, noise):
            return
    log.info("generating the '%s' synthetic field (seed %d, noise %s) ...", preset, seed, noise)
    generate_field(preset=preset, seed=seed, out=field, vigour=True, second_date=True, noise=noise)


def _step_times(pipe: Path, results: dict, prefix: str = "") -> dict:
    """Each step's status and the seconds its last run took (from the pipeline's stamps)."""
    timings = {}
    top, steps = read_pipeline(pipe)
    for st in steps:
        stamp = pipe.parent / top["output_dir"] / ".pipeline" / f"{st.name}.json"
        secs = demo_record(stamp).get("seconds", 0.0)
        timings[prefix + st.name] = (results.get(st.name, "?"), secs)
    return timings


def held_out_record(out: Path, held: list[str], splits: dict) -> dict:
    """Which photos were scored, and a check from module 8's own views that no training photo was projected."""
    views = out / "8_plants" / "views.csv"
    projected = sorted(pd.read_csv(views, usecols=["image"])["image"].unique()) if views.is_file() else []
    train = set(splits.get("train", [])) | set(splits.get("val", []))
    return {
        "rule": "every photo of the flight outside module 5's train and val splits: module 3's unselected "
        "photos and the test split",
        "photos": held,
        "splits": splits,
        "photos_projected": len(projected),
        "training_photos_projected": len(set(projected) & train),
    }


def environment(out: Path) -> dict:
    """What the figures depend on besides the seeds: the thread count and device training used (from its
    summary: a re-run from a later step trains nothing, and this process's own threads say nothing) and the
    library versions."""
    import torch

    summary = out / "6_train" / "training_summary.json"
    trained = demo_record(summary)
    return {
        "torch": torch.__version__,
        "torch_threads": trained.get("threads"),
        "cpus": os.cpu_count(),
        "device": trained.get("device"),
    }


def run_noisy(out: Path, preset: str, seed: int, crs: str, from_step: str, timings: dict) -> dict:
    """The realistic field (same scene and photos): modules 8 and 9 again with the exact run's detections."""
    t0 = time.time()
    field = out / "field_noisy"
    _field(field, preset, seed, "realistic")
    timings["realistic field"] = ("generated" if time.time() - t0 > 1 else "reused", time.time() - t0)
    pipe = out / "pipeline_noisy.yaml"
    write_pipeline(
        pipe,
        noisy_spec(field, crs, out / "7_detect" / "predictions.json"),
        STEP_NOTES,
        "written by `python -m matchplant.demo --noise realistic`: modules 8 and 9 on the realistic field",
    )
    names = [st.name for st in read_pipeline(pipe)[1]]
    try:
        results = run_pipeline(PipelineConfig(pipeline=pipe, from_step=from_step if from_step in names else ""))
    except MatchPlantError as exc:  # the exact field's report stands; say why the noisy figures are missing
        log.warning("the realistic field's modules 8-9 failed: %s", exc)
        return {"error": str(exc)}
    timings.update(_step_times(pipe, results, prefix="noisy "))
    result = compare_with_truth(out / NOISY, field)
    evaluation = out / NOISY / "8_plants" / "evaluation.json"
    result["projection"] = demo_record(evaluation)
    result["noise"] = read_json(FieldPaths(field).noise_json)
    return result


def update_docs(out: Path, root: Path = REPO) -> None:
    """Copy the run's figures into ``docs/`` and rewrite the demo table of ``docs/demo.md`` from
    ``report/summary.json``, so that what the documentation shows is what this run measured."""
    summary = read_json(out / "report" / "summary.json")
    figures = {
        "3_select/coverage.png": "coverage.jpg",
        "8_plants/evaluation.png": "evaluation.jpg",
        "6_train/training_curves.png": "training_curves.png",
        "report/traits_vs_truth.png": "traits_vs_truth.png",
    }
    for src, dst in figures.items():
        if (out / src).is_file():
            with Image.open(out / src) as im, atomic_path(root / "docs" / dst) as tmp:
                (im.convert("RGB").save(tmp, quality=85) if dst.endswith(".jpg") else im.save(tmp))
    page = root / DEMO_PAGE
    text = page.read_text(encoding="utf-8")
    start, end = text.index(TABLE_START), text.index(TABLE_END)
    write_text(page, text[: start + len(TABLE_START)] + "\n" + demo_table(summary) + text[end:])
    log.info("updated %s and the figures in %s from %s", page, root / "docs", out / "report" / "summary.json")


class _Parser(argparse.ArgumentParser):
    """argparse's own errors (a value that is not a number, an unknown option) in the project's style: the
    problem and the fix, exit 2."""

    def error(self, message: str):
        self.exit(2, f"error: {message}\n  fix:  see the options with: {self.prog} --help\n")


CHOICES = {
    "preset": ("tiny", "small", "large"),
    "noise": ("exact", "realistic"),
    "pretrained": ("none", "imagenet", "coco"),
}


def check_args(args: argparse.Namespace) -> None:
    """Every option checked before the field is generated: its choices and ranges, and ``--from`` (a step of the
    demo whose earlier steps have finished in ``--out``)."""
    for key, allowed in CHOICES.items():
        value = getattr(args, key)
        if value not in allowed:
            hint = did_you_mean(value, allowed)
            raise ConfigError(
                f"--{key} {value!r} is not one of {', '.join(allowed)}{'; ' + hint if hint else ''}",
                fix=f"give --{key} one of: {', '.join(allowed)}",
            )
    for key, low in (("epochs", 1), ("minutes", 0), ("threads", 0)):
        if getattr(args, key) is not None and getattr(args, key) < low:
            raise ConfigError(f"--{key} {getattr(args, key)} is below {low}", fix=f"give --{key} {low} or more")
    if not args.from_step:
        return
    names = [
        s["name"] for s in pipeline_spec(Path("field"), "", epochs=1, minutes=0, pretrained="none", tile=128)["steps"]
    ]
    if args.from_step not in names:
        hint = did_you_mean(args.from_step, names)
        raise ConfigError(
            f"--from {args.from_step!r}: the demo has no such step{'; ' + hint if hint else ''}",
            fix=f"give --from one of: {', '.join(names)}",
        )
    stamps = Path(args.out).resolve() / ".pipeline"
    missing = [n for n in names[: names.index(args.from_step)] if not (stamps / f"{n}.json").is_file()]
    if missing:
        raise ConfigError(
            f"--from {args.from_step}: the steps before it have not finished in {args.out} ({', '.join(missing)})",
            fix=f"run the demo without --from first (python -m matchplant.demo --out {args.out}); --from re-runs a "
            "finished demo from a step on",
        )


def kept(out: Path) -> str:
    """What an interrupted demo keeps: the finished steps and, when training was stopped, where it stopped (the
    pipeline continues it from there: matchplant/pipeline/run.py)."""
    summary = out / "6_train" / "training_summary.json"
    try:
        trained = demo_record(summary) if (out / ".pipeline" / "6_train.started.json").is_file() else {}
    except MatchPlantError:
        trained = {}
    if trained.get("status") != "interrupted":
        return "the finished steps are kept"
    return f"the finished steps and training's checkpoint ({trained['message'].split(';')[0]}) are kept"


def main(argv: list[str] | None = None) -> int:
    """``python -m matchplant.demo``: parse the options and run the demo; the exit status (130 on Ctrl-C)."""
    p = _Parser(prog="python -m matchplant.demo", description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=Path("demo_output"), help="output folder (default demo_output)")
    p.add_argument("--preset", default="small", help="synthetic field size: " + ", ".join(CHOICES["preset"]))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--noise",
        default="exact",
        help="exact (default): the field's DSM, DTM and rasters are exact; realistic: also run modules 8 "
        "and 9 on the same field with a photogrammetric DSM/DTM and a 5-band multispectral raster "
        "and report both (a second field folder: about 600 MB more for the small field, and minutes)",
    )
    p.add_argument(
        "--epochs",
        type=int,
        default=None,
        help=f"training epochs (default {EPOCHS}; {PRESET_EPOCHS['tiny']} for the tiny field, whose epochs are 9 "
        "iterations): a fixed number, so every machine trains the same model",
    )
    p.add_argument(
        "--minutes",
        type=float,
        default=0.0,
        help="optional time budget for training (0 = none); the results then depend on the machine",
    )
    p.add_argument(
        "--pretrained",
        default="none",
        help="starting weights: none, imagenet or coco (coco needs internet once; none trains from scratch)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=0,
        help="CPU threads for training and detection (default 0: the cores free now, logged); another "
        "thread count trains a slightly different detector (docs/demo.md: the demo's tolerance)",
    )
    p.add_argument("--from", dest="from_step", default="", help="re-run from this step on (e.g. 6_train)")
    p.add_argument(
        "--update-docs",
        action="store_true",
        help="then copy the figures into docs/ and rewrite the demo table of docs/demo.md from this run",
    )
    p.add_argument("--debug", action="store_true")
    args = p.parse_args(argv)
    signal.signal(signal.SIGINT, signal.default_int_handler)  # from here on Ctrl-C lets the steps clean up
    try:
        check_args(args)  # before any work: a wrong option costs no field and no step
        setup_console()
        run_demo(
            args.out,
            preset=args.preset,
            seed=args.seed,
            epochs=args.epochs,
            minutes=args.minutes,
            pretrained=args.pretrained,
            from_step=args.from_step,
            noise=args.noise,
            threads=args.threads,
        )
        if args.update_docs:
            update_docs(Path(args.out).resolve())
    except KeyboardInterrupt:
        # a second Ctrl-C (or the same one reaching us again) must not interrupt the exit itself: progress bars and
        # worker pools still close while Python shuts down, and an interrupt there prints a traceback
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        print(
            f"interrupted (Ctrl-C); {kept(Path(args.out).resolve())}: run the demo again to go on from there",
            file=sys.stderr,
        )
        return 130
    except MatchPlantError as exc:
        if args.debug:
            raise
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
