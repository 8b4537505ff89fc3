"""Physics outside the library, modelled once the diagnosis has located it.

When the final model leaves a stiffness trend with time (:mod:`diagnosis.remaining`), no
library effect is named beside it (:func:`diagnosis.engine.decide`); what the library
lacks may be a stiffness drifting over the session (tissue degrading, drying, warming).
:func:`drift_model` fits that model jointly with the base parameters and says how much
of the misfit it takes, as a candidate, not a verdict: other physics can leave a trend
too.  A new model of left-out physics goes here, beside it.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd

from brain_fe.parameters import Param
from simulators.base import Prediction

from .fitting import Fit, UnsolvableStart, fit
from .remaining import trend_basis, trend_span

log = logging.getLogger(__name__)

DRIFT = Param("drift")  # relative change of the stiffness over the longest cycled test


def _level(i: int) -> Param:
    """The stiffness of test ``i`` (> 0) relative to the first test's."""
    return Param("level", i)


class _Drifting:
    """``sim`` with every load of test i scaled by level_i (1 + drift (t - mid) / span), 1
    for the first test, the rate term in each test of several cycles
    (:func:`diagnosis.remaining.trend_basis`): a stiffness drifting over the session, one
    rate within the tests and a level per test (the recordings do not give the order of
    the tests or the time between them).  Exact for a one-term Ogden specimen at fixed
    nu0 under displacement control (every load is proportional to mu) to first order in
    the drift; an approximation beside anything else."""

    def __init__(self, sim, obs: pd.DataFrame):
        self.sim = sim
        self.tau = trend_basis(obs, np.ones(len(obs)))[:, 0]
        curves = list(dict.fromkeys(obs["curve"]))
        self.test = obs["curve"].map({c: i for i, c in enumerate(curves)}).to_numpy()
        self.levels = [_level(i) for i in range(1, len(curves))]

    def predict(self, values, wrt=()):
        values = {Param.parse(k): v for k, v in values.items()}
        wrt = tuple(Param.parse(q) for q in wrt)
        d = values.pop(DRIFT, 0.0)
        lv = np.ones(len(self.levels) + 1)
        for i, q in enumerate(self.levels, 1):
            lv[i] = values.pop(q, 1.0)
        own = {DRIFT, *self.levels}
        p = self.sim.predict(values, [q for q in wrt if q not in own])
        level = lv[self.test]
        scale = level * (1.0 + d * self.tau)
        cols = iter((p.jacobian * scale[:, None]).T)
        J = [p.y * level * self.tau if q == DRIFT
             else np.where(self.test == q.index, p.y * (1.0 + d * self.tau), 0.0)
             if q in own else next(cols) for q in wrt]
        return Prediction(p.y * scale, np.column_stack(J) if J else
                          np.zeros((len(p.y), 0)), wrt)


class _DriftBounds:
    @staticmethod
    def bounds(name):
        return (-0.9, 0.9) if name == DRIFT else (0.2, 5.0)


def drift_model(sim, obs: pd.DataFrame, base: Fit, sd: np.ndarray,
                max_nfev: int = 20) -> dict:
    """The base model with its stiffness drifting (:class:`_Drifting`: one rate within the
    tests, a level per test), fitted jointly with the base parameters (weights ``sd``):
    the relative change over the longest test of several cycles with its standard error,
    the parameters and the RMS misfit in units of ``sd``; {} without such a test or when
    the model cannot be solved."""
    obs = obs.reset_index(drop=True)
    model = _Drifting(sim, obs)
    span = trend_span(obs)
    if span <= 0:
        return {}
    start = {**base.values, DRIFT: 0.0, **{q: 1.0 for q in model.levels}}
    try:
        f = fit(model, obs, sd, start, [*base.names, DRIFT, *model.levels],
                effect="drift", max_nfev=max_nfev, effect_def=_DriftBounds)
    except (RuntimeError, UnsolvableStart) as exc:
        log.warning("the drift model could not be fitted: %s", exc)
        return {}
    return {"change": float(f.values[DRIFT]), "change_se": float(f.stderr.get(DRIFT, math.nan)),
            "span_s": span, "rms_after": math.sqrt(f.chi2 / f.n),  # f.z: residual / sd
            "extra_parameters": 1 + len(model.levels),
            "parameters": {str(k): float(v) for k, v in f.values.items()}}
