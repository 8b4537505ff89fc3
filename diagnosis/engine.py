"""Locate the mismatch, name the missing physics, model it, show the fit improve.

1. Base fit (one-term Ogden, nu0 fixed) by trust-region least squares on the residuals
   z = (prediction - recording) / sigma, sigma the noise of each (curve, channel) estimated
   from the second differences of the base residual (diagnosis.locate), so smooth misfit
   does not inflate it.  The FE model's discretisation error is estimated against the next
   finer mesh at the base optimum and added to every prediction (deferred correction), so
   that it is never mistaken for physics.
2. Locate: the base residual decomposed along the protocol's axes with chi-square and runs
   tests (diagnosis.locate).
3. Name: every candidate effect (diagnosis.effects) is fitted from the base fit, base and
   effect parameters together, FE in the loop with sensitivities.  Nested models compared
   by the likelihood-ratio statistic chi2_base - chi2_effect ~ chi2(k_effect) (Gaussian
   noise of known sigma) and by BIC = chi2 + k ln n.  An effect is significant when its LRT
   p-value is below ``alpha`` / (number of candidates) and its BIC beats the base by more
   than ``bic_margin`` ("very strong" evidence on the Kass-Raftery scale); the verdict is
   the significant effect of lowest BIC, or ``none``.  Two significant effects within
   ``bic_margin`` of each other cannot be told apart: the report says so and names the test
   that would separate them.
4. Model it: the winner's refit, residual RMS before/after against the noise, and the bias
   of the base parameters (mu, alpha) caused by the omission.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import optimize, stats

from . import locate as loc
from .effects import BASE_NAMES, library, separating_test

log = logging.getLogger(__name__)

BASE_BOUNDS = {"mu_0": (1e-3, 100.0), "alpha_0": (-60.0, 60.0)}


@dataclass
class Fit:
    effect: str
    names: list[str]
    values: dict
    chi2: float
    n: int
    prediction: np.ndarray
    z: np.ndarray
    nfev: int
    stderr: dict = field(default_factory=dict)

    @property
    def k(self) -> int:
        return len(self.names)

    @property
    def bic(self) -> float:
        return self.chi2 + self.k * math.log(self.n)

    @property
    def aic(self) -> float:
        return self.chi2 + 2 * self.k


def _bounds(names, effect=None):
    lo, hi = [], []
    for n in names:
        if n in BASE_BOUNDS:
            a, b = BASE_BOUNDS[n]
        else:
            e = effect
            i = e.names.index(n)
            a, b = e.lower[i], e.upper[i]
        lo.append(a)
        hi.append(b)
    return np.array(lo), np.array(hi)


def fit(sim, obs: pd.DataFrame, sigma: np.ndarray, start: dict, names: list[str], *,
        effect: str = "base", max_nfev: int = 20, effect_def=None) -> Fit:
    """Trust-region least squares of z = (y(values) - value) / sigma over ``names``."""
    if effect_def is None and effect != "base":
        effect_def = library(sim.kind)[effect]
    lo, hi = _bounds(names, effect_def)
    x0 = np.clip([start[n] for n in names], lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    fixed = {k: v for k, v in start.items() if k not in names}
    value = obs["value"].to_numpy(float)
    cache: dict = {}

    def evaluate(x):
        key = tuple(np.round(x, 14))
        if key not in cache:
            vals = dict(fixed, **dict(zip(names, x, strict=True)))
            y, J = sim.predict(vals, names)
            cache.clear()
            cache[key] = (y, J)
        return cache[key]

    def fun(x):
        y, _ = evaluate(x)
        return (y - value) / sigma

    def jac(x):
        _, J = evaluate(x)
        return J / sigma[:, None]

    res = optimize.least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf",
                                 x_scale="jac", max_nfev=max_nfev, xtol=1e-8, ftol=1e-8)
    vals = dict(fixed, **dict(zip(names, res.x, strict=True)))
    y, J = evaluate(res.x)
    z = (y - value) / sigma
    stderr = {}
    try:
        Jw = J / sigma[:, None]
        cov = np.linalg.pinv(Jw.T @ Jw)
        stderr = {n: float(math.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(names)}
    except np.linalg.LinAlgError:  # pragma: no cover
        pass
    return Fit(effect, list(names), vals, float(z @ z), len(z), y, z, int(res.nfev), stderr)


def initial_guess(obs: pd.DataFrame) -> dict:
    """mu from the small-strain slope of the torque-derived shear stress (tau = mu gamma)
    or of the nominal stress (P = 3 mu (lambda - 1)); alpha = -10."""
    mu = 1.0
    tor = obs[(obs.channel == "torque") & (obs.control > 0)]
    if len(tor):
        g = tor.nsmallest(3, "control")
        radius = obs.attrs.get("radius_mm", 4.0)
        tau = 2 * g["value"].to_numpy() / (math.pi * radius**3)
        mu = float(np.median(tau / g["control"].to_numpy()))
    else:
        st = obs[(obs.channel == "stress") & (np.abs(obs.control - 1) > 0)
                 & ~obs.curve.str.contains("shear")]
        if len(st):
            g = st.loc[np.abs(st.control - 1).nsmallest(3).index]
            mu = float(np.median(g["value"] / (3 * (g["control"] - 1))))
    return {"mu_0": float(np.clip(mu, 0.01, 50.0)), "alpha_0": -10.0}


def _sigma_guess(obs: pd.DataFrame) -> np.ndarray:
    peak = obs.groupby(["curve", "channel"])["value"].transform(lambda v: np.abs(v).max())
    return np.maximum(0.01 * peak.to_numpy(float), 1e-12)


@dataclass
class Diagnosis:
    base: Fit
    fits: dict
    sigma: np.ndarray
    located: pd.DataFrame
    verdict: str
    ranking: list
    ambiguous: list
    discretisation: dict
    elapsed_s: float
    obs: pd.DataFrame

    @property
    def winner(self) -> Fit:
        return self.fits.get(self.verdict, self.base)

    def rms(self, fit: Fit) -> dict:
        """Residual RMS per (curve, channel) in recording units and in units of the noise."""
        out = {}
        r = fit.prediction - self.obs["value"].to_numpy(float)
        for (c, ch), g in self.obs.groupby(["curve", "channel"], sort=False):
            i = g.index.to_numpy()
            out[f"{c}/{ch}"] = {"rms": float(np.sqrt(np.mean(r[i] ** 2))),
                                "noise": float(np.sqrt(np.mean(self.sigma[i] ** 2))),
                                "rms_over_noise": float(np.sqrt(np.mean(fit.z[i] ** 2)))}
        return out

    def to_json(self) -> dict:
        w = self.winner
        bias = {n: {"base": self.base.values[n], "refit": w.values[n],
                    "relative": (self.base.values[n] - w.values[n]) / abs(w.values[n])}
                for n in BASE_NAMES}
        return {
            "located": loc.summary(self.located)["located"],
            "verdict": self.verdict,
            "ranking": self.ranking,
            "ambiguous": self.ambiguous,
            "rms_before": float(np.sqrt(np.mean(self.base.z ** 2))),
            "rms_after": float(np.sqrt(np.mean(w.z ** 2))),
            "rms_unit": "noise standard deviations (1 = fit at the noise level)",
            "noise": {k: v["noise"] for k, v in self.rms(self.base).items()},
            "rms_by_curve_before": self.rms(self.base),
            "rms_by_curve_after": self.rms(w),
            "base_parameters": _plain(self.base.values),
            "refit_parameters": _plain(w.values),
            "refit_stderr": _plain(w.stderr),
            "base_bias": bias,
            "discretisation": self.discretisation,
            "elapsed_s": self.elapsed_s,
        }


def _plain(d: dict) -> dict:
    return {k: float(v) for k, v in d.items()}


def diagnose(sim, obs: pd.DataFrame, *, fine_sim=None, effects=None, alpha: float = 1e-3,
             bic_margin: float = 10.0, max_nfev: int = 15, comm=None,
             progress=None) -> Diagnosis:
    """Diagnose one specimen. ``sim``/``fine_sim``: simulators on the working mesh and on
    the next finer one (None: no discretisation correction, e.g. analytical models).
    With ``comm`` (MPI) the candidate fits are shared among the ranks."""
    t0 = time.perf_counter()
    obs = obs.reset_index(drop=True)
    names = list(BASE_NAMES)
    sigma = _sigma_guess(obs)
    base = fit(sim, obs, sigma, dict(initial_guess(obs), nu0=sim.nu0), names, max_nfev=40)
    disc = {"corrected": False}
    if fine_sim is not None:
        y_fine, _ = fine_sim.predict(base.values, [])
        sim.correction = np.zeros(len(obs))
        y_coarse, _ = sim.predict(base.values, [])
        sim.correction = y_fine - y_coarse
        disc = {"corrected": True, "refinement": sim.refinement,
                "reference_refinement": fine_sim.refinement}
    sigma = loc.estimate_noise(obs, base.prediction - obs["value"].to_numpy(float))
    base = fit(sim, obs, sigma, base.values, names, max_nfev=20)
    if fine_sim is not None:
        rel = np.abs(sim.correction) / sigma
        disc.update(max_over_noise=float(rel.max()), rms_over_noise=float(
            np.sqrt(np.mean(rel**2))))
    located = loc.locate(obs, base.prediction - obs["value"].to_numpy(float), sigma)
    if progress:
        progress("base")
    lib = library(sim.kind)
    cands = [e for e in (effects or lib) if e in lib]
    rank, size = (comm.rank, comm.size) if comm is not None else (0, 1)
    mine = {}
    for i, name in enumerate(cands):
        if i % size != rank:
            continue
        e = lib[name]
        best = None
        for s in e.starts:
            start = dict(base.values, **s)
            if name == "compressibility":
                start["nu0"] = min(sim.nu0 - 0.04, s["nu0"])
            try:
                f = fit(sim, obs, sigma, start, names + list(e.names), effect=name,
                        max_nfev=max_nfev, effect_def=e)
            except Exception as exc:  # a failed candidate is reported, not fatal
                log.warning("candidate %s from %s failed: %s", name, s, exc)
                continue
            if best is None or f.chi2 < best.chi2:
                best = f
        if best is not None:
            mine[name] = best
        if progress:
            progress(name)
    fits = mine
    if comm is not None and size > 1:
        fits = {}
        for part in comm.allgather(mine):
            fits.update(part)
    ranking = []
    m = max(len(cands), 1)
    for name, f in fits.items():
        dchi2 = base.chi2 - f.chi2
        p = float(stats.chi2.sf(max(dchi2, 0.0), f.k - base.k))
        ranking.append({"effect": name, "bic": f.bic, "delta_bic": f.bic - base.bic,
                        "aic": f.aic, "chi2": f.chi2, "lrt": dchi2, "p_value": p,
                        "significant": bool(p < alpha / m and base.bic - f.bic > bic_margin),
                        "parameters": _plain({n: f.values[n] for n in lib[name].names}),
                        "stderr": _plain({n: f.stderr.get(n, float("nan"))
                                          for n in lib[name].names})})
    ranking.sort(key=lambda r: r["bic"])
    significant = [r for r in ranking if r["significant"]]
    verdict = significant[0]["effect"] if significant else "none"
    ambiguous = []
    if significant:
        for r in significant[1:]:
            if r["bic"] - significant[0]["bic"] < bic_margin:
                ambiguous.append({"effects": [verdict, r["effect"]],
                                  "delta_bic": r["bic"] - significant[0]["bic"],
                                  "separating_test": separating_test(verdict, r["effect"])})
    for a in ambiguous:
        log.warning("%s and %s cannot be told apart with these tests (dBIC %.1f); %s",
                    *a["effects"], a["delta_bic"], a["separating_test"])
    return Diagnosis(base, fits, sigma, located, verdict, ranking, ambiguous, disc,
                     time.perf_counter() - t0, obs)
