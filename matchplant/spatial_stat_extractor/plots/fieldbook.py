"""Field books: one row per plot (plot id -> genotype, rep, ...), as breeders keep them.

Read as Excel and other tools save them: CSV in UTF-8 with or without a byte-order mark (else Windows-1252),
Windows line ends, quoted cells holding the delimiter, ``,`` ``;`` or tab separated, and the empty rows
Excel leaves at the end (``,,``) ignored; or an ``.xlsx`` workbook (its first sheet, through openpyxl).
Plot ids are joined as text; where they differ from the plots' by a prefix or leading zeros (``P1``,
``plot_001`` against ``1``) they are matched by their numbers, and the log says so. A field book of which
no row joins a plot is refused; rows that join none are counted and named.
"""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import pandas as pd

from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.log import get_logger
from matchplant.core.runtime.validate import did_you_mean

log = get_logger("spatial_stat_extractor")

EXCEL = (".xlsx", ".xlsm")
ID_NAMES = ("plot_id", "plotid", "plot", "plot_no", "plotno", "plot_number", "plotnumber", "plot_nr", "id")


def _loose(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", str(name).casefold())


def _read_text(path: Path) -> pd.DataFrame:
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("cp1252", errors="replace")
        log.info("field book %s is not UTF-8: read as Windows-1252 (Excel's 'CSV' on Windows)", path.name)
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines:
        raise InputError("the field book is empty", path=path, fix="give a CSV with a header row and one row per plot")
    try:
        sep = csv.Sniffer().sniff("\n".join(lines[:20]), delimiters=",;\t|").delimiter
    except csv.Error:
        sep = max(",;\t", key=lines[0].count)
    try:
        book = pd.read_csv(io.StringIO(text), sep=sep, dtype=str, keep_default_na=False, skip_blank_lines=True)
    except (pd.errors.ParserError, ValueError) as exc:
        raise InputError(
            f"the field book cannot be read as a table: {exc}",
            path=path,
            fix="save it as CSV with one header row (or as .xlsx)",
        ) from exc
    return book.fillna("")  # (cells missing from short rows)


def _read_excel(path: Path) -> pd.DataFrame:
    try:
        import openpyxl  # noqa: F401  (pandas reads .xlsx through it)
    except ImportError as exc:
        raise InputError(
            "reading an .xlsx field book needs the openpyxl package, which is not installed",
            path=path,
            fix="pip install openpyxl (requirements.txt lists it), or save the sheet as CSV",
        ) from exc
    try:
        book = pd.read_excel(path, sheet_name=0, dtype=object, engine="openpyxl")
    except Exception as exc:  # openpyxl raises zip, XML and key errors for a damaged or mislabelled file
        raise InputError(
            f"cannot read the workbook: {exc}",
            path=path,
            fix="open it in a spreadsheet and save it again as .xlsx, or as CSV",
        ) from exc
    log.info("field book %s: first sheet of the workbook read", path.name)
    return book.apply(lambda c: c.map(lambda v: "" if pd.isna(v) else _cell_text(v)))


def _cell_text(v) -> str:
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    return str(v).strip()


def read_field_book(path: Path) -> pd.DataFrame:
    """The field book as text cells, empty rows and unnamed empty columns dropped."""
    path = Path(path)
    if not path.is_file():
        raise InputError("field book not found", path=path, fix="correct plots.field_book")
    suffix = path.suffix.lower()
    if suffix == ".xls" or suffix == ".ods":
        raise InputError(f"{suffix} workbooks are not read", path=path, fix="save the sheet as .xlsx or as CSV")
    book = _read_excel(path) if suffix in EXCEL else _read_text(path)
    book.columns = [str(c).strip() for c in book.columns]
    book = book.apply(lambda c: c.str.strip() if c.dtype == object else c)
    empty_cols = [c for c in book.columns if c.startswith("Unnamed:") and (book[c] == "").all()]
    book = book.drop(columns=empty_cols)
    blank = (book == "").all(axis=1)
    if blank.any():
        log.info("field book %s: %d empty rows ignored", path.name, int(blank.sum()))
    book = book[~blank].reset_index(drop=True)
    if book.empty:
        raise InputError("the field book has no data rows", path=path, fix="one row per plot under the header")
    return book


def id_column_of(book: pd.DataFrame, wanted: str, path: Path, key: str) -> str:
    """The field book's plot id column: ``wanted``, else its loose spelling (case, spaces), else a usual
    name for plot ids."""
    if wanted in book.columns:
        return wanted
    loose = {_loose(c): c for c in book.columns}
    for name in (wanted, *ID_NAMES):
        if _loose(name) in loose:
            col = loose[_loose(name)]
            log.info("field book %s: plot ids read from its column '%s' (%s = '%s')", path.name, col, key, wanted)
            return col
    hint = did_you_mean(wanted, book.columns)
    raise InputError(
        f"the field book has no '{wanted}' column ({hint or 'columns: ' + str(list(book.columns))})",
        path=path,
        fix=f"set {key} to its plot id column",
    )


def _number(s: str) -> str | None:
    m = re.fullmatch(r"\D*?0*(\d+)\D*", s)
    return m.group(1) if m else None


def _keys(values) -> list[str]:
    return [_cell_text(v) if not isinstance(v, str) else v.strip() for v in values]


def join_field_book(table: pd.DataFrame, path: Path, id_column: str, key: str = "plots.field_book_id_column"):
    """``table`` (one row per plot, ``plot_id``) with the field book's columns joined by plot id."""
    path = Path(path)
    book = read_field_book(path)
    col = id_column_of(book, id_column, path, key)
    ids = _keys(book[col])
    missing = [i + 2 for i, s in enumerate(ids) if s == ""]
    if missing:
        raise InputError(
            f"field book rows without a plot id in '{col}' (lines {missing[:5]})",
            path=path,
            fix="give every row its plot id, or delete the row",
        )
    plot_ids = _keys(table["plot_id"])
    book_keys, plot_keys, how = ids, plot_ids, "as written"
    joined = sum(k in set(plot_keys) for k in book_keys)
    by_number = ([_number(s) for s in ids], [_number(s) for s in plot_ids])
    if joined < len(ids) and all(by_number[0]) and all(by_number[1]) and len(set(by_number[1])) == len(plot_ids):
        n_num = sum(k in set(by_number[1]) for k in by_number[0])
        if n_num > joined:
            book_keys, plot_keys, how = by_number[0], by_number[1], "by their numbers"
            log.warning(
                "field book %s: plot ids matched to the plots' ids by their numbers (e.g. '%s' -> plot "
                "%s; did you mean the plots' ids?): %d of %d rows join",
                path.name,
                ids[0],
                plot_ids[by_number[1].index(by_number[0][0])] if by_number[0][0] in by_number[1] else "?",
                n_num,
                len(ids),
            )
            joined = n_num
    dup = pd.Series(book_keys)[pd.Series(book_keys).duplicated()].unique().tolist()
    if dup:
        raise InputError(
            f"plot ids repeat in the field book ({how}, e.g. {dup[:5]})", path=path, fix="one row per plot"
        )
    if joined == 0:
        raise InputError(
            f"none of the {len(ids)} field-book rows joins a plot: its plot ids (column '{col}', e.g. "
            f"{ids[:3]}) are not the plots' ids (e.g. {plot_ids[:3]})",
            path=path,
            fix="make the field book's plot id column hold the plots' ids (a grid numbers them 1..N; "
            "see plots.csv), or set plots.field_book_id_column",
        )
    unjoined = [s for s, k in zip(ids, book_keys) if k not in set(plot_keys)]
    if unjoined:
        log.warning(
            "field book %s: %d of %d rows join no plot (ids e.g. %s; %s)",
            path.name,
            len(unjoined),
            len(ids),
            unjoined[:5],
            did_you_mean(unjoined[0], plot_ids) or "not near any plot id",
        )
    without = len(set(plot_keys) - set(book_keys))
    if without:
        log.warning("%d of %d plots have no row in the field book %s", without, len(plot_keys), path.name)
    book = book.drop(columns=col)
    for c in book.columns:  # numbers back to numbers (rep, block) where the whole column is numeric
        num = pd.to_numeric(book[c].replace("", None), errors="coerce")
        if num.notna().sum() == (book[c] != "").sum():
            book[c] = num
    book["_key"] = book_keys
    out = table.assign(_key=plot_keys).merge(book, on="_key", how="left", suffixes=("", "_book"))
    return out.drop(columns="_key")
