"""Errors (matchplant.core.runtime.errors): the problem, the file and the fix, one a line."""

from __future__ import annotations

from matchplant.core.runtime.errors import MatchPlantError


def test_errors_format():
    e = MatchPlantError("bad thing", path="x/y.tif", fix="do this")
    assert str(e) == "bad thing\n  file: x/y.tif\n  fix:  do this"
