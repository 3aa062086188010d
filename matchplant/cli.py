"""The one command line: ``matchplant <step> --config FILE [--set key=value ...] [--gui]``.

Each numbered folder's script calls :func:`folder_main`, so ``python 8_plant_projection/plant_projection.py``
and ``matchplant plant_projection`` are the same program. The steps come from :mod:`matchplant.steps`
(one small file per step there); this file only parses arguments, sets up logging and reports errors.
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import logging
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path

from matchplant import __version__
from matchplant.core.runtime.config import load_config, save_config
from matchplant.core.runtime.errors import ConfigError, MatchPlantError
from matchplant.core.runtime.guard import check_outputs
from matchplant.core.runtime.gui import require_display
from matchplant.core.runtime.io import WRITE_ERRORS, is_stream, write_error
from matchplant.core.runtime.log import setup_console, start_run_log, stop_run_log
from matchplant.steps import ALIASES, STEPS, StepSpec, resolve_step


def resolve_module(name: str) -> StepSpec:
    """The step named ``name`` (the CLI's own hook: tests replace it to run a stand-in step)."""
    return resolve_step(name)


def help_example(spec: StepSpec) -> str:
    """A ``--set`` example that belongs to the step: its first plain number or choice, at its default."""
    for f in dataclasses.fields(spec.config):
        if f.name.startswith("_") or dataclasses.is_dataclass(f.default) or f.default is dataclasses.MISSING:
            continue
        if isinstance(f.default, (int, float, str)) and not isinstance(f.default, bool) and f.default != "":
            return f"{f.name}={f.default}"
    return "KEY=VALUE"


def build_parser(spec: StepSpec) -> argparse.ArgumentParser:
    """The argument parser of one module: its config file, ``--set KEY=VALUE``, ``--gui`` and the other options."""
    p = argparse.ArgumentParser(
        prog=f"matchplant {spec.name}", description=(spec.config.__doc__ or "").strip().split("\n")[0]
    )
    if spec.positional_key:
        p.add_argument(
            "positional", nargs="?", metavar=spec.positional_key.upper(), help=f"sets '{spec.positional_key}'"
        )
    else:
        p.add_argument("config_file", nargs="?", type=Path, help="YAML config (same as --config)")
    p.add_argument("--config", "-c", type=Path, help="YAML config file")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"override a config key (repeatable), e.g. --set {help_example(spec)}",
    )
    if spec.gui is not None:
        p.add_argument("--gui", action="store_true", help="open the graphical interface")
    else:  # accepted, so that it ends in the project's message (no window; the command) instead of argparse's
        p.add_argument("--gui", action="store_true", help=argparse.SUPPRESS)
    p.add_argument(
        "--write-config",
        type=Path,
        metavar="FILE",
        help="write a commented config (every key, its meaning and its default, or the value from "
        "--config and --set), then exit",
    )
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug messages")
    p.add_argument("--quiet", action="store_true", help="only warnings and errors on the console")
    if spec.output_key and spec.output_key in {f.name for f in dataclasses.fields(spec.config)}:
        # one name in every module; --out is the older spelling of modules 0, 1 and 8
        p.add_argument(
            "--output",
            "--out",
            dest=f"flag__{spec.output_key}",
            default=None,
            metavar="FOLDER",
            help=f"sets '{spec.output_key}': the folder for every output of this step",
        )
    for flag, (key, text, *const) in spec.flags.items():
        if const:
            p.add_argument(flag, dest=f"flag__{key}", default=None, action="store_const", const=const[0], help=text)
        else:
            p.add_argument(flag, dest=f"flag__{key}", default=None, metavar=key.split(".")[-1].upper(), help=text)
    return p


def run_module(name: str, argv: Sequence[str], default_config: Path | None = None) -> int:
    """Parse ``argv`` for module ``name`` and run it; return the exit code. Never raises for user errors."""
    debug = "--debug" in argv
    spec = None
    try:
        spec = resolve_module(name)
        args = build_parser(spec).parse_args(list(argv))
        return _run(spec, args, default_config)
    except MatchPlantError as exc:
        if debug:
            traceback.print_exc()
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.errno not in WRITE_ERRORS or isinstance(exc, FileNotFoundError) or debug:
            return _internal_error(exc, debug)
        # a file no reader or writer of core/runtime/ opened (a library's own): still named, with the fix
        print(f"error: {file_error(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # a step that resumes (module 6) says how; `matchplant run` continues it by itself when re-run
        goes_on = f"; add --{spec.resume_key} to continue from there" if spec is not None and spec.resume_key else ""
        print(f"interrupted (Ctrl-C); outputs written so far are complete and kept{goes_on}", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - last resort: a short message, the traceback with --debug
        return _internal_error(exc, debug)


def file_error(exc: OSError) -> MatchPlantError:
    """The error of a file that could not be used (a full disk, no permission, a folder in the way), named."""
    what, fix = WRITE_ERRORS[exc.errno]
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG):  # only a write meets these
        if exc.filename is None:
            return MatchPlantError(f"cannot write an output: {what} ({exc.strerror or exc})", fix=fix)
        return write_error(exc.filename, exc)
    return MatchPlantError(
        f"cannot use {exc.filename or 'a file'}: {what} ({exc.strerror or exc})",
        path=exc.filename,
        fix="check that file's permissions and that it is a file, or give another path",
    )


def _internal_error(exc: BaseException, debug: bool) -> int:
    """A failure of ours: a short message (the traceback with --debug); exit code 1."""
    if debug:
        raise exc
    logging.getLogger("matchplant").debug("internal error", exc_info=True)
    print(
        f"internal error: {type(exc).__name__}: {exc}\n"
        f"  rerun with --debug for the traceback and report it with the log file",
        file=sys.stderr,
    )
    return 1


def config_header(spec: StepSpec) -> list[str]:
    """The lines under a written config's title: how to write it again, and how its paths are read."""
    return [
        f"Written by 'matchplant {spec.name} --write-config FILE' (add --config FILE to keep a file's values).",
        "Relative paths are relative to this file's folder.",
    ]


def _run(spec: StepSpec, args: argparse.Namespace, default_config: Path | None) -> int:
    level = logging.DEBUG if args.debug else logging.WARNING if args.quiet else logging.INFO
    logger = setup_console(level)
    positional_config = getattr(args, "config_file", None)
    if args.config and positional_config:
        raise ConfigError("give the config once: either as the first argument or with --config")
    config_path = args.config or positional_config or default_config
    overrides = list(args.overrides)
    if getattr(args, "positional", None):
        overrides.insert(0, f"{spec.positional_key}={args.positional}")
    for key, value in vars(args).items():
        if key.startswith("flag__") and value is not None:
            overrides.append(f"{key[len('flag__') :]}={value}")
    if args.write_config:
        # with a config or --set: those values, with the comments of this version; else the defaults
        cfg = (
            load_config(spec.config, config_path, overrides, strict=False)
            if config_path or overrides
            else spec.config()
        )
        stream = is_stream(args.write_config)  # '-', /dev/stdout: the config alone on that stream
        path = save_config(cfg, args.write_config, header=config_header(spec))
        print(f"wrote {path}", file=sys.stderr if stream else sys.stdout)
        return 0
    gui = getattr(args, "gui", False)
    if gui and spec.gui is None:
        raise ConfigError(
            f"module {spec.name} has no window (--gui)",
            fix=f"run it without --gui: matchplant {spec.name} --config FILE --set KEY=VALUE "
            f"(its options: matchplant {spec.name} --help)",
        )
    if gui:
        # no window possible: exit 2 with the headless command, instead of a GUI that silently does nothing
        require_display(f"matchplant {spec.name} --config FILE --set KEY=VALUE")
        cfg = load_config(spec.config, config_path, overrides, check_paths=False, strict=False)
        spec.load_gui()(cfg, config_path)
        return 0
    cfg = load_config(spec.config, config_path, overrides)
    check_outputs(cfg)  # outputs apart from the inputs and writable, before logs/ is made in the output folder
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


def folder_main(script: str | Path, config_name: str = "config.yaml") -> int:
    """Entry point of a numbered folder's script (``8_plant_projection/plant_projection.py``).

    The step is the folder's word (``8_plant_projection`` -> ``plant_projection``); its default config
    is ``config_name`` beside the script.
    """
    here = Path(script).resolve().parent
    name = here.name.split("_", 1)[1]
    default = here / config_name
    return run_module(name, sys.argv[1:], default_config=default if default.is_file() else None)


def main(argv: Sequence[str] | None = None) -> int:
    """``matchplant <module> ...``: list the modules, or run one; the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: matchplant <module> [--config FILE] [--set KEY=VALUE ...] [--gui] [--debug]\n")
        print("modules:")
        for i, (name, (folder, summary)) in enumerate(STEPS.items()):
            number = f"{i}" if folder else " "
            older = [a for a, n in ALIASES.items() if n == name and not a.isdigit()]
            also = f" (also: {', '.join(older)})" if older else ""
            print(f"  {number:>2} {name:<23} {summary}{also}")
        print(
            "\n'matchplant <module> --help' shows a module's options; "
            "'--write-config FILE' writes its commented config."
        )
        return 0
    if argv[0] in ("--version", "-V"):
        print(f"matchplant {__version__}")
        return 0
    return run_module(argv[0], argv[1:])


if __name__ == "__main__":
    raise SystemExit(main())
