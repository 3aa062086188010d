"""Safe file output: every file is written to a temporary name beside it, then renamed into place.

A crash or Ctrl-C therefore never leaves a half-written output, and an existing file is replaced only
by a complete new one (``os.replace`` is atomic on Linux, macOS and Windows for the same volume).
:class:`BatchedWrites` does the same for many files with one folder sync per batch instead of one per file.

A rename only ever replaces a regular file (:func:`output_target` decides where a write goes):

- a symlink is written through: its target (a regular file, or a new file where the link dangles) is replaced
  atomically and the link is kept;
- ``-`` is standard output, and a character device, a FIFO or a link through ``/proc`` (``/dev/stdout``,
  ``/dev/fd/N``) is opened and written directly, once the whole content is ready;
- a folder, a socket or a link to a folder is refused with an :class:`OutputError` naming the path.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import stat
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from matchplant.core.runtime import readers
from matchplant.core.runtime.errors import OutputError

STDOUT = "-"
FIFO_WAIT_S = 10.0  # how long a write to a FIFO waits for a program to read it

# the errors of writing a file, each with what it means and what to do
WRITE_ERRORS = {
    errno.ENOSPC: ("the disk is full", "free space on that disk, or write the output to another one"),
    errno.EDQUOT: ("the disk quota is used up", "free space, or write the output elsewhere"),
    errno.EFBIG: ("the file is too large for that file system", "write the output to another disk"),
    errno.EROFS: ("the file system is read-only", "give an output path on a disk that can be written"),
    errno.EACCES: ("permission denied", "give an output in a folder you can write to, or change its permissions"),
    errno.EPERM: ("the operation is not permitted", "give an output in a folder you can write to"),
    errno.EISDIR: ("a folder is in the way", "give the path of a file, or move the folder away"),
    errno.ENOTDIR: ("a part of the path is a file, not a folder", "give a path whose folders are folders"),
    errno.EIO: ("an input/output error of the disk", "check the disk, or write the output elsewhere"),
}


def write_error(path: str | Path, exc: OSError) -> OutputError:
    """The OutputError for a failed write of ``path``: what happened, in words, the file and the fix."""
    what, fix = WRITE_ERRORS.get(exc.errno, (exc.strerror or str(exc), "give an output path that can be written"))
    return OutputError(f"cannot write {path}: {what} ({exc.strerror or exc})", path=path, fix=fix)


def is_write_error(exc: BaseException, *paths: str | Path) -> bool:
    """An OSError of writing one of ``paths`` (or of no named file: a write to an open file), not of reading
    an input that happened inside the same block."""
    if not isinstance(exc, OSError) or isinstance(exc, FileNotFoundError) or exc.errno not in WRITE_ERRORS:
        return False
    return exc.filename is None or str(exc.filename) in {str(p) for p in paths}


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "a regular file" if stat.S_ISREG(mode) else "a special file"


def _through_proc(path: Path) -> bool:
    """The path is, or its chain of links passes through, ``/proc`` (``/dev/stdout`` -> ``/proc/self/fd/1``):
    such a link names an open file of a process, which must be written, never renamed over."""
    p = Path(os.path.abspath(path))
    for _ in range(40):
        if p.parts[1:2] == ("proc",):
            return True
        if not p.is_symlink():
            return False
        p = Path(os.path.abspath(p.parent / os.readlink(p)))
    return False


def output_target(path: str | Path) -> tuple[str, Path]:
    """Where a write to ``path`` goes: ``("file", real path)`` to replace atomically (the path itself, or a
    symlink's final target), or ``("stream", path)`` to open and write directly (``-`` is standard output,
    a device, a FIFO, a link through /proc). Refuses (OutputError) what must be neither written nor replaced."""
    path = Path(path)
    if str(path) == STDOUT:
        return "stream", path
    link = path.is_symlink()
    try:
        st = os.stat(path)  # follows links
    except FileNotFoundError:
        st = None
    except OSError as exc:  # a loop of links, a component that is a file
        raise OutputError(
            f"cannot write {path}: {exc.strerror or exc}", path=path, fix="give an output path that can be written"
        ) from exc
    if st is not None and stat.S_ISREG(st.st_mode):
        if _through_proc(path):
            return "stream", path  # /dev/stdout redirected to a file: that open file, not a new one
        return "file", Path(os.path.realpath(path)) if link else path
    if st is None:
        if not link:
            return "file", path
        target = Path(os.path.realpath(path))
        if not target.parent.is_dir():
            raise OutputError(
                f"{path} is a symlink to {target}, whose folder does not exist",
                path=path,
                fix=f"create {target.parent}, or remove the link and run again",
            )
        return "file", target  # a dangling link: its target is created, the link kept
    if stat.S_ISCHR(st.st_mode) or stat.S_ISFIFO(st.st_mode) or _through_proc(path):
        return "stream", path
    via = f" (a symlink to {os.path.realpath(path)})" if link else ""
    raise OutputError(
        f"cannot write the output {path}{via}: it is {_kind(st.st_mode)}; only regular files are replaced",
        path=path,
        fix="give the path of a file (or '-' for standard output), or move what is there away",
    )


def is_stream(path: str | Path) -> bool:
    """The path is written directly (standard output, a device, a FIFO), not as a file."""
    try:
        return output_target(path)[0] == "stream"
    except OutputError:
        return False


def _is_own_stdout(path: Path) -> bool:
    try:
        return os.path.samestat(os.stat(path), os.fstat(sys.stdout.fileno()))
    except (OSError, ValueError, AttributeError):  # no file behind stdout (a test's capture): not it
        return False


def _open_stream(path: Path):
    """A binary file object for a stream target; a FIFO waits up to FIFO_WAIT_S for a reader."""
    if str(path) == STDOUT or _is_own_stdout(path):  # /dev/stdout: after what was printed, not over it
        sys.stdout.flush()
        return contextlib.nullcontext(getattr(sys.stdout, "buffer", None) or sys.stdout)
    if not stat.S_ISFIFO(os.stat(path).st_mode):
        return open(path, "wb")
    deadline = time.monotonic() + FIFO_WAIT_S
    while True:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
            break
        except OSError as exc:
            if exc.errno != errno.ENXIO or time.monotonic() > deadline:
                raise OutputError(
                    f"no program reads the FIFO {path} (waited {FIFO_WAIT_S:.0f} s)",
                    path=path,
                    fix="start the reading program first, or give a file path",
                ) from exc
            time.sleep(0.05)
    os.set_blocking(fd, True)
    return os.fdopen(fd, "wb")


def _write_stream(src: Path, path: Path) -> None:
    with open(src, "rb") as fh, _open_stream(path) as out:
        if hasattr(out, "buffer") or not hasattr(out, "encoding"):
            shutil.copyfileobj(fh, out)
        else:  # a text-only stdout (a test's capture): the bytes as text
            out.write(fh.read().decode("utf-8", "replace"))
        out.flush()


def _temp_beside(path: Path) -> Path:
    """A free name beside ``path`` (same folder, so that the final rename is atomic), keeping the suffix so
    that drivers choosing a format from it still work."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    except OSError as exc:
        raise (
            write_error(path, exc)
            if exc.errno in WRITE_ERRORS
            else OutputError(
                f"cannot write in {path.parent}: {exc.strerror or exc}",
                path=path,
                fix="give an output path in a folder you can write to",
            )
        ) from exc
    os.close(fd)
    tmp_path = Path(tmp)
    tmp_path.unlink()  # writers such as GDAL refuse to overwrite some formats; give them a free name
    return tmp_path


def place(tmp: str | Path, path: str | Path) -> Path:
    """Put the finished file ``tmp`` at ``path`` as :func:`output_target` says: renamed over a regular file (a
    symlink's target), or copied into a stream and removed. Returns where it went."""
    tmp = Path(tmp)
    kind, target = output_target(path)
    try:
        return _place(tmp, path, kind, target)
    except OSError as exc:
        if is_write_error(exc, tmp, path, target):
            raise write_error(path, exc) from exc
        raise


def _place(tmp: Path, path: Path, kind: str, target: Path) -> Path:
    if kind == "stream":
        try:
            _write_stream(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return target
    with contextlib.suppress(OSError):  # the replaced file's permissions stay (a private config stays private)
        os.chmod(tmp, stat.S_IMODE(os.stat(target).st_mode))
    try:
        os.replace(tmp, target)
    except OSError as exc:
        if exc.errno != errno.EXDEV:  # a link's target on another drive: copy beside it, then rename
            raise
        beside = _temp_beside(target)
        try:
            shutil.copyfile(tmp, beside)
            os.replace(beside, target)
        finally:
            beside.unlink(missing_ok=True)
            tmp.unlink(missing_ok=True)
    return target


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``'s target; move it onto ``path`` if the block succeeds.

    For writers that want a file name (rasterio, GeoPandas, OpenCV). The suffix is kept so that
    drivers choosing a format from the extension still work. A stream target (``-``, a device, a FIFO) gets a
    temporary file elsewhere, copied into it on success.
    """
    path = Path(path)
    kind, target = output_target(path)
    scratch = None
    if kind == "stream":
        scratch = Path(tempfile.mkdtemp(prefix=".matchplant-out-"))
        tmp_path = scratch / ("stdout" if str(path) == STDOUT else path.name)
    else:
        tmp_path = _temp_beside(target)
    try:
        yield tmp_path
        place(tmp_path, path)
    except OSError as exc:  # the writer's own error (a full disk while it wrote): named, not an internal error
        if is_write_error(exc, tmp_path, path, target):
            raise write_error(path, exc) from exc
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)


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
    """Write a text file whole, or nothing if it fails."""
    with atomic_open(path, "w") as fh:
        fh.write(text)
    return Path(path)


def write_json(path: str | Path, data: Any, indent: int | None = 1) -> Path:
    """Write JSON whole, or nothing if it fails (``indent=None``: compact)."""
    with atomic_open(path, "w") as fh:
        json.dump(data, fh, indent=indent)
        fh.write("\n")
    return Path(path)


def read_json(path: str | Path) -> Any:
    """Read JSON with an error that names the file (:func:`matchplant.core.runtime.readers.read_json`)."""
    return readers.read_json(path)


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
        """Write one file of the batch under a temporary name; it is renamed into place with its batch."""
        dst = self.folder / name
        output_target(dst)  # a folder in the way: refused now, before the batch is written
        tmp = None
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{dst.name}.", suffix=".partial", dir=self.folder)
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
        except BaseException as exc:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
            if isinstance(exc, OSError) and is_write_error(exc, *([tmp] if tmp else []), dst, self.folder):
                self.discard()
                raise write_error(dst, exc) from exc
            raise
        self.pending.append((Path(tmp), dst))
        if len(self.pending) >= self.batch:
            self.flush()
        return dst

    def flush(self) -> None:
        """Sync the pending files, rename them into place and sync the folder once."""
        if not self.pending:
            return
        for tmp, dst in self.pending:
            try:
                _fsync_path(tmp)
            except OSError as exc:
                self.discard()
                raise write_error(dst, exc) if is_write_error(exc, tmp) else exc from exc
        try:
            for tmp, dst in self.pending:
                place(tmp, dst)  # a rename over a regular file; a link written through, a device written
        except BaseException:
            self.discard()
            raise
        self.pending = []
        _fsync_path(self.folder, directory=True)
        self.syncs += 1

    def discard(self) -> None:
        """Remove the pending temporaries without placing them."""
        for tmp, _ in self.pending:
            tmp.unlink(missing_ok=True)
        self.pending = []

    def close(self) -> None:
        """Place the last pending files."""
        self.flush()

    def __enter__(self) -> BatchedWrites:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.flush()
        else:
            self.discard()
