"""Shared input checks: read a file, check its structure, and raise one clear error naming the file, the line
or key, the problem and the fix (:mod:`matchplant.core.runtime.errors`). Steps call these instead of ``json.load``,
``csv.reader``, ``rasterio.open``... so that a broken input never ends in a traceback or a silent wrong result.

=========================  ==================================================================================
names                      :func:`did_you_mean`, :func:`match_name`, :func:`match_names`, :func:`name_key`
text files                 :func:`read_text` (UTF-8 with or without BOM, UTF-16 with BOM, CRLF, cp1252 last)
JSON / YAML                :func:`read_json` (truncated, top-level type, required keys), :func:`read_yaml`
CSV                        :func:`read_csv` -> :class:`Table` (delimiter sniffing, required columns with
                           "did you mean", numeric columns naming the line, decimal commas with ``;``)
values and units           :func:`check_range`, :func:`check_coordinates` (degrees vs metres, swapped lat/lon)
paths                      :func:`check_path`
JPEG                       :func:`check_jpeg`
rasters / vectors          :mod:`matchplant.core.runtime.validate_gis` (GDAL through rasterio and pyogrio)
=========================  ==================================================================================

Every function raises :class:`~matchplant.core.runtime.errors.InputError` (or ``ConfigError`` for config keys); none
returns a partial result silently.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from matchplant.core.runtime.errors import ConfigError, InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.readers import did_you_mean, read_json, read_text, read_yaml

log = get_logger("validate")

# --------------------------------------------------------------------------------------------------
# names


_EXT = re.compile(r"\.[A-Za-z][A-Za-z0-9]{0,4}$")


def name_key(name: str) -> str:
    """The loose form of a file name or id: no folder, no extension, case-folded (``IMG_1.JPG`` -> ``img_1``)."""
    base = str(name).replace("\\", "/").rsplit("/", 1)[-1]
    return _EXT.sub("", base).casefold()


def match_names(names: Iterable[str], targets: Iterable[str]) -> tuple[dict[str, str], list[str]]:
    """Match ``names`` (e.g. image file names) to ``targets`` (e.g. reconstruction shot ids).

    Exact matches first, then loose ones (:func:`name_key`: case and extension ignored) when they are
    unique. Returns ``({name: target}, unmatched names)``; a caller should say how many matched loosely.
    """
    targets = list(dict.fromkeys(str(t) for t in targets))
    exact = set(targets)
    loose: dict[str, list[str]] = {}
    for t in targets:
        loose.setdefault(name_key(t), []).append(t)
    matched: dict[str, str] = {}
    unmatched: list[str] = []
    for n in names:
        n = str(n)
        if n in exact:
            matched[n] = n
        elif len(loose.get(name_key(n), [])) == 1:
            matched[n] = loose[name_key(n)][0]
        else:
            unmatched.append(n)
    return matched, unmatched


def match_name(
    name: str,
    choices: Iterable[str],
    *,
    what: str,
    path: str | Path | None = None,
    fix: str | None = None,
    error: type = InputError,
) -> str:
    """The one of ``choices`` that ``name`` means (exactly, else loosely); else an error with "did you mean"."""
    choices = [str(c) for c in choices]
    matched, _ = match_names([name], choices)
    if name in matched:
        return matched[name]
    hint = did_you_mean(name, choices)
    listing = (
        hint or f"known: {', '.join(choices[:12])}{' ...' if len(choices) > 12 else ''}"
        if choices
        else "there are none"
    )
    raise error(f"{what} '{name}' not found; {listing}", path=path, fix=fix or f"use one of the existing {what}s")


# --------------------------------------------------------------------------------------------------
# text, JSON, YAML


# --------------------------------------------------------------------------------------------------
# CSV


@dataclass
class Table:
    """A checked CSV: ``columns`` as written (stripped), ``rows`` as ``{required column: text}`` (every column,
    under its name as written, plus the required names), ``lines[i]`` the file line of ``rows[i]``."""

    path: Path
    columns: list[str]
    rows: list[dict[str, str]]
    lines: list[int]
    delimiter: str
    numbers: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.rows)

    def column(self, name: str) -> list[str]:
        """Every row's text in one column."""
        return [r[name] for r in self.rows]


def _sniff(header: str) -> str | None:
    counts = {d: header.count(d) for d in (",", ";", "\t", "|")}
    best = max(counts, key=counts.get)
    return best if counts[best] else None


def _number(text: str, decimal_comma: bool) -> float:
    t = text.strip()
    if decimal_comma and "," in t and "." not in t:
        t = t.replace(",", ".")
    return float(t)


def read_csv(
    path: str | Path,
    *,
    required: Sequence[str] = (),
    numeric: Sequence[str] = (),
    aliases: dict[str, Sequence[str]] | None = None,
    allow_empty: bool = False,
    comment: str = "#",
    what: str = "CSV file",
) -> Table:
    """Read a delimited table with a header line and check it.

    - delimiter sniffed from the header (``,`` ``;`` TAB ``|``, else whitespace); BOM, CRLF, UTF-16 accepted;
    - ``required`` columns matched case-insensitively (``aliases`` maps a required name to accepted other
      names, e.g. ``{"x": ["easting", "lon"]}``); a missing one gives "did you mean" from the header;
    - ``numeric`` columns must hold finite numbers; the first bad value is named with its line
      (``;``-separated files may use decimal commas); parsed arrays are in ``Table.numbers``;
    - a row with more or fewer values than the header, and a file without data rows, are errors.
    """
    path = Path(path)
    text = read_text(path, what=what)
    numbered = [
        (i + 1, ln)
        for i, ln in enumerate(text.split("\n"))
        if ln.strip() and not (comment and ln.lstrip().startswith(comment))
    ]
    if not numbered:
        raise InputError(
            f"{what} is empty",
            path=path,
            fix=f"the first line must be the header: {','.join(required) or 'column names'}",
        )
    delim = _sniff(numbered[0][1])

    def split(line: str) -> list[str]:
        if delim is None:
            return line.split()
        return [c.strip() for c in next(csv.reader(io.StringIO(line), delimiter=delim, skipinitialspace=True))]

    header = split(numbered[0][1])
    _check_header(header, required, numeric, aliases or {}, path, what)
    folded = {h.casefold(): h for h in header}
    rename = {}
    for name in [*required, *numeric]:
        for option in [name, *(aliases or {}).get(name, [])]:
            if option.casefold() in folded:
                rename[name] = folded[option.casefold()]
                break
    rows, lines = [], []
    for lineno, line in numbered[1:]:
        values = split(line)
        if len(values) != len(header):
            raise InputError(
                f"{what}, line {lineno}: {len(values)} values, but the header has {len(header)} columns",
                path=path,
                fix="give every line one value per column (quote values that contain the delimiter)",
            )
        row = dict(zip(header, values))
        row.update({name: row[col] for name, col in rename.items()})
        rows.append(row)
        lines.append(lineno)
    if not rows and not allow_empty:
        raise InputError(
            f"{what} has a header but no data rows",
            path=path,
            fix="add the data, or point the config at the right file",
        )
    table = Table(path, header, rows, lines, delim or " ")
    for name in numeric:
        values = np.empty(len(rows))
        for i, row in enumerate(rows):
            try:
                values[i] = _number(row[name], delim == ";")
            except ValueError:
                values[i] = math.nan
            if not math.isfinite(values[i]):
                shown = repr(row[name]) if row[name] else "empty"
                raise InputError(
                    f"{what}, line {lines[i]}: column '{rename[name]}' is {shown}, not a number",
                    path=path,
                    fix=f"write a number there (a dot for decimals), or remove line {lines[i]}",
                )
        table.numbers[name] = values
    return table


def _check_header(
    header: list[str],
    required: Sequence[str],
    numeric: Sequence[str],
    aliases: dict[str, Sequence[str]],
    path: Path,
    what: str,
) -> None:
    folded = [h.casefold() for h in header]
    if len(set(folded)) != len(folded):
        dup = next(h for h in header if folded.count(h.casefold()) > 1)
        raise InputError(
            f"{what}: column '{dup}' appears twice in the header", path=path, fix="give each column a unique name"
        )
    needed = list(dict.fromkeys([*required, *numeric]))
    for name in needed:
        options = [name, *aliases.get(name, [])]
        if any(o.casefold() in folded for o in options):
            continue
        if header and sum(_is_number(h) for h in header) >= max(1, len(header) // 2):
            raise InputError(
                f"{what} has no header line (the first line holds numbers)",
                path=path,
                fix=f"add the header line: {','.join(needed)}",
            )
        hint = did_you_mean(name, header)
        raise InputError(
            f"{what} has no column '{name}'{'; ' + hint if hint else ''} (columns: {', '.join(header)})",
            path=path,
            fix=f"rename the column to '{name}'" + (f" (or {', '.join(aliases[name])})" if aliases.get(name) else ""),
        )


def _is_number(text: str) -> bool:
    try:
        float(text.replace(",", "."))
        return True
    except ValueError:
        return False


# --------------------------------------------------------------------------------------------------
# values and units


def check_range(
    values: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    what: str,
    path: str | Path | None = None,
    lines: Sequence[int] | None = None,
    unit: str = "",
    fix: str | None = None,
    error: type = InputError,
) -> None:
    """Every value finite and within ``[lo, hi]``; else name the first bad one (and its line) and the count."""
    arr = np.asarray(values, dtype=float).ravel()
    bad = ~np.isfinite(arr)
    if lo is not None:
        bad |= arr < lo
    if hi is not None:
        bad |= arr > hi
    if not bad.any():
        return
    i = int(np.flatnonzero(bad)[0])
    where = f"line {lines[i]}: " if lines is not None else ""
    span = f"[{'' if lo is None else lo}, {'' if hi is None else hi}]{' ' + unit if unit else ''}"
    raise error(
        f"{where}{what} = {arr[i]:g} is outside {span} ({int(bad.sum())} of {arr.size} values)",
        path=path,
        fix=fix or f"correct {what} (expected {span})",
    )


def check_coordinates(
    x: Any,
    y: Any,
    *,
    geographic: bool,
    what: str = "coordinates",
    path: str | Path | None = None,
    lines: Sequence[int] | None = None,
    fix: str | None = None,
) -> None:
    """Coordinates against their units: degrees (``geographic``: x = lon, y = lat) or projected metres.

    Catches projected metres in a lat/lon column, lat/lon swapped, and degrees labelled as a projected CRS.
    """
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    check_range(x, what=f"{what} x", path=path, lines=lines)
    check_range(y, what=f"{what} y", path=path, lines=lines)
    if not x.size:
        return
    if geographic:
        if np.all(np.abs(x) <= 90) and np.any(np.abs(y) > 90) and np.all(np.abs(y) <= 180):
            raise InputError(
                f"{what}: latitude and longitude look swapped (latitude {y[np.abs(y) > 90][0]:g})",
                path=path,
                fix=fix or "swap the two columns (x = longitude, y = latitude)",
            )
        bad = (np.abs(x) > 180) | (np.abs(y) > 90)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            where = f"line {lines[i]}: " if lines is not None else ""
            raise InputError(
                f"{where}{what} ({x[i]:g}, {y[i]:g}) are not degrees: they look like projected "
                f"metres ({int(bad.sum())} of {x.size} points)",
                path=path,
                fix=fix
                or "give the data's projected CRS (e.g. EPSG:326xx for UTM) instead of a "
                "lat/lon one, or convert the coordinates to degrees",
            )
    elif np.all(np.abs(x) <= 180) and np.all(np.abs(y) <= 90) and np.ptp(x) < 1 and np.ptp(y) < 1:
        raise InputError(
            f"{what} ({x[0]:g}, {y[0]:g}) look like degrees, but a projected CRS (metres) is set",
            path=path,
            fix=fix or "set a geographic CRS (EPSG:4326) for them, or convert them to the projected CRS",
        )


# --------------------------------------------------------------------------------------------------
# paths


def check_path(p: str | Path, kind: str, *, key: str, source: str = "config") -> None:
    """An input path named by config ``key`` exists and is a ``"file"``, a ``"dir"`` or (``"exists"``) either."""
    p = Path(p)
    expected = {"file": "file", "dir": "folder"}.get(kind, "path")
    if not p.exists():
        raise ConfigError(
            f"config key '{key}': {expected} not found ({source})",
            path=p,
            fix=f"correct '{key}' (relative paths in a YAML file are relative to that file)",
        )
    if (kind == "file" and p.is_dir()) or (kind == "dir" and not p.is_dir()):
        actual = "a folder" if p.is_dir() else "a file"
        raise ConfigError(
            f"config key '{key}' must be a {expected}, but this is {actual} ({source})",
            path=p,
            fix=f"point '{key}' at a {expected}",
        )


# --------------------------------------------------------------------------------------------------
# JPEG


def check_jpeg(path: str | Path, *, decode: bool = False, what: str = "image") -> None:
    """A whole JPEG: starts with SOI, ends with EOI (zero padding allowed) and, with ``decode``, decodes
    without error (at 1/8 scale: the whole entropy-coded stream is still read)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{what} cannot be read: {exc.strerror}", path=path, fix="check the file") from exc
    if not data.startswith(b"\xff\xd8"):
        raise InputError(
            f"{what} is not a JPEG (no start-of-image marker)",
            path=path,
            fix="remove it from the folder, or convert it to JPEG",
        )
    if not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise InputError(
            f"{what} is truncated (no end-of-image marker; {len(data)} bytes)",
            path=path,
            fix="copy the photo again from the card, or remove it from the folder",
        )
    if decode:
        try:
            with Image.open(path) as im:
                im.draft("RGB", (max(1, im.width // 8), max(1, im.height // 8)))
                im.load()
        except (OSError, SyntaxError, ValueError) as exc:
            raise InputError(
                f"{what} cannot be decoded: {exc}", path=path, fix="copy the photo again, or remove it from the folder"
            ) from exc


__all__ = [
    "did_you_mean",
    "name_key",
    "match_names",
    "match_name",
    "read_text",
    "read_json",
    "read_yaml",
    "Table",
    "read_csv",
    "check_range",
    "check_coordinates",
    "check_path",
    "check_jpeg",
]
