"""Two-stage inverse identification of (mu, alpha) for one specimen or region average.

Stage 1 minimises the objective on the surrogates (scipy ``least_squares``, trust-region
reflective, bounded by the surrogates' training range, started from the best point of a
coarse grid).  Stage 2 restarts from the stage-1 optimum with the FE model in the loop and
its exact parameter sensitivities.  Both are :class:`~simulators.base.Simulator`\\ s of the
same observation table, and both work in z = (ln mu, alpha), which balances the two
parameters' scales; nu0 is held fixed (kappa moves with mu).

Uncertainty: with the residual variance s^2 = ||r||^2 / (n - 2), cov = s^2 (J^T J)^-1 from
the FE Jacobian at the optimum gives standard errors and the mu-alpha correlation; a
warning is raised when the parameters are not identifiable from the tests used.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from brain_fe.parameters import alpha as ALPHA
from brain_fe.parameters import mu as MU
from brain_fe.vocabulary import COMPRESSION_TENSION
from simulators.base import PredictionMemo, Simulator
from simulators.coordinates import NU0

from .objective import curve_norms, gavrus_errors, residuals

log = logging.getLogger(__name__)

ALPHA_LIMIT = 80.0
MU_LIMITS = (1e-3, 1e3)  # kPa
FITS = (COMPRESSION_TENSION, "all")
WRT = (MU(0), ALPHA(0))


class IdentifiabilityWarning(UserWarning):
    pass


@dataclass
class Stage:
    name: str
    mu_kPa: float
    alpha: float
    objective: float  # sum_t eps_t^2
    errors: dict  # eps_t per test key
    history: list = field(default_factory=list)  # (evaluation, mu, alpha, objective)
    evaluations: int = 0
    protocol_solves: int = 0
    wall_time_s: float = 0.0
    message: str = ""


@dataclass
class Identification:
    fit: str
    tests: list
    stage1: Stage
    stage2: Stage
    mu_se_kPa: float
    alpha_se: float
    correlation: float
    identifiable: bool

    @property
    def mu_kPa(self) -> float:
        return self.stage2.mu_kPa

    @property
    def alpha(self) -> float:
        return self.stage2.alpha


def _values(z, nu0: float) -> dict:
    return {MU(0): float(np.exp(z[0])), ALPHA(0): float(z[1]), NU0: nu0}


def _least_squares(pred: PredictionMemo, z0, zlo, zhi, *, history: list, **kw):
    """least_squares in z = (ln mu, alpha) on the Gavrus residuals of ``pred.sim``."""
    sim = pred.sim
    obs = sim.obs
    norms = curve_norms(obs)

    def fun(z):
        y = pred(_values(z, sim.nu0), WRT).y
        r = residuals(obs, y)
        point = (float(np.exp(z[0])), float(z[1]))
        if not history or tuple(history[-1][1:3]) != point:
            history.append((len(history) + 1, *point, float(r @ r)))
        return r

    def jac(z):
        J = pred(_values(z, sim.nu0), WRT).jacobian / norms[:, None]
        return J * np.array([np.exp(z[0]), 1.0])  # d/d ln mu

    return least_squares(fun, z0, jac=jac, bounds=(zlo, zhi), method="trf",
                         x_scale=[1.0, 10.0], **kw)


def stage_surrogate(sim: Simulator, *, grid: int = 9) -> Stage:
    """Stage 1 on the surrogates: grid start, then bounded trust-region least squares."""
    lo, hi = sim.bounds()
    zlo, zhi = np.array([np.log(lo[0]), lo[1]]), np.array([np.log(hi[0]), hi[1]])
    t0 = time.perf_counter()
    best = None
    for lm in np.linspace(zlo[0], zhi[0], grid):
        for a in np.linspace(zlo[1], zhi[1], grid):
            r = residuals(sim.obs, sim.predict(_values([lm, a], sim.nu0)).y)
            if best is None or r @ r < best[0]:
                best = (r @ r, np.array([lm, a]))
    # keep the start strictly inside the box (trust-region reflective needs it)
    z0 = np.clip(best[1], zlo + 1e-6 * (zhi - zlo), zhi - 1e-6 * (zhi - zlo))
    hist: list = []
    res = _least_squares(PredictionMemo(sim), z0, zlo, zhi, history=hist, ftol=1e-12, xtol=1e-10,
                         gtol=1e-12, max_nfev=400)
    mu, alpha = float(np.exp(res.x[0])), float(res.x[1])
    y = sim.predict(_values(res.x, sim.nu0)).y
    errs = gavrus_errors(sim.obs, y)
    return Stage("surrogate", mu, alpha, float(sum(e**2 for e in errs.values())), errs,
                 history=hist, evaluations=grid * grid + len(hist), protocol_solves=0,
                 wall_time_s=time.perf_counter() - t0, message=res.message)


def _alpha_bounds(alpha0: float) -> tuple[float, float]:
    # alpha = 0 is excluded (W ~ 1/alpha^2): stay on the side the start lies on
    return (-ALPHA_LIMIT, -0.1) if alpha0 < 0 else (0.1, ALPHA_LIMIT)


def stage_fe(sim: Simulator, mu0: float, alpha0: float, *,
             max_evaluations: int = 30) -> tuple[Stage, np.ndarray, np.ndarray]:
    """Stage 2: FE in the loop with exact sensitivities.  Returns the stage, the residual
    vector and the Jacobian d r / d(mu, alpha) at the optimum."""
    a_lo, a_hi = _alpha_bounds(alpha0)
    zlo = np.array([np.log(MU_LIMITS[0]), a_lo])
    zhi = np.array([np.log(MU_LIMITS[1]), a_hi])
    t0 = time.perf_counter()
    solves0 = sim.solves
    hist: list = []
    z0 = np.clip([np.log(mu0), alpha0], zlo + 1e-9, zhi - 1e-9)
    # xtol 1e-5: a parameter change of 1e-5 (relative) is ~1 % of a typical standard error
    # with 1 % noise, so further FE solves would not change the answer
    memo = PredictionMemo(sim)
    res = _least_squares(memo, z0, zlo, zhi, history=hist, ftol=1e-6, xtol=1e-5, gtol=1e-8,
                         max_nfev=max_evaluations)
    mu, alpha = float(np.exp(res.x[0])), float(res.x[1])
    pred = memo(_values(res.x, sim.nu0), WRT)
    r = residuals(sim.obs, pred.y)
    J = pred.jacobian / curve_norms(sim.obs)[:, None]
    errs = gavrus_errors(sim.obs, pred.y)
    st = Stage("fe", mu, alpha, float(sum(e**2 for e in errs.values())), errs, history=hist,
               evaluations=len(hist), protocol_solves=sim.solves - solves0,
               wall_time_s=time.perf_counter() - t0, message=res.message)
    return st, r, J


def uncertainty(r: np.ndarray, J: np.ndarray, *, corr_limit: float = 0.99,
                cond_limit: float = 1e10) -> tuple[float, float, float, bool]:
    """Standard errors of (mu, alpha), their correlation and an identifiability flag."""
    n, p = J.shape
    s2 = float(r @ r) / max(n - p, 1)
    JTJ = J.T @ J
    scale = np.sqrt(np.diag(JTJ))
    ok = bool(np.all(scale > 0))
    if ok:
        Jn = JTJ / np.outer(scale, scale)
        ok = np.linalg.cond(Jn) < cond_limit
    if not ok:
        return float("nan"), float("nan"), float("nan"), False
    cov = s2 * np.linalg.inv(JTJ)
    se = np.sqrt(np.diag(cov))
    corr = float(cov[0, 1] / (se[0] * se[1]))
    return float(se[0]), float(se[1]), corr, abs(corr) < corr_limit


def identify(surrogate_sim: Simulator, fe_sim: Simulator, *, fit: str = "all"
             ) -> Identification:
    """Both stages for one specimen / region on the simulators' observation table (the
    curves of ``fit``: compression/tension only, or all)."""
    tests = list(dict.fromkeys(fe_sim.obs["curve"]))
    s1 = stage_surrogate(surrogate_sim)
    s2, r, J = stage_fe(fe_sim, s1.mu_kPa, s1.alpha)
    mu_se, alpha_se, corr, ok = uncertainty(r, J)
    if not ok:
        warnings.warn(f"fit {fit!r}: mu and alpha are not separately identifiable from "
                      f"{', '.join(tests)} (correlation {corr:.3f})",
                      IdentifiabilityWarning, stacklevel=2)
    return Identification(fit, tests, s1, s2, mu_se, alpha_se, corr, ok)


def select(obs: pd.DataFrame, fit: str) -> pd.DataFrame:
    """The observation rows a fit uses."""
    if fit == "all":
        used = obs
    elif fit == COMPRESSION_TENSION:
        used = obs[obs["test"] == COMPRESSION_TENSION]
    else:
        raise ValueError(f"fit must be one of {', '.join(FITS)}, got {fit!r}")
    if used.empty:
        raise ValueError(f"no recorded curves for fit {fit!r}")
    return used.reset_index(drop=True)
