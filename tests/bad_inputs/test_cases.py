"""Runs every case of the bad-input corpus (``cases_*.py`` beside this file); see harness.py."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
from fixtures import artifacts, work  # noqa: F401  (the fixtures; not a conftest.py, whose module name
from harness import run_case  # would shadow tests/conftest.py for the tests that import from it)

CASES = [
    case
    for path in sorted(Path(__file__).parent.glob("cases_*.py"))
    for case in importlib.import_module(path.stem).CASES
]
# the cases over ~10 s (pytest --durations on 2 shared cores): the slow tier
SLOW = {
    "m3-aoi-polygon-and-point-layers",
    "m6-sizes-differ-boxes-inside",
    "m6-windows-json-unicode-folder",
    "m7-nothing-found",
    "m7-unicode-paths-and-junk",
    "m8-evaluate-reference-of-another-field",
}


def marks(case) -> tuple:
    return (*case.marks, pytest.mark.slow) if case.name in SLOW else case.marks


def test_case_names_are_unique():
    names = [c.name for c in CASES]
    assert len(names) == len(set(names))


def test_slow_cases_exist():
    assert SLOW <= {c.name for c in CASES}


@pytest.mark.parametrize("case", [pytest.param(c, id=c.name, marks=marks(c)) for c in CASES])
def test_case(case, work, capsys):  # noqa: F811 - the fixture imported above
    run_case(case, work, capsys)
