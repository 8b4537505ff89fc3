"""Recordings as an observation table, and recorded paths the FE model can follow.

Observation table: one row per recorded value, columns ``specimen, curve, test,
amplitude, channel, branch, cycle, control, time_s, value``; ``curve`` is
``compression_tension`` / ``torsion_0.15`` / ``torsion_0.30`` and ``channel`` is
``stress`` (nominal stress, kPa), ``torque`` (mN mm) or ``axial_force`` (mN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from brain_fe.protocols import CONTROL, NEUTRAL, Step

CHANNEL_COLUMN = {"stress": "nominal_stress_kPa", "torque": "torque_mNmm",
                  "axial_force": "axial_force_mN"}
CHANNEL_UNIT = {"stress": "kPa", "torque": "mN mm", "axial_force": "mN"}
TEST_CHANNELS = {"compression_tension": ("stress",), "torsion": ("torque", "axial_force")}


def observations(rec: pd.DataFrame) -> pd.DataFrame:
    """Observation table of validated recordings (identification.recordings format)."""
    from identification.recordings import key_for_test

    parts = []
    for (spec, test, amp), g in rec.groupby(["specimen", "test", "amplitude"], sort=False):
        for ch in TEST_CHANNELS[test]:
            col = CHANNEL_COLUMN[ch]
            if col not in g or g[col].isna().all():
                continue
            parts.append(pd.DataFrame({
                "specimen": spec, "curve": key_for_test(test, amp), "test": test,
                "amplitude": float(amp), "channel": ch, "branch": g["branch"].to_numpy(),
                "cycle": g["cycle"].to_numpy(int), "control": g[CONTROL[test]].to_numpy(float),
                "time_s": g["time_s"].to_numpy(float), "value": g[col].to_numpy(float)}))
    return pd.concat(parts, ignore_index=True)


@dataclass
class RecordedPath:
    """The recorded (time, control) points of one test as a protocol for ForwardModel.run:
    the model follows the piecewise-linear path through them and reports at every one."""

    test: str
    amplitude: float
    points: list[Step]
    rate_per_s: float

    @property
    def control(self) -> str:
        return CONTROL[self.test]

    def steps(self) -> list[Step]:
        return self.points

    @classmethod
    def from_curve(cls, g: pd.DataFrame) -> tuple[RecordedPath, np.ndarray]:
        """Path of one curve (rows of one channel) and, for each row, its step index."""
        test = str(g["test"].iloc[0])
        t = g["time_s"].to_numpy(float)
        x = g["control"].to_numpy(float)
        if np.isnan(t).any():  # no clock: assume the default rate
            t = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(x)))]) / 0.01
        steps = [Step(float(ti), int(c), str(b), float(xi))
                 for ti, c, b, xi in zip(t, g["cycle"], g["branch"], x, strict=True)]
        index = np.arange(len(steps))
        neutral = NEUTRAL[test]
        dt = np.diff(t)
        rate = float(np.median(np.abs(np.diff(x))[dt > 0] / dt[dt > 0])) if (dt > 0).any() \
            else 0.01
        if not np.isclose(x[0], neutral):  # start from the undeformed state
            t0 = t[0] - abs(x[0] - neutral) / rate
            steps.insert(0, Step(float(t0), 1, "loading", neutral))
            index = index + 1
        return cls(test, float(g["amplitude"].iloc[0]), steps, rate), index
