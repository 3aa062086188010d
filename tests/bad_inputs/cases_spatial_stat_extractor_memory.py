"""Module 9's memory setting (issue 30): a max_memory that is not a size, or too small to be useful."""

from __future__ import annotations

from cases_spatial_stat_extractor import args, gpkg
from harness import Case, Work


def memory(value: str):
    def prepare(w: Work) -> list[str]:
        return args(w, gpkg(w), f"max_memory={value}")

    return prepare


CASES = [
    Case("m9-max-memory-not-a-size", "spatial_stat_extractor", memory("lots"), mentions=("max_memory", "3GB")),
    Case("m9-max-memory-unknown-unit", "spatial_stat_extractor", memory("3 parsecs"), mentions=("max_memory",)),
    Case("m9-max-memory-too-small", "spatial_stat_extractor", memory("64MB"), mentions=("max_memory", "256MB")),
]
