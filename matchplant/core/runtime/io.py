"""Safe file output: every file is written to a temporary name beside it, then renamed into place.

A crash or Ctrl-C therefore never leaves a half-written output, and an existing file is replaced only
by a complete new one (``os.replace`` is atomic on Linux, macOS and Windows for the same volume).
:class:`BatchedWrites` does the same for many files with one folder sync per batch instead of one per file.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from matchplant.core.runtime.errors import InputError


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
        raise InputError(
            f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})",
            path=path,
            fix="repair or regenerate the file",
        ) from exc
    except UnicodeDecodeError as exc:
        raise InputError(
            "not a text (UTF-8) file", path=path, fix="point the config at the JSON file, not a binary file"
        ) from exc


def _fsync_path(path: Path, directory: bool = False) -> None:
    if directory and os.name == "nt":
        return  # Windows cannot open a folder for fsync; its renames are journalled
    fd = os.open(path, os.O_RDONLY if directory else os.O_RDWR)
    try:
        # the data (and the size) only: fdatasync skips the timestamps' metadata where it exists (Linux)
        (os.fsync if directory else _datasync)(fd)
    finally:
        os.close(fd)


_datasync = getattr(os, "fdatasync", os.fsync)


class BatchedWrites:
    """Whole files into one folder, durable with one folder sync per batch instead of one per file.

    ``write(name, data)`` writes to a hidden temporary name beside the target; every ``batch`` files
    (and on :meth:`close`) each file of the batch is synced (its own data only: never a sync of the
    whole file system, which would also wait for every other program's writes), the batch is renamed
    into place, and the folder is synced once. A crash therefore leaves at the final
    names only complete files (and perhaps hidden ``.*.partial`` temporaries); an error inside the
    ``with`` block removes the pending temporaries. Use as a context manager.
    """

    def __init__(self, folder: str | Path, batch: int = 128):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.batch = max(int(batch), 1)
        self.pending: list[tuple[Path, Path]] = []
        self.syncs = 0

    def write(self, name: str, data: bytes) -> Path:
        dst = self.folder / name
        fd, tmp = tempfile.mkstemp(prefix=f".{dst.name}.", suffix=".partial", dir=self.folder)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        self.pending.append((Path(tmp), dst))
        if len(self.pending) >= self.batch:
            self.flush()
        return dst

    def flush(self) -> None:
        if not self.pending:
            return
        for tmp, _ in self.pending:
            _fsync_path(tmp)
        for tmp, dst in self.pending:
            os.replace(tmp, dst)
        self.pending = []
        _fsync_path(self.folder, directory=True)
        self.syncs += 1

    def discard(self) -> None:
        for tmp, _ in self.pending:
            tmp.unlink(missing_ok=True)
        self.pending = []

    def close(self) -> None:
        self.flush()

    def __enter__(self) -> BatchedWrites:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.flush()
        else:
            self.discard()
