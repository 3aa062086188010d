"""Atomic writes replace only regular files (issue 39): a symlink is written through and kept, a device, a FIFO
and ``-`` are written directly, a folder is refused; staged output folders never replace a link or a file.
Every case runs the same as root (CI): /dev/null is only ever opened, and the checks look at what is left."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

import matchplant.cli as cli
import matchplant.core.runtime.io as io_mod
from matchplant.core.runtime.errors import OutputError
from matchplant.core.runtime.guard import check_writable, staged_outputs
from matchplant.core.runtime.io import BatchedWrites, atomic_path, write_json, write_text
from matchplant.detection.synth import make_tiles

needs_posix = pytest.mark.skipif(os.name != "posix", reason="symlinks, FIFOs and /dev/null as on Linux and macOS")


def _is_chr(path) -> bool:
    return stat.S_ISCHR(os.stat(path).st_mode)


def test_regular_file_is_replaced_whole(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("old")
    os.chmod(p, 0o640)
    write_text(p, "new")
    assert p.read_text() == "new" and not p.is_symlink()
    assert os.name != "posix" or stat.S_IMODE(os.stat(p).st_mode) == 0o640  # its permissions kept
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.txt"]  # no temporary left


@needs_posix
def test_symlink_to_file_is_written_through(tmp_path):
    target = tmp_path / "real" / "config.yaml"
    target.parent.mkdir()
    target.write_text("old")
    link = tmp_path / "link.yaml"
    link.symlink_to(target)
    write_text(link, "new: 1\n")
    assert link.is_symlink() and os.readlink(link) == str(target)  # the link is kept
    assert target.read_text() == "new: 1\n"  # and its target holds the new content
    with atomic_path(link) as tmp:  # writers that want a file name: the temporary lies beside the target
        assert tmp.parent == target.parent
        tmp.write_bytes(b"bytes")
    assert link.is_symlink() and target.read_bytes() == b"bytes"


@needs_posix
def test_dangling_symlink_creates_its_target(tmp_path):
    link = tmp_path / "out.json"
    link.symlink_to(tmp_path / "elsewhere.json")
    write_json(link, {"a": 1})
    assert link.is_symlink() and (tmp_path / "elsewhere.json").read_text() == '{\n "a": 1\n}\n'
    gone = tmp_path / "gone.json"
    gone.symlink_to(tmp_path / "no_such_folder" / "x.json")
    with pytest.raises(OutputError, match="does not exist"):
        write_json(gone, {})
    assert gone.is_symlink()


@needs_posix
def test_folder_and_symlink_to_folder_are_refused(tmp_path):
    d = tmp_path / "dir"
    d.mkdir()
    (d / "keep.txt").write_text("k")
    link = tmp_path / "link"
    link.symlink_to(d)
    for p in (d, link):
        with pytest.raises(OutputError, match="a folder") as err:
            write_text(p, "x")
        assert str(p) in str(err.value)
    assert link.is_symlink() and d.is_dir() and (d / "keep.txt").read_text() == "k"


@needs_posix
@pytest.mark.skipif(not os.path.exists("/dev/null"), reason="no /dev/null")
def test_character_device_is_written_not_replaced(tmp_path):
    write_text("/dev/null", "discarded\n")
    assert _is_chr("/dev/null")
    link = tmp_path / "null_link"  # like /dev/stdout: a link to a device
    link.symlink_to("/dev/null")
    write_json(link, {"a": 1})
    with BatchedWrites(tmp_path) as bw:
        bw.write("null_link", b"data")
    assert link.is_symlink() and os.readlink(link) == "/dev/null" and _is_chr("/dev/null")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["null_link"]


@needs_posix
@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="no /proc")
def test_link_through_proc_writes_the_open_file(tmp_path):
    """/dev/stdout redirected to a file: the open file gets the text; it is not replaced by a new one."""
    opened = tmp_path / "redirected.txt"
    with open(opened, "w") as fh:
        inode = os.stat(opened).st_ino
        link = tmp_path / "stdout_link"
        link.symlink_to(f"/proc/self/fd/{fh.fileno()}")
        write_text(link, "through\n")
    assert link.is_symlink() and opened.read_text() == "through\n" and os.stat(opened).st_ino == inode


@needs_posix
def test_fifo_is_written_directly(tmp_path, monkeypatch):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    write_text(fifo, "streamed\n")
    reader.join(10)
    assert got == ["streamed\n"] and stat.S_ISFIFO(os.stat(fifo).st_mode)
    monkeypatch.setattr(io_mod, "FIFO_WAIT_S", 0.2)  # nobody reads: a clear error, not a hang
    with pytest.raises(OutputError, match="no program reads the FIFO"):
        write_text(fifo, "lost\n")
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


def test_dash_is_stdout(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    write_text("-", "to stdout\n")
    write_json("-", {"b": 2})
    assert capsys.readouterr().out == 'to stdout\n{\n "b": 2\n}\n'
    assert list(tmp_path.iterdir()) == []  # no file named '-'


def _write_config(tmp_path, target, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = cli.main(["inspect", "--write-config", str(target)])
    return rc, capsys.readouterr()


@needs_posix
def test_cli_write_config_to_dash_and_through_a_link(tmp_path, capsys, monkeypatch):
    rc, out = _write_config(tmp_path, "-", capsys, monkeypatch)
    assert rc == 0, out.err
    config = yaml.safe_load(out.out)
    assert isinstance(config, dict) and "wrote" not in out.out  # the config alone on stdout
    target = tmp_path / "kept" / "inspect.yaml"
    target.parent.mkdir()
    target.write_text("stale: true\n")
    link = tmp_path / "link.yaml"
    link.symlink_to(target)
    rc, out = _write_config(tmp_path, link, capsys, monkeypatch)
    assert rc == 0, out.err
    assert link.is_symlink() and yaml.safe_load(target.read_text()) == config
    assert sorted(f.name for f in tmp_path.iterdir()) == ["kept", "link.yaml"]


# ---- staged output folders (core/runtime/guard.py)


@needs_posix
def test_staged_outputs_write_through_a_link_to_a_folder(tmp_path):
    real = tmp_path / "real_out"
    real.mkdir()
    (real / "old.txt").write_text("old")
    link = tmp_path / "out"
    link.symlink_to(real)
    with staged_outputs(link) as stage:
        (stage / "new.txt").write_text("new")
    assert link.is_symlink() and (real / "new.txt").read_text() == "new" and (real / "old.txt").exists()
    dangling = tmp_path / "out2"  # a folder no step can make (os.makedirs fails there): refused, link kept
    dangling.symlink_to(tmp_path / "not_made")
    refused = "is a symlink to .*not_made, which does not exist"
    with pytest.raises(OutputError, match=refused):
        check_writable(dangling / "sub")  # what the command line checks before a step runs
    with pytest.raises(OutputError, match=refused):
        with staged_outputs(dangling):
            pass
    assert dangling.is_symlink() and not (tmp_path / "not_made").exists()


@needs_posix
def test_staged_outputs_refuse_what_they_do_not_own(tmp_path):
    f = tmp_path / "file_out"
    f.write_text("mine")
    link = tmp_path / "link_out"
    link.symlink_to(f)
    for out in (f, link):
        with pytest.raises(OutputError):
            with staged_outputs(out) as stage:
                (stage / "x.txt").write_text("x")
    assert f.read_text() == "mine" and link.is_symlink()
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.txt").write_text("old a")
    elsewhere = tmp_path / "user.txt"
    elsewhere.write_text("user")
    (out / "b.txt").symlink_to(elsewhere)
    os.mkfifo(out / "c.txt")
    for name, what in (("b.txt", "symlink"), ("c.txt", "not a regular file")):
        with pytest.raises(OutputError, match=what):
            with staged_outputs(out) as stage:
                (stage / "a.txt").write_text("new a")
                (stage / name).write_text("new")
        # refused before any move: the folder is as it was
        assert (out / "a.txt").read_text() == "old a" and elsewhere.read_text() == "user"
    assert (out / "b.txt").is_symlink() and stat.S_ISFIFO(os.stat(out / "c.txt").st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file_out", "link_out", "out", "user.txt"]


@needs_posix
@pytest.mark.skipif(not os.path.exists("/dev/stdout"), reason="no /dev/stdout")
def test_dev_stdout_appended_to_a_redirected_file(tmp_path):
    """``... --write-config /dev/stdout >> log``: the text follows what was printed, the log is not truncated."""
    log = tmp_path / "log.txt"
    log.write_text("before\n")
    code = "from matchplant.core.runtime.io import write_text; print('first', flush=True); "
    code += "write_text('/dev/stdout', 'config\\n'); print('after')"
    with open(log, "a") as fh:
        subprocess.run([sys.executable, "-c", code], stdout=fh, check=True, timeout=60, env=_env())
    assert log.read_text() == "before\nfirst\nconfig\nafter\n"
    assert os.path.islink("/dev/stdout") or _is_chr("/dev/stdout")


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}


def test_an_output_file_key_is_rewritten_on_a_rerun_and_may_be_stdout(tmp_path, capsys, monkeypatch):
    """``inspect``'s ``report`` (an output file, not a folder): an earlier report is replaced on a rerun, "-" is
    standard output (also from a config file, not a file named '-' beside it), a folder is refused."""
    coco = make_tiles(tmp_path / "tiles", n_images=3, size=64, plants=(1, 2), radius=(5, 8), negatives=0, name="t.json")
    monkeypatch.chdir(tmp_path)
    report = tmp_path / "report.json"
    report.write_text("{}")
    run = ["inspect", "--set", f"annotations={coco}", "--set"]
    assert cli.main([*run, f"report={report}"]) == 0
    assert json.loads(report.read_text())  # the earlier report replaced, not refused as "a file"
    capsys.readouterr()
    config = tmp_path / "inspect.yaml"
    config.write_text(f"annotations: {coco}\nreport: '-'\n")
    assert cli.main(["inspect", "--config", str(config)]) == 0
    assert '"' in capsys.readouterr().out and not (tmp_path / "-").exists()
    assert cli.main([*run, f"report={tmp_path}"]) == 2
    assert "it is a folder" in capsys.readouterr().err
