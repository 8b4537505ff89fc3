"""Reading, validating and writing the specimens and recordings tables (DESIGN.md §6).

The two tables (specimens: one row per specimen; recordings: one row per sample point) and
their columns are defined once, in :mod:`recordings.schema`; the cell parsing and the
one-line errors are in :mod:`recordings.cells`.

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

import logging
import os

import numpy as np
import pandas as pd

from brain_fe.io import write_table_atomic as _write_table
from brain_fe.vocabulary import (
    COMPRESSION_TENSION,
    NOMINAL_STRESS,
    SHEAR,
    STRETCH,
    TESTS,
    TIME,
    TORQUE,
    test_key,
)

from .cells import (
    Raw,
    RecordingsError,
    choice_column,
    float_column,
    id_column,
    id_text,
    is_missing,
    kind_of,
    output_table,
    parse_numbers,
    read_raw,
    require_columns,
)
from .schema import (
    ALWAYS,
    AMPLITUDE_RTOL,
    BY_TEST,
    FLOAT_COLUMNS,
    HEIGHT_RANGE_MM,
    MIN_RAMP_POINTS,
    MIN_SERIES_POINTS,
    RADIUS_RANGE_MM,
    RECORDED_BRANCHES,
    RECORDING_COLUMNS,
    SPECIMEN_COLUMNS,
    SPECIMEN_ENDS,
)

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ specimens
def read_specimens(path) -> pd.DataFrame:
    """Read and validate a specimens table (CSV or Parquet, see the module docstring).

    Returns a DataFrame in file order with columns ``specimen``, ``region``, ``brain`` (text),
    ``radius_mm``, ``height_mm`` (float, mm, > 0), then any extra columns (``ends``, when
    given, one of ``SPECIMEN_ENDS``).  Raises
    :class:`RecordingsError` with a one-line message on any problem.
    """
    raw = read_raw(path)
    require_columns(raw, SPECIMEN_COLUMNS)
    conv: dict[str, object] = {}
    conv["specimen"] = id_column(raw, "specimen")
    conv["region"] = id_column(raw, "region")
    conv["brain"] = id_column(raw, "brain")
    conv["radius_mm"] = float_column(raw, "radius_mm", True, positive=True)
    conv["height_mm"] = float_column(raw, "height_mm", True, positive=True)
    ends = (choice_column(raw, "ends", SPECIMEN_ENDS, "end condition")
            if "ends" in raw.df else None)
    raw.raise_first()
    for col, (lo, hi) in (("radius_mm", RADIUS_RANGE_MM), ("height_mm", HEIGHT_RANGE_MM)):
        v = conv[col]
        raw.add_first((v < lo) | (v > hi), col, lambda pos, v=v, col=col, lo=lo, hi=hi:
                      f"{v[pos]:g} mm is not a plausible specimen {col.split('_')[0]} "
                      f"(expected {lo:g}-{hi:g} mm; lengths are in mm)")
    raw.raise_first()
    ids = conv["specimen"]
    dup = ids.duplicated().to_numpy()
    first = {}
    for pos, v in enumerate(ids):
        first.setdefault(v, pos)
    raw.add_first(dup, "specimen", lambda pos: f"duplicate specimen id {ids.iloc[pos]!r} "
                  f"(first on {raw.row(first[ids.iloc[pos]])})")
    raw.raise_first()
    df = output_table(raw, conv, SPECIMEN_COLUMNS)
    if ends is not None:
        df["ends"] = ends.to_numpy(object)
    log.debug("%s: %d specimens in %d regions", raw.path, len(df), df["region"].nunique())
    return df


# ------------------------------------------------------------------------------ recordings
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
    raw = read_raw(path)
    require_columns(raw, ALWAYS)
    test_text = raw.df["test"].map(lambda v: str(v).strip())
    for test, cols in BY_TEST.items():
        rows = np.flatnonzero((test_text == test).to_numpy())
        if rows.size:
            require_columns(raw, cols, f" for {test} rows (first on {raw.row(int(rows[0]))})")

    conv: dict[str, object] = {}
    conv["specimen"] = id_column(raw, "specimen")
    test = choice_column(raw, "test", TESTS, "test")
    conv["test"] = test
    is_ct = (test == "compression_tension").to_numpy()
    is_to = (test == "torsion").to_numpy()
    amp = float_column(raw, "amplitude", True, positive=True)
    raw.add_first(is_ct & (amp >= 1), "amplitude", lambda pos: "a compression_tension "
                  f"amplitude must lie in (0, 1), got {raw.raw(pos, 'amplitude')} (it is a "
                  "fraction: 0.15 for 15 %)")
    conv["amplitude"] = amp
    cycle, _ = parse_numbers(raw, "cycle")
    raw.add_first(is_missing(raw.df["cycle"]), "cycle",
                  lambda pos: "missing value (required)")
    with np.errstate(invalid="ignore"):
        bad_cycle = ~np.isnan(cycle) & ~((cycle >= 1) & (np.mod(cycle, 1) == 0)
                                         & (cycle < 2**53))
    raw.add_first(bad_cycle, "cycle",
                  lambda pos: f"expected a whole number >= 1, got {raw.raw(pos, 'cycle')}")
    conv["branch"] = choice_column(raw, "branch", RECORDED_BRANCHES, "branch")
    needs = {"time_s": True, "stretch": is_ct, "shear": is_to, "nominal_stress_kPa": is_ct,
             "torque_mNmm": is_to, "axial_force_mN": False}
    for c in FLOAT_COLUMNS:
        if c in raw.df.columns:
            conv[c] = float_column(raw, c, needs[c], positive=is_ct if c == "stretch" else False)
        else:
            conv[c] = np.full(raw.df.shape[0], np.nan)
    raw.raise_first()
    conv["cycle"] = cycle.astype(np.int64)

    df = output_table(raw, conv, RECORDING_COLUMNS)
    _check_specimens(raw, df, specimens, require_specimens)
    _check_series(raw, df)
    raw.raise_first()
    _check_physics(raw, df)
    raw.raise_first()
    _warn_truncated(raw, df)
    log.debug("%s: %d rows, %d series, %d specimens", raw.path, len(df),
             df.groupby(["specimen", "test", "amplitude"], sort=False).ngroups,
             df["specimen"].nunique())
    return df


def _check_specimens(raw: Raw, df: pd.DataFrame, specimens, require: bool) -> None:
    if specimens is None:
        return
    known = {id_text(v) for v in specimens["specimen"]}
    unknown = ~df["specimen"].isin(known).to_numpy()
    if not unknown.any():
        return
    regions = ({id_text(v) for v in specimens["region"]} if "region" in specimens.columns
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


def _check_series(raw: Raw, df: pd.DataFrame) -> None:
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


def _warn_truncated(raw: Raw, df: pd.DataFrame) -> None:
    """Warn about series far below their amplitude (no error: truncated recordings exist)."""
    keys = [df["specimen"], df["test"], df["amplitude"]]
    is_ct = (df["test"] == COMPRESSION_TENSION).to_numpy()
    dev = np.where(is_ct, np.abs(df[STRETCH].to_numpy() - 1.0), np.abs(df[SHEAR].to_numpy()))
    reach = pd.Series(dev, index=df.index).groupby(keys, sort=False).max()
    for (sid, test, a), r in reach.items():
        if r < 0.9 * a:
            log.warning("%s: series (%s, %s, amplitude %g) reaches only %.4g of its "
                        "amplitude (truncated recording, or a wrong amplitude?)",
                        raw.path, sid, test, a, r)


def _check_physics(raw: Raw, df: pd.DataFrame) -> None:
    """Physically degenerate series: no motion, no load, a clock that stands still, too few
    points per ramp.  Such data cannot tell a model anything; refused with the first row of
    the series."""
    keys = [df["specimen"], df["test"], df["amplitude"]]
    is_ct = (df["test"] == COMPRESSION_TENSION).to_numpy()
    control = np.where(is_ct, df[STRETCH].to_numpy(float), df[SHEAR].to_numpy(float))
    load = np.where(is_ct, df[NOMINAL_STRESS].to_numpy(float), df[TORQUE].to_numpy(float))
    frame = pd.DataFrame({"control": control, "load": load, "time": df[TIME].to_numpy(float),
                          "ramp": _ramp_ids(df)}, index=df.index)
    g = frame.groupby(keys, sort=False)
    first = pd.Series(np.arange(len(df)), index=df.index).groupby(keys, sort=False) \
        .transform("first").to_numpy()
    is_first = first == np.arange(len(df))

    def name(p):
        return (f"series ({df['specimen'].iloc[p]}, {df['test'].iloc[p]}, amplitude "
                f"{raw.raw(p, 'amplitude')})")

    def spread(col):
        return (g[col].transform("max") - g[col].transform("min")).to_numpy()

    size = g["control"].transform("size").to_numpy()
    raw.add_first(is_first & (size < MIN_SERIES_POINTS), "specimen",
                  lambda p: f"{name(p)} has only {size[p]} points; at least {MIN_SERIES_POINTS} "
                  "are needed to fit a curve")
    still = is_first & (spread("control") <= 1e-9 * df["amplitude"].to_numpy())
    raw.add_first(still & is_ct, STRETCH, lambda p: f"{name(p)} never changes its stretch "
                  f"({control[p]:g} throughout): nothing was tested")
    raw.add_first(still & ~is_ct, SHEAR, lambda p: f"{name(p)} never changes its shear "
                  f"({control[p]:g} throughout): nothing was tested")
    flat = is_first & (spread("load") == 0)
    col = np.where(is_ct, NOMINAL_STRESS, TORQUE)
    for c in (NOMINAL_STRESS, TORQUE):
        raw.add_first(flat & (col == c), c, lambda p, c=c: f"{c} is {load[p]:g} throughout "
                      f"{name(p)}: no load was recorded")
    frozen = is_first & (spread("time") == 0)
    raw.add_first(frozen, TIME, lambda p: f"time does not advance in {name(p)} "
                  f"({df[TIME].iloc[p]:g} s throughout)")
    per_ramp = frame.groupby([*keys, frame["ramp"]], sort=False).size() \
        .groupby(level=[0, 1, 2], sort=False).median()
    sparse = pd.Series([per_ramp.loc[k] for k in zip(*keys, strict=True)],
                       index=df.index).to_numpy()
    for c, rows in ((STRETCH, is_ct), (SHEAR, ~is_ct)):
        raw.add_first(is_first & rows & (sparse < MIN_RAMP_POINTS), c,
                      lambda p: f"{name(p)} has {sparse[p]:g} points per ramp (median); at "
                      f"least {MIN_RAMP_POINTS} are needed to tell the shape of a curve from "
                      "its noise")


def _ramp_ids(df: pd.DataFrame) -> np.ndarray:
    """Per row, the number of its ramp: consecutive rows of one (cycle, branch) in file
    order (a change of cycle or branch starts a new ramp)."""
    bc = df["cycle"].astype(str) + "/" + df["branch"].astype(str)
    return (bc != bc.shift()).cumsum().to_numpy()


def _test_keys(df: pd.DataFrame) -> pd.Series:
    pairs = {(t, a): test_key(t, a) for t, a in
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
def write_table(df: pd.DataFrame, path) -> None:
    """Write ``df`` as CSV or Parquet atomically (:func:`brain_fe.io.write_table_atomic`);
    an unknown extension or a missing directory is a :class:`RecordingsError`."""
    path = os.fspath(path)
    kind_of(path)
    try:
        _write_table(df, path)
    except ValueError as exc:
        raise RecordingsError(str(exc)) from None
    log.debug("wrote %d rows to %s", len(df), path)
