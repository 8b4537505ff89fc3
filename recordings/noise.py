"""The noise a testing rig puts on its channels, for synthetic recordings.

Per channel, in the channel's own unit (kPa, mN mm, mN), added to each series (one test's
channel, in time order):

* ``white``: independent Gaussian noise, SD ``white``;
* ``filtered``: the instrument's low-pass filter colours part of the noise: an
  Ornstein-Uhlenbeck process (exactly first-order filtered white noise) of SD ``filtered``
  and correlation time ``filter_s`` [s];
* ``wander``: slow wander of the baseline (temperature, friction), an Ornstein-Uhlenbeck
  process of SD ``wander`` and correlation time ``wander_s`` [s];
* ``drift``: the load cell drifts away from its tare, linearly in time from the start of
  each test, at a random rate of SD ``drift`` per second;
* ``quantum``: the recorded value is rounded to a multiple of ``quantum`` (0: none).

:func:`rig_noise` draws one series of noise; :func:`add_noise` applies it to every series of
a recordings table.  The diagnosis never sees these parameters; it estimates its own noise
model (:mod:`diagnosis.noise`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from brain_fe.vocabulary import CHANNELS, TEST_CHANNELS, TIME


@dataclass(frozen=True)
class RigNoise:
    """Noise of one channel (see the module docstring); every level in the channel's unit."""

    white: float
    filtered: float = 0.0
    filter_s: float = 1.0
    wander: float = 0.0
    wander_s: float = 30.0
    drift: float = 0.0
    quantum: float = 0.0

    def __post_init__(self):
        for k, v in asdict(self).items():
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"rig noise {k} must be a number >= 0, got {v}")
        if self.filter_s <= 0 or self.wander_s <= 0:
            raise ValueError("correlation times must be positive")

    def stationary_sd(self) -> float:
        """SD of the stationary part (white, filtered, wander)."""
        return math.sqrt(self.white**2 + self.filtered**2 + self.wander**2)

    def series_sd(self, t) -> float:
        """Root-mean-square noise this channel adds to a series recorded at the times ``t``
        [s], in expectation over its draws: the stationary part, the rounding error (uniform,
        ``quantum^2 / 12``) and the drift, whose rate is drawn once per series, so that it
        contributes ``drift^2`` times the mean of ``(t - t[0])^2``."""
        t = np.asarray(t, float)
        ramp = float(np.mean((t - t[0]) ** 2)) if len(t) else 0.0
        return math.sqrt(self.stationary_sd() ** 2 + self.quantum**2 / 12
                         + self.drift**2 * ramp)


def _ou(t: np.ndarray, sd: float, tau: float, rng) -> np.ndarray:
    """Ornstein-Uhlenbeck process of stationary SD ``sd`` and correlation time ``tau`` at
    the (increasing) times ``t``: x_{k+1} = rho x_k + sqrt(1 - rho^2) sd xi, rho =
    exp(-dt / tau), started in its stationary distribution."""
    x = np.empty(len(t))
    if not len(t):
        return x
    x[0] = sd * rng.standard_normal()
    for k in range(1, len(t)):
        rho = math.exp(-max(t[k] - t[k - 1], 0.0) / tau)
        x[k] = rho * x[k - 1] + math.sqrt(1.0 - rho * rho) * sd * rng.standard_normal()
    return x


def rig_noise(t: np.ndarray, noise: RigNoise, rng) -> np.ndarray:
    """One series of noise at the times ``t`` [s] (in time order)."""
    t = np.asarray(t, float)
    e = noise.white * rng.standard_normal(len(t))
    if noise.filtered:
        e += _ou(t, noise.filtered, noise.filter_s, rng)
    if noise.wander:
        e += _ou(t, noise.wander, noise.wander_s, rng)
    if noise.drift and len(t):
        e += noise.drift * rng.standard_normal() * (t - t[0])
    return e


def add_noise(rec: pd.DataFrame, noise: dict[str, RigNoise], rng) -> pd.DataFrame:
    """Recordings with rig noise added to every channel of every series; ``noise`` maps a
    channel name (``stress``, ``torque``, ``axial_force``) to its noise."""
    out = rec.copy()
    for (_, test, _), g in out.groupby(["specimen", "test", "amplitude"], sort=False):
        for ch in TEST_CHANNELS[test]:
            col = CHANNELS[ch].column
            if ch not in noise or col not in g or g[col].isna().all():
                continue
            n = noise[ch]
            v = g[col].to_numpy(float) + rig_noise(g[TIME].to_numpy(float), n, rng)
            if n.quantum:
                v = n.quantum * np.round(v / n.quantum)
            out.loc[g.index, col] = v
    return out
