"""Series of an observation table (:mod:`recordings.observations`) and their runs.

A *series* is one ``(specimen, curve, channel)``; its rows are in recording (time) order.
A *run* is consecutive rows of one series with equal (branch, cycle): a turning point of the
protocol starts a new run.  Shared by the noise estimate, the locating tests and the map.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from brain_fe.vocabulary import is_shear_curve

REQUIRED_COLUMNS = ("specimen", "curve", "channel", "branch", "cycle", "control", "value")
SERIES = ("specimen", "curve", "channel")


def neutral_of(curve: str) -> float:
    """Neutral control value: 0 for shear curves (``torsion*``, ``simple_shear*``), else 1."""
    return 0.0 if is_shear_curve(curve) else 1.0


def check(obs: pd.DataFrame, *arrays: tuple[str, np.ndarray | None]) -> None:
    missing = [c for c in REQUIRED_COLUMNS if c not in obs.columns]
    if missing:
        raise ValueError(f"observation table lacks column(s) {', '.join(missing)}")
    for name, a in arrays:
        if a is not None and len(a) != len(obs):
            raise ValueError(f"{name} has {len(a)} values, observation table has {len(obs)} rows")


def as_float(a, name: str, n: int) -> np.ndarray:
    out = np.asarray(a, dtype=float).reshape(-1)
    if out.size != n:
        raise ValueError(f"{name} has {out.size} values, observation table has {n} rows")
    return out


def series_ids(obs: pd.DataFrame, keys: Sequence[str] = SERIES) -> np.ndarray:
    """Integer id per row of the ``keys`` group, numbered by first appearance."""
    combined = np.zeros(len(obs), dtype=np.int64)
    for k in keys:
        codes, uniques = pd.factorize(obs[k], use_na_sentinel=False)
        combined = combined * max(len(uniques), 1) + codes
        combined = pd.factorize(combined)[0].astype(np.int64)  # keep the numbers small
    return combined


def run_ids(obs: pd.DataFrame) -> np.ndarray:
    """Id per row of its *run*: consecutive rows (recording order) of one series with equal
    (branch, cycle); a turning point of the protocol starts a new run."""
    n = len(obs)
    sid = series_ids(obs)
    bc = series_ids(obs, ("branch", "cycle"))
    run = np.zeros(n, dtype=np.int64)
    for _, pos in groups(obs):
        new = np.r_[True, bc[pos][1:] != bc[pos][:-1]]
        run[pos] = np.cumsum(new) - 1
    return series_ids(pd.DataFrame({"s": sid, "r": run}), ("s", "r")) if n else run


def groups(obs: pd.DataFrame, keys: Sequence[str] = SERIES) -> list[tuple[tuple, np.ndarray]]:
    """``[(key values, ascending row positions)]`` per group, in order of first appearance."""
    ids = series_ids(obs, keys)
    order = np.argsort(ids, kind="stable")
    bounds = np.flatnonzero(np.diff(ids[order])) + 1
    cols = [obs[k].to_numpy() for k in keys]
    return [(tuple(c[pos[0]] for c in cols), pos) for pos in np.split(order, bounds)
            if pos.size]
