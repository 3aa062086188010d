"""Safe file output: every file is written to a temporary name beside it, then renamed into place.

A crash or Ctrl-C therefore never leaves a half-written output, and an existing file is replaced only
by a complete new one (``os.replace`` is atomic on Linux, macOS and Windows for the same volume).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

from matchplant.core.errors import InputError


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` if the block succeeds.

    For writers that want a file name (rasterio, GeoPandas, OpenCV). The suffix is kept so that
    drivers choosing a format from the extension still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    tmp_path.unlink()  # writers such as GDAL refuse to overwrite some formats; give them a free name
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", **kwargs: Any):
    """``open()`` that writes to a temporary file and renames it into place on success."""
    if "r" in mode or "a" in mode:
        raise ValueError("atomic_open is for writing whole files ('w' or 'wb')")
    if "b" not in mode:
        kwargs.setdefault("encoding", "utf-8")
        kwargs.setdefault("newline", "")
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())


def write_text(path: str | Path, text: str) -> Path:
    with atomic_open(path, "w") as fh:
        fh.write(text)
    return Path(path)


def write_json(path: str | Path, data: Any, indent: int | None = 1) -> Path:
    with atomic_open(path, "w") as fh:
        json.dump(data, fh, indent=indent)
        fh.write("\n")
    return Path(path)


def read_json(path: str | Path) -> Any:
    """Read JSON with an error that names the file and the line of a syntax error."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path=path, fix="check the path in your config")
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})",
                         path=path, fix="repair or regenerate the file") from exc
    except UnicodeDecodeError as exc:
        raise InputError("not a text (UTF-8) file", path=path,
                         fix="point the config at the JSON file, not a binary file") from exc
