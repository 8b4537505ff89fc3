"""A rig's noise stated in full (``--noise`` JSON), checked against an independent
reference: the generator's draws."""

import argparse
import json
import math

import numpy as np
import pandas as pd
import pytest

from diagnosis.noise import ChannelNoise, fit_noise, statement
from recordings.noise import RigNoise, rig_noise


def _obs(t: np.ndarray, per_ramp: int) -> pd.DataFrame:
    """One (curve, channel) series of ramps of ``per_ramp`` points, loading and unloading
    in turn, recorded at the times ``t``."""
    k = np.arange(len(t)) // per_ramp
    return pd.DataFrame({"specimen": "s", "curve": "torsion_0.2", "test": "torsion",
                         "amplitude": 0.2, "channel": "torque",
                         "branch": np.where(k % 2, "unloading", "loading"),
                         "cycle": k // 2 + 1, "control": 1.0, "time_s": t, "value": 0.0})


RIG = RigNoise(white=0.3, filtered=0.2, filter_s=2.0, wander=0.4, wander_s=25.0, drift=0.01,
               quantum=0.05)


def test_a_noise_stated_in_full_is_held_whole():
    """Stated in full, nothing of a channel's noise is fitted: the model is the statement,
    its degrees of freedom infinite (the tests are chi-square tests), and the report says
    it was stated."""
    from diagnosis.open_world import noise_statement

    t = np.arange(40.0)
    r = rig_noise(t, RIG, np.random.default_rng(0))
    stated = noise_statement({"torque": RIG})
    nm = fit_noise(_obs(t, 10), r, stated=stated)
    (cn,) = nm.params.values()
    assert cn == stated["torque"]
    assert cn.white == pytest.approx(math.sqrt(0.3**2 + 0.05**2 / 12))
    assert (cn.corr, cn.corr_s, cn.drift, cn.more) == (0.2, 2.0, 0.01, ((0.4, 25.0),))
    assert np.isinf(nm.dof).all() and math.isinf(nm.nu_level())
    assert nm.rival() is None
    (d,) = nm.describe().values()
    assert d["stated"] == "in full" and d["more_correlated"] == [[0.4, 25.0]]
    assert statement(d) == cn  # a diagnosis.json's noise_model states itself


def test_the_stated_covariance_is_the_one_the_rig_draws():
    """The engine's covariance of a noise stated in full (filter, wander, drift and rounding,
    :func:`diagnosis.open_world.noise_statement`) against the covariance of 6000 series
    drawn by the generator (:func:`recordings.noise.rig_noise`, rounded to the quantum around
    an offset): every entry within 0.03 (Monte Carlo error of a covariance of variances
    ~0.3-0.5: ~0.01)."""
    from diagnosis.noise import noise_series
    from diagnosis.open_world import noise_statement

    t = np.array([0.0, 0.5, 1.0, 3.0, 7.0, 15.0, 30.0, 31.0])
    rng = np.random.default_rng(1)
    x = np.array([RIG.quantum * np.round((1.234 + rig_noise(t, RIG, rng)) / RIG.quantum)
                  - 1.234 for _ in range(6000)])
    (series,) = noise_series(_obs(t, 4))
    engine = series.covariance(noise_statement({"torque": RIG})["torque"])
    np.testing.assert_allclose(engine, np.cov(x, rowvar=False), atol=0.03)


def test_a_noise_statement_parses_and_refuses():
    assert statement(0.2) == 0.2
    full = statement({"white": 0.1, "correlated": 0.2, "correlation_time_s": 3,
                      "drift_per_s": 0.001, "more_correlated": [[0.5, 40]]})
    assert full == ChannelNoise(white=0.1, corr=0.2, corr_s=3.0, drift=0.001,
                                more=((0.5, 40.0),))
    assert statement({"white": 0.1}) == ChannelNoise(white=0.1)
    for bad, why in ((0, "positive"), (True, "positive"), ({"corr": 1}, "unknown key 'corr'"),
                     ({"correlated": 0.1}, "'white'"), ({"white": -1}, "white"),
                     ({"white": 1, "more_correlated": [1, 2]}, "list of \\[SD, seconds\\]"),
                     ({"white": 1, "correlation_time_s": 0}, "correlation_time_s")):
        with pytest.raises(ValueError, match=why):
            statement(bad)


def test_the_noise_file_states_a_rig_in_full_for_every_specimen(tmp_path):
    """``--noise noise.json``: a channel's value may be its whole noise; the specimen
    ``"*"`` stands for every specimen the file does not list; a bad statement is one line
    naming the file, the specimen and the channel."""
    from brainmech.args import noise_option
    from diagnosis.batch import noise_of

    f = tmp_path / "noise.json"
    rig = {"white": 0.02, "correlated": 0.03, "correlation_time_s": 20.0,
           "drift_per_s": 1e-4}
    f.write_text(json.dumps({"*": {"torque": rig}, "a": {"stress": 0.5}}))
    opt = noise_option(str(f))
    assert noise_of(opt, "a") == {"stress": 0.5}
    assert noise_of(opt, "b") == {"torque": ChannelNoise(0.02, 0.03, 20.0, 1e-4)}
    f.write_text(json.dumps({"a": {"torque": {"white": 0.02, "wander": 1}}}))
    with pytest.raises(argparse.ArgumentTypeError, match="unknown key 'wander'") as exc:
        noise_option(str(f))
    msg = str(exc.value)
    assert str(f) in msg and "'a'" in msg and "'torque'" in msg and "\n" not in msg



def _linear_case():
    """60 torque rows of y = 2 a + 3 b plus the rig's whole noise (``RIG``, seeded), for
    the linear model :class:`_Linear`: times, observations, the two columns, the noise
    statement and the noise model it states."""
    from diagnosis.open_world import noise_statement

    t = np.arange(60.0)
    obs = _obs(t, 15)
    a, b = np.sin(np.pi * (t % 15) / 14), t / 60.0
    stated = noise_statement({"torque": RIG})
    obs["value"] = 2.0 * a + 3.0 * b + rig_noise(t, RIG, np.random.default_rng(4))
    return t, obs, a, b, stated, fit_noise(obs, np.zeros(len(t)), stated=stated)


class _Linear:
    """y = mu a + alpha b: a model the generalised least squares solve in closed form."""

    def __init__(self, a, b, refuse=False):
        self.a, self.b, self.refuse = a, b, refuse

    def predict(self, values, wrt=()):
        from brain_fe.parameters import Param
        from simulators.base import Prediction

        if self.refuse:
            raise RuntimeError("Newton did not converge")
        y = values[Param("mu", 0)] * self.a + values[Param("alpha", 0)] * self.b
        return Prediction(y, np.zeros((len(y), 0)), ())


def test_every_comparison_judges_a_fit_at_its_gls_step():
    """:func:`diagnosis.selection.gls_step` on a linear model with the rig's noise stated in
    full: from the ordinary least-squares fit (what a diagonal fit finds), one evaluated
    step reaches the generalised least-squares optimum, against the closed form with the
    explicit covariance (x = (A' C^-1 A)^-1 A' C^-1 v), to rtol 1e-9; from that optimum no
    step is taken; where the model refuses the stepped point the fit's own residual
    stands."""
    from diagnosis.effects import BASE_NAMES
    from diagnosis.fitting import Fit
    from diagnosis.noise import noise_series
    from diagnosis.selection import Context, gls_step
    from diagnosis.sharing import share_with

    t, obs, a, b, stated, nm = _linear_case()
    v = obs["value"].to_numpy()
    (series,) = noise_series(obs)
    C = series.covariance(stated["torque"])
    A = np.c_[a, b]

    def chi2_at(x):
        r = A @ x - v
        return float(r @ np.linalg.solve(C, r))

    x_gls = np.linalg.solve(A.T @ np.linalg.solve(C, A), A.T @ np.linalg.solve(C, v))
    x_ols = np.linalg.lstsq(A, v, rcond=None)[0]
    assert chi2_at(x_ols) > chi2_at(x_gls) + 1.0  # the two metrics' optima differ here

    def fitted(x):
        return Fit("base", list(BASE_NAMES), dict(zip(BASE_NAMES, x, strict=True)), 0.0,
                   len(t), A @ x, None, 0, jacobian=A)

    def ctx(refuse=False):
        return Context(_Linear(a, b, refuse), obs, np.ones(len(t)), {}, list(BASE_NAMES),
                       1e-3, 10.0, 20, share_with(None))

    c, f = ctx(), fitted(x_ols)
    z = c.judged(nm, f)
    assert z @ z == pytest.approx(chi2_at(x_gls), rel=1e-9)
    np.testing.assert_allclose(c.judged_prediction(nm, f), A @ x_gls, rtol=1e-9)
    np.testing.assert_allclose(gls_step(c, nm, f), A @ x_gls, rtol=1e-9)
    z = ctx().judged(nm, fitted(x_gls))
    assert z @ z == pytest.approx(chi2_at(x_gls), rel=1e-9)
    f = fitted(x_ols)
    assert gls_step(ctx(refuse=True), nm, f) is f.prediction


class _Broken(_Linear):
    """A model whose solves meet an internal error (not the model's own failure)."""

    def __init__(self, a, b):
        super().__init__(a, b)
        self.calls = 0

    def predict(self, values, wrt=()):
        self.calls += 1
        raise OSError("disk full")


def test_a_step_that_met_an_internal_error_is_judged_where_it_was_fitted():
    """:meth:`Context.judge_all`: a GLS step whose solve raises an internal error is left
    out once, recorded in ``errors``, and the fit is then judged at its own prediction
    (its whitened residual exactly, no second attempt that would raise outside the work
    sharing)."""
    from diagnosis.effects import BASE_NAMES
    from diagnosis.fitting import Fit
    from diagnosis.selection import Context
    from diagnosis.sharing import share_with

    t, obs, a, b, _, nm = _linear_case()
    A = np.c_[a, b]
    x = np.linalg.lstsq(A, obs["value"].to_numpy(), rcond=None)[0]
    f = Fit("base", list(BASE_NAMES), dict(zip(BASE_NAMES, x, strict=True)), 0.0,
            len(t), A @ x, None, 0, jacobian=A)
    errors: list = []
    sim = _Broken(a, b)
    c = Context(sim, obs, np.ones(len(t)), {}, list(BASE_NAMES), 1e-3, 10.0, 20,
                share_with(None, sim, errors), None, errors)
    c.judge_all(nm, [f, f])
    assert sim.calls == 1 and len(errors) == 1 and "OSError" in errors[0]
    np.testing.assert_array_equal(c.judged(nm, f), nm.whiten(f.residual(obs)))
    assert sim.calls == 1
