"""Reader for the region-averaged human brain curves of Budday et al. (2017).

The data live outside the project (``../shared/data/budday2017/budday2017_averaged.csv``,
validation only, never copied into the repository); code using them must skip cleanly when
:func:`available` is False.

File columns: ``region`` (CX | CR | BG | CC), ``test`` (tension | compression |
simple_shear), ``strain_measure`` (stretch | shear), ``value`` (stretch [-] or amount of
shear [-]), ``nominal_stress_kPa`` (P11 or P12 [kPa]).
"""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path

import pandas as pd

logger = logging.getLogger(__name__)

DATA_PATH = (Path(__file__).resolve().parents[1].parent
             / "shared/data/budday2017/budday2017_averaged.csv")

REGIONS = ("CX", "CR", "BG", "CC")
TESTS = {"tension": "stretch", "compression": "stretch", "simple_shear": "shear"}
COLUMNS = ("region", "test", "strain_measure", "value", "nominal_stress_kPa")
OBS_COLUMNS = ("specimen", "curve", "channel", "branch", "cycle", "control", "time_s", "value")


def available(path: str | Path = DATA_PATH) -> bool:
    """True when the Budday et al. data file exists."""
    return Path(path).is_file()


def _number(text: str, path: Path, row: int, column: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise ValueError(f"{path}: row {row}, column {column}: not a number: {text!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{path}: row {row}, column {column}: not finite: {text!r}")
    return x


def read_budday(path: str | Path = DATA_PATH) -> pd.DataFrame:
    """Read and validate the averaged curves as an observation table.

    Returns one row per data point, in file order, with columns ``specimen`` (region),
    ``curve`` (the ``test``), ``channel`` = "stress", ``branch`` = "loading", ``cycle`` = 1,
    ``control`` (stretch or amount of shear [-]), ``time_s`` = NaN and ``value``
    (nominal stress [kPa]).

    Raises:
        ValueError: one line naming the file, the row (spreadsheet numbering: the header is
            row 1) and the column, for a missing file, missing columns, a wrong number of
            fields, non-numeric or non-finite numbers, unknown regions or tests, a
            strain measure that does not match the test, or a non-positive stretch.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    records: list[tuple] = []
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        header = [h.strip() for h in next(reader, [])]
        for column in COLUMNS:
            if column not in header:
                raise ValueError(f"{path}: row 1, column {column}: missing column "
                                 f"(header {header})")
        where = {c: header.index(c) for c in COLUMNS}
        for row, fields in enumerate(reader, start=2):
            if not any(f.strip() for f in fields):
                continue
            if len(fields) != len(header):
                raise ValueError(f"{path}: row {row}, column -: {len(fields)} fields, "
                                 f"expected {len(header)}")
            get = {c: fields[i].strip() for c, i in where.items()}
            if get["region"] not in REGIONS:
                raise ValueError(f"{path}: row {row}, column region: unknown region "
                                 f"{get['region']!r} (expected one of {REGIONS})")
            test = get["test"]
            if test not in TESTS:
                raise ValueError(f"{path}: row {row}, column test: unknown test {test!r} "
                                 f"(expected one of {tuple(TESTS)})")
            if get["strain_measure"] != TESTS[test]:
                raise ValueError(f"{path}: row {row}, column strain_measure: "
                                 f"{get['strain_measure']!r} does not match test {test!r} "
                                 f"(expected {TESTS[test]!r})")
            control = _number(get["value"], path, row, "value")
            if TESTS[test] == "stretch" and control <= 0.0:
                raise ValueError(f"{path}: row {row}, column value: stretch must be positive, "
                                 f"got {control}")
            stress = _number(get["nominal_stress_kPa"], path, row, "nominal_stress_kPa")
            records.append((get["region"], test, "stress", "loading", 1, control,
                            float("nan"), stress))
    if not records:
        raise ValueError(f"{path}: row 2, column -: no data rows")
    obs = pd.DataFrame.from_records(records, columns=list(OBS_COLUMNS))
    logger.debug("read %d points (%d curves) from %s", len(obs),
                 obs.groupby(["specimen", "curve"]).ngroups, path)
    return obs
