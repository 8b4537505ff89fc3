"""Raw tables and their cells: CSV and Parquet parsing, missing values, numbers, ids, and
the one-line errors that name the file, the line (CSV) or row (Parquet) and the column.

Files are CSV (UTF-8, comma-separated, ``.csv``) or Parquet (``.parquet``), chosen by the
extension (case-insensitive).  Surrounding blanks of names and text values are ignored; in
CSV files blank lines (and rows of empty cells) are skipped, and an empty cell or one of
``nan``, ``NA``, ``N/A``, ``null``, ``none`` (any case) is a missing value (Parquet: null,
NaN, or those strings).  CSV extra columns become floats when all their cells are numbers.

For CSV, ``line N`` is the physical line of the file as a text editor shows it, the header
being line 1 (so the first data row is line 2).  Parquet files have no lines: ``row N``
counts data rows from 1, and ``schema`` stands for the header.  When a file has several
problems, the first in file order (then in column order) of the earliest check stage is
reported.
"""

from __future__ import annotations

import csv
import io
import itertools
import logging
import math
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import pandas as pd

log = logging.getLogger(__name__)

_NA_TOKENS = frozenset({"", "nan", "na", "n/a", "null", "none"})
# Every capitalisation of the tokens: a hashed isin() is far faster than lower() per cell.
_NA_CELLS = sorted({"".join(c) for t in _NA_TOKENS
                    for c in itertools.product(*[(ch.lower(), ch.upper()) for ch in t])})
_SUFFIXES = {".csv": "csv", ".parquet": "parquet"}


class RecordingsError(ValueError):
    """A specimens or recordings table is unusable; the message is one line naming the file,
    the line (CSV) or row (Parquet) and the column."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).splitlines()))


# ------------------------------------------------------------------------------ raw tables
class Raw:
    """A table as read, before validation: cells as text (CSV) or Parquet's own types, the
    place of each row for messages, and a collector that keeps the first error."""

    def __init__(self, path: str, kind: str, df: pd.DataFrame, lines: np.ndarray | None,
                 header_line: int = 1):
        self.path = path
        self.kind = kind
        self.df = df
        self.lines = lines  # CSV: physical line of each row; None for Parquet
        self.header_line = header_line
        self._first: tuple | None = None

    # -- places
    def row(self, pos: int) -> str:
        return f"line {self.lines[pos]}" if self.kind == "csv" else f"row {pos + 1}"

    def where(self, pos: int | None, column: str | None) -> str:
        if pos is None:
            place = f"line {self.header_line}" if self.kind == "csv" else "schema"
        else:
            place = self.row(pos)
        return f"{self.path} {place}" + (f", column {column}" if column is not None else "")

    def error(self, pos: int | None, column: str | None, what: str) -> RecordingsError:
        return RecordingsError(f"{self.where(pos, column)}: {what}")

    # -- first-error collection (one stage at a time)
    def add(self, pos: int | None, column: str, what: str) -> None:
        cols = list(self.df.columns)
        key = (-1 if pos is None else pos, cols.index(column) if column in cols else len(cols))
        if self._first is None or key < self._first[0]:
            self._first = (key, pos, column, what)

    def add_first(self, mask, column: str, what) -> None:
        """Record the first row where ``mask`` holds; ``what(pos)`` builds the message."""
        hits = np.flatnonzero(np.asarray(mask, dtype=bool))
        if hits.size:
            pos = int(hits[0])
            self.add(pos, column, what(pos))

    def raise_first(self) -> None:
        if self._first is not None:
            _, pos, column, what = self._first
            self._first = None
            raise self.error(pos, column, what)

    # -- cells
    def raw(self, pos: int, column: str) -> str:
        """A cell as the user wrote it, for messages."""
        v = self.df[column].iloc[pos]
        if isinstance(v, str):
            try:
                float(v)
                return _short(v)
            except ValueError:
                return repr(_short(v))
        if isinstance(v, float | np.floating):
            return repr(float(v))
        return _short(repr(v) if not isinstance(v, int | np.integer) else str(v))


def _short(s: str, n: int = 40) -> str:
    return s if len(s) <= n else s[: n - 3] + "..."


def kind_of(path: str) -> str:
    kind = _SUFFIXES.get(Path(path).suffix.lower())
    if kind is None:
        raise RecordingsError(f"{path}: unsupported file type {Path(path).suffix or '(none)'!r}; "
                              "expected a .csv or .parquet file")
    return kind


def read_raw(path) -> Raw:
    path = os.fspath(path)
    kind = kind_of(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except FileNotFoundError:
        raise RecordingsError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise RecordingsError(f"{path}: is a directory, not a file") from None
    except OSError as e:
        raise RecordingsError(f"{path}: cannot read ({e.strerror or e})") from None
    if not data.strip():
        raise RecordingsError(f"{path}: file is empty")
    raw = _parse_csv(path, data) if kind == "csv" else _parse_parquet(path, data)
    if raw.df.shape[0] == 0:
        raise raw.error(None, None, "no data rows (only a header)")
    log.debug("read %d rows x %d columns from %s", *raw.df.shape, path)
    return raw


def _parse_csv(path: str, data: bytes) -> Raw:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise RecordingsError(f"{path} line {line}: not UTF-8 text (byte 0x{data[e.start]:02x}); "
                              "save the file as UTF-8 CSV") from None
    # skipinitialspace: hand-written files put a blank before quoted fields ("a, "b, c"").
    reader = csv.reader(io.StringIO(text, newline=""), skipinitialspace=True)
    header: list[str] | None = None
    header_line = 1
    rows: list[list[str]] = []
    lines: list[int] = []
    last = 0
    try:
        for rec in reader:
            start, last = last + 1, reader.line_num
            multiline = any("\n" in c or "\r" in c for c in rec)
            rec = [c.strip() for c in rec]
            if not any(rec):
                continue  # blank line, or a spreadsheet's row of empty cells
            if header is None:
                header, header_line = rec, start
                sep = next((c for c in ";\t" if len(rec) == 1 and c in rec[0]), None)
                if sep is not None:
                    raise RecordingsError(
                        f"{path} line {start}: the columns must be separated by commas, not "
                        f"{sep!r} (header {_short(rec[0], 60)!r})")
                continue
            if len(rec) != len(header):
                n, m = len(rec), len(header)
                if n > m:
                    raise RecordingsError(
                        f"{path} line {start}: {n} fields but the header has {m} columns "
                        "(a stray comma, or a decimal comma instead of a point?)")
                why = "an unclosed quote?" if multiline else "truncated line?"
                raise RecordingsError(
                    f"{path} line {start}, column {header[n]}: missing field (the line has {n} "
                    f"fields, the header {m}; {why})")
            rows.append(rec)
            lines.append(start)
    except csv.Error as e:
        raise RecordingsError(f"{path} line {reader.line_num}: not valid CSV ({e})") from None
    if header is None:
        raise RecordingsError(f"{path}: file is empty")
    _check_header(path, header, header_line)
    df = pd.DataFrame(rows, columns=header, dtype=object) if rows else pd.DataFrame(
        columns=header, dtype=object)
    raw = Raw(path, "csv", df, np.asarray(lines, dtype=np.int64), header_line)
    # Spreadsheets often export trailing separators: drop nameless columns that are empty.
    for j in [j for j, name in enumerate(header) if name == ""]:
        col = df.iloc[:, j]
        if (col != "").any():
            pos = int(np.flatnonzero((col != "").to_numpy())[0])
            raise RecordingsError(f"{raw.where(pos, None)}, column {j + 1}: the column has no "
                                  "name in the header but holds values")
    keep = [name != "" for name in header]
    if not all(keep):
        raw.df = df.loc[:, keep]
    return raw


def _check_header(path: str, header: list[str], line: int | None) -> None:
    seen: dict[str, int] = {}
    for j, name in enumerate(header):
        if name and name in seen:
            place = f"line {line}" if line is not None else "schema"
            raise RecordingsError(f"{path} {place}, column {name}: the column appears twice "
                                  f"(columns {seen[name] + 1} and {j + 1})")
        seen[name] = j


def _parse_parquet(path: str, data: bytes) -> Raw:
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(pa.BufferReader(data))
    except Exception as e:  # pyarrow raises several types for foreign or damaged files
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise RecordingsError(f"{path}: cannot read as Parquet ({_short(first, 120)})") from None
    names = [str(n).strip() for n in table.column_names]
    _check_header(path, names, None)
    columns = {}
    for name, col in zip(names, table.columns, strict=True):
        if pa.types.is_dictionary(col.type):
            col = col.cast(col.type.value_type)
        if pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
            col = pc.utf8_trim_whitespace(col)  # as in CSV: surrounding blanks do not count
        s = col.to_pandas()
        columns[name] = s if pd.api.types.is_numeric_dtype(s) and s.dtype != bool else s.astype(
            object)
    df = pd.DataFrame(columns, index=pd.RangeIndex(table.num_rows))
    return Raw(path, "parquet", df, None)


# ------------------------------------------------------------------------------ cells
def _is_text(s: pd.Series) -> bool:
    """Every non-null cell is a string (all CSV columns; Parquet string columns)."""
    if isinstance(s.dtype, pd.StringDtype):  # pandas >= 3 reads text as ``str``
        return True
    return s.dtype == object and pd.api.types.infer_dtype(s, skipna=True) in ("string", "empty")


def is_missing(s: pd.Series) -> np.ndarray:
    if pd.api.types.is_numeric_dtype(s) and s.dtype != bool:
        return s.isna().to_numpy()
    if _is_text(s):
        return (s.isna() | s.isin(_NA_CELLS)).to_numpy(dtype=bool)  # text cells are stripped
    return s.map(lambda v: v is None or v is pd.NA or (isinstance(v, float) and math.isnan(v))
                 or (isinstance(v, str) and v.strip().lower() in _NA_TOKENS)).to_numpy(dtype=bool)


def parse_numbers(raw: Raw, column: str, positive=False) -> tuple[np.ndarray, np.ndarray]:
    """``(values, missing)`` of a numeric column; non-numbers are reported and become NaN.
    ``positive`` (bool or row mask) only words the message."""
    s = raw.df[column]
    missing = is_missing(s)
    if pd.api.types.is_numeric_dtype(s) and s.dtype != bool:
        return s.to_numpy(dtype=float, na_value=np.nan), missing
    cells = s.to_numpy(dtype=object)
    if _is_text(s):
        strings = ~missing
    else:
        strings = ~missing & np.fromiter((isinstance(v, str) for v in cells), bool, len(cells))
    numeric = _parse_floats(cells, strings)
    others = ~strings & ~missing  # booleans, bytes, ... in Parquet
    for pos in np.flatnonzero(others):
        v = cells[pos]
        if isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool):
            numeric[pos], others[pos] = float(v), False
    bad = (np.isnan(numeric) & strings) | others
    pos_mask = np.broadcast_to(np.asarray(positive, dtype=bool), missing.shape)
    raw.add_first(bad, column, lambda pos: _not_a_number(raw, pos, column, pos_mask[pos]))
    numeric[bad] = np.nan
    return numeric, missing


def _parse_floats(values: np.ndarray, strings: np.ndarray) -> np.ndarray:
    """Exact (round-trip) parsing of the text cells; NaN where a cell is no number.  Python's
    float syntax without digit separators ('1_0' is more likely a typo than ten)."""
    out = np.full(values.shape, np.nan)
    idx = np.flatnonzero(strings)
    cells = values[idx]
    try:
        if "_" not in "".join(cells):
            out[idx] = cells.astype(str).astype(float)
            return out
    except ValueError:
        pass
    for i, c in zip(idx, cells, strict=True):
        try:
            out[i] = np.nan if "_" in c else float(c)
        except ValueError:
            out[i] = np.nan
    return out


def _not_a_number(raw: Raw, pos: int, column: str, positive: bool) -> str:
    v = raw.df[column].iloc[pos]
    try:
        if isinstance(v, str) and not math.isfinite(float(v)):
            return f"expected a finite number, got {raw.raw(pos, column)}"
    except ValueError:
        pass
    hint = " (use a decimal point, not a comma)" if isinstance(v, str) and "," in v else ""
    kind = "a positive number" if positive else "a number"
    return f"expected {kind}, got {raw.raw(pos, column)}{hint}"


def float_column(raw: Raw, column: str, required, positive=False) -> np.ndarray:
    """Finite floats.  ``required`` and ``positive`` are bools or row masks: those rows must
    hold a value, resp. a value > 0.  Missing optional values are NaN."""
    values, missing = parse_numbers(raw, column, positive)
    req = np.broadcast_to(np.asarray(required, dtype=bool), missing.shape)
    pos_mask = np.broadcast_to(np.asarray(positive, dtype=bool), missing.shape)
    raw.add_first(missing & req, column, lambda pos: "missing value (required"
                  + (")" if isinstance(required, bool) else f" for {_test_of(raw, pos)} rows)"))
    parsed = ~missing & ~np.isnan(values)
    raw.add_first(parsed & ~np.isfinite(values), column,
                  lambda pos: f"expected a finite number, got {raw.raw(pos, column)}")
    with np.errstate(invalid="ignore"):
        raw.add_first(pos_mask & parsed & np.isfinite(values) & (values <= 0), column,
                      lambda pos: f"expected a positive number, got {raw.raw(pos, column)}")
    values = values.copy()
    values[~np.isfinite(values)] = np.nan
    return values


def _test_of(raw: Raw, pos: int) -> str:
    return str(raw.df["test"].iloc[pos]).strip() if "test" in raw.df.columns else "these"


def id_column(raw: Raw, column: str) -> pd.Series:
    """Ids as text: integers (also integral floats, as Parquet stores ints with gaps) without
    a decimal part; surrounding blanks removed; an empty id is an error."""
    s = raw.df[column]
    missing = is_missing(s)
    raw.add_first(missing, column, lambda pos: "missing value (required)")
    return text_column(s, missing, id_text)


def text_column(s: pd.Series, missing: np.ndarray, convert=lambda v: str(v).strip()) -> pd.Series:
    """Cells as stripped text, None where missing."""
    if _is_text(s):
        return s.where(~missing, None).astype(object)  # text cells are stripped
    return pd.Series([None if m else convert(v) for v, m in zip(s, missing, strict=True)],
                     index=s.index, dtype=object)


def id_text(v) -> str:
    if isinstance(v, bool | np.bool_):
        return str(v)
    if isinstance(v, float | np.floating) and float(v).is_integer():
        return str(int(v))
    return str(v).strip()


def choice_column(raw: Raw, column: str, allowed: tuple[str, ...], noun: str) -> pd.Series:
    s = raw.df[column]
    missing = is_missing(s)
    text = text_column(s, missing)
    ok = text.isin(allowed).to_numpy()
    expected = " or ".join(allowed)
    raw.add_first(missing, column, lambda pos: f"missing value (expected {expected})")
    raw.add_first(~missing & ~ok, column, lambda pos: f"unknown {noun} "
                  f"{text.iloc[pos]!r}; expected {expected}")
    return text


def require_columns(raw: Raw, columns: Iterable[str], why: str = "") -> None:
    have = list(raw.df.columns)
    for c in columns:
        if c not in have:
            cols = ", ".join(have) or "none"
            raise raw.error(None, c, f"missing required column{why}; the columns are: "
                            f"{_short(cols, 400)}")


def output_table(raw: Raw, converted: dict[str, object],
                 canonical: tuple[str, ...]) -> pd.DataFrame:
    """Canonical columns in canonical order, then the extra columns in file order (CSV extras
    that are all numbers or missing become floats)."""
    out = {c: converted[c] for c in canonical}
    for c in raw.df.columns:
        if c in out:
            continue
        s = raw.df[c]
        if raw.kind == "csv":
            missing = is_missing(s)
            num = _parse_floats(s.to_numpy(dtype=object), ~missing)
            if not (np.isnan(num) & ~missing).any():
                s = pd.Series(num, index=s.index)
            else:
                s = s.where(~missing, None)
        out[c] = s
    df = pd.DataFrame({c: (v.to_numpy() if isinstance(v, pd.Series) else v)
                       for c, v in out.items()}, index=pd.RangeIndex(raw.df.shape[0]))
    df.attrs["source"] = raw.path
    return df
