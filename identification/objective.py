r"""The identification objective (after Gavrus et al., as in the paper).

Per test (curve) t with recorded values e_i and simulated values s_i at the recorded
control values:

.. math::  \varepsilon_t = \sqrt{\sum_i (s_i - e_i)^2 / \sum_i e_i^2}

The residual vector concatenates (s_i - e_i) / sqrt(sum_i e_i^2) over the curves used, so
that ``||r||^2 = sum_t eps_t^2``: the quantity minimised by both stages (a least-squares
form, which the trust-region FE stage needs).  Each curve is fitted on one channel: the
nominal stress (compression/tension) or the torque (torsion; eps_t is scale-invariant, so
it equals the error of the torque-derived shear stress 2 T / (pi R^3) of the paper).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from brain_fe.vocabulary import COMPRESSION_TENSION, TORSION
from recordings.observations import observations

# The channel each test is identified on
FIT_CHANNELS = {COMPRESSION_TENSION: ("stress",), TORSION: ("torque",)}


def identification_obs(rec: pd.DataFrame) -> pd.DataFrame:
    """Observation table of one specimen's recordings with the fitted channel of each test."""
    return observations(rec, FIT_CHANNELS)


def curve_norms(obs: pd.DataFrame) -> np.ndarray:
    """sqrt(sum e_i^2) of each row's curve, per row."""
    return obs.groupby("curve")["value"].transform(
        lambda v: np.sqrt(np.sum(v.to_numpy(float) ** 2))).to_numpy(float)


def residuals(obs: pd.DataFrame, y: np.ndarray) -> np.ndarray:
    return (y - obs["value"].to_numpy(float)) / curve_norms(obs)


def gavrus_errors(obs: pd.DataFrame, y: np.ndarray) -> dict[str, float]:
    """eps_t for every curve, in order of appearance."""
    r = residuals(obs, y)
    return {str(c): float(np.sqrt(np.sum(r[g.index.to_numpy()] ** 2)))
            for c, g in obs.groupby("curve", sort=False)}
