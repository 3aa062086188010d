"""Runs every case of the bad-input corpus (``cases_*.py`` beside this file); see harness.py."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
from fixtures import artifacts, work  # noqa: F401  (the fixtures; not a conftest.py, whose module name
from harness import run_case  # would shadow tests/conftest.py for the tests that import from it)

CASES = [case for path in sorted(Path(__file__).parent.glob("cases_*.py"))
         for case in importlib.import_module(path.stem).CASES]


def test_case_names_are_unique():
    names = [c.name for c in CASES]
    assert len(names) == len(set(names))


@pytest.mark.parametrize("case", [pytest.param(c, id=c.name, marks=c.marks) for c in CASES])
def test_case(case, work, capsys):
    run_case(case, work, capsys)
