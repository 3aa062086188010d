"""File I/O (matchplant.core.runtime.io): atomic output, JSON errors that name the file."""

from __future__ import annotations

import pytest

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import atomic_open, read_json, write_json


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    p = tmp_path / "a.json"
    write_json(p, {"v": 1})
    with pytest.raises(RuntimeError):
        with atomic_open(p) as fh:
            fh.write("{partial")
            raise RuntimeError("crash")
    assert read_json(p) == {"v": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["a.json"]


def test_read_json_errors_name_file(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{oops")
    with pytest.raises(InputError, match="line 1"):
        read_json(p)
    with pytest.raises(InputError, match="not found"):
        read_json(tmp_path / "none.json")
