"""The tables the reliability tests run over, discovered from the code rather than listed by hand, so that a new
step, flag, config key or file reader is checked without anyone adding it here (issue 47):

- :func:`config_classes`: every step's config class (``matchplant.steps.STEPS``), and the pipeline's;
- :func:`config_fields`: every key of a config class, nested sections included, with its type and path kind;
- :func:`flags`: every command-line option of every step (argparse, as ``matchplant <step> --help`` shows them);
- :func:`calls`: every call of a given function in the package's source (``json.load``, ``yaml.safe_load``...).
"""

from __future__ import annotations

import ast
import dataclasses
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union, get_args, get_origin, get_type_hints

from matchplant.cli import build_parser
from matchplant.steps import STEPS, resolve_step

PACKAGE = Path(__file__).resolve().parents[1] / "matchplant"


def step_names() -> list[str]:
    """Every step of the command line, in ``matchplant --help``'s order."""
    return list(STEPS)


def config_classes() -> dict[str, type]:
    """Step name -> its config class."""
    return {name: resolve_step(name).config for name in STEPS}


@dataclass(frozen=True)
class Key:
    """One config key: ``step``, dotted ``name``, declared type, ``path`` kind (None, file, dir, out, out_file...)."""

    step: str
    name: str
    type: Any
    path: str | None

    def __str__(self) -> str:
        return f"{self.step}:{self.name}"


def _unwrap(typ: Any) -> set[Any]:
    """The types a declared type can hold: Optional/Union members and list/tuple items."""
    origin = get_origin(typ)
    if origin in (Union, types.UnionType):
        return set().union(*(_unwrap(a) for a in get_args(typ) if a is not type(None)))
    if origin in (list, tuple, typing.Sequence):
        return set().union(*(_unwrap(a) for a in get_args(typ) if a is not Ellipsis)) if get_args(typ) else set()
    return {typ}


def config_fields(step: str, cls: type, prefix: str = "") -> list[Key]:
    """Every key of ``cls`` (nested sections as dotted keys); private keys (``_x``) left out."""
    out = []
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name.startswith("_"):
            continue
        typ = hints[f.name]
        if dataclasses.is_dataclass(typ):
            out += config_fields(step, typ, f"{prefix}{f.name}.")
        else:
            out.append(Key(step, prefix + f.name, typ, f.metadata.get("path")))
    return out


def all_keys() -> list[Key]:
    """Every key of every step's config."""
    return [k for name, cls in config_classes().items() for k in config_fields(name, cls)]


def holds(key: Key, typ: type) -> bool:
    """The key holds values of ``typ`` (alone, optional, or as list items)."""
    return typ in _unwrap(key.type)


@dataclass(frozen=True)
class Flag:
    """One option of ``matchplant <step>``: its spellings, where it goes (``dest``) and the config key it sets."""

    step: str
    option: str
    dest: str
    key: str | None  # the config key it sets (None: --write-config, --config...)
    takes_value: bool

    def __str__(self) -> str:
        return f"{self.step} {self.option}"


def flags() -> list[Flag]:
    """Every option of every step's parser (help and the switches without a value included)."""
    out = []
    for name in STEPS:
        parser = build_parser(resolve_step(name))
        for action in parser._actions:  # noqa: SLF001 - argparse has no public list of its options
            if not action.option_strings:
                continue
            key = action.dest[len("flag__") :] if action.dest.startswith("flag__") else None
            out.append(Flag(name, action.option_strings[0], action.dest, key, action.nargs != 0))
    return out


def key_of(step: str, dotted: str) -> Key | None:
    """The config key ``dotted`` of ``step`` (None when there is none)."""
    return next((k for k in config_fields(step, resolve_step(step).config) if k.name == dotted), None)


def output_flags() -> list[Flag]:
    """Every option whose value names an output: ``--write-config`` and the flags that set an output key."""
    out = []
    for flag in flags():
        if not flag.takes_value:
            continue
        key = key_of(flag.step, flag.key) if flag.key else None
        if flag.dest == "write_config" or (key is not None and key.path in ("out", "out_file")):
            out.append(flag)
    return out


# --------------------------------------------------------------------------------------------------
# the package's source


def source_files() -> list[Path]:
    """Every Python file of the package."""
    return sorted(PACKAGE.rglob("*.py"))


def calls(module: str, functions: set[str]) -> list[tuple[str, int, str]]:
    """``(file relative to the package, line, call)`` of every ``module.function(...)`` in the package, the module
    imported under its name or the function imported from it."""
    found = []
    for path in source_files():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        direct = {
            a.asname or a.name
            for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and node.module == module
            for a in node.names
            if a.name in functions
        }
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            name = None
            if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id == module:
                name = f"{module}.{f.attr}" if f.attr in functions else None
            elif isinstance(f, ast.Name) and f.id in direct:
                name = f.id
            if name:
                found.append((path.relative_to(PACKAGE).as_posix(), node.lineno, name))
    return found
