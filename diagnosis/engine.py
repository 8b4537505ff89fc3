"""Locate the mismatch, name the missing physics, model it, show the fit improve.

1. Base fit (one-term Ogden, nu0 fixed) by trust-region least squares on the residuals
   z = (prediction - recording) / sigma, sigma the noise of each (curve, channel) estimated
   from the second differences of the base residual (diagnosis.noise), so smooth misfit
   does not inflate it.  The FE model's discretisation error is estimated against the next
   finer mesh at the base optimum and added to every prediction (deferred correction), so
   that it is never mistaken for physics.
2. Locate: the base residual decomposed along the protocol's axes with chi-square and runs
   tests (diagnosis.noise).
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

import contextlib
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from brain_fe.parallel import SharedCounter, dynamic_items
from simulators.coordinates import NU0

from . import locate as loc
from .effects import BASE_NAMES, check_effects, library, separating_test
from .fitting import Fit, fit, initial_guess, sigma_guess
from .noise import estimate_noise
from .screen import data_scales, design, score

log = logging.getLogger(__name__)


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
        bias = {str(n): {"base": self.base.values[n], "refit": w.values[n],
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
    return {str(k): float(v) for k, v in d.items()}


def diagnose(sim, obs: pd.DataFrame, *, fine_sim=None, effects=None, alpha: float = 1e-3,
             bic_margin: float = 10.0, max_nfev: int = 15, comm=None,
             progress=None) -> Diagnosis:
    """Diagnose one specimen. ``sim``/``fine_sim``: simulators on the working mesh and on
    the next finer one (None: no discretisation correction, e.g. analytical models).
    With ``comm`` (MPI) the candidate fits are shared among the ranks."""
    t0 = time.perf_counter()
    obs = obs.reset_index(drop=True)
    with _sharing(sim, comm), _sharing(fine_sim, comm):  # the ranks share every curve
        base, sigma, disc, J_base = _base(sim, fine_sim, obs, comm)
    located = loc.locate(obs, base.prediction - obs["value"].to_numpy(float), sigma)
    if progress:
        progress("base")
    names = list(BASE_NAMES)
    lib = library(sim.kind)
    check_effects(effects, sim.kind)
    cands = list(effects or lib)

    def share(items, work, cost):
        """``work`` on the ``items``, most expensive first (by the estimated ``cost``),
        each taken by whichever rank of ``comm`` is free; every rank gets every result,
        in the order of ``items``."""
        order = sorted(range(len(items)), key=lambda i: -cost(items[i]))
        if comm is None or comm.size == 1:
            done = [(i, work(items[i])) for i in order]
        else:
            counter = SharedCounter(comm)
            done = [(i, work(items[i])) for i in dynamic_items(order, counter)]
            counter.free()
            done = [x for part in comm.allgather(done) for x in part]
        return [r for _, r in sorted(done, key=lambda x: x[0])]

    # score every candidate at the base fit; fit those that could earn their place
    scales = data_scales(obs, base.values)
    points = [(n, p) for n in cands for p in design(lib[n], sim.nu0, scales)]
    scored = share(points, lambda it: _score_or_none(sim, obs, sigma, base, lib[it[0]],
                                                     it[1], names, J_base),
                   lambda it: HISTORY_COST if it[0] in HISTORY else 1.0)
    best: dict = {}
    for s in scored:
        if s is not None and (s.effect not in best or s.lm > best[s.effect].lm):
            best[s.effect] = s
    n_obs, m = len(obs), max(len(cands), 1)
    to_fit = [n for n in cands if n in best and best[n].lm >= SCREEN_FRACTION * _needed(
        len(lib[n].names), n_obs, alpha / m, bic_margin)]
    if progress:
        progress(f"screened: fitting {', '.join(to_fit) or 'nothing'}")
    results = share(to_fit, lambda name: _fit_or_none(sim, obs, sigma, best[name].start,
                                                      names + list(lib[name].names), name,
                                                      RANKING_NFEV, lib[name]),
                    lambda name: best[name].seconds)
    fits = {n: f for n, f in zip(to_fit, results, strict=True) if f is not None}
    leader = min(fits.values(), key=lambda f: f.bic, default=None)
    if leader is not None and not leader.converged:  # the winner's fit runs to the end
        more = _fit_or_none(sim, obs, sigma, leader.values, leader.names, leader.effect,
                            max_nfev, lib[leader.effect])
        if more is not None and more.chi2 <= leader.chi2:
            fits[leader.effect] = more
    ranking = []
    for name, f in fits.items():
        dchi2 = base.chi2 - f.chi2
        p = float(stats.chi2.sf(max(dchi2, 0.0), f.k - base.k))
        ranking.append({"effect": name, "bic": f.bic, "delta_bic": f.bic - base.bic,
                        "aic": f.aic, "chi2": f.chi2, "lrt": dchi2, "p_value": p,
                        "significant": bool(p < alpha / m and base.bic - f.bic > bic_margin),
                        "parameters": _plain({n: f.values[n] for n in lib[name].names}),
                        "stderr": _plain({n: f.stderr.get(n, float("nan"))
                                          for n in lib[name].names}),
                        "score": best[name].lm})
    for name in cands:
        if name not in fits:
            s = best.get(name)
            ranking.append({"effect": name, "bic": float("nan"), "delta_bic": float("nan"),
                            "aic": float("nan"), "chi2": float("nan"), "lrt": float("nan"),
                            "p_value": float("nan"), "significant": False,
                            "parameters": {}, "stderr": {},
                            "score": s.lm if s is not None else float("nan"),
                            "screened_out": True})
    ranking.sort(key=lambda r: (math.isnan(r["bic"]), r["bic"], -r["score"]))
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


SCREEN_FRACTION = 0.25  # fit a candidate whose score reaches this share of what it needs
# Effects that follow the recorded path (history) cost about this many elastic evaluations
HISTORY = ("viscoelastic", "mullins")
HISTORY_COST = 4.0
RANKING_NFEV = 8  # evaluations of a competitor's fit (the leader's fit is then completed)


def _needed(k: int, n: int, p: float, bic_margin: float) -> float:
    """The chi-square reduction an effect with k parameters needs to be significant."""
    return max(float(stats.chi2.isf(p, k)), k * math.log(n) + bic_margin)


def _base(sim, fine_sim, obs, comm):
    """Base fit, discretisation correction, noise estimate, refit and the base Jacobian."""
    names = list(BASE_NAMES)
    sigma = sigma_guess(obs)
    base = fit(sim, obs, sigma, {**initial_guess(obs), NU0: sim.nu0}, names, max_nfev=40)
    disc = {"corrected": False}
    if fine_sim is not None:
        y_fine, _ = fine_sim.predict(base.values, [])
        sim.correction = np.zeros(len(obs))
        y_coarse, _ = sim.predict(base.values, [])
        sim.correction = y_fine - y_coarse
        disc = {"corrected": True, "refinement": sim.refinement,
                "reference_refinement": fine_sim.refinement}
    sigma = estimate_noise(obs, base.prediction - obs["value"].to_numpy(float))
    base = fit(sim, obs, sigma, base.values, names, max_nfev=20)
    if fine_sim is not None:
        rel = np.abs(sim.correction) / sigma
        disc.update(max_over_noise=float(rel.max()), rms_over_noise=float(
            np.sqrt(np.mean(rel**2))))
    return base, sigma, disc, sim.predict(base.values, names).jacobian


@contextlib.contextmanager
def _sharing(sim, comm):
    """Let the ranks of ``comm`` share the curves of ``sim``'s predictions, where the
    simulator can (the FE model); otherwise every rank computes everything."""
    if sim is None or not hasattr(sim, "sharing"):
        yield sim
        return
    with sim.sharing(comm):
        yield sim


def _score_or_none(sim, obs, sigma, current, effect, point, names, J_base):
    try:
        return score(sim, obs, sigma, current, effect, point, names, J_base)
    except Exception as exc:  # a model that cannot be solved there scores nothing
        log.warning("score of %s at %s failed: %s", effect.name, point, exc)
        return None


def _fit_or_none(sim, obs, sigma, start, names, effect, max_nfev, effect_def):
    try:
        return fit(sim, obs, sigma, start, names, effect=effect, max_nfev=max_nfev,
                   effect_def=effect_def)
    except Exception as exc:  # a failed candidate is reported, not fatal
        log.warning("candidate %s failed: %s", effect, exc)
        return None
