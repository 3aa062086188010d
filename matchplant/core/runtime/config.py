"""Typed configuration: each module's settings are a dataclass with documented defaults.

Declare fields with :func:`param`, which records the help text and the checks::

    @dataclass
    class ImgSplitterConfig:
        tile_size: int = param(1024, "tile side in pixels", min=64)
        images: Path = param(None, "folder of annotated images", path="dir")

Load with :func:`load_config` (YAML file plus ``key=value`` overrides). Unknown keys are an error that
names the closest valid key; values are converted to the declared type and checked (ranges, choices,
existing paths), and every message names the key, the file and what to change.

Relative paths in a YAML file are relative to that file's folder (so a project folder can be moved);
relative paths given on the command line are relative to the current directory.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
import math
import os
import textwrap
import types
import typing
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

import yaml

from matchplant.core.runtime.errors import ConfigError
from matchplant.core.runtime.io import STDOUT, write_text
from matchplant.core.runtime.readers import parse_value, read_yaml

PATH_KINDS = (None, "file", "dir", "exists", "out", "out_file")


def param(
    default: Any = MISSING,
    help: str = "",
    *,
    min: float | None = None,
    max: float | None = None,
    choices: typing.Sequence[Any] | None = None,
    path: str | None = None,
    required: bool = False,
    default_factory: Any = MISSING,
) -> Any:
    """A documented config field.

    ``min``/``max`` bound numbers (and every item of a list of numbers); ``choices`` lists the allowed
    values; ``path`` is ``"file"``, ``"dir"`` or ``"exists"`` for inputs that must exist, ``"out"``
    for output folders (created when the module runs), ``"out_file"`` for an output file (``-`` is standard
    output). ``required`` fields default to None
    and must be given.
    """
    if path not in PATH_KINDS:
        raise ValueError(f"path must be one of {PATH_KINDS}")
    metadata = {"help": help, "min": min, "max": max, "choices": choices, "path": path, "required": required}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=metadata)
    if isinstance(default, (list, dict, set)):
        value = default
        return field(default_factory=lambda: type(value)(value), metadata=metadata)
    return field(default=default, metadata=metadata)


def section(cls: type) -> Any:
    """A nested config section (a dataclass instance with its own defaults)."""
    return field(default_factory=cls, metadata={"help": (cls.__doc__ or "").strip().split("\n")[0]})


# --------------------------------------------------------------------------------------------------
# loading


def load_config(
    cls: type,
    path: str | Path | None = None,
    overrides: typing.Iterable[str] = (),
    *,
    check_paths: bool = True,
    strict: bool = True,
) -> Any:
    """Build a ``cls`` instance from a YAML file and ``key=value`` overrides, then validate it.

    ``strict=False`` skips validation (a GUI loads an incomplete config and lets the user finish it).
    """
    data: dict = {}
    source = "defaults"
    base = Path.cwd()
    if path is not None:
        path = Path(path)
        data = read_yaml_mapping(path)
        source = str(path)
        base = path.resolve().parent
    cfg = _build(cls, data, prefix="", source=source, base=base)
    overrides = list(overrides)
    for item in overrides:
        key, value = parse_override(item)
        set_value(cfg, key, value, source="--set", base=Path.cwd())
    if overrides:  # a value that fails validation may come from either
        source = "the command line" if path is None else f"{source} or the command line"
    if strict:
        validate(cfg, source=source, check_paths=check_paths)
    return cfg


def read_yaml_mapping(path: Path) -> dict:
    """A config file's settings (:func:`matchplant.core.runtime.readers.read_yaml`: a key given twice, a syntax
    error and a file that is not 'key: value' lines are errors naming the file and the line)."""
    if str(path) == STDOUT:
        raise ConfigError(
            "--config -: a config is read from a file, not from standard input",
            fix="save the config to a file and give its path (matchplant <module> --write-config FILE writes one)",
        )
    if not Path(path).is_file():
        raise ConfigError(
            "config file not found" if not Path(path).exists() else "the config is a folder, not a file",
            path=path,
            fix="check the path, or write a template with --write-config FILE",
        )
    return read_yaml(path, what="config file", allow_empty=True)


def parse_override(item: str) -> tuple[str, Any]:
    """``key=value`` from ``--set`` or a flag: the key, and the value read as in a YAML file (``-`` is itself)."""
    if "=" not in item:
        raise ConfigError(
            f"--set expects key=value, got {item!r}",
            fix="write it as --set key=value, for example --set output_dir=runs/mine",
        )
    key, text = item.split("=", 1)
    return key.strip(), parse_value(text)


def set_value(cfg: Any, dotted_key: str, value: Any, *, source: str = "--set", base: Path | None = None) -> None:
    """Set ``a.b.c`` on a config instance, converting and checking the key like the YAML loader."""
    parts = dotted_key.split(".")
    target = cfg
    for i, part in enumerate(parts):
        prefix = ".".join(parts[:i])
        names = {f.name: f for f in fields(target)}
        part = next(iter(_resolve_aliases(type(target), {part: None}, prefix, source)))
        if part not in names:
            raise _unknown_key(part, names, prefix, source, type(target))
        if i < len(parts) - 1:
            target = getattr(target, part)
            if not is_dataclass(target):
                raise ConfigError(f"'{'.'.join(parts[: i + 1])}' has no sub-keys", fix=f"use --set {part}=VALUE")
        else:
            hints = get_type_hints(type(target))
            value = _coerce(value, hints[part], dotted_key, source, base or Path.cwd())
            _check_stdout(value, names[part].metadata, dotted_key, source)
            setattr(target, part, value)


def _unknown_key(key: str, names: typing.Iterable[str], prefix: str, source: str, cls: type) -> ConfigError:
    """An unknown key: a key the class renamed (its ``renamed_keys``: old -> (new, how to convert)) names its
    successor, any other the closest valid key."""
    full = f"{prefix}.{key}" if prefix else key
    renamed = getattr(cls, "renamed_keys", {})
    if key in renamed:
        new, how = renamed[key]
        new = f"{prefix}.{new}" if prefix else new
        return ConfigError(f"config key '{full}' ({source}) was replaced by '{new}'", fix=f"write {new}: {how}")
    close = difflib.get_close_matches(key, list(names), n=1, cutoff=0.5)
    hint = (
        f"did you mean '{(prefix + '.') if prefix else ''}{close[0]}'?"
        if close
        else f"valid keys here: {', '.join(sorted(names))}"
    )
    return ConfigError(
        f"unknown config key '{full}' ({source}); {hint}",
        fix="correct or remove the key; see the module's config.yaml for every key",
    )


def from_dict(cls: type, data: dict, *, prefix: str = "", source: str = "a mapping", base: Path | None = None) -> Any:
    """A ``cls`` instance from plain data (e.g. settings stored in a checkpoint), converted and checked
    exactly as a YAML file would be, so a stored config cannot bypass the loader's rules."""
    return _build(cls, data, prefix=prefix, source=source, base=base or Path.cwd())


def _resolve_aliases(cls: type, data: dict, prefix: str, source: str) -> dict:
    """Keys under another name the class still accepts (its ``key_aliases``: other name -> key), so the same
    thing has one name in every module while older configs keep working; each use is noted in the log."""
    aliases = getattr(cls, "key_aliases", {})
    if not aliases or not any(k in aliases for k in data):
        return data
    out = {}
    for key, value in data.items():
        name = aliases.get(key, key)
        if name != key:
            full = f"{prefix}.{key}" if prefix else str(key)
            if name in data:
                raise ConfigError(
                    f"config keys '{full}' and '{name}' ({source}) name the same setting", fix=f"keep only '{name}'"
                )
            logging.getLogger("matchplant.config").info(
                "config key '%s' (%s) is read as '%s', its name in every module", full, source, name
            )
        out[name] = value
    return out


def _build(cls: type, data: dict, *, prefix: str, source: str, base: Path) -> Any:
    names = {f.name: f for f in fields(cls)}
    hints = get_type_hints(cls)
    data = _resolve_aliases(cls, data, prefix, source)
    for key in data:
        if key not in names:
            raise _unknown_key(str(key), names, prefix, source, cls)
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else str(name)
        typ = hints[name]
        if is_dataclass(typ):
            if value is None:
                value = {}
            if not isinstance(value, dict):
                raise ConfigError(
                    f"config key '{key}' must be a section of 'key: value' lines ({source})",
                    fix=f"indent the settings of '{key}' under it",
                )
            kwargs[name] = _build(typ, value, prefix=key, source=source, base=base)
        else:
            kwargs[name] = _coerce(value, typ, key, source, base)
            _check_stdout(kwargs[name], names[name].metadata, key, source)
    for f in fields(cls):
        # defaults go through the same conversion: a default path is relative to the config file too
        if f.name not in kwargs and f.default is not MISSING and f.default is not None:
            key = f"{prefix}.{f.name}" if prefix else f.name
            kwargs[f.name] = _coerce(f.default, hints[f.name], key, "defaults", base)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid settings in {source}: {exc}", fix="see the module's config.yaml") from exc


def _type_name(typ: Any) -> str:
    if typ is type(None):
        return "null"
    if get_origin(typ) is Literal:
        return " or ".join(repr(a) for a in get_args(typ))
    return getattr(typ, "__name__", str(typ).replace("typing.", ""))


class NotFiniteError(ConfigError):
    """A number key given inf or nan: refused whatever else the key's type allows."""


def _check_stdout(value: Any, metadata: Any, key: str, source: str) -> None:
    """``-`` (standard output) only where the key is an output file; elsewhere a refusal that says why."""
    values = value if isinstance(value, (list, tuple)) else [value]
    if metadata.get("path") == "out_file" or not any(isinstance(v, Path) and str(v) == STDOUT for v in values):
        return
    kind = metadata.get("path")
    what = {"out": "an output folder"}.get(
        kind, "an input" if kind in ("file", "dir", "exists") else "not a file to write"
    )
    raise ConfigError(
        f"config key '{key}' is {what}: '-' (standard output) is only for an output file ({source})",
        fix=f"give '{key}' a path",
    )


def _finite(number: float, value: Any, key: str, source: str) -> float:
    if not math.isfinite(number):
        raise NotFiniteError(
            f"config key '{key}' must be a finite number, got {value!r} ({source})",
            fix=f"set '{key}' to a number (0 where the key's help says 0 means none)",
        )
    return number


def _coerce(value: Any, typ: Any, key: str, source: str, base: Path) -> Any:
    def bad(expected: str) -> ConfigError:
        return ConfigError(
            f"config key '{key}' must be {expected}, got {value!r} ({source})", fix=f"set '{key}' to {expected}"
        )

    origin = get_origin(typ)
    if origin in (Union, types.UnionType):
        options = get_args(typ)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(value, option, key, source, base)
            except NotFiniteError:
                raise
            except ConfigError as exc:
                errors.append(exc)
        raise bad(" or ".join(_type_name(o) for o in options))
    if origin is Literal:
        if value in get_args(typ):
            return value
        raise bad(_type_name(typ))
    if typ is Any:
        return value
    if value is None:
        raise bad(_type_name(typ))
    if typ is bool:
        if isinstance(value, bool):
            return value
        raise bad("true or false")
    if typ is int:
        if isinstance(value, bool):
            raise bad("a whole number")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise bad("a whole number")
    if typ is float:
        if isinstance(value, bool):
            raise bad("a number")
        if isinstance(value, (int, float)):
            return _finite(float(value), value, key, source)
        if isinstance(value, str):
            try:
                number = float(value)  # YAML reads "1e-3" as a string
            except ValueError:
                pass
            else:
                return _finite(number, value, key, source)
        raise bad("a number")
    if typ is str:
        if isinstance(value, float):
            _finite(value, value, key, source)
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            return str(value)
        raise bad("text")
    if typ is Path:
        if isinstance(value, (str, Path)) and str(value) != "":
            p = Path(value).expanduser()
            # normalised: a config written beside its inputs refers to them with '..'; '-' (standard output) stays
            return p if p.is_absolute() or str(p) == "-" else Path(os.path.normpath(base / p))
        raise bad("a path")
    if origin in (list, tuple, typing.Sequence) or typ in (list, tuple):
        args = get_args(typ)
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            value = [value]  # a single value where a list is expected
        if not isinstance(value, (list, tuple)):
            raise bad("a list")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise bad(f"a list of {len(args)} values")
            return tuple(_coerce(v, a, f"{key}[{i}]", source, base) for i, (v, a) in enumerate(zip(value, args)))
        item = args[0] if args else Any
        items = [_coerce(v, item, f"{key}[{i}]", source, base) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict or typ is dict:
        if not isinstance(value, dict):
            raise bad("a mapping")
        return dict(value)
    if is_dataclass(typ):
        if not isinstance(value, dict):
            raise bad("a section of 'key: value' lines")
        return _build(typ, value, prefix=key, source=source, base=base)
    return value


# --------------------------------------------------------------------------------------------------
# validation


def validate(cfg: Any, *, source: str = "config", check_paths: bool = True, prefix: str = "") -> None:
    """Check ranges, choices and paths of every field (recursively); call the class's ``check()``. Paths of
    the keys the settings do not read (the class's ``unused_keys()``, e.g. module 7's predictions in module
    8's mode evaluate) are not checked: a config written for the whole step still runs one part of it."""
    unused = cfg.unused_keys() if callable(getattr(cfg, "unused_keys", None)) else set()
    for f in fields(cfg):
        key = prefix + f.name
        value = getattr(cfg, f.name)
        if is_dataclass(value):
            validate(value, source=source, check_paths=check_paths, prefix=key + ".")
            continue
        md = f.metadata
        if value is None and md.get("required"):
            raise ConfigError(
                f"config key '{key}' is required but not set ({source})",
                fix=f"add '{key}: ...' to the config, or pass --set {key}=...",
            )
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if v is None:
                continue
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                if isinstance(v, float) and math.isnan(v):
                    raise ConfigError(f"config key '{key}' is NaN ({source})", fix=f"set '{key}' to a number")
                if md.get("min") is not None and v < md["min"]:
                    raise ConfigError(
                        f"config key '{key}' = {v} is below its minimum {md['min']} ({source})",
                        fix=f"set '{key}' to at least {md['min']}",
                    )
                if md.get("max") is not None and v > md["max"]:
                    raise ConfigError(
                        f"config key '{key}' = {v} is above its maximum {md['max']} ({source})",
                        fix=f"set '{key}' to at most {md['max']}",
                    )
            if md.get("choices") is not None and v not in md["choices"]:
                close = difflib.get_close_matches(str(v), [str(c) for c in md["choices"]], n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ConfigError(
                    f"config key '{key}' = {v!r} is not one of {list(md['choices'])}{hint} ({source})",
                    fix=f"set '{key}' to one of {list(md['choices'])}",
                )
            kind = md.get("path")
            if check_paths and kind in ("file", "dir", "exists") and isinstance(v, Path) and f.name not in unused:
                _check_path(v, kind, key, source)
    check = getattr(cfg, "check", None)
    if callable(check):
        check()


def _check_path(p: Path, kind: str, key: str, source: str) -> None:
    if not p.exists():
        raise ConfigError(
            f"config key '{key}': {kind if kind != 'exists' else 'path'} not found ({source})",
            path=p,
            fix=f"correct '{key}' (relative paths in a YAML file are relative to that file)",
        )
    if kind == "file" and not p.is_file():
        raise ConfigError(
            f"config key '{key}' must be a file, but this is a folder ({source})",
            path=p,
            fix=f"point '{key}' at a file inside it",
        )
    if kind == "dir" and not p.is_dir():
        raise ConfigError(
            f"config key '{key}' must be a folder, but this is a file ({source})",
            path=p,
            fix=f"point '{key}' at the folder that holds it",
        )


# --------------------------------------------------------------------------------------------------
# writing


def to_dict(cfg: Any) -> dict:
    """Plain data (paths as strings) for YAML, JSON and logs."""

    def plain(v: Any) -> Any:
        if is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in fields(v)}
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {str(k): plain(x) for k, x in v.items()}
        return v

    return plain(cfg)


def to_yaml(
    cfg_or_cls: Any, *, comments: bool = True, header: typing.Sequence[str] = (), base: Path | None = None
) -> str:
    """YAML text of a config (or of a class's defaults) with each key's help as a comment.

    ``header`` lines follow the class's description at the top. With ``base`` (the folder the file will be
    in), absolute paths near it are written relative to it, as a YAML config's paths are read.
    """
    cfg = cfg_or_cls() if isinstance(cfg_or_cls, type) else cfg_or_cls
    lines: list[str] = []
    doc = (type(cfg).__doc__ or "").strip()
    if comments and (doc or header):
        lines += [f"# {line}".rstrip() for line in [*doc.splitlines(), *header]]
        lines.append("")
    _yaml_lines(cfg, lines, indent="", comments=comments, base=base)
    return "\n".join(lines) + "\n"


def _yaml_lines(cfg: Any, lines: list[str], indent: str, comments: bool, base: Path | None) -> None:
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        md = f.metadata
        if comments and md.get("help"):
            extra = ["required: set this"] if md.get("required") else []
            if md.get("choices") is not None:
                extra.append("one of: " + ", ".join(str(c) for c in md["choices"]))
            if md.get("min") is not None or md.get("max") is not None:
                extra.append(f"range: {md.get('min', '')}..{md.get('max', '')}".replace("None", ""))
            text = md["help"] + (f" ({'; '.join(extra)})" if extra else "")
            lines += [f"{indent}# {line}" for line in textwrap.wrap(text, width=110 - len(indent))]
        if is_dataclass(value):
            lines.append(f"{indent}{f.name}:")
            _yaml_lines(value, lines, indent + "  ", comments, base)
        else:
            dumped = yaml.safe_dump(
                {f.name: to_dict_value(value, base)}, default_flow_style=True, sort_keys=False, width=1000
            ).strip()
            lines.append(indent + dumped[1:-1])  # strip the braces of the one-key flow mapping


def _path_text(p: Path, base: Path | None) -> str:
    """A path as written in a YAML file in ``base``: relative when it is near (at most two levels up)."""
    if base is None or not p.is_absolute():
        return str(p)
    try:
        rel = Path(os.path.relpath(p, Path(base).resolve()))
    except ValueError:  # another drive on Windows
        return str(p)
    return rel.as_posix() if rel.parts[:3].count("..") < 3 else str(p)


def to_dict_value(v: Any, base: Path | None = None) -> Any:
    if isinstance(v, Path):
        return _path_text(v, base)
    if isinstance(v, (tuple, list)):
        return [to_dict_value(x, base) for x in v]
    if is_dataclass(v):  # a list of sections (e.g. several dates of rasters)
        return {f.name: to_dict_value(getattr(v, f.name), base) for f in fields(v)}
    if isinstance(v, dict):
        return {str(k): to_dict_value(x, base) for k, x in v.items()}
    return v


def save_config(cfg: Any, path: str | Path, header: typing.Sequence[str] = ()) -> Path:
    """Write ``cfg`` as a commented YAML file; paths near the file are written relative to its folder."""
    path = Path(path)
    return write_text(path, to_yaml(cfg, header=header, base=path.parent))


def field_help(cls: type) -> dict[str, str]:
    """Flat ``{dotted.key: help}`` for documentation and GUIs."""
    out: dict[str, str] = {}
    hints = get_type_hints(cls)
    for f in fields(cls):
        if is_dataclass(hints[f.name]):
            for k, v in field_help(hints[f.name]).items():
                out[f"{f.name}.{k}"] = v
        else:
            out[f.name] = f.metadata.get("help", "")
    return out


__all__ = [
    "param",
    "section",
    "load_config",
    "from_dict",
    "set_value",
    "validate",
    "to_dict",
    "to_yaml",
    "save_config",
    "field_help",
    "dataclass",
    "dataclasses",
]
