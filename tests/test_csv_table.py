"""The fast CSV writer against pandas' own ``to_csv(index=False, float_format="%.12g")``: the same text."""

import io

import numpy as np
import pandas as pd

from matchplant.core.formats.csv_table import write_table


def _pandas(df):
    buf = io.StringIO(newline="")
    df.to_csv(buf, index=False, float_format="%.12g")
    return buf.getvalue()


def _ours(df):
    buf = io.StringIO(newline="")
    write_table(df, buf)
    return buf.getvalue()


def test_same_text_as_pandas_for_every_kind_of_column():
    rng = np.random.default_rng(0)
    n = 300
    df = pd.DataFrame(
        {
            "plant_id": np.arange(n),
            "height": rng.normal(0, 1, n) * 10.0 ** rng.integers(-8, 9, n),  # small and large: exponents
            "count": rng.integers(0, 5, n).astype(float),  # whole numbers as floats
            "f32": rng.random(n).astype(np.float32),
            "u8": rng.integers(0, 255, n).astype(np.uint8),
            "fills_box": rng.random(n) < 0.5,
            "flag": rng.choice(["", "small", "low", "dup, second box", 'a "quoted" name', None], n),
            "date": rng.choice(["2024-06-01", "w3"], n),
            "mixed": rng.choice([1.5, np.nan, "x", None, 3], n),
        }
    )
    df.loc[::7, "height"] = np.nan
    df.loc[3, "height"], df.loc[4, "height"], df.loc[5, "height"] = np.inf, -np.inf, -0.0
    assert _ours(df) == _pandas(df)
    assert _ours(df.iloc[:0]) == _pandas(df.iloc[:0])  # no rows: the header


def test_other_kinds_of_columns_are_left_to_pandas():
    df = pd.DataFrame(
        {
            "id": pd.array([1, None, 3], dtype="Int64"),
            "day": pd.to_datetime(["2024-06-01"] * 3),
            "kind": pd.Categorical(["a", "b", "a"]),
            "v": [0.1, 0.2, np.nan],
        }
    )
    assert _ours(df) == _pandas(df)
