"""Recordings as an *observation table*: one row per recorded value.

Columns ``specimen, curve, test, amplitude, channel, branch, cycle, control, time_s,
value``; ``curve`` is the test key (``compression_tension``, ``torsion_0.15``, ...) and
``channel`` a channel name of :data:`brain_fe.vocabulary.CHANNELS` (``stress`` nominal
stress [kPa], ``torque`` [mN mm], ``axial_force`` [mN]).  Rows of one (curve, channel) are
in recording order.  Simulators predict these rows; the diagnosis locates misfit on them.
Recordings with an ``in_contact`` column (imported rheometer compressions) keep it (1/0).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from brain_fe.protocols import RecordedPath
from brain_fe.vocabulary import CHANNELS, CONTROL, TEST_CHANNELS, TIME, test_key

COLUMNS = ("specimen", "curve", "test", "amplitude", "channel", "branch", "cycle", "control",
           "time_s", "value")


def observations(rec: pd.DataFrame, channels: dict[str, tuple[str, ...]] | None = None
                 ) -> pd.DataFrame:
    """Observation table of validated recordings (:func:`recordings.tables.read_recordings`).

    ``channels``: the channels to take per test (default: every channel the test records
    and the table holds)."""
    wanted = channels or TEST_CHANNELS
    parts = []
    for (spec, test, amp), g in rec.groupby(["specimen", "test", "amplitude"], sort=False):
        for ch in wanted[test]:
            col = CHANNELS[ch].column
            if col not in g or g[col].isna().all():
                continue
            parts.append(pd.DataFrame({
                "specimen": spec, "curve": test_key(test, amp), "test": test,
                "amplitude": float(amp), "channel": ch, "branch": g["branch"].to_numpy(),
                "cycle": g["cycle"].to_numpy(int), "control": g[CONTROL[test]].to_numpy(float),
                TIME: g[TIME].to_numpy(float), "value": g[col].to_numpy(float),
                **({"in_contact": g["in_contact"].fillna(1).to_numpy(int)}
                   if "in_contact" in g else {})}))
    if not parts:
        raise ValueError("the recordings hold no recorded channel")
    return pd.concat(parts, ignore_index=True)


def recorded_paths(obs: pd.DataFrame) -> list[tuple[str, RecordedPath, dict]]:
    """Per curve: its name, the recorded path the forward model follows, and per channel
    ``(observation rows, step index of each row)``."""
    out = []
    for curve, g in obs.groupby("curve", sort=False):
        first = g[g.channel == g.channel.iloc[0]]
        path, index = RecordedPath.through(
            str(first["test"].iloc[0]), float(first["amplitude"].iloc[0]),
            first[TIME].to_numpy(float), first["control"].to_numpy(float),
            first["cycle"].to_numpy(int), first["branch"].to_numpy())
        rows = {ch: (gc.index.to_numpy(), index) for ch, gc in g.groupby("channel")}
        out.append((str(curve), path, rows))
    return out


def peak_per_series(obs: pd.DataFrame) -> np.ndarray:
    """max |value| of each row's (curve, channel), per row."""
    return obs.groupby(["curve", "channel"])["value"].transform(
        lambda v: np.abs(v).max()).to_numpy(float)
