"""Re-runs leave nothing stale (issue 29): a step (modules 7 and 9) lists every file a run wrote in
``manifest.json``; the next run into the same folder removes what the previous manifest listed and this run did
not write again (module 7's drawn images of other photos or a ``metrics.json`` of an evaluation not repeated,
module 9's outlines of a run with canopy outlines), and nothing else: files the user put in the folder stay. The
removal happens only after the new outputs are in place (a failed run changes
nothing)."""

from __future__ import annotations

from pathlib import Path

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import write_json
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.readers import read_record

log = get_logger()

MANIFEST = "manifest.json"
NOT_LISTED = ("logs",)  # the run log is kept across runs (the guard writes it directly)


def previous_files(out_dir: Path) -> list[str]:
    """The files the previous run into ``out_dir`` listed (none when it left no readable manifest)."""
    path = Path(out_dir) / MANIFEST
    try:
        data = read_record(path, what="the list of the previous run's files", fix="", default={})
    except InputError as exc:  # nothing is removed then: a damaged list must not remove the user's files
        log.warning("%s; no earlier output is removed (delete %s to silence this)", exc.problem, path)
        return []
    files = data.get("files", [])
    return [f for f in files if isinstance(f, str)] if isinstance(files, list) else []


def write_manifest(stage: Path, extra: list[str] = ()) -> list[str]:
    """List the files under ``stage`` (and ``extra``: files other processes of a torchrun job write) in
    ``stage/manifest.json``; returns the list."""
    stage = Path(stage)
    files = sorted(
        {
            p.relative_to(stage).as_posix()
            for p in stage.rglob("*")
            if p.is_file() and p.relative_to(stage).parts[0] not in NOT_LISTED
        }
        | set(extra)
        | {MANIFEST}
    )
    write_json(
        stage / MANIFEST,
        {
            "description": "the files of this step's last run in this folder; the next run "
            "removes those it does not write again",
            "files": files,
        },
    )
    return files


def remove_stale(out_dir: Path, before: list[str], now: list[str]) -> int:
    """Remove the files of ``before`` that are not in ``now`` (inside ``out_dir`` only), and folders left
    empty by that; returns how many files were removed."""
    out_dir = Path(out_dir).resolve()
    removed = 0
    for rel in sorted(set(before) - set(now)):
        path = (out_dir / rel).resolve()
        if out_dir not in path.parents or not path.is_file():
            continue  # a manifest edited to point elsewhere, or a file already gone
        path.unlink()
        removed += 1
        for parent in path.parents:
            if parent == out_dir or any(parent.iterdir()):
                break
            parent.rmdir()
    if removed:
        log.info(
            "%d file(s) of the previous run removed from %s (listed in its %s, not written this time)",
            removed,
            out_dir,
            MANIFEST,
        )
    return removed
