"""The run guard: inputs are never written, outputs can be written, and outputs appear whole or not at all.

A config's fields say which paths are inputs (``param(..., path="file" | "dir" | "exists")``) and which are
outputs (``path="out"``); see :func:`matchplant.core.runtime.config.param`. Before a step runs:

- :func:`check_outputs_are_not_inputs` refuses an output that is an input, lies inside an input folder the
  step reads, or is the folder of an input file (the message names both keys);
- :func:`check_outputs_writable` refuses an output folder that cannot be created or written (the message
  names the key and the folder, instead of a ``PermissionError`` half-way through);
- :func:`check_outputs` does both (the command line calls it once per run).

Two class attributes of a config relax the rule where a step's design needs it:

- ``writes_into_inputs = ("output_dir",)``: output keys that may be, hold or lie in input folders (ODM
  writes into its project folder);
- ``outputs_inside_inputs = ("project_dir",)``: input folders that are read by fixed names (an ODM project),
  not listed, so that an output folder may lie inside them (``<project>/min_images``). An output that is the
  folder itself, or holds an input, is still refused.

While a step runs, :func:`staged_outputs` gives it a private folder beside the output folder; its files are
moved into place only when the step succeeds, so a failed run leaves the output folder as it found it.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any

from matchplant.core.runtime.errors import ConfigError, OutputError
from matchplant.core.runtime.io import output_target
from matchplant.core.runtime.log import naming_final

INPUT_KINDS = ("file", "dir", "exists")
OUTPUT_KINDS = ("out", "out_file")  # an output folder, an output file


def path_fields(cfg: Any, prefix: str = "") -> Iterator[tuple[str, Path, str]]:
    """``(dotted key, path, kind)`` for every path-valued field with a path kind, nested sections and lists of
    sections included (``more_dates[1].dsm``); unset (None) values are left out."""
    for f in fields(cfg):
        key = prefix + f.name
        value = getattr(cfg, f.name)
        kind = f.metadata.get("path")
        items = list(enumerate(value)) if isinstance(value, (list, tuple)) else [(None, value)]
        for i, item in items:
            k = key if i is None else f"{key}[{i}]"
            if is_dataclass(item):
                yield from path_fields(item, k + ".")
            elif kind and isinstance(item, (str, Path)) and str(item):
                yield k, Path(item), kind


def inputs_and_outputs(cfg: Any) -> tuple[list[tuple[str, Path, str]], list[tuple[str, Path]]]:
    """A config's input paths ``(key, path, kind)`` and output paths ``(key, path)``."""
    items = list(path_fields(cfg))
    return (
        [(k, p, kind) for k, p, kind in items if kind in INPUT_KINDS],
        [(k, p) for k, p, kind in items if kind in OUTPUT_KINDS],
    )


def _real(p: Path) -> Path:
    return Path(os.path.normcase(os.path.realpath(p)))


def _same(a: Path, b: Path) -> bool:
    if _real(a) == _real(b):
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)  # hard links, case-insensitive disks
    except OSError:
        return False


def _inside(child: Path, parent: Path) -> bool:
    c, p = _real(child), _real(parent)
    return c != p and p in c.parents


def overlap(out_key: str, out: Path, in_key: str, inp: Path, kind: str, *, inside_ok: bool = False) -> str | None:
    """Why output ``out`` must not be written given input ``inp`` (of ``kind``), or None when they are apart.
    ``inside_ok``: the input is a folder read by fixed names, so an output inside it is fine."""
    if _same(out, inp):
        return f"output '{out_key}' is the same path as input '{in_key}' ({inp})"
    if _inside(out, inp) and (kind == "dir" or inp.is_dir()) and not inside_ok:
        return f"output '{out_key}' ({out}) is inside the input folder '{in_key}' ({inp}) that this step reads"
    # a file right in the output folder can be written over; an input folder below it (an ODM project's
    # images/, which gcp_list.txt sits beside) is not, unless a step writes that very subfolder (it checks)
    if _inside(inp, out) and not inp.is_dir() and _real(inp).parent == _real(out):
        return f"output folder '{out_key}' ({out}) contains the input '{in_key}' ({inp})"
    return None


def check_no_overlap(
    outputs: list[tuple[str, Path]],
    inputs: list[tuple[str, Path, str]],
    *,
    source: str = "config",
    inside_ok: Iterable[str] = (),
) -> None:
    """Raise a ConfigError for the first output that would write over, into or around an input (an output may
    lie inside the input folders named in ``inside_ok``)."""
    inside_ok = set(inside_ok)
    for out_key, out in outputs:
        for in_key, inp, kind in inputs:
            why = overlap(out_key, out, in_key, inp, kind, inside_ok=in_key in inside_ok)
            if why:
                raise ConfigError(
                    f"{why} ({source}); inputs are never written over",
                    path=out,
                    fix=f"set '{out_key}' to a new folder of its own, apart from the inputs",
                )


def check_outputs_are_not_inputs(cfg: Any, *, source: str = "config") -> None:
    """Refuse an output path that is an input, is inside an input folder, or contains an input."""
    inputs, outputs = inputs_and_outputs(cfg)
    exempt = set(getattr(type(cfg), "writes_into_inputs", ()))
    check_no_overlap(
        [(k, p) for k, p in outputs if k not in exempt],
        inputs,
        source=source,
        inside_ok=getattr(type(cfg), "outputs_inside_inputs", ()),
    )


def check_writable(folder: str | Path, *, key: str = "output_dir") -> None:
    """The folder exists and takes a new file, or can be created (its nearest existing parent takes one)."""
    folder = Path(folder)
    probe = folder
    while not probe.exists():
        if probe.is_symlink():  # a dangling link: no step can make a folder there, and none replaces the link
            raise OutputError(
                f"output folder '{key}' ({folder}) cannot be created: {probe} is a symlink to "
                f"{os.path.realpath(probe)}, which does not exist",
                path=probe,
                fix=f"create {os.path.realpath(probe)} (or remove the link), or set '{key}' to another folder",
            )
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        kind = "a file" if probe.is_file() else "not a folder (a device, FIFO or socket)"
        what = f"is {kind}" if probe == folder else f"cannot be created: {probe} is {kind}"
        raise OutputError(
            f"output folder '{key}' ({folder}) {what}",
            path=probe,
            fix=f"set '{key}' to a folder (or move the file away)",
        )
    try:
        fd, name = tempfile.mkstemp(prefix=".matchplant-write-test-", dir=probe)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        what = "cannot be written" if probe == folder else f"cannot be created in {probe}"
        raise OutputError(
            f"output folder '{key}' ({folder}) {what}: {exc.strerror or exc}",
            path=folder,
            fix=f"set '{key}' to a folder you can write to, or change its permissions",
        ) from exc


def check_outputs_writable(cfg: Any) -> None:
    """Check that every output folder (and the folder of every output file) can be written; an error naming the key."""
    for key, path, kind in path_fields(cfg):
        if kind == "out":
            check_writable(path, key=key)
        elif kind == "out_file" and output_target(path)[0] == "file":  # a folder, a socket: refused here
            check_writable(output_target(path)[1].parent, key=key)


def check_outputs(cfg: Any, *, source: str = "config") -> None:
    """Both checks, before a step runs: outputs apart from inputs, and writable."""
    check_outputs_are_not_inputs(cfg, source=source)
    check_outputs_writable(cfg)


# --------------------------------------------------------------------------------------------------
# whole or nothing


def _check_replaceable(dst: Path, rel: Path) -> None:
    """Refuse (OutputError) to put a staged file at ``dst / rel`` where something other than a regular file is,
    or where a folder on the way is a file: a staged run replaces only files of its own kind."""
    p = dst
    for i, part in enumerate(rel.parts):
        p = p / part
        last = i == len(rel.parts) - 1
        if p.is_symlink() and last:
            what = f"a symlink (to {os.path.realpath(p)})"
        elif not p.exists():
            return
        elif last and not p.is_file():
            what = "a folder" if p.is_dir() else "not a regular file (a device, FIFO or socket)"
        elif not last and not p.is_dir():
            what = "a file where the output needs a folder"
        else:
            continue
        raise OutputError(
            f"cannot write {dst / rel}: {p} is {what}, which a run never replaces",
            path=p,
            fix="move it away (or write the outputs to another folder), then run again",
        )


def _output_folder(out_dir: Path) -> Path:
    """The folder a step writes: ``out_dir``, or the target of a symlink to a folder (written through, the link
    kept). Refuses a path that is, or links to, something other than a folder (a dangling link:
    :func:`check_writable`)."""
    target = Path(os.path.realpath(out_dir)) if out_dir.is_symlink() else out_dir
    if target.exists() and not target.is_dir():
        via = f" (a symlink to {target})" if target != out_dir else ""
        raise OutputError(
            f"the output folder {out_dir}{via} is not a folder",
            path=out_dir,
            fix="give a folder as the output (or move the file away)",
        )
    return target


def _move_tree(src: Path, dst: Path) -> None:
    """Move every file of ``src`` to the same place under ``dst``, replacing files there and keeping the
    others; on a failure half-way, undo the moves already made."""
    staged = sorted(p for p in src.rglob("*") if p.is_file() or p.is_symlink())
    for f in staged:  # before any move: nothing but regular files (and folders) is ever replaced
        _check_replaceable(dst, f.relative_to(src))
    backup = Path(tempfile.mkdtemp(prefix=f".{dst.name}.replaced-", dir=dst.parent))
    done: list[tuple[Path, Path, bool]] = []  # (staged file, its destination, an old file was put aside)
    try:
        for f in staged:
            rel = f.relative_to(src)
            target = dst / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            had = target.exists()
            if had:
                (backup / rel).parent.mkdir(parents=True, exist_ok=True)
                os.replace(target, backup / rel)
            done.append((f, target, had))
            os.replace(f, target)
    except BaseException:
        for f, target, had in reversed(done):
            if target.exists() and not f.exists():
                os.replace(target, f)
            if had:
                os.replace(backup / f.relative_to(src), target)
        raise
    finally:
        shutil.rmtree(backup, ignore_errors=True)


@contextlib.contextmanager
def staged_outputs(out_dir: str | Path) -> Iterator[Path]:
    """A temporary folder beside ``out_dir`` for a step's outputs, moved into place only on success.

    ::

        with staged_outputs(cfg.output_dir) as out:     # write everything under `out`
            write_json(out / "selection.json", ...)
        # success: the files are in cfg.output_dir (existing files the step did not rewrite are kept);
        # an exception: cfg.output_dir is as it was, the temporary folder is gone

    Read earlier results (resume) from ``out_dir`` itself; paths written *into* files should name
    ``out_dir``, not the temporary folder. The run log goes to ``out_dir/logs`` directly.
    """
    check_writable(out_dir)
    out_dir = _output_folder(Path(out_dir))  # a link to a folder is written through, never replaced
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = out_dir.parent / f".{out_dir.name}.partial-{uuid.uuid4().hex[:12]}"
    stage.mkdir()  # not mkdtemp: a new output folder gets the usual permissions, not 0700
    try:
        with naming_final(stage, out_dir):  # the console names the folder the files end up in
            yield stage
        if not out_dir.exists():
            os.replace(stage, out_dir)  # a new folder appears in one rename
        else:
            _move_tree(stage, out_dir)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


__all__ = [
    "path_fields",
    "inputs_and_outputs",
    "overlap",
    "check_no_overlap",
    "check_outputs_are_not_inputs",
    "check_writable",
    "check_outputs_writable",
    "check_outputs",
    "staged_outputs",
]
