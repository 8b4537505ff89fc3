"""Rig noise (the generator) and the diagnosis's noise model (the estimator), each checked
against closed forms and against the other: the generator's Ornstein-Uhlenbeck wander has
the exponential covariance it is defined by, and the maximum-likelihood noise model
recovers white and wander levels it did not generate."""

import math

import numpy as np
import pandas as pd
import pytest

from diagnosis.noise import fit_noise
from recordings.noise import RigNoise, rig_noise


def test_wander_has_the_exponential_covariance():
    """Stationary SD and lag-k correlation exp(-k dt / tau) of the OU wander, from 4000
    realisations (sampling error of a correlation ~ 1/sqrt(4000) = 0.016: tolerance 0.05)."""
    rng = np.random.default_rng(3)
    t = np.arange(12) * 0.5
    n = RigNoise(white=0.0, wander=2.0, wander_s=1.5)
    x = np.array([rig_noise(t, n, rng) for _ in range(4000)])
    assert x.std(axis=0).mean() == pytest.approx(2.0, rel=0.04)
    for lag in (1, 3):
        c = np.mean([np.corrcoef(x[:, i], x[:, i + lag])[0, 1] for i in range(12 - lag)])
        assert c == pytest.approx(math.exp(-lag * 0.5 / 1.5), abs=0.05)


def test_white_noise_and_drift_closed_forms():
    """White noise is uncorrelated with the stated SD; drift grows linearly from the tare
    (SD of the drift term at time t: drift * t)."""
    rng = np.random.default_rng(4)
    t = np.linspace(0.0, 10.0, 6)
    x = np.array([rig_noise(t, RigNoise(white=0.0, drift=0.3), rng) for _ in range(4000)])
    np.testing.assert_allclose(x.std(axis=0)[1:], 0.3 * t[1:], rtol=0.05)
    w = np.array([rig_noise(t, RigNoise(white=0.7), rng) for _ in range(4000)])
    assert w.std() == pytest.approx(0.7, rel=0.03)
    assert abs(np.corrcoef(w[:, 0], w[:, 1])[0, 1]) < 0.05


def _obs(t: np.ndarray, value: np.ndarray, per_ramp: int) -> pd.DataFrame:
    """An observation table of one (curve, channel) series: ramps of ``per_ramp`` points,
    loading and unloading in turn."""
    k = np.arange(len(t)) // per_ramp
    return pd.DataFrame({"specimen": "s", "curve": "compression_tension",
                         "test": "compression_tension", "amplitude": 0.15,
                         "channel": "stress", "branch": np.where(k % 2, "unloading", "loading"),
                         "cycle": k // 2 + 1, "control": 1.0, "time_s": t, "value": value})


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noise_model_recovers_white_and_wander(seed):
    """Residual = white (SD 1) + wander (SD 1.5, tau 4 s), 480 points at 1 s in ramps of
    40 s: the ML model's white and correlated SDs within 25 %, the correlation time within
    a factor 2 (the sampling error of 480 points of a 4 s process)."""
    rng = np.random.default_rng(seed)
    t = np.arange(480.0)
    r = rig_noise(t, RigNoise(white=1.0, wander=1.5, wander_s=4.0), rng)
    nm = fit_noise(_obs(t, r, 40), r, drift=False)
    (cn,) = nm.params.values()
    assert cn.white == pytest.approx(1.0, rel=0.25)
    assert cn.corr == pytest.approx(1.5, rel=0.25)
    assert 2.0 < cn.corr_s < 8.0
    z = nm.whiten(r)  # whitened residual: unit variance, no lag-1 correlation left
    assert z.std() == pytest.approx(1.0, rel=0.1)
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 0.15


def test_stated_white_noise_is_held():
    """A stated instrument noise (``--noise``) is held; the wander is still fitted."""
    rng = np.random.default_rng(5)
    t = np.arange(480.0)
    r = rig_noise(t, RigNoise(white=1.0, wander=1.5, wander_s=4.0), rng)
    (cn,) = fit_noise(_obs(t, r, 40), r, stated={"stress": 0.9}, drift=False).params.values()
    assert cn.white == 0.9
    assert cn.corr == pytest.approx(1.5, rel=0.3)


def test_channel_noise_option_parses_and_refuses():
    import argparse

    from brainmech.args import channel_noise

    assert channel_noise("stress=0.01, torque=2e-2") == {"stress": 0.01, "torque": 0.02}
    for bad in ("stress", "force=1", "stress=-1", "stress=nan", ","):
        with pytest.raises(argparse.ArgumentTypeError):
            channel_noise(bad)
