"""Progress bars for long work (tqdm), quiet when MATCHPLANT_QUIET=1 or when stderr is not a terminal
and the caller did not ask for them."""

from __future__ import annotations

import os
import sys
from typing import Iterable, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")


def progress(iterable: Iterable[T], desc: str = "", total: int | None = None, unit: str = "it",
             **kwargs) -> Iterable[T]:
    disable = os.environ.get("MATCHPLANT_QUIET") == "1" or (not sys.stderr.isatty() and
                                                            os.environ.get("MATCHPLANT_PROGRESS") != "1")
    return tqdm(iterable, desc=desc, total=total, unit=unit, disable=disable, dynamic_ncols=True,
                leave=False, **kwargs)
