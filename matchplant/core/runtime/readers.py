"""The one reader of each kind of text file: every YAML file (a module's ``--config``, a pipeline, ``init --config``,
a ``--set`` value), every JSON file, and every state file the project writes and reads back.

- :func:`read_text`: UTF-8 with or without BOM, UTF-16 with BOM, CRLF line ends; cp1252 last, with a warning.
- :func:`read_yaml` / :func:`load_yaml`: a key given twice in one mapping is an error naming the file, both lines and
  the key (a plain YAML load keeps the last value silently); an empty file, a tab, a syntax error name their line.
- :func:`read_json`: a truncated file is named as such; a syntax error's line; the top-level type; required keys.
- :func:`read_record`: a file MatchPlant wrote and reads back (a pipeline's ``.pipeline/<step>.json``, a training
  summary, a manifest, the demo's records): a damaged one is an error naming it, with the way out (delete it, or
  the flag that starts over) instead of an internal error.

A leaf of :mod:`matchplant.core.runtime` (it imports only the errors), so that the config loader, the logger and
the input checks (:mod:`~matchplant.core.runtime.validate`, which re-exports these) all use it.
"""

from __future__ import annotations

import difflib
import json
import logging
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import yaml

from matchplant.core.runtime.errors import ConfigError, InputError, MatchPlantError

log = logging.getLogger("matchplant.validate")

STDOUT = "-"  # as an output value: standard output (never a YAML list)


# --------------------------------------------------------------------------------------------------
# names and text


def did_you_mean(name: str, choices: Iterable[str], *, cutoff: float = 0.6) -> str:
    """``"did you mean 'x'?"`` for the closest of ``choices`` (case-insensitive), or ``""``."""
    choices = [str(c) for c in choices]
    folded = {c.casefold(): c for c in choices}
    close = difflib.get_close_matches(str(name).casefold(), list(folded), n=1, cutoff=cutoff)
    return f"did you mean '{folded[close[0]]}'?" if close else ""


def read_text(path: str | Path, *, what: str = "file") -> str:
    """A text file as ``str`` whatever a Windows editor saved: UTF-8 (BOM or not), UTF-16 with BOM, CRLF line
    ends (turned into ``\\n``); cp1252 as a last resort, with a warning."""
    path = Path(path)
    if not path.is_file():
        raise InputError(
            f"{what} not found" if not path.exists() else f"{what} is a folder, not a file",
            path=path,
            fix="check the path in your config",
        )
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(
            f"cannot read the {what}: {exc.strerror or exc}", path=path, fix="check the file's permissions"
        ) from exc
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        text = data.decode("utf-16", errors="replace")
    else:
        try:
            text = data.decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            if b"\x00" in data[:4096]:
                raise InputError(
                    f"{what} is binary, not text (byte {exc.start})", path=path, fix="point the config at the text file"
                ) from exc
            text = data.decode("cp1252", errors="replace")
            log.warning("%s is not UTF-8; read it as Windows-1252 (save it as UTF-8 to silence this)", path)
    return text.replace("\r\n", "\n").replace("\r", "\n")


# --------------------------------------------------------------------------------------------------
# YAML


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A key given twice in one YAML mapping: ``key``, and the ``lines`` (1-based) of its two places."""

    def __init__(self, key: Any, lines: tuple[int, int], mark: Any):
        self.key, self.lines = key, lines
        super().__init__(None, None, f"key '{key}' appears twice (lines {lines[0]} and {lines[1]})", mark)


class UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader that refuses a key given twice in one mapping (YAML would keep the last silently)."""

    def construct_mapping(self, node, deep=False):
        """The mapping of ``node``, after checking that no key repeats."""
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                continue
            line = key_node.start_mark.line + 1
            if key in seen:
                raise DuplicateKeyError(key, (seen[key], line), key_node.start_mark)
            seen[key] = line
        return super().construct_mapping(node, deep)


def load_yaml(text: str, *, path: Path | None = None, what: str = "YAML file", error: type = ConfigError) -> Any:
    """Parse YAML text with :class:`UniqueKeyLoader`; a repeated key, a tab and a syntax error are ``error``
    naming ``path``, the line and the key."""
    try:
        return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except DuplicateKeyError as exc:
        first, second = exc.lines
        raise error(
            f"{what}: the key '{exc.key}' is given twice, at lines {first} and {second} (only one value can be used)",
            path=path,
            fix=f"keep one of the two '{exc.key}:' lines (line {first} or {second}) and delete the other",
        ) from exc
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        tab = next((i + 1 for i, ln in enumerate(text.splitlines()) if re.match(r"^ *\t", ln)), None)
        if tab is not None:
            raise error(
                f"{what}: line {tab} is indented with a tab",
                path=path,
                fix="indent with spaces only (YAML does not allow tabs)",
            ) from exc
        problem = getattr(exc, "problem", None) or str(exc)
        lines = text.splitlines()
        if line is not None and 0 < line <= len(lines) and re.search(r":\s+-\s*(#.*)?$", lines[line - 1]):
            raise error(
                f"{what} is not valid YAML at line {line}: a bare '-' there starts a list",
                path=path,
                fix="write '-' (standard output) in quotes: key: \"-\"",
            ) from exc
        raise error(
            f"{what} is not valid YAML{f' at line {line}' if line else ''}: {problem}",
            path=path,
            fix="check the indentation and the 'key: value' syntax there",
        ) from exc


def _is_blank(text: str) -> bool:
    return all(not ln.strip() or ln.lstrip().startswith("#") for ln in text.splitlines())


def read_yaml(
    path: str | Path,
    *,
    expect: type | None = dict,
    what: str = "YAML file",
    error: type = ConfigError,
    allow_empty: bool = False,
) -> Any:
    """Parse a YAML file (BOM and CRLF accepted); an empty file (unless ``allow_empty``: then ``{}``), a syntax
    error (with its line), tabs used for indentation, a key given twice and a wrong top-level type are errors."""
    path = Path(path)
    try:
        text = read_text(path, what=what)
    except InputError as exc:
        raise error(exc.problem, path=exc.path, fix=exc.fix) from exc
    if _is_blank(text):
        if allow_empty:
            return {}
        raise error(f"{what} is empty", path=path, fix="write its settings as 'key: value' lines")
    data = load_yaml(text, path=path, what=what, error=error)
    if data is None and allow_empty:
        return {}
    if expect is not None and not isinstance(data, expect):
        expected = "an object {...} (a mapping)" if expect is dict else _kind_of(expect)
        raise error(
            f"{what} holds {_kind(data)}, expected {expected} of 'key: value' lines",
            path=path,
            fix="write one 'key: value' setting per line",
        )
    return data


def parse_value(text: str) -> Any:
    """A value written on the command line (``--set key=VALUE``, a flag) read as YAML, as in a config file; ``-``
    alone is the text ``-`` (standard output), never YAML's list of one null; text that is not YAML stays text."""
    text = text.strip()
    if not text:
        return ""
    if text == STDOUT:
        return STDOUT
    try:
        return load_yaml(text, what="the value")
    except ConfigError as exc:
        if isinstance(exc.__cause__, DuplicateKeyError):
            raise
        return text


# --------------------------------------------------------------------------------------------------
# JSON


def _kind(value: Any) -> str:
    return {dict: "an object {...}", list: "a list [...]", str: "a string", type(None): "null"}.get(
        type(value), f"a {type(value).__name__}"
    )


def _kind_of(expect: type | tuple[type, ...]) -> str:
    types = expect if isinstance(expect, tuple) else (expect,)
    return " or ".join({dict: "an object {...}", list: "a list [...]"}.get(t, t.__name__) for t in types)


def _require_keys(data: Any, required: Sequence[str], what: str, path: Path) -> None:
    if not isinstance(data, dict):
        raise InputError(
            f"{what} holds {_kind(data)}, expected an object with {list(required)}",
            path=path,
            fix="point the config at the right file",
        )
    for key in required:
        if key not in data:
            hint = did_you_mean(key, data)
            raise InputError(
                f"{what} has no '{key}'{'; ' + hint if hint else ''}",
                path=path,
                fix=f"the file needs a top-level '{key}'; regenerate it or point the config at the right file",
            )


def read_json(
    path: str | Path,
    *,
    expect: type | tuple[type, ...] | None = None,
    required: Sequence[str] = (),
    what: str = "JSON file",
) -> Any:
    """Parse a JSON file; name a truncated file as such, a syntax error's line, a wrong top-level type and
    missing top-level keys (``required``, with "did you mean" from the keys present)."""
    path = Path(path)
    text = read_text(path, what=what)
    if not text.strip():
        raise InputError(
            f"{what} is empty", path=path, fix="regenerate the file (the step that wrote it may have been interrupted)"
        )
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        tail = text.rstrip()
        # cut off: the error is at the very end, or the text stops inside a string or before its last bracket
        cut = exc.pos >= len(tail) - 1 or exc.msg.startswith("Unterminated string") or tail[-1:] not in "}]"
        if cut and not exc.msg.startswith("Extra data"):
            raise InputError(
                f"{what} is not valid JSON: it ends early, at line {exc.lineno} ({exc.msg}), as a truncated file does",
                path=path,
                fix="the file was cut off (disk full, interrupted copy or run); copy or regenerate it",
            ) from exc
        raise InputError(
            f"{what} is not valid JSON: line {exc.lineno}, column {exc.colno}: {exc.msg}",
            path=path,
            fix="repair the file there, or regenerate it",
        ) from exc
    if expect is not None and not isinstance(data, expect):
        raise InputError(
            f"{what} holds {_kind(data)}, expected {_kind_of(expect)}",
            path=path,
            fix="point the config at the right file",
        )
    if required:
        _require_keys(data, required, what, path)
    return data


def read_record(
    path: str | Path,
    *,
    what: str,
    fix: str,
    required: Sequence[str] = (),
    default: Any = None,
) -> Any:
    """A JSON object that MatchPlant wrote and reads back (a state file), or ``default`` when there is none.

    A damaged one (cut off by a full disk or a killed run, edited, another file in its place) is an
    :class:`~matchplant.core.runtime.errors.InputError` that names it and says ``what`` it is and ``fix``: how
    to go on without it (delete it, or the flag that starts over), never an internal error."""
    path = Path(path)
    if not path.exists():
        return default
    try:
        return read_json(path, expect=dict, required=required, what=what)
    except MatchPlantError as exc:
        raise InputError(f"{what} is damaged: {exc.problem}", path=path, fix=fix) from exc


__all__ = [
    "DuplicateKeyError",
    "did_you_mean",
    "UniqueKeyLoader",
    "load_yaml",
    "parse_value",
    "read_json",
    "read_record",
    "read_text",
    "read_yaml",
]
