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


def test_series_sd_is_the_mean_square_of_every_kind_drawn():
    """The benchmark's "true noise" of a series (RigNoise.series_sd) against the mean square
    of 4000 series drawn with every kind at once (and rounding to a coarse quantum): the
    drift's share is drift^2 mean((t - t0)^2), a third of its end value squared on a
    uniform clock.  Monte Carlo tolerance 3 %."""
    rng = np.random.default_rng(8)
    t = np.linspace(5.0, 65.0, 61)
    n = RigNoise(white=0.2, filtered=0.1, filter_s=2.0, wander=0.15, wander_s=20.0,
                 drift=0.01, quantum=0.3)
    ms = np.mean([np.mean((n.quantum * np.round((3.7 + rig_noise(t, n, rng)) / n.quantum)
                           - 3.7) ** 2) for _ in range(4000)])
    assert math.sqrt(ms) == pytest.approx(n.series_sd(t), rel=0.03)
    assert n.series_sd(t) ** 2 == pytest.approx(0.2**2 + 0.1**2 + 0.15**2 + 0.3**2 / 12
                                                + 0.01**2 * 60.0**2 * (1 + 1 / 120) / 3)


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


def test_noise_file_option_gives_each_specimen_its_own(tmp_path):
    """``--noise noise.json`` (as written by ``brainmech import``): each specimen its own
    stated noise; one the file does not list is estimated; a bad file is one clear line."""
    import argparse
    import json

    from brainmech.args import noise_option
    from diagnosis.batch import noise_of

    f = tmp_path / "noise.json"
    f.write_text(json.dumps({"a/1": {"stress": 0.2}, "b": {"torque": 0.05}}))
    opt = noise_option(str(f))
    assert noise_of(opt, "a/1") == {"stress": 0.2}
    assert noise_of(opt, "b") == {"torque": 0.05}
    assert noise_of(opt, "c") is None
    assert noise_of(noise_option("stress=0.1"), "c") == {"stress": 0.1}
    assert noise_of(None, "c") is None
    for text, why in ((json.dumps({"a": {"force": 1}}), "channel 'force'"),
                      (json.dumps({"a": {"stress": -1}}), "SD must be a positive number"),
                      ("[1, 2]", "expected {specimen"), ("{", "not a JSON file")):
        f.write_text(text)
        with pytest.raises(argparse.ArgumentTypeError, match=why) as exc:
            noise_option(str(f))
        assert str(f) in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(argparse.ArgumentTypeError, match="no such file"):
        noise_option(str(tmp_path / "missing.json"))


def _cycled_obs(r: np.ndarray, per_ramp: int) -> pd.DataFrame:
    """``_obs`` with a control that ramps 0 -> 0.15 on loading and back on unloading."""
    obs = _obs(np.arange(float(len(r))), r, per_ramp)
    up = np.linspace(0.0, 0.15, per_ramp)
    obs["control"] = np.where(obs["branch"] == "loading", np.tile(up, len(r) // per_ramp),
                              np.tile(up[::-1], len(r) // per_ramp))
    return obs


def _offset_gain(cov: np.ndarray, r: np.ndarray) -> float:
    """The gain of a constant column on ``r`` under the covariance ``cov`` (generalised
    least squares): chi2 with one degree of freedom when ``cov`` is the noise's."""
    import scipy.linalg as sl

    ones = np.ones(len(r))
    a = sl.cho_solve(sl.cho_factor(cov, lower=True), ones)
    return float((a @ r) ** 2 / (a @ ones))


def _engine_covariance(obs: pd.DataFrame, cn) -> np.ndarray:
    """The covariance the engine's noise model ``cn`` gives the one series of ``obs``."""
    from diagnosis.noise import noise_series

    (series,) = noise_series(obs)
    return series.covariance(cn)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_repeated_misfit_is_kept_out_of_the_noise(seed):
    """Residual = white noise (SD 1) + a smooth misfit repeated at all 6 cycles (a
    hysteresis of amplitude 4 the model lacks, 480 points).  Plain ML takes a large part of
    the misfit for wander; restricted ML with the reproducible basis projected out recovers
    the white SD within 15 % (its sampling error at ~430 residual dof is ~3.4 %, the rest is
    the basis' approximation of the misfit) and leaves at most 0.4 for the correlated part."""
    from diagnosis.remaining import systematic_basis

    rng = np.random.default_rng(seed)
    per_ramp = 40
    x = np.linspace(0.0, 1.0, per_ramp)
    hysteresis = np.r_[4.0 * np.sin(np.pi * x), -4.0 * np.sin(np.pi * x[::-1])]
    r = np.tile(hysteresis, 6) + rng.normal(0.0, 1.0, 480)
    obs = _cycled_obs(r, per_ramp)
    (plain,) = fit_noise(obs, r, drift=False).params.values()
    assert plain.sd > 1.5  # the misfit inflates the noise without the projection
    (cn,) = fit_noise(obs, r, drift=False,
                      systematic=systematic_basis(obs)).params.values()
    assert cn.white == pytest.approx(1.0, rel=0.15)
    assert cn.corr < 0.4


@pytest.mark.parametrize("seed", [0, 1])
def test_wander_survives_the_projection(seed):
    """The projection removes only what repeats: wander (independent between cycles) is
    still recovered by restricted ML, within the tolerances of the plain fit above."""
    from diagnosis.remaining import systematic_basis

    rng = np.random.default_rng(seed)
    t = np.arange(480.0)
    r = rig_noise(t, RigNoise(white=1.0, wander=1.5, wander_s=4.0), rng)
    obs = _cycled_obs(r, 40)
    (cn,) = fit_noise(obs, r, drift=False, systematic=systematic_basis(obs)).params.values()
    assert cn.white == pytest.approx(1.0, rel=0.25)
    assert cn.corr == pytest.approx(1.5, rel=0.3)
    assert 2.0 < cn.corr_s < 8.0


def _two_curves(per_ramp: int, cycles: int) -> tuple[pd.DataFrame, np.ndarray]:
    """Two curves (compression/tension, torsion) of ``cycles`` cycles each, time from 0 in
    each, with a model prediction that swings between -1 and 1 along every ramp."""
    parts, preds = [], []
    n = 2 * cycles * per_ramp
    x = np.linspace(0.0, 1.0, per_ramp)
    for curve in ("compression_tension", "torsion"):
        o = _cycled_obs(np.zeros(n), per_ramp)
        o["curve"] = curve
        parts.append(o)
        preds.append(np.tile(np.r_[np.sin(np.pi * x), np.sin(np.pi * x[::-1])], cycles))
    return pd.concat(parts, ignore_index=True), np.concatenate(preds)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_rate_stiffness_trend(seed):
    """A stiffness changing at one rate during both tests (residual -d p (t - t_mid) / T, p the
    model's prediction) is one column of the trend test.  With d = 0.17 and white noise of
    SD 0.1 on 480 points its chi-square is d^2 / 0.1^2 * sum p^2 ((t - t_mid) / T)^2 ~
    2000 d^2 ~ 58 (<p^2> = 1/2, <((t - t_mid)/T)^2> = 1/12); the test's gain is that plus
    chi-square(1) noise, within 30 %, and significant (the BIC bar is log 480 + 10 = 16.2);
    without the drift, on the same noise, it is not.  The rate it reports is the planted
    one."""
    from diagnosis.remaining import remaining, trend_basis

    rng = np.random.default_rng(seed)
    obs, p = _two_curves(40, 3)
    assert trend_basis(obs, p).shape == (len(obs), 1)  # one column for both curves
    t = obs["time_s"].to_numpy()
    # the residual is model minus recorded: here the recordings stiffen, recorded =
    # p (1 + 0.17 (t - t_mid) / T); each curve's time runs 0..239 s
    drift = -0.17 * p * (t - 119.5) / 239.0
    expected = float(np.sum((drift / 0.1) ** 2))
    assert expected == pytest.approx(2000 * 0.17**2, rel=0.1)
    white = rng.normal(0.0, 0.1, len(obs))
    nm = fit_noise(obs, white, stated={"stress": 0.1}, drift=False)
    out = remaining(obs, white + drift, nm, prediction=p)
    assert out["trend"]["dof"] == 1
    assert out["trend"]["gain"] == pytest.approx(expected, rel=0.3)
    assert out["trend"]["significant"]
    # the trend modelled: the planted rate, +0.17 of the stiffness over a test of 239 s,
    # recovered within three standard errors, each 1 / sqrt(2000) = 0.022
    assert out["trend"]["span_s"] == pytest.approx(239.0)
    assert out["trend"]["change_se"] == pytest.approx(2000**-0.5, rel=0.1)
    assert abs(out["trend"]["change"] - 0.17) < 3 * out["trend"]["change_se"]
    clean = remaining(obs, white, nm, prediction=p)
    assert not clean["trend"]["significant"]


def test_a_short_series_keeps_the_trend_out_of_its_noise():
    """Two curves of two cycles of 4 points per ramp (16 rows each, 15 s): too short to
    keep the whole systematic basis (the repeated misfit and the trend, 21 columns) out of
    the noise with 8 degrees of freedom left.  Kept whole, a series' noise takes up a
    stiffness drift (residual -0.1 p (t - t_mid) / T on white noise of SD 0.02: the misfit
    about as large as the noise); given the trend alone as the fallback (``systematic`` a
    list, fullest first) it keeps that out.  Over 8 draws: the median SD of the 16 series
    within 20 % of 0.02 (each from 15 degrees of freedom, sampling error ~18 %) against
    > 1.15 x kept whole, the trend found in every draw (kept whole: missed in some), and
    without the drift no trend is found under either (no false alarm bought)."""
    from diagnosis.remaining import remaining, systematic_basis, trend_basis

    obs, p = _two_curves(4, 2)
    t = obs["time_s"].to_numpy()
    span = float(np.ptp(t[:16]))
    B, T = systematic_basis(obs, p), trend_basis(obs, p)
    assert B.shape == (32, 21) and T.shape == (32, 1)
    sds = {"whole": [], "fallback": []}
    found = {"whole": 0, "fallback": 0}
    for seed in range(8):
        white = np.random.default_rng(seed).normal(0.0, 0.02, len(obs))
        r = -0.1 * p * (t - 0.5 * span) / span + white
        for how, systematic in (("whole", B), ("fallback", [B, T])):
            nm = fit_noise(obs, r, systematic=systematic)
            sds[how] += [cn.sd for cn in nm.params.values()]
            found[how] += remaining(obs, r, nm, prediction=p)["trend"]["significant"]
            clean = fit_noise(obs, white, systematic=systematic)
            assert not remaining(obs, white, clean, prediction=p)["trend"]["significant"]
        assert set(nm.dof) == {15.0}  # 16 rows less the trend's one column
    assert np.median(sds["fallback"]) == pytest.approx(0.02, rel=0.2)
    assert np.median(sds["whole"]) > 1.15 * 0.02
    assert found == {"whole": found["whole"], "fallback": 8} and found["whole"] < 8


def test_what_the_diagnosis_keeps_out_of_a_short_series():
    """The diagnosis's noise model (``engine._noise_of``) on short series: a curve of two
    cycles (16 rows) keeps out the trend and the model's two parameter columns (13 degrees
    of freedom left), a curve of one pass (8 rows) keeps nothing out (8 left), and a long
    curve of two cycles (80 rows) keeps out the whole systematic basis (repeated misfit,
    trend and parameters)."""
    import types

    from diagnosis.engine import _noise_of
    from diagnosis.remaining import reproducible_basis

    short, p = _two_curves(4, 2)
    one = _cycled_obs(np.zeros(8), 4).assign(curve="torsion_0.1")
    long, p_long = _two_curves(20, 2)
    long["curve"] = long["curve"] + "_long"
    obs = pd.concat([short, one, long], ignore_index=True)
    pred = np.concatenate([p, np.sin(np.linspace(0.0, np.pi, 8)), p_long])
    rng = np.random.default_rng(0)
    J = np.column_stack([pred, rng.normal(0.0, 1.0, len(obs))])  # two parameters' columns
    fit = types.SimpleNamespace(prediction=pred, jacobian=J,
                                residual=lambda o: rng.normal(0.0, 1.0, len(o)))
    nm = _noise_of(obs, fit, None)
    full = np.hstack([reproducible_basis(obs)[0], J])
    per_curve = {c: set(nm.dof[obs["curve"].to_numpy() == c]) for c in obs["curve"].unique()}
    assert per_curve["compression_tension"] == {16 - 3} == per_curve["torsion"]
    assert per_curve["torsion_0.1"] == {8}
    rows = (obs["curve"] == "torsion_long").to_numpy()
    cols = np.abs(full[rows]).max(axis=0) > 0
    assert per_curve["torsion_long"] == {80 - (np.linalg.matrix_rank(full[rows][:, cols]) + 1)}


@pytest.mark.parametrize("seed", [0, 1])
def test_the_shear_tests_asking_for_other_parameters(seed):
    """The split test on a linear model, where the score test is the likelihood ratio
    exactly: two material columns (p and p x^2 along each ramp) and a rig offset on the
    compression/tension rows only.  With the material parameters 0.2 apart between the
    tests, the gain equals the chi-square of the joint least-squares fit minus those of
    the two tests fitted alone (an independent reference: numpy's lstsq per test), to
    1e-6; the steps are the fitted differences (torsion minus compression/tension), the
    change of the torsion's response is its own fit's minus the joint fit's, the offset is
    never split, and with one set of parameters the test passes."""
    from diagnosis.remaining import remaining

    rng = np.random.default_rng(seed)
    obs, p = _two_curves(40, 2)
    x = np.tile(np.linspace(0.0, 1.0, 40), len(obs) // 40)
    shear = obs["curve"].eq("torsion").to_numpy()
    J = np.column_stack([p, p * x**2, (~shear).astype(float)])
    names = ["mu_0", "alpha_0", "force_offset"]
    nm = fit_noise(obs, np.zeros(len(obs)), stated={"stress": 0.1}, drift=False)
    for diff, split in ((0.2, True), (0.0, False)):
        theta = np.where(shear[:, None], [1.0 + diff, 0.5 + diff, 0.0], [1.0, 0.5, 0.2])
        y = np.sum(J * theta, axis=1) + rng.normal(0.0, 0.1, len(obs))

        def chi2(rows, cols, y=y):
            A, b = J[np.ix_(rows, cols)], y[rows]
            c, *_ = np.linalg.lstsq(A, b, rcond=None)
            return float(np.sum((A @ c - b) ** 2)) / 0.01, c

        every = np.arange(len(obs))
        joint, c = chi2(every, [0, 1, 2])
        alone_ct, c_ct = chi2(every[~shear], [0, 1, 2])
        alone_t, c_t = chi2(every[shear], [0, 1])
        out = remaining(obs, J @ c - y, nm, prediction=J @ c, jacobian=J,
                        names=names)["split"]
        assert out["dof"] == 2
        assert out["gain"] == pytest.approx(joint - alone_ct - alone_t, rel=1e-6)
        assert set(out["steps"]) == {"mu_0", "alpha_0"}
        assert out["steps"]["mu_0"] == pytest.approx(c_t[0] - c_ct[0], rel=1e-6)
        assert out["steps"]["alpha_0"] == pytest.approx(c_t[1] - c_ct[1], rel=1e-6)
        assert out["significant"] is split
        # the torsion's response with its own parameters against the joint fit's, as a
        # factor on the joint prediction there and the rest
        y_t = (J @ c)[shear]
        dy = J[np.ix_(shear, [0, 1])] @ (c_t[:2] - c[:2])
        scale = float(dy @ y_t / (y_t @ y_t))
        assert out["scale"] == pytest.approx(scale, rel=1e-6)
        assert out["shape"] == pytest.approx(
            np.linalg.norm(dy - scale * y_t) / np.linalg.norm(y_t), rel=1e-6)


@pytest.mark.parametrize("seed", [9, 16])
def test_noise_model_finds_a_drift_its_first_start_cannot(seed, monkeypatch):
    """White (SD 1) + wander (SD 0.5, 5 s) + a drift of 0.01 per s over 120 s at 0.5 s: the
    likelihood is flat in log drift far below the white noise, and from the small drift of
    the first start alone the fit stays there (these seeds: -2 log L more than 1 above
    the best point of a grid).  The maximum-likelihood model must be at least as likely
    as every point of a grid over the four parameters (an optimiser-free reference;
    tolerance 0.01 in -2 log L)."""
    import itertools

    from diagnosis import noise
    from diagnosis.noise import ChannelNoise, NoiseModel

    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0, 0.5)
    r = rig_noise(t, RigNoise(white=1.0, drift=0.01, wander=0.5, wander_s=5.0), rng)
    obs = _obs(t, r, 40)
    ((key, fitted),) = fit_noise(obs, r).params.items()

    def nll(cn: ChannelNoise) -> float:
        return NoiseModel(obs, {key: cn}).nll(r)

    grid = min(nll(ChannelNoise(white=w, corr=c, corr_s=cs, drift=d))
               for w, c, cs, d in itertools.product(
                   np.geomspace(0.7, 1.3, 13), (1e-6, 0.25, 0.5, 0.75), (2.5, 5.0, 9.75),
                   (1e-8, 0.0025, 0.005, 0.0075, 0.01, 0.015)))
    assert nll(fitted) <= grid + 0.01
    monkeypatch.setattr(noise, "DRIFT_STARTS", noise.DRIFT_STARTS[:1])
    # and as a series of one cycle (these 3 cycles may take a wander as slow as a cycle,
    # with one more start there, since open-world-33: with them seed 9 reaches a 7 s
    # wander instead, 0.8 above the grid)
    monkeypatch.setattr(noise, "cycle_duration", lambda obs, rows: None)
    (first_only,) = fit_noise(obs, r).params.values()
    assert nll(first_only) > grid + 1.0


def test_slow_part_of_the_noise_counts_wander_and_drift():
    """``slow_sd`` = hypot(wander SD, drift x RMS of (t - t0) over the series): for samples
    every 0.5 s from 0 to 119.5 s the RMS of t is 0.5 sqrt((n - 1)(2n - 1) / 6) with
    n = 240 (closed form of the sum of squares); to 1e-12."""
    from diagnosis.noise import ChannelNoise, NoiseModel

    t = np.arange(0.0, 120.0, 0.5)
    obs = _obs(t, np.zeros_like(t), 40)
    ((key, _),) = fit_noise(obs, np.random.default_rng(0).normal(size=t.size)).params.items()
    n = t.size
    rms_t = 0.5 * np.sqrt((n - 1) * (2 * n - 1) / 6)
    (d,) = NoiseModel(obs, {key: ChannelNoise(white=1.0, corr=0.3, drift=0.002)}
                      ).describe().values()
    assert d["slow_sd"] == pytest.approx(np.hypot(0.3, 0.002 * rms_t), rel=1e-12)
    (w,) = NoiseModel(obs, {key: ChannelNoise(white=1.0)}).describe().values()
    assert w["slow_sd"] == 0.0


def _smooth_misfit(amplitude: float, seed: int = 0):
    """One ramp of 40 points: white noise of SD 1 plus a half-sine misfit, with the
    columns 1, t, t^2 kept out of the likelihood (REML, as a model's own parameters are)."""
    rng = np.random.default_rng(seed)
    t = np.arange(40.0)
    r = rig_noise(t, RigNoise(white=1.0), rng) + amplitude * np.sin(np.pi * t / 40)
    return _obs(t, r, 40), r, np.vander(t / 40, 3)


def test_a_slow_noise_the_recordings_leave_open_is_kept_as_a_rival():
    """A large smooth misfit on one ramp, its drift direction projected out: the likelihood
    is flat along the drift, and the two drift starts end with slow SDs 2.7 times apart at
    the same -2 log L (to 1e-6): the model keeps the other one as a rival (``rival()``
    differs only in that series' parameters) instead of choosing by the last digits.
    White noise alone: no rival."""
    from diagnosis.noise import NOISE_TIE, RIVAL_FACTOR

    obs, r, B = _smooth_misfit(30.0)
    nm = fit_noise(obs, r, stated={"stress": 1.0}, systematic=B)
    ((key, (rival, delta)),) = nm.rivals.items()
    assert abs(delta) < 1e-6 < NOISE_TIE
    d = nm.describe_rivals()[f"{key[0]}/{key[1]}"]
    assert max(d["slow_sd"], d["rival_slow_sd"]) > RIVAL_FACTOR * min(d["slow_sd"],
                                                                    d["rival_slow_sd"])
    other = nm.rival()
    assert other.params[key] == rival and other.params[key] != nm.params[key]
    assert other.nll(r) != pytest.approx(nm.nll(r))  # the full likelihood sees it
    obs, r, B = _smooth_misfit(0.0)
    assert fit_noise(obs, r, stated={"stress": 1.0}, systematic=B).rival() is None


def test_an_effect_tested_under_a_noise_estimated_from_the_same_recordings():
    """The significance of an effect (``diagnosis.selection``) when the noise SD was
    estimated from the recordings with nu degrees of freedom: LRT / k ~ F(k, nu).  Checked
    against closed forms (F(1, nu) = t(nu)^2; the chi-square limit for a known noise) and
    by simulation: a straight line fitted to 24 noisy points, an absent quadratic term
    tested with the noise SD estimated from the residual of the model with it (nu = 21),
    20 000 times.  Under F the false alarms occur at the nominal rate 0.01 (sampling SD
    0.0007: tolerance 0.003); read as chi2(1) they occur at 0.018 (P(F(1, 21) > 6.63))."""
    from scipy import stats

    from diagnosis.selection import chi2_needed, lrt_p_value

    for lrt, nu in ((4.0, 21.0), (12.5, 7.0)):
        assert lrt_p_value(lrt, 1, nu) == pytest.approx(2 * stats.t.sf(math.sqrt(lrt), nu),
                                                        rel=1e-9)
    assert lrt_p_value(9.0, 2) == pytest.approx(math.exp(-4.5), rel=1e-12)  # chi2(2)
    assert lrt_p_value(9.0, 2, 1e9) == pytest.approx(math.exp(-4.5), rel=1e-6)
    # the bar: p = alpha / m exactly at it when the test part dominates (n small)
    for k, nu in ((1, 20.0), (3, 9.0)):
        bar = chi2_needed(k, 4, 5, nu=nu)
        assert lrt_p_value(bar, k, nu) == pytest.approx(1e-3 / 4, rel=1e-6)
        assert bar > chi2_needed(k, 4, 5)  # above the known-noise bar
    assert chi2_needed(2, 6, 2000, nu=500.0) == chi2_needed(2, 6, 2000)  # BIC decides

    rng = np.random.default_rng(7)
    x = np.linspace(-1.0, 1.0, 24)
    X0 = np.c_[np.ones_like(x), x]
    X1 = np.c_[X0, x**2 - np.mean(x**2)]
    y = rng.normal(0.0, 1.0, (20000, 24))  # the line is 0: pure noise

    def rss(X):
        coef = np.linalg.lstsq(X, y.T, rcond=None)[0]
        return np.sum((y.T - X @ coef) ** 2, axis=0)

    nu = 24 - 3
    s2 = rss(X1) / nu  # the noise variance from the model with the candidate
    lrt = (rss(X0) - rss(X1)) / s2
    p_f = np.array([lrt_p_value(v, 1, nu) for v in lrt])
    assert np.mean(p_f < 0.01) == pytest.approx(0.01, abs=0.003)
    assert np.mean(stats.chi2.sf(lrt, 1) < 0.01) > 0.015


def _stress_and_torque(rng) -> pd.DataFrame:
    """Two series of white noise: a stress of 30 points and a torque of 20."""
    a = _obs(np.arange(30.0), rng.normal(size=30), 10)
    b = _obs(np.arange(20.0), rng.normal(size=20), 10).assign(curve="torsion",
                                                              test="torsion",
                                                              channel="torque")
    return pd.concat([a, b], ignore_index=True)


def test_noise_model_degrees_of_freedom_for_the_tests():
    """``NoiseModel.nu_level``: two series of 30 and 20 points, 3 columns projected out of
    each (REML), so nu_s = 27 and 17, and 1 / nu = (30/50)^2 / 27 + (20/50)^2 / 17; nothing
    projected out: 30 and 20.  With the white SD of one channel stated, only its slow
    part is estimated: none fitted (white noise alone), that series is known (it drops
    out of the sum); a slow part with share f of its variance divides nu_s by f^2."""
    from diagnosis.noise import ChannelNoise, NoiseModel

    rng = np.random.default_rng(1)
    obs = _stress_and_torque(rng)
    r = obs["value"].to_numpy()
    B = np.c_[np.ones(50), np.arange(50.0), rng.normal(size=50)]
    nm = fit_noise(obs, r, drift=False, correlated=False, systematic=B)
    assert nm.nu_level() == pytest.approx(1.0 / (0.6**2 / 27 + 0.4**2 / 17), rel=1e-12)
    plain = fit_noise(obs, r, drift=False, correlated=False)  # nothing projected out
    assert plain.nu_level() == pytest.approx(1.0 / (0.6**2 / 30 + 0.4**2 / 20), rel=1e-12)
    stated = fit_noise(obs, r, drift=False, correlated=False, stated={"torque": 1.0})
    assert stated.nu_level() == pytest.approx(30.0 / 0.6**2, rel=1e-12)
    slow = {("compression_tension", "stress"): ChannelNoise(white=1.0),
            ("torsion", "torque"): ChannelNoise(white=1.0, corr=1.0, corr_s=2.0)}
    held = NoiseModel(obs, slow, np.r_[np.full(30, 30.0), np.full(20, 20.0)],
                      held=frozenset({("torsion", "torque")}))
    assert held.nu_level() == pytest.approx(1.0 / (0.6**2 / 30 + 0.4**2 / (20 / 0.5**2)),
                                            rel=1e-12)


def test_a_second_ogden_term_from_one_kind_of_test_is_a_cannot_tell():
    """A second Ogden term named from compression/tension alone or torsion alone says it
    cannot tell it from a fibre family (one mode of deformation: any law bending that one
    response alike fits as well); named from both kinds, or any other effect from one
    kind, it does not."""
    from diagnosis.notes import one_kind_doubt

    obs, _ = _two_curves(4, 2)  # compression_tension and torsion
    ct = obs[obs["curve"] == "compression_tension"]
    tors = obs[obs["curve"] == "torsion"]
    assert "compression/tension tests alone" in one_kind_doubt(["ogden_2term"], ct)
    assert "a torsion test" in one_kind_doubt(["ogden_2term", "viscoelastic"], ct)
    assert "torsion tests alone" in one_kind_doubt(["ogden_2term"], tors)
    assert one_kind_doubt(["ogden_2term"], obs) == ""
    assert one_kind_doubt(["viscoelastic"], ct) == one_kind_doubt([], tors) == ""


def test_artefacts_that_only_bend_a_torsion_response_are_a_cannot_tell():
    """Torsion alone sees a stretch offset only through how it bends the response; with an
    axial-force offset cancelling the force the stretch offset makes at rest (both beyond
    2 standard errors, opposite signs: a pre-stretched specimen, its load cell zeroed), the
    named artefacts are that bend alone, which a fibre family makes too. The values are
    world076's of the open benchmark's seed 5 (axial fibres named ``artefacts``: stretch
    offset 0.0159 +- 0.0004, force offset -10.4 +- 0.36 mN) and world074's of seed 3 (a
    right ``artefacts``: -0.0066 +- 0.0009 with -0.65 +- 0.39 mN, the same sign)."""
    from brain_fe.parameters import Param
    from diagnosis.fitting import Fit
    from diagnosis.notes import one_kind_doubt

    def fit(stretch, force):
        names = [Param("stretch_offset"), Param("force_offset"), Param("torque_offset")]
        vals = dict(zip(names, (stretch[0], force[0], 0.01), strict=True))
        errs = dict(zip(names, (stretch[1], force[1], 0.1), strict=True))
        return Fit("artefacts", names, vals, 0.0, 0, np.zeros(0), np.zeros(0), 0, errs)

    obs, _ = _two_curves(4, 2)
    tors = obs[obs["curve"] == "torsion"]
    fibres = fit((0.0159, 0.0004), (-10.39, 0.364))
    doubt = one_kind_doubt(["artefacts"], tors, fibres)
    assert "artefacts named from torsion tests alone" in doubt
    assert "(39.8 standard errors)" in doubt and "(28.5)" in doubt
    assert one_kind_doubt(["artefacts"], tors, fit((-0.0066, 0.0009), (-0.65, 0.39))) == ""
    assert one_kind_doubt(["artefacts"], tors, fit((0.0159, 0.0004), (-0.7, 0.36))) == ""
    assert one_kind_doubt(["artefacts"], tors, fit((0.0159, 0.0004), (10.39, 0.364))) == ""
    assert one_kind_doubt(["artefacts"], obs, fibres) == ""  # both kinds of test
    assert one_kind_doubt(["viscoelastic"], tors, fibres) == ""
    both = one_kind_doubt(["artefacts", "ogden_2term"], tors, fibres)
    assert both.startswith("a second Ogden term") and "; artefacts named" in both


def test_a_misfit_taken_for_the_slowest_wander_is_a_cannot_tell():
    """One cycle (loading 0 -> 0.15 and back, 12 points per ramp at 1 s, 20 draws of white
    noise of SD 1): a smooth misfit that a model without hysteresis leaves, amplitude 4 of a
    half sine per ramp (RMS 2.8), opposite on loading and unloading, is taken by the noise
    model for a wander larger than the white part at the longest correlation it allows
    (half a ramp, 5.5 s) in at least 15 of 20 draws (17 measured): `none` or `explained`
    then carry a *cannot tell*.  White noise alone raises it in none of the 20 (measured:
    0); neither does any status that already names a misfit, nor recordings of repeated
    cycles, where the reproducibility test tells a misfit from wander."""
    from diagnosis.notes import slowest_wander_doubt

    per_ramp = 12
    x = np.linspace(0.0, 1.0, per_ramp)
    misfit = 4.0 * np.concatenate([np.sin(np.pi * x), -np.sin(np.pi * x[::-1])])
    branches = {"reproducible": {"repeats": "branches"}}
    said, white_said = 0, 0
    for seed in range(20):
        white = np.random.default_rng(seed).normal(size=2 * per_ramp)
        nm = fit_noise(_cycled_obs(misfit + white, per_ramp), misfit + white)
        doubt = slowest_wander_doubt("explained", branches, nm)
        said += bool(doubt)
        if doubt:
            assert "as slow as the noise model allows (5.5 s, half a ramp)" in doubt
            assert slowest_wander_doubt("unexplained", branches, nm) == ""
            assert slowest_wander_doubt("none", {"reproducible": {"repeats": "cycles"}},
                                        nm) == ""
        white_said += bool(slowest_wander_doubt(
            "none", branches, fit_noise(_cycled_obs(white, per_ramp), white)))
    assert said >= 15
    assert white_said == 0


def test_a_repeated_misfit_between_the_two_bars_is_a_cannot_tell():
    """Two cycles of 12 points per ramp, white noise of SD 1 whose level is known: the test
    of a misfit repeated at every cycle (10 columns) needs chi2 > 29.6 for p < 1e-3 and a
    gain > 10 ln 48 + 10 = 48.7 for the BIC margin.  A repeated half sine per ramp of
    amplitude 1.2, opposite on loading and unloading, falls between the two bars in most
    draws (median gain 38.8; measured: 13 of 20 draws); `none` or `explained` then carry a
    *cannot tell*, a status that already names a misfit does not.  White noise alone
    raises it in none of 20 (its rate is alpha = 1e-3 per case); a misfit of amplitude 3
    passes both bars (gain > 48.7 in every draw) and raises none either."""
    from diagnosis.noise import ChannelNoise, NoiseModel
    from diagnosis.notes import threshold_doubt
    from diagnosis.remaining import remaining

    per_ramp, n = 12, 48
    obs = _cycled_obs(np.zeros(n), per_ramp)
    nm = NoiseModel(obs, {("compression_tension", "stress"): ChannelNoise(white=1.0)})
    x = np.linspace(0.0, 1.0, per_ramp)
    shape = np.tile(np.concatenate([np.sin(np.pi * x), -np.sin(np.pi * x[::-1])]), 2)
    said = {0.0: 0, 1.2: 0, 3.0: 0}
    for seed in range(20):
        white = np.random.default_rng(seed).normal(size=n)
        for amp in said:
            rem = remaining(obs, amp * shape + white, nm)
            assert rem["reproducible"]["dof"] == 10
            doubt = threshold_doubt("explained", rem, 1e-3)
            said[amp] += bool(doubt)
            if doubt:
                assert 29.6 < rem["reproducible"]["gain"] < 10 * math.log(n) + 10
                assert "the misfit repeated at every cycle" in doubt
                assert threshold_doubt("partially explained", rem, 1e-3) == ""
    assert said[1.2] >= 10
    assert said[0.0] == 0
    assert said[3.0] == 0


def test_the_f_test_weighs_the_noise_by_where_the_gain_lies():
    """``nu_gain``: two series of 30 and 20 points whose noises have 27 and 17 degrees of
    freedom.  1 / nu = sum_s w_s^2 / nu_s with w_s the share of the gain on series s,
    capped at the row-weighted value 1 / ((30/50)^2 / 27 + (20/50)^2 / 17) = 43.97: a gain
    all on the short series is tested with its 17, all on the long one with its 27, one
    split evenly with 1 / (0.25 / 27 + 0.25 / 17) = 41.7, one in proportion to the
    series' dof (the largest value, 27 + 17 = 44) with the cap; a negative share counts
    as none."""
    from diagnosis.noise import nu_eff, nu_gain

    rng = np.random.default_rng(1)
    obs = _stress_and_torque(rng)
    dof = np.r_[np.full(30, 27.0), np.full(20, 17.0)]
    rows = 1.0 / (0.6**2 / 27 + 0.4**2 / 17)
    assert nu_eff(obs, dof) == pytest.approx(rows, rel=1e-12)
    short = np.r_[np.zeros(30), np.full(20, 0.5)]
    assert nu_gain(obs, dof, short) == pytest.approx(17.0, rel=1e-12)
    even = np.r_[np.full(30, 1.0 / 30), np.full(20, 1.0 / 20)]
    assert nu_gain(obs, dof, even) == pytest.approx(1.0 / (0.25 / 27 + 0.25 / 17), rel=1e-12)
    assert nu_gain(obs, dof, np.r_[np.ones(30), np.zeros(20)]) == pytest.approx(27.0)
    by_dof = np.r_[np.full(30, 27.0 / 30), np.full(20, 17.0 / 20)]
    assert nu_gain(obs, dof, by_dof) == pytest.approx(rows, rel=1e-12)
    assert nu_gain(obs, dof, np.r_[np.ones(30), -np.ones(20)]) == pytest.approx(27.0)
    assert nu_gain(obs, dof, np.r_[np.full(30, -1.0), np.ones(20)]) == pytest.approx(17.0)


def _low_pass(rng, n: int, sd: float, width: int) -> np.ndarray:
    """Gaussian noise of SD ``sd`` smoothed by a moving average over ``width`` samples
    (the instrument's filter), rescaled to SD ``sd``."""
    e = np.convolve(rng.standard_normal(n + width - 1), np.ones(width) / width, "valid")
    return sd * e / np.sqrt(1.0 / width)


def test_the_split_is_also_tested_against_the_noise_of_the_smooth_columns():
    """The split test where the noise model knows only the white part (SD 0.1, stated)
    and a low-pass filtered noise (SD 0.05, a moving average over 12 samples) puts more
    into the smooth directions than that model says, on a linear model (two material
    columns on two curves of two cycles).  Exact: the F test reported beside the split
    (``smooth_noise``) is the nested least-squares one, computed here with numpy alone
    (the split's chi-square gain per column over the gain of the repeated-misfit columns
    beyond it per column, F(dof, reference dof)).  Its point: over 100 draws without any
    split, the test against the noise model alone passes alpha = 0.01 in a quarter of
    them (measured 25), the F test in 4 (the filtered noise is not spread evenly over the
    smooth directions, so it is not exact, but near its level); bounds 15 and 8.  A true
    split of 0.3 between the tests on white noise is significant, and there the repeated
    misfit is too, so no second test is made."""
    from scipy import stats

    from diagnosis.remaining import remaining, reproducible_basis, shear_rows

    obs, p = _two_curves(40, 2)
    x = np.tile(np.linspace(0.0, 1.0, 40), len(obs) // 40)
    J = np.column_stack([p, p * x**2])
    names = ["mu_0", "alpha_0"]
    shear = shear_rows(obs)
    S = J * shear[:, None]
    B, how = reproducible_basis(obs)
    assert how == "cycles"
    nm = fit_noise(obs, np.zeros(len(obs)), stated={"stress": 0.1}, correlated=False,
                   drift=False)

    def chi2(cols, y):
        c, *_ = np.linalg.lstsq(cols, y, rcond=None)
        return float(np.sum((cols @ c - y) ** 2)) / 0.01

    def split_of(y):
        c, *_ = np.linalg.lstsq(J, y, rcond=None)
        return remaining(obs, J @ c - y, nm, alpha=0.01, prediction=J @ c, jacobian=J,
                         names=names)["split"]

    rng = np.random.default_rng(3)
    plain = f_test = 0
    for _ in range(100):
        y = J @ [1.0, 0.5] + rng.normal(0.0, 0.1, len(obs)) + np.concatenate(
            [_low_pass(rng, int(n), 0.05, 12) for n in np.bincount(shear.astype(int))[::-1]])
        out = split_of(y)
        plain += out["p_value"] < 0.01
        f_test += out["smooth_noise"]["p_value"] < 0.01
    gain = chi2(J, y) - chi2(np.hstack([J, S]), y)
    extra = chi2(np.hstack([J, S]), y) - chi2(np.hstack([J, S, B]), y)
    dof = np.linalg.matrix_rank(np.hstack([J, S, B])) - np.linalg.matrix_rank(
        np.hstack([J, S]))
    assert out["gain"] == pytest.approx(gain, rel=1e-6)
    assert out["smooth_noise"]["gain"] == pytest.approx(extra, rel=1e-6)
    assert out["smooth_noise"]["dof"] == dof
    f_ref = stats.f.sf(gain / 2 / (extra / dof), 2, dof)
    assert out["smooth_noise"]["p_value"] == pytest.approx(f_ref, rel=1e-6)
    assert plain >= 15 and f_test <= 8, (plain, f_test)
    # a true split, white noise: significant, and the repeated-misfit test finds it too,
    # so the smooth columns are no noise reference there
    theta = np.where(shear[:, None], [1.3, 0.8], [1.0, 0.5])
    y = np.sum(J * theta, axis=1) + np.random.default_rng(4).normal(0.0, 0.1, len(obs))
    out = split_of(y)
    assert out["significant"] and out["p_value"] < 1e-6 and "smooth_noise" not in out


def test_a_status_the_split_alone_decides_says_cannot_tell():
    """split_doubt: the doubt only where the split passes against the noise model, not
    against the smooth columns' noise, and decides the status (seed 7's world055: gain
    36.2 on 3, F p 0.0064, `unexplained` where `explained` without it); none where the
    second test passes, where there is no second test, or where the status is the same
    without the split."""
    from diagnosis.notes import split_doubt

    split = {"gain": 36.2, "dof": 3, "p_value": 1.5e-6, "significant": True,
             "smooth_noise": {"p_value": 0.0064, "significant": False, "gain": 78.6,
                              "dof": 32}}
    rem = {"split": split}
    said = split_doubt("unexplained", rem, "explained")
    assert "p = 0.0064" in said and "gain 36.2 on 3" in said and "(without it: explained)" in said
    assert split_doubt("unexplained", rem, "unexplained") == ""
    passed = {**split, "smooth_noise": {**split["smooth_noise"], "significant": True}}
    assert split_doubt("unexplained", {"split": passed}, "explained") == ""
    alone = {k: v for k, v in split.items() if k != "smooth_noise"}
    assert split_doubt("unexplained", {"split": alone}, "explained") == ""
    assert split_doubt("explained", {"split": {**split, "significant": False}},
                       "explained") == ""


def test_a_series_of_several_cycles_takes_a_wander_as_slow_as_a_cycle():
    """Wander slower than half a ramp (tau 15 s; 10 points at 1 s a ramp, cycles of 20 s,
    8 cycles, white SD 1, wander SD 1.5), with the misfit repeated at every cycle kept out
    (restricted ML): the noise model takes a correlation time beyond half a ramp (4.5 s,
    the bound of a series of one cycle) in most of 12 draws, and a constant offset, which a
    wander slower than half a ramp imitates, gains under it what it gains under the true
    covariance: chi2 with one degree of freedom, mean 1 (0.4-2.0 over the 12 draws;
    measured 1.1, and 1.4 under the true covariance). Held at half a ramp, as before
    open-world-33, the same draws give the offset a mean gain of 6.1."""
    from diagnosis.noise import cycle_duration
    from diagnosis.remaining import systematic_basis

    per_ramp, cycles = 10, 8
    t = np.arange(float(2 * per_ramp * cycles))
    lags = np.abs(t[:, None] - t[None, :])
    true_cov = 1.5**2 * np.exp(-lags / 15.0) + np.eye(len(t))
    taus, gains, true_gains = [], [], []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        r = rig_noise(t, RigNoise(white=1.0, wander=1.5, wander_s=15.0), rng)
        obs = _cycled_obs(r, per_ramp)
        assert cycle_duration(obs, np.arange(len(t))) == pytest.approx(20.0)
        nm = fit_noise(obs, r, drift=False, systematic=systematic_basis(obs))
        (cn,) = nm.params.values()
        taus.append(cn.corr_s)
        gains.append(_offset_gain(_engine_covariance(obs, cn), r))
        true_gains.append(_offset_gain(true_cov, r))
    assert np.median(taus) > 5.0
    assert 0.4 < np.mean(gains) < 2.0
    assert 0.4 < np.mean(true_gains) < 2.0


def test_white_noise_over_several_cycles_leaves_no_rival_noise_model():
    """The start at the slowest wander a cycle allows only helps choose: from white noise
    it ends at no wander at that bound, which differs in name only from the chosen wander
    of one sampling interval (white noise too) and must not be kept as a rival (the
    recordings would look undetermined). 30 draws of white noise, two cycles of 20 points
    a ramp, the repeated misfit kept out: a rival in at most 1 (measured: 0; 4 when the
    start's end could be a rival)."""
    from diagnosis.remaining import systematic_basis

    rivals = 0
    for seed in range(30):
        r = np.random.default_rng(seed).normal(0.0, 1.0, 80)
        obs = _cycled_obs(r, 20)
        rivals += bool(fit_noise(obs, r, systematic=systematic_basis(obs)).rivals)
    assert rivals <= 1


def test_an_offset_on_two_short_cycles_is_tested_right_when_the_noise_has_the_models_shape():
    """Two cycles of 11 points a ramp (44 points, the length of seed 7's control world062),
    white SD 1 beside a filter of SD 0.7 over 1.4 sampling intervals (the model's own shape:
    white + one Ornstein-Uhlenbeck part), the repeated misfit kept out: a constant offset
    gains under the fitted model what it gains under the true covariance, chi2 with one
    degree of freedom (mean 1; over 40 draws measured 1.13, 1.05 under the true covariance).
    Where the noise is not of that shape the fitted model inflates the gain, and no
    noise model of this one series calibrates it (benchmarks/noise_calibration.py)."""
    from diagnosis.remaining import systematic_basis

    per_ramp, draws = 11, 40
    t = np.arange(float(4 * per_ramp))
    lags = np.abs(t[:, None] - t[None, :])
    true_cov = np.eye(len(t)) + 0.7**2 * np.exp(-lags / 1.4)
    gains, true_gains = [], []
    for seed in range(draws):
        r = rig_noise(t, RigNoise(white=1.0, filtered=0.7, filter_s=1.4),
                      np.random.default_rng(seed))
        obs = _cycled_obs(r, per_ramp)
        (cn,) = fit_noise(obs, r, systematic=systematic_basis(obs)).params.values()
        gains.append(_offset_gain(_engine_covariance(obs, cn), r))
        true_gains.append(_offset_gain(true_cov, r))
    assert 0.5 < np.mean(gains) < 1.6
    assert 0.5 < np.mean(true_gains) < 1.6
