r"""Score (Lagrange-multiplier) screening of candidate effects at the current fit.

An effect nests the current model at its *neutral point* (beta = 0, d = 0, mu_1 = 0, nu0 at
its assumed value, a stiff glue layer, zero offsets).  There, with the whitened residual
z = (y - data) / sigma and the whitened Jacobian J = [J_model, J_effect], one Gauss-Newton
step predicts the chi-square the effect can remove:

.. math::  LM = \|P_{[J_m\,J_e]} z\|^2 - \|P_{J_m} z\|^2

(the score statistic; chi-square with as many degrees of freedom as active effect
parameters when the effect is absent).  Parameters that act only through another one
(tau when beta = 0, m when d = 0, alpha_1 when mu_1 = 0) have zero columns at the neutral
point; they are set from a fixed generic *design* instead, scaled by the data themselves
(the duration of a ramp, the energy the specimen reaches), never by a benchmark's ranges,
and the design point with the largest LM is kept.  Its Gauss-Newton step is the start of
the effect's fit, and an effect whose LM is far below what significance would need is not
fitted at all.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd

from brain_fe.parameters import Param

# Fixed generic design of the parameters that act only through another (see docstring)
TAU_OVER_RAMP = (0.1, 1.0, 10.0)  # relaxation time / duration of a ramp
M_OVER_ENERGY = (0.01, 0.1, 1.0)  # softening energy scale / energy reached
ALPHA_1 = (-20.0, -5.0, 5.0, 20.0)  # exponent of a second Ogden term
STIFF_LOG10_K = 4.0  # a glue layer 1e4 kPa/mm stiff acts as glued (k -> infinity)
FRICTIONLESS_LOG10_K = -3.0  # the glued-cube candidate's neutral end: no friction


@dataclass
class Score:
    effect: str
    lm: float  # predicted chi-square reduction
    dof: int  # active effect parameters
    start: dict  # Gauss-Newton start of the effect's fit (all parameters)
    point: dict  # the neutral design point the score was taken at
    seconds: float = 0.0  # cost of the prediction (a guide to the cost of the fit)


def data_scales(obs: pd.DataFrame, values: dict) -> dict:
    """The time and energy scales the generic design is built on: the median duration of a
    ramp [s] and mu (max strain)^2 [kPa], the isochoric energy the specimen reaches."""
    t = obs["time_s"].to_numpy(float)
    ramp = []
    for _, g in obs.groupby(["curve", "channel", "cycle", "branch"], sort=False):
        tt = g["time_s"].to_numpy(float)
        if tt.size > 1 and np.isfinite(tt).all():
            ramp.append(tt.max() - tt.min())
    t_ramp = float(np.median(ramp)) if ramp and np.isfinite(t).all() else 15.0
    curve = obs["curve"].astype(str)
    shear = curve.str.startswith(("torsion", "simple_shear")).to_numpy()
    ctl = obs["control"].to_numpy(float)
    strain = np.where(shear, np.abs(ctl) / math.sqrt(3.0), np.abs(ctl - 1.0))
    mu = float(values.get(Param("mu", 0), 1.0))
    return {"t_ramp": max(t_ramp, 1e-6), "energy": max(mu * float(np.max(strain)) ** 2, 1e-9)}


def design(effect, nu0: float, scales: dict) -> list[dict]:
    """Neutral design points of an effect: its parameters at their neutral values, those
    that act only through another (listed in :data:`NUISANCE`) from the generic design."""
    names = {str(n) for n in effect.names}
    if names == {"beta_0", "log10_tau_0"}:
        return [{"beta_0": 0.0, "log10_tau_0": math.log10(f * scales["t_ramp"])}
                for f in TAU_OVER_RAMP]
    if names == {"softening", "log10_softening_m"}:
        return [{"softening": 0.0, "log10_softening_m": math.log10(f * scales["energy"])}
                for f in M_OVER_ENERGY]
    if names == {"mu_1", "alpha_1"}:
        return [{"mu_1": 0.0, "alpha_1": a} for a in ALPHA_1]
    if names == {"nu0"}:
        return [{"nu0": nu0}]
    if names == {"log10_k"}:
        k = FRICTIONLESS_LOG10_K if effect.name == "glued_ends" else STIFF_LOG10_K
        return [{"log10_k": k}]
    return [{str(n): 0.0 for n in effect.names}]  # offsets: zero


# Parameters with no effect at the neutral point (they act through another): not scored
NUISANCE = {Param("log10_tau", 0), Param("log10_softening_m"), Param("alpha", 1)}


def score(sim, obs: pd.DataFrame, sigma: np.ndarray, current, effect, point: dict,
          base_names, base_jacobian: np.ndarray) -> Score:
    """The score statistic of ``effect`` at the design ``point`` added to the ``current``
    fit (whose parameters ``base_names`` move too, with ``base_jacobian`` the current
    model's Jacobian with respect to them: at the neutral point it is the effect model's
    too), and the Gauss-Newton start."""
    pt = {Param.parse(k): float(v) for k, v in point.items()}
    values = {**current.values, **pt}
    scored = [n for n in effect.names if n not in NUISANCE]
    names = list(base_names) + scored
    t0 = time.perf_counter()
    pred = sim.predict(values, scored)
    seconds = time.perf_counter() - t0
    z = (pred.y - obs["value"].to_numpy(float)) / sigma
    J = np.column_stack([base_jacobian, pred.jacobian]) / sigma[:, None]
    nb = len(base_names)
    norms = np.linalg.norm(J, axis=0)
    scale = max(float(norms[:nb].max()) if nb else 1.0, 1e-300)
    active = [j for j in range(len(names)) if j < nb or norms[j] > 1e-9 * scale]
    Ja = J[:, active] / np.where(norms[active] > 0, norms[active], 1.0)
    step, *_ = np.linalg.lstsq(Ja, -z, rcond=None)
    full = float(z @ z - np.sum((z + Ja @ step) ** 2))
    Jb = J[:, :nb] / np.where(norms[:nb] > 0, norms[:nb], 1.0)
    sb, *_ = np.linalg.lstsq(Jb, -z, rcond=None)
    base = float(z @ z - np.sum((z + Jb @ sb) ** 2))
    start = dict(values)
    d = step / np.where(norms[active] > 0, norms[active], 1.0)
    for j, dj in zip(active, d, strict=True):
        start[names[j]] = values[names[j]] + float(dj)  # the fit clips it to the bounds
    return Score(effect.name, max(full - base, 0.0), len(active) - nb, start, point,
                 seconds)
