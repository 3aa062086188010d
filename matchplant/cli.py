"""The one command line: ``matchplant <module> --config FILE [--set key=value ...] [--gui]``.

Each numbered folder's script calls :func:`folder_main`, so ``python 8_plant_projection/project_boxes.py``
and ``matchplant project_boxes`` are the same program. A module plugs in by exposing ``SPEC``, a
:class:`ModuleSpec`, from the Python module named in :data:`MODULES`.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from .errors import ConfigError, MatchPlantError

# name -> (python module exposing SPEC, numbered folder, one-line summary)
MODULES: dict[str, tuple[str, str, str]] = {
    "gps_embed": ("matchplant.gps_embed", "0_gps_embeder", "write GNSS positions into image EXIF"),
    "gcp_finder": ("matchplant.gcp_finder", "1_gcp_finder", "find and mark GCPs, write gcp_list.txt"),
    "odm_runner": ("matchplant.odm_runner", "2_odm_runner", "run OpenDroneMap and check its outputs"),
    "min_img_finder": ("matchplant.min_images", "3_min_img_finder", "fewest undistorted images covering the field"),
    "bbox_drawer": ("matchplant.annotate", "4_bbox_drawer", "draw plant boxes; COCO and YOLO"),
    "img_splitter": ("matchplant.tiling", "5_img_splitter", "tile annotated images, split train/val/test"),
    "train": ("matchplant.train", "6_model_train", "train a Faster R-CNN detector"),
    "model_test": ("matchplant.model_test", "7_model_test", "COCO evaluation and detection on new images"),
    "project_boxes": ("matchplant.projection", "8_plant_projection", "put detected plants on the map"),
    "stat_extractor": ("matchplant.stats", "9_spatial_stat_extractor", "plant polygons and per-plant statistics"),
    "simfield": ("matchplant.simfield", "", "generate a synthetic ODM project with exact ground truth"),
    "run": ("matchplant.pipeline", "", "run several modules in order from one pipeline.yaml"),
}
ALIASES = {str(i): name for i, name in enumerate(list(MODULES)[:10])}


@dataclass
class ModuleSpec:
    """How the command line drives one module."""

    name: str
    config: type
    run: Callable[[Any], Any]
    gui: Callable[[Any, Path | None], Any] | None = None
    # extra flags as shortcuts for --set: "--preset" -> ("preset", "help text"); a third item makes it a
    # switch without a value: "--resume" -> ("resume", "help", "true") means --set resume=true
    flags: dict[str, tuple[str, ...]] = field(default_factory=dict)
    output_key: str = "output_dir"
    # when set, the positional argument fills this key instead of naming a config file
    # (``matchplant run pipeline.yaml``)
    positional_key: str | None = None


def resolve_module(name: str) -> ModuleSpec:
    name = ALIASES.get(name, name).replace("-", "_")
    if name not in MODULES:
        import difflib
        close = difflib.get_close_matches(name, list(MODULES), n=1)
        hint = f"did you mean '{close[0]}'?" if close else "run 'matchplant --help' for the list"
        raise ConfigError(f"unknown module '{name}'; {hint}")
    target = MODULES[name][0]
    try:
        mod = importlib.import_module(target)
    except ModuleNotFoundError as exc:
        if exc.name and (exc.name == target or target.startswith(exc.name + ".")):
            raise ConfigError(f"module '{name}' is not part of this version of MatchPlant yet",
                              fix="update MatchPlant (git pull) or check the README for available modules") from exc
        raise
    return mod.SPEC


def build_parser(spec: ModuleSpec) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"matchplant {spec.name}",
                                description=(spec.config.__doc__ or "").strip().split("\n")[0])
    if spec.positional_key:
        p.add_argument("positional", nargs="?", metavar=spec.positional_key.upper(),
                       help=f"sets '{spec.positional_key}'")
    else:
        p.add_argument("config_file", nargs="?", type=Path, help="YAML config (same as --config)")
    p.add_argument("--config", "-c", type=Path, help="YAML config file")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key (repeatable), e.g. --set tile_size=512")
    if spec.gui is not None:
        p.add_argument("--gui", action="store_true", help="open the graphical interface")
    p.add_argument("--write-config", type=Path, metavar="FILE",
                   help="write a commented config with every key and its default, then exit")
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug messages")
    p.add_argument("--quiet", action="store_true", help="only warnings and errors on the console")
    for flag, (key, text, *const) in spec.flags.items():
        if const:
            p.add_argument(flag, dest=f"flag__{key}", default=None, action="store_const", const=const[0], help=text)
        else:
            p.add_argument(flag, dest=f"flag__{key}", default=None, metavar=key.split(".")[-1].upper(), help=text)
    return p


def run_module(name: str, argv: Sequence[str], default_config: Path | None = None) -> int:
    """Parse ``argv`` for module ``name`` and run it; return the exit code. Never raises for user errors."""
    debug = "--debug" in argv
    try:
        spec = resolve_module(name)
        args = build_parser(spec).parse_args(list(argv))
        return _run(spec, args, default_config)
    except MatchPlantError as exc:
        if debug:
            traceback.print_exc()
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; outputs written so far are complete and kept", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - last resort: a short message, the traceback with --debug
        if debug:
            raise
        logging.getLogger("matchplant").debug("internal error", exc_info=True)
        print(f"internal error: {type(exc).__name__}: {exc}\n"
              f"  rerun with --debug for the traceback and report it with the log file", file=sys.stderr)
        return 1


def _run(spec: ModuleSpec, args: argparse.Namespace, default_config: Path | None) -> int:
    from .config import load_config, save_config
    from .log import setup_console, start_run_log, stop_run_log

    level = logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO
    logger = setup_console(level)
    if args.write_config:
        path = save_config(spec.config(), args.write_config)
        print(f"wrote {path}")
        return 0
    positional_config = getattr(args, "config_file", None)
    if args.config and positional_config:
        raise ConfigError("give the config once: either as the first argument or with --config")
    config_path = args.config or positional_config or default_config
    overrides = list(args.overrides)
    if getattr(args, "positional", None):
        overrides.insert(0, f"{spec.positional_key}={args.positional}")
    for key, value in vars(args).items():
        if key.startswith("flag__") and value is not None:
            overrides.append(f"{key[len('flag__'):]}={value}")
    gui = getattr(args, "gui", False)
    if gui:
        cfg = load_config(spec.config, config_path, overrides, check_paths=False, strict=False)
        spec.gui(cfg, config_path)
        return 0
    cfg = load_config(spec.config, config_path, overrides)
    out = getattr(cfg, spec.output_key, None) if spec.output_key else None
    log_path = start_run_log(out, spec.name, cfg) if out is not None else None
    try:
        if config_path:
            logger.debug("config file: %s", config_path)
        spec.run(cfg)
        if log_path is not None:
            logger.info("log: %s", log_path)
    except MatchPlantError as exc:
        logger.debug("error", exc_info=True)
        raise exc
    finally:
        stop_run_log()
    return 0


def folder_main(name: str, script: str | Path) -> int:
    """Entry point of a numbered folder's script: uses the ``config.yaml`` beside it by default."""
    here = Path(script).resolve().parent
    default = here / "config.yaml"
    return run_module(name, sys.argv[1:], default_config=default if default.is_file() else None)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: matchplant <module> [--config FILE] [--set KEY=VALUE ...] [--gui] [--debug]\n")
        print("modules:")
        for i, (name, (_, folder, summary)) in enumerate(MODULES.items()):
            number = f"{i}" if folder else " "
            print(f"  {number:>2} {name:<16} {summary}")
        print("\n'matchplant <module> --help' shows a module's options; "
              "'--write-config FILE' writes its commented config.")
        return 0
    if argv[0] in ("--version", "-V"):
        from . import __version__
        print(f"matchplant {__version__}")
        return 0
    return run_module(argv[0], argv[1:])


if __name__ == "__main__":
    raise SystemExit(main())
