"""Weighted least-squares fits of a simulator's parameters to an observation table.

z = (prediction - recording) / sigma, sigma the noise of each row; trust-region reflective
least squares (scipy) with the simulator's Jacobian, within the bounds of the base
parameters and of each effect (:mod:`diagnosis.effects`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import optimize

from brain_fe.parameters import Param
from brain_fe.vocabulary import torque_mNmm
from recordings.observations import peak_per_series
from simulators.base import PredictionMemo

from .effects import library

log = logging.getLogger(__name__)

BASE_BOUNDS = {Param("mu", 0): (1e-3, 100.0), Param("alpha", 0): (-60.0, 60.0)}
# Start values of alpha tried in turn when the model cannot be solved at the first one
# (alpha = -10, brain-like, locks up at large compression): a generic design, not a range
ALPHA_STARTS = (-10.0, 2.0, -2.0, 10.0)


class UnsolvableStart(ValueError):
    """The model cannot be solved at the start values of a fit (one line: which fit, why)."""


def solvable_start(sim, start: dict) -> dict:
    """``start`` with the first alpha of (its own, *ALPHA_STARTS) at which ``sim`` can be
    solved along the whole protocol; :class:`UnsolvableStart` when there is none."""
    alpha = Param("alpha", 0)
    start = {Param.parse(k): v for k, v in start.items()}
    why = ""
    for a in dict.fromkeys((start[alpha], *ALPHA_STARTS)):
        trial = {**start, alpha: a}
        try:
            y, _ = sim.predict(trial, [])
        except RuntimeError as exc:
            why = str(exc)
            log.info("start alpha = %g cannot be solved (%s)", a, exc)
            continue
        if np.isfinite(y).all():
            return trial
    raise UnsolvableStart(f"the base model cannot be solved along this protocol at any start "
                          f"value (alpha in {', '.join(f'{a:g}' for a in ALPHA_STARTS)}): "
                          f"{why or 'non-finite prediction'}")


@dataclass
class Fit:
    effect: str
    names: list[Param]
    values: dict
    chi2: float
    n: int
    prediction: np.ndarray
    z: np.ndarray
    nfev: int
    stderr: dict = field(default_factory=dict)
    converged: bool = True  # False when the evaluation budget ended the fit
    # trial points the model could not be solved at (refused: the trust region shrank
    # there); a fit that met many may have stopped at the edge of what the model can
    # follow instead of at the optimum, with a tolerance reached all the same
    refused: int = 0
    jacobian: np.ndarray | None = None  # d prediction / d parameters at the optimum
    seconds: float = 0.0  # wall time of the fit

    @property
    def k(self) -> int:
        return len(self.names)

    @property
    def bic(self) -> float:
        return self.chi2 + self.k * math.log(self.n)

    @property
    def aic(self) -> float:
        return self.chi2 + 2 * self.k

    def residual(self, obs: pd.DataFrame) -> np.ndarray:
        """Prediction minus recording, per row of ``obs``."""
        return self.prediction - obs["value"].to_numpy(float)

    def rms(self, obs: pd.DataFrame, sd: np.ndarray, rows=slice(None)) -> float:
        """RMS of the residual in units of ``sd`` (per row), over ``rows``."""
        return float(np.sqrt(np.mean((self.residual(obs)[rows] / sd[rows]) ** 2)))


def _bounds(names, effect=None):
    lo, hi = [], []
    for n in names:
        a, b = BASE_BOUNDS[n] if n in BASE_BOUNDS else effect.bounds(n)
        lo.append(a)
        hi.append(b)
    return np.array(lo), np.array(hi)


def fit(sim, obs: pd.DataFrame, sigma: np.ndarray, start: dict, names: list, *,
        effect: str = "base", max_nfev: int = 20, effect_def=None) -> Fit:
    """Trust-region least squares of z = (y(values) - value) / sigma over ``names``."""
    t0 = time.perf_counter()
    names = [Param.parse(n) for n in names]
    start = {Param.parse(k): v for k, v in start.items()}
    if effect_def is None and effect != "base":
        effect_def = library(sim.kind)[effect]
    lo, hi = _bounds(names, effect_def)
    x0 = np.clip([start[n] for n in names], lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    fixed = {k: v for k, v in start.items() if k not in names}
    value = obs["value"].to_numpy(float)
    pred = PredictionMemo(sim)
    refused = set()  # distinct trial points the model could not solve

    def evaluate(x):
        return pred({**fixed, **dict(zip(names, x, strict=True))}, names)

    def fun(x):
        try:
            return (evaluate(x).y - value) / sigma
        except RuntimeError as exc:  # a trial point the model cannot follow (Newton fails)
            # is refused: non-finite residuals make the trust region shrink and try again
            log.info("fit of %s: trial point refused (%s)", effect, exc)
            refused.add(tuple(np.asarray(x, float)))
            return np.full(value.shape, np.inf)

    def jac(x):
        return evaluate(x).jacobian / sigma[:, None]

    if not np.isfinite(fun(x0)).all():  # cached: least_squares' first call costs nothing
        raise UnsolvableStart(f"the {effect} model cannot be solved at its start values")
    res = optimize.least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf",
                                 x_scale="jac", max_nfev=max_nfev, xtol=1e-8, ftol=1e-8)
    vals = {**fixed, **dict(zip(names, res.x, strict=True))}
    p = evaluate(res.x)
    z = (p.y - value) / sigma
    stderr = {}
    try:
        Jw = p.jacobian / sigma[:, None]
        cov = np.linalg.pinv(Jw.T @ Jw)
        stderr = {n: float(math.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(names)}
    except np.linalg.LinAlgError:  # pragma: no cover
        pass
    return Fit(effect, list(names), vals, float(z @ z), len(z), p.y, z, int(res.nfev), stderr,
               converged=res.status > 0, refused=len(refused), jacobian=p.jacobian,
               seconds=time.perf_counter() - t0)


def initial_guess(obs: pd.DataFrame) -> dict:
    """mu from the small-strain slope of the torque-derived shear stress (tau = mu gamma)
    or of the nominal stress (P = 3 mu (lambda - 1)); alpha = -10."""
    mu = 1.0
    tor = obs[(obs.channel == "torque") & (obs.control > 0)]
    if len(tor):
        g = tor.nsmallest(3, "control")
        radius = obs.attrs.get("radius_mm", 4.0)
        tau = g["value"].to_numpy() / torque_mNmm(1.0, radius)
        mu = float(np.median(tau / g["control"].to_numpy()))
    else:
        st = obs[(obs.channel == "stress") & (np.abs(obs.control - 1) > 0)
                 & ~obs.curve.str.contains("shear")]
        if len(st):
            g = st.loc[np.abs(st.control - 1).nsmallest(3).index]
            mu = float(np.median(g["value"] / (3 * (g["control"] - 1))))
    return {Param("mu", 0): float(np.clip(mu, 0.01, 50.0)), Param("alpha", 0): -10.0}


def sigma_guess(obs: pd.DataFrame) -> np.ndarray:
    """1 % of each series' peak: the weights of the first base fit."""
    return np.maximum(0.01 * peak_per_series(obs), 1e-12)

