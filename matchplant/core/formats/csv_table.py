"""A table to CSV as ``DataFrame.to_csv(index=False, float_format="%.12g")`` writes it, in half the time.

pandas formats every float through a Python call per value and then writes row by row; module 9's statistics
table of 20,000 plants took a tenth of its whole run (issue 30: the command is timed as a whole process against
exactextract). Here each float column is formatted in one list comprehension and the rows go through the
standard library's CSV writer (the same quoting: minimal, quotes doubled). Columns of other kinds (nullable
integers, categories, dates) leave the whole table to pandas, which knows their text forms.
"""

from __future__ import annotations

import csv
import os
from typing import IO

import numpy as np
import pandas as pd

_SIMPLE = "fiub"  # float, signed and unsigned integer, bool


def write_table(df: pd.DataFrame, fh: IO[str], digits: int = 12) -> None:
    """``df`` (no index) to the text file ``fh`` (opened with ``newline=""``): floats to ``digits``
    significant digits, NaN and None as empty fields."""
    if not all(dt.kind in _SIMPLE or dt.kind == "O" for dt in df.dtypes) or df.columns.duplicated().any():
        df.to_csv(fh, index=False, float_format=f"%.{digits}g")
        return
    columns = [_texts(df[c], digits) for c in df.columns]
    writer = csv.writer(fh, lineterminator=os.linesep)
    writer.writerow([str(c) for c in df.columns])
    writer.writerows(zip(*columns))


def _texts(col: pd.Series, digits: int) -> list:
    kind = col.dtype.kind
    if kind == "f":
        values = col.to_numpy()
        text = [f"{x:.{digits}g}" for x in values.tolist()]
        for i in np.flatnonzero(np.isnan(values)).tolist():
            text[i] = ""
        return text
    if kind in "iub":
        return col.tolist()
    # objects (flags, dates as text): missing values as empty fields, others as str() (as pandas writes them)
    return ["" if x is None or (isinstance(x, float) and x != x) else x for x in col.tolist()]
