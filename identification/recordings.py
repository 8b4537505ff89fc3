"""Reading and validating the two tidy input tables of the identification (DESIGN.md §6).

**Specimens table** (one row per specimen)::

    specimen   str    unique id
    region     str    brain region (e.g. ``cortex``)
    brain      str    id of the donor brain (integers are accepted and turned into text)
    radius_mm  float  undeformed radius R [mm], > 0
    height_mm  float  undeformed height H [mm], > 0
    ...               any further columns (``notes``, composition, ...) are kept

**Recordings table** (one row per sample point)::

    specimen            str    specimen id (or a region name for region-averaged curves)
    test                str    ``compression_tension`` or ``torsion``
    amplitude           float  stretch amplitude A in (0, 1) (protocol 1 -> 1-A -> 1 -> 1+A -> 1)
                               or maximum amount of shear at the outer radius (> 0)
    cycle               int    >= 1
    branch              str    ``loading`` or ``unloading``
    time_s              float  time [s], finite, non-decreasing within a series
    stretch             float  lambda = h / H [-], compression_tension rows: required, > 0
    shear               float  gamma = theta R / H [-] at the outer radius, torsion: required
    nominal_stress_kPa  float  F / (pi R^2) [kPa], compression_tension rows: required
    torque_mNmm         float  torque on the top plate [mN mm], torsion rows: required
    axial_force_mN      float  axial force [mN], optional (empty / NaN allowed)
    ...                        any further columns (e.g. ``shear_stress_kPa``) are kept

A column that does not apply to a row's test may be empty; if it holds a value, that value
must still be a finite number.  A *series* (one curve) is all rows with the same
``(specimen, test, amplitude)``, in file order; :func:`series` names it by the test key of
``brain_fe.sampling.TestSpec.name`` (``compression_tension``, ``compression_tension_0.10``,
``torsion_0.15``, ``torsion_0.30``).

Files are CSV (UTF-8, comma-separated, ``.csv``) or Parquet (``.parquet``), chosen by the
extension (case-insensitive).  Surrounding blanks of names and text values are ignored; in
CSV files blank lines (and rows of empty cells) are skipped, and an empty cell or one of
``nan``, ``NA``, ``N/A``, ``null``, ``none`` (any case) is a missing value (Parquet: null,
NaN, or those strings).  CSV extra columns become floats when all their cells are numbers.

**Errors.** Every problem raises :class:`RecordingsError` (a ``ValueError``) with one line
that names the file, the place and the column, e.g.::

    recordings.csv line 17, column stretch: expected a positive number, got 'abc'

For CSV, ``line N`` is the physical line of the file as a text editor shows it, the header
being line 1 (so the first data row is line 2).  Parquet files have no lines: ``row N``
counts data rows from 1, and ``schema`` stands for the header.  When a file has several
problems, the first in file order (then in column order) of the earliest check stage is
reported: file, columns, cell values, then table-wide checks (duplicate ids, unknown
specimens, time order, series size, amplitude bounds).  Nothing is ever written by the
readers; callers validate every input before producing any output.
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

from brain_fe.sampling import TestSpec

log = logging.getLogger(__name__)

SPECIMEN_COLUMNS = ("specimen", "region", "brain", "radius_mm", "height_mm")
RECORDING_COLUMNS = ("specimen", "test", "amplitude", "cycle", "branch", "time_s", "stretch",
                     "shear", "nominal_stress_kPa", "torque_mNmm", "axial_force_mN")
TESTS = ("compression_tension", "torsion")
BRANCHES = ("loading", "unloading")
# Columns required for every row, and those required only by rows of one test.
_ALWAYS = ("specimen", "test", "amplitude", "cycle", "branch", "time_s")
_BY_TEST = {"compression_tension": ("stretch", "nominal_stress_kPa"),
            "torsion": ("shear", "torque_mNmm")}
_FLOAT_RECORDING = ("time_s", "stretch", "shear", "nominal_stress_kPa", "torque_mNmm",
                    "axial_force_mN")
# The controlled value may exceed the series amplitude by this fraction of the amplitude
# (round-off of a written file), not more.
AMPLITUDE_RTOL = 1e-6
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
class _Raw:
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


def _kind(path: str) -> str:
    kind = _SUFFIXES.get(Path(path).suffix.lower())
    if kind is None:
        raise RecordingsError(f"{path}: unsupported file type {Path(path).suffix or '(none)'!r}; "
                              "expected a .csv or .parquet file")
    return kind


def _read_raw(path) -> _Raw:
    path = os.fspath(path)
    kind = _kind(path)
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


def _parse_csv(path: str, data: bytes) -> _Raw:
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
    raw = _Raw(path, "csv", df, np.asarray(lines, dtype=np.int64), header_line)
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


def _parse_parquet(path: str, data: bytes) -> _Raw:
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
    return _Raw(path, "parquet", df, None)


# ------------------------------------------------------------------------------ cells
def _is_text(s: pd.Series) -> bool:
    """Every non-null cell is a string (all CSV columns; Parquet string columns)."""
    return s.dtype == object and pd.api.types.infer_dtype(s, skipna=True) in ("string", "empty")


def _missing(s: pd.Series) -> np.ndarray:
    if pd.api.types.is_numeric_dtype(s) and s.dtype != bool:
        return s.isna().to_numpy()
    if _is_text(s):
        return (s.isna() | s.isin(_NA_CELLS)).to_numpy(dtype=bool)  # text cells are stripped
    return s.map(lambda v: v is None or v is pd.NA or (isinstance(v, float) and math.isnan(v))
                 or (isinstance(v, str) and v.strip().lower() in _NA_TOKENS)).to_numpy(dtype=bool)


def _numbers(raw: _Raw, column: str, positive=False) -> tuple[np.ndarray, np.ndarray]:
    """``(values, missing)`` of a numeric column; non-numbers are reported and become NaN.
    ``positive`` (bool or row mask) only words the message."""
    s = raw.df[column]
    missing = _missing(s)
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


def _not_a_number(raw: _Raw, pos: int, column: str, positive: bool) -> str:
    v = raw.df[column].iloc[pos]
    try:
        if isinstance(v, str) and not math.isfinite(float(v)):
            return f"expected a finite number, got {raw.raw(pos, column)}"
    except ValueError:
        pass
    hint = " (use a decimal point, not a comma)" if isinstance(v, str) and "," in v else ""
    kind = "a positive number" if positive else "a number"
    return f"expected {kind}, got {raw.raw(pos, column)}{hint}"


def _float_column(raw: _Raw, column: str, required, positive=False) -> np.ndarray:
    """Finite floats.  ``required`` and ``positive`` are bools or row masks: those rows must
    hold a value, resp. a value > 0.  Missing optional values are NaN."""
    values, missing = _numbers(raw, column, positive)
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


def _test_of(raw: _Raw, pos: int) -> str:
    return str(raw.df["test"].iloc[pos]).strip() if "test" in raw.df.columns else "these"


def _ids(raw: _Raw, column: str) -> pd.Series:
    """Ids as text: integers (also integral floats, as Parquet stores ints with gaps) without
    a decimal part; surrounding blanks removed; an empty id is an error."""
    s = raw.df[column]
    missing = _missing(s)
    raw.add_first(missing, column, lambda pos: "missing value (required)")
    return _text(s, missing, _id_text)


def _text(s: pd.Series, missing: np.ndarray, convert=lambda v: str(v).strip()) -> pd.Series:
    """Cells as stripped text, None where missing."""
    if _is_text(s):
        return s.where(~missing, None).astype(object)  # text cells are stripped
    return pd.Series([None if m else convert(v) for v, m in zip(s, missing, strict=True)],
                     index=s.index, dtype=object)


def _id_text(v) -> str:
    if isinstance(v, bool | np.bool_):
        return str(v)
    if isinstance(v, float | np.floating) and float(v).is_integer():
        return str(int(v))
    return str(v).strip()


def _choice(raw: _Raw, column: str, allowed: tuple[str, ...], noun: str) -> pd.Series:
    s = raw.df[column]
    missing = _missing(s)
    text = _text(s, missing)
    ok = text.isin(allowed).to_numpy()
    expected = " or ".join(allowed)
    raw.add_first(missing, column, lambda pos: f"missing value (expected {expected})")
    raw.add_first(~missing & ~ok, column, lambda pos: f"unknown {noun} "
                  f"{text.iloc[pos]!r}; expected {expected}")
    return text


def _require_columns(raw: _Raw, columns: Iterable[str], why: str = "") -> None:
    have = list(raw.df.columns)
    for c in columns:
        if c not in have:
            cols = ", ".join(have) or "none"
            raise raw.error(None, c, f"missing required column{why}; the columns are: "
                            f"{_short(cols, 400)}")


def _output(raw: _Raw, converted: dict[str, object], canonical: tuple[str, ...]) -> pd.DataFrame:
    """Canonical columns in canonical order, then the extra columns in file order (CSV extras
    that are all numbers or missing become floats)."""
    out = {c: converted[c] for c in canonical}
    for c in raw.df.columns:
        if c in out:
            continue
        s = raw.df[c]
        if raw.kind == "csv":
            missing = _missing(s)
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


# ------------------------------------------------------------------------------ specimens
def read_specimens(path) -> pd.DataFrame:
    """Read and validate a specimens table (CSV or Parquet, see the module docstring).

    Returns a DataFrame in file order with columns ``specimen``, ``region``, ``brain`` (text),
    ``radius_mm``, ``height_mm`` (float, mm, > 0), then any extra columns.  Raises
    :class:`RecordingsError` with a one-line message on any problem.
    """
    raw = _read_raw(path)
    _require_columns(raw, SPECIMEN_COLUMNS)
    conv: dict[str, object] = {}
    conv["specimen"] = _ids(raw, "specimen")
    conv["region"] = _ids(raw, "region")
    conv["brain"] = _ids(raw, "brain")
    conv["radius_mm"] = _float_column(raw, "radius_mm", True, positive=True)
    conv["height_mm"] = _float_column(raw, "height_mm", True, positive=True)
    raw.raise_first()
    ids = conv["specimen"]
    dup = ids.duplicated().to_numpy()
    first = {}
    for pos, v in enumerate(ids):
        first.setdefault(v, pos)
    raw.add_first(dup, "specimen", lambda pos: f"duplicate specimen id {ids.iloc[pos]!r} "
                  f"(first on {raw.row(first[ids.iloc[pos]])})")
    raw.raise_first()
    df = _output(raw, conv, SPECIMEN_COLUMNS)
    log.debug("%s: %d specimens in %d regions", raw.path, len(df), df["region"].nunique())
    return df


# ------------------------------------------------------------------------------ recordings
def key_for_test(test: str, amplitude: float) -> str:
    """Name of a test protocol, as ``brain_fe.sampling.TestSpec.name``: ``compression_tension``
    (amplitude 0.15), ``compression_tension_0.10``, ``torsion_0.15``, ``torsion_0.30``."""
    return TestSpec(test, float(amplitude)).name


def read_recordings(path, specimens: pd.DataFrame | None = None,
                    require_specimens: bool = True) -> pd.DataFrame:
    """Read and validate a recordings table (CSV or Parquet, see the module docstring).

    Parameters
    ----------
    path: the ``.csv`` or ``.parquet`` file.
    specimens: the specimens table (:func:`read_specimens`); every ``specimen`` of the
        recordings must be one of its ids unless ``require_specimens`` is False.
    require_specimens: False accepts ids absent from ``specimens`` (region-averaged curves
        whose ``specimen`` column holds a region name); ``specimens`` may then be None.
        With the default True, ``specimens`` must be given (a ``TypeError`` otherwise: that
        is a programming error, not bad input).

    Checks, besides types, missing values and value sets: amplitude > 0 (and < 1 for
    compression_tension, where it is a stretch amplitude), stretch > 0; ``time_s``
    non-decreasing in file order within each series ``(specimen, test, amplitude)``; at
    least 2 points per series; and the controlled value within the series amplitude:
    ``1 - A <= stretch <= 1 + A`` (compression_tension) or ``|shear| <= A`` (torsion, either
    sense of twist), with a tolerance of ``AMPLITUDE_RTOL * A`` (1e-6 relative, for the
    round-off of written numbers).  The amplitude is the protocol's largest excursion from
    the neutral value (``brain_fe.protocols.Protocol.amplitude``), and the surrogates and the
    FE model are built for that protocol, so a recorded value beyond it (typically a wrong
    amplitude, a percentage instead of a fraction, or a mixed-up series) would silently be
    extrapolated: it is an error.  Measured control values that overshoot the nominal
    amplitude must be clipped, or the amplitude set to their maximum, before identification.
    A series that stays below 90 % of its amplitude is accepted with a logged warning (a
    truncated recording, or an amplitude given in the wrong unit).

    Returns a DataFrame in file order: the columns of ``RECORDING_COLUMNS`` (absent optional
    columns filled with NaN) with ``specimen``, ``test``, ``branch`` as text, ``cycle`` as
    int64, the others float64 (stretch, shear [-]; time s; kPa; mN mm; mN), then any extra
    columns.  Raises :class:`RecordingsError` with a one-line message on bad input.
    """
    if require_specimens and specimens is None:
        raise TypeError("read_recordings needs the specimens table, or require_specimens=False")
    if specimens is not None:
        if not isinstance(specimens, pd.DataFrame) or "specimen" not in specimens.columns:
            raise TypeError("specimens must be a DataFrame with a 'specimen' column "
                            "(see read_specimens)")
    raw = _read_raw(path)
    _require_columns(raw, _ALWAYS)
    test_text = raw.df["test"].map(lambda v: str(v).strip())
    for test, cols in _BY_TEST.items():
        rows = np.flatnonzero((test_text == test).to_numpy())
        if rows.size:
            _require_columns(raw, cols, f" for {test} rows (first on {raw.row(int(rows[0]))})")

    conv: dict[str, object] = {}
    conv["specimen"] = _ids(raw, "specimen")
    test = _choice(raw, "test", TESTS, "test")
    conv["test"] = test
    is_ct = (test == "compression_tension").to_numpy()
    is_to = (test == "torsion").to_numpy()
    amp = _float_column(raw, "amplitude", True, positive=True)
    raw.add_first(is_ct & (amp >= 1), "amplitude", lambda pos: "a compression_tension "
                  f"amplitude must lie in (0, 1), got {raw.raw(pos, 'amplitude')} (it is a "
                  "fraction: 0.15 for 15 %)")
    conv["amplitude"] = amp
    cycle, _ = _numbers(raw, "cycle")
    raw.add_first(_missing(raw.df["cycle"]), "cycle",
                  lambda pos: "missing value (required)")
    with np.errstate(invalid="ignore"):
        bad_cycle = ~np.isnan(cycle) & ~((cycle >= 1) & (np.mod(cycle, 1) == 0)
                                         & (cycle < 2**53))
    raw.add_first(bad_cycle, "cycle",
                  lambda pos: f"expected a whole number >= 1, got {raw.raw(pos, 'cycle')}")
    conv["branch"] = _choice(raw, "branch", BRANCHES, "branch")
    needs = {"time_s": True, "stretch": is_ct, "shear": is_to, "nominal_stress_kPa": is_ct,
             "torque_mNmm": is_to, "axial_force_mN": False}
    for c in _FLOAT_RECORDING:
        if c in raw.df.columns:
            conv[c] = _float_column(raw, c, needs[c], positive=is_ct if c == "stretch" else False)
        else:
            conv[c] = np.full(raw.df.shape[0], np.nan)
    raw.raise_first()
    conv["cycle"] = cycle.astype(np.int64)

    df = _output(raw, conv, RECORDING_COLUMNS)
    _check_specimens(raw, df, specimens, require_specimens)
    _check_series(raw, df)
    raw.raise_first()
    log.debug("%s: %d rows, %d series, %d specimens", raw.path, len(df),
             df.groupby(["specimen", "test", "amplitude"], sort=False).ngroups,
             df["specimen"].nunique())
    return df


def _check_specimens(raw: _Raw, df: pd.DataFrame, specimens, require: bool) -> None:
    if specimens is None:
        return
    known = {_id_text(v) for v in specimens["specimen"]}
    unknown = ~df["specimen"].isin(known).to_numpy()
    if not unknown.any():
        return
    regions = ({_id_text(v) for v in specimens["region"]} if "region" in specimens.columns
               else set())
    source = specimens.attrs.get("source", "the specimens table")
    if require:
        def what(pos):
            sid = df["specimen"].iloc[pos]
            hint = (f"; {sid!r} is a region: region-averaged curves need "
                    "require_specimens=False") if sid in regions else ""
            return f"specimen {sid!r} is not in {source}{hint}"

        raw.add_first(unknown, "specimen", what)
    else:
        ids = sorted(set(df["specimen"][unknown]))
        log.info("%s: %d ids not in %s (region names: %s)", raw.path, len(ids), source,
                 ", ".join(i for i in ids if i in regions) or "none")


def _check_series(raw: _Raw, df: pd.DataFrame) -> None:
    keys = [df["specimen"], df["test"], df["amplitude"]]
    g = df.groupby(keys, sort=False)
    pos = pd.Series(np.arange(len(df)), index=df.index)

    def name(p):
        return (f"series ({df['specimen'].iloc[p]}, {df['test'].iloc[p]}, amplitude "
                f"{raw.raw(p, 'amplitude')})")

    # time order within each series, in file order
    back = (g["time_s"].diff() < 0).to_numpy()
    prev = pos.groupby(keys, sort=False).shift(1).to_numpy()
    raw.add_first(back, "time_s", lambda p: f"time goes backwards in {name(p)}: "
                  f"{raw.raw(p, 'time_s')} s after {raw.raw(int(prev[p]), 'time_s')} s on "
                  f"{raw.row(int(prev[p]))}")
    # at least two points
    size = g["time_s"].transform("size").to_numpy()
    raw.add_first(size < 2, "specimen", lambda p: f"{name(p)} has only 1 point; a curve needs "
                  "at least 2 (check the specimen id and the amplitude)")
    # controlled value within the amplitude
    amp = df["amplitude"].to_numpy()
    is_ct = (df["test"] == "compression_tension").to_numpy()
    tol = AMPLITUDE_RTOL * amp
    with np.errstate(invalid="ignore"):
        ct_out = is_ct & (np.abs(df["stretch"].to_numpy() - 1.0) > amp + tol)
        to_out = ~is_ct & (np.abs(df["shear"].to_numpy()) > amp + tol)
    raw.add_first(ct_out, "stretch", lambda p: f"stretch {raw.raw(p, 'stretch')} lies outside "
                  f"[{1 - amp[p]:.6g}, {1 + amp[p]:.6g}] = 1 -/+ the amplitude of its "
                  f"{name(p)}")
    raw.add_first(to_out, "shear", lambda p: f"|shear| = {abs(df['shear'].iloc[p]):.6g} exceeds "
                  f"the amplitude of its {name(p)}")
    # two amplitudes that give the same test key would be one curve for series()
    tkey = _test_keys(df)
    n_amp = df.groupby([df["specimen"], tkey], sort=False)["amplitude"].transform("nunique")
    first = pos.groupby([df["specimen"], tkey], sort=False).transform("first").to_numpy()
    clash = ((n_amp > 1).to_numpy() & (df["amplitude"].to_numpy()
                                       != df["amplitude"].to_numpy()[first]))
    raw.add_first(clash, "amplitude", lambda p: f"amplitude {raw.raw(p, 'amplitude')} here "
                  f"and {raw.raw(int(first[p]), 'amplitude')} on {raw.row(int(first[p]))} "
                  f"both give specimen {df['specimen'].iloc[p]!r} the test {tkey.iloc[p]}; "
                  "use one amplitude per curve")
    # warn about series far below their amplitude (no error: truncated recordings exist)
    if not (ct_out.any() or to_out.any()):
        dev = np.where(is_ct, np.abs(df["stretch"].to_numpy() - 1.0),
                       np.abs(df["shear"].to_numpy()))
        reach = pd.Series(dev, index=df.index).groupby(keys, sort=False).max()
        for (sid, test, a), r in reach.items():
            if r < 0.9 * a:
                log.warning("%s: series (%s, %s, amplitude %g) reaches only %.4g of its "
                            "amplitude (truncated recording, or a wrong amplitude?)",
                            raw.path, sid, test, a, r)


def _test_keys(df: pd.DataFrame) -> pd.Series:
    pairs = {(t, a): key_for_test(t, a) for t, a in
             df[["test", "amplitude"]].drop_duplicates().itertuples(index=False)}
    return pd.Series([pairs[(t, a)] for t, a in zip(df["test"], df["amplitude"], strict=True)],
                     index=df.index, dtype=object)


# ------------------------------------------------------------------------------ series
def series(recordings: pd.DataFrame) -> dict[tuple[str, str], pd.DataFrame]:
    """The curves of a recordings table: ``{(specimen, test key): rows}`` in order of first
    appearance, each DataFrame in file order with the original index (row position in the
    table).  Test keys follow ``TestSpec.name``: ``compression_tension`` (A = 0.15, else
    ``compression_tension_<A:.2f>``), ``torsion_<A:.2f>`` (``torsion_0.15``, ``torsion_0.30``).
    Raises ``ValueError`` if two amplitudes of one specimen share a key (read_recordings
    rejects such tables)."""
    if len(recordings) == 0:
        return {}
    keys = _test_keys(recordings)
    out: dict[tuple[str, str], pd.DataFrame] = {}
    for (sid, key), part in recordings.groupby([recordings["specimen"], keys], sort=False):
        a = part["amplitude"].unique()
        if len(a) > 1:
            raise ValueError(f"specimen {sid!r}: amplitudes {', '.join(f'{v:g}' for v in a)} "
                             f"all give the test {key}")
        out[(str(sid), str(key))] = part
    return out


# ------------------------------------------------------------------------------ writing
def write_table_atomic(df: pd.DataFrame, path) -> None:
    """Write ``df`` as CSV or Parquet atomically (see :func:`brain_fe.io.write_table_atomic`);
    an unknown extension or a missing directory is a :class:`RecordingsError`."""
    from brain_fe.io import write_table_atomic as _write

    path = os.fspath(path)
    _kind(path)
    try:
        _write(df, path)
    except FileNotFoundError as exc:
        raise RecordingsError(str(exc)) from None
    log.debug("wrote %d rows to %s", len(df), path)
