"""The bad-input corpus: each case starts from the tiny synthetic field, breaks one thing, runs a step as a
user would (the command line, in-process) and checks the promise of docs/troubleshooting.md ("When
something goes wrong"):

- a bad input ends with exit code 2 and one message (no traceback) that names the file or the key and
  says how to fix it (``fix:``); exit code 1 ("internal error") is a failure of ours;
- no input file changes (every file under the case's input folder is hashed before and after);
- a failed run leaves its output folder as it found it, apart from ``logs/``;
- the cases that must *work* (paths with spaces and non-ASCII letters, BOM/CRLF text, junk files in image
  folders) exit 0 and write what they should.

A case module lists :class:`Case` objects; ``test_cases.py`` runs them all.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from matchplant.cli import run_module


@dataclass
class Work:
    """One case's folders: ``inputs`` (a private copy of what the step reads) and ``out`` (its output)."""

    root: Path
    artifacts: Path  # read-only: the tiny field and the files derived from it once per session

    @property
    def inputs(self) -> Path:
        return self.root / "in"

    @property
    def out(self) -> Path:
        return self.root / "out"

    def copy(self, relative: str, name: str | None = None) -> Path:
        """Copy ``artifacts/relative`` (file or folder) into the inputs; returns the copy's path."""
        src = self.artifacts / relative
        dst = self.inputs / (name or Path(relative).name)
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst)
        else:
            shutil.copy2(src, dst)
        return dst


@dataclass
class Case:
    """``prepare(work)`` copies and breaks the inputs and returns the command-line arguments.

    ``expect``: "error" (exit 2, message naming every string of ``mentions``) or "ok" (exit 0, then
    ``check(work)`` must hold). ``outputs_allowed`` lists output files a failed run may leave on
    purpose (for example a report of what was dropped).
    """

    name: str
    step: str
    prepare: Callable[[Work], list[str]]
    expect: str = "error"
    mentions: tuple[str, ...] = ()
    check: Callable[[Work], None] | None = None
    outputs_allowed: tuple[str, ...] = ()
    marks: tuple = field(default_factory=tuple)
    env: dict = field(default_factory=dict)  # environment variables set for the run only (None: unset)


def write_text_file(path: Path, text: str, *, bom: bool = False, crlf: bool = False) -> Path:
    """Write ``text`` as a user's editor might: with a UTF-8 byte-order mark and Windows line ends, if asked."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if crlf:
        text = text.replace("\n", "\r\n")
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8"))
    return path


def read_rows(path: Path, sep: str) -> list[list[str]]:
    """A delimited text file (events.txt, a survey CSV) as rows of fields, header first."""
    return [ln.split(sep) for ln in path.read_text().splitlines()]


def write_rows(w: Work, rows: list[list[str]], name: str, sep: str) -> Path:
    """Rows of fields written as a delimited file among the case's inputs."""
    path = w.inputs / name
    path.write_text("".join(sep.join(r) + "\n" for r in rows))
    return path


@contextlib.contextmanager
def environment(values: dict):
    """``os.environ`` with ``values`` set (None: unset) inside the block, as it was after it."""
    old = {k: os.environ.get(k) for k in values}
    try:
        for k, v in values.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, str(v))
        yield
    finally:
        for k, v in old.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)


def tree_hashes(folder: Path) -> dict[str, str]:
    if not folder.exists():
        return {}
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def leftovers(out: Path, before: set[str], allowed: tuple[str, ...]) -> list[str]:
    """Files in ``out`` that the failed run created, other than its log and the allowed ones."""
    now = {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} if out.exists() else set()
    return sorted(
        p
        for p in now - before
        if not p.startswith("logs") and Path(p).name not in allowed and not Path(p).name.startswith(".")
    )


def run_case(case: Case, work: Work, capsys) -> None:
    work.inputs.mkdir(parents=True, exist_ok=True)
    argv = case.prepare(work)
    before_inputs = tree_hashes(work.inputs)
    before_out = set(tree_hashes(work.out))
    with environment(case.env):
        code = run_module(case.step, [*argv, "--quiet"])
    err = capsys.readouterr().err
    assert tree_hashes(work.inputs) == before_inputs, f"{case.name}: an input file changed"
    if case.expect == "ok":
        assert code == 0, f"{case.name}: must work, but exited {code}:\n{err}"
        if case.check is not None:
            case.check(work)
        return
    assert code != 1, f"{case.name}: internal error instead of a clear message:\n{err}"
    assert code == 2, f"{case.name}: bad input must fail with exit code 2, got {code}:\n{err}"
    # warnings may come first; the error is the last message, whole, without a traceback
    assert "Traceback" not in err and (err.startswith("error: ") or "\nerror: " in err), (
        f"{case.name}: not one clean message:\n{err}"
    )
    err = err[err.find("error: ") if err.startswith("error: ") else err.rfind("\nerror: ") + 1 :]
    assert "fix:" in err or "did you mean" in err, f"{case.name}: the message gives no fix:\n{err}"
    # the case's own folder is named after the case: words must come from the message, not from that name
    said = err.replace(str(work.root), "<case folder>").lower()
    for text in case.mentions:
        assert text.lower() in said, f"{case.name}: the message does not name {text!r}:\n{err}"
    left = leftovers(work.out, before_out, case.outputs_allowed)
    assert not left, f"{case.name}: the failed run left partial outputs: {left}"
