"""Which effects earn their place: forward selection with backward re-tests.

One *round* adds at most one effect to the current model (the base, then base + the
effects selected so far):

1. every remaining candidate is scored at the current fit (:mod:`diagnosis.screen`) and
   those that could matter are fitted together with the current model's parameters;
2. the noise model (:mod:`diagnosis.noise`) is estimated from the residual of the best of
   these fits, the closest thing to pure noise, and every comparison of the round is made
   under it: with whitened residuals, chi2 = z.z, the likelihood-ratio statistic
   LRT = chi2_current - chi2_candidate and BIC = chi2 + k ln n.  The noise was estimated
   from these same recordings with nu effective degrees of freedom
   (:meth:`NoiseModel.nu_level`; infinite for a stated noise without a slow part), so
   LRT / k ~ F(k, nu), not chi2(k) / k: on a short
   recording (tens of points) a misfit that a noise level estimated too low makes look
   large is not taken for an effect (the tests of what remains, :mod:`diagnosis.remaining`,
   were F tests already); for hundreds of points the two agree;
3. a candidate is *significant* when p < alpha / m (Bonferroni over the m candidates) and
   its BIC beats the current model's by more than the margin; the lowest-BIC significant one
   is added, and once the model holds two or more effects every one of them, the new one
   too, is re-tested in the presence of the others (refitted without it from the joint
   fit's values; dropped when it no longer earns its place: ``engine._retest``).

The rounds stop when nothing is significant or ``max_effects`` are in.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from .effects import parameter_names
from .fitting import BASE_BOUNDS, Fit, UnsolvableStart, fit
from .noise import lrt_p_value
from .screen import at_point, design, design_scales, neutral_point, score

log = logging.getLogger(__name__)

SCREEN_FRACTION = 0.25  # fit a candidate whose score reaches this share of what it needs
# Effects that follow the recorded path (history) cost about this many elastic evaluations
HISTORY = ("viscoelastic", "mullins")
HISTORY_COST = 4.0
RANKING_NFEV = 8  # evaluations of a competitor's fit (the leader's fit is then completed)
# Effects that cannot be combined (they model the same parameters)
EXCLUSIVE = {frozenset({"artefacts", "glued_ends"})}
# A candidate's model failing to follow the data (Newton, the linear solver, a refused
# start, a protocol the model cannot express): the candidate is left out of the round.
# Anything else (a timeout, an OSError, a bug) is an internal error: it escapes to the
# work sharing (sharing.share_with), which leaves the item out too but records it, and the
# diagnosis says it is incomplete
MODEL_FAILURES = (RuntimeError, ValueError, ArithmeticError, np.linalg.LinAlgError)
ALPHA = 1e-3  # significance level of an effect (Bonferroni over the round's candidates)
BIC_MARGIN = 10.0  # and the BIC improvement it must bring


def chi2_needed(k: int, m: int, n: int, alpha: float = ALPHA,
                bic_margin: float = BIC_MARGIN, nu: float = math.inf) -> float:
    """The chi-square reduction k extra parameters need to be significant among m
    candidates with n observations: p < alpha / m (:func:`lrt_p_value`, with the noise
    estimated with ``nu`` degrees of freedom; infinite: known) and a BIC gain above the
    margin."""
    test = (k * float(stats.f.isf(alpha / m, k, nu)) if math.isfinite(nu)
            else float(stats.chi2.isf(alpha / m, k)))
    return max(test, k * math.log(n) + bic_margin)


@dataclass
class Context:
    """What every round needs: the problem, its rules and how to share work."""

    sim: object
    obs: object
    weights: np.ndarray  # sigma per row for the fits (diagonal)
    lib: dict
    base_names: list
    alpha: float
    bic_margin: float
    max_nfev: int
    share: object  # share(items, work, cost) -> results (MPI-aware)
    stated: dict | None = None
    errors: list = field(default_factory=list)  # internal errors met (the same on every rank)
    # (fit, noise) -> (fit, noise, prediction, whitened residual) of :meth:`judged`; the
    # objects are held with it
    _judged: dict = field(default_factory=dict, repr=False)

    def _keep(self, noise, f: Fit, y: np.ndarray) -> tuple:
        z = noise.whiten(np.asarray(y, float) - self.obs["value"].to_numpy(float))
        self._judged[(id(f), id(noise))] = hit = (f, noise, y, z)
        return hit

    def _hit(self, noise, f: Fit) -> tuple:
        hit = self._judged.get((id(f), id(noise)))
        return hit if hit is not None else self._keep(noise, f, gls_step(self, noise, f))

    def judged(self, noise, f: Fit) -> np.ndarray:
        """``f``'s whitened residual under ``noise`` where every comparison and test reads
        it: at the better of ``f`` and its base parameters' step of generalised least
        squares under ``noise``, evaluated (:func:`gls_step`).  Computed once per pair."""
        return self._hit(noise, f)[3]

    def judged_prediction(self, noise, f: Fit) -> np.ndarray:
        """The prediction :meth:`judged` reads ``f`` at (``f.prediction`` or its step)."""
        return self._hit(noise, f)[2]

    def judge_all(self, noise, fits) -> None:
        """:meth:`judged` for several fits at once, their steps shared among the ranks
        (not inside :func:`diagnosis.sharing.sharing`, whose solves are collective).  A
        step that met an internal error (recorded in ``errors`` by the sharing, the same
        on every rank) is not tried again: ``f`` is judged where it was fitted."""
        todo = list({id(f): f for f in fits
                     if (id(f), id(noise)) not in self._judged}.values())
        ys = self.share(todo, lambda f: gls_step(self, noise, f),
                        lambda f: HISTORY_COST if any(e in f.effect for e in HISTORY)
                        else 1.0)
        for f, y in zip(todo, ys, strict=True):
            self._keep(noise, f, f.prediction if y is None else y)

    def chi2(self, noise, f: Fit) -> float:
        z = self.judged(noise, f)
        return float(z @ z)

    def nu(self, noise, f0: Fit, f1: Fit) -> float:
        """The F test's noise degrees of freedom for the gain of ``f1`` over ``f0`` under
        ``noise``, weighted by the series the gain lies on (``NoiseModel.nu_of_gain``);
        infinite without a noise model."""
        if noise is None:
            return math.inf
        z0, z1 = (self.judged(noise, f) for f in (f0, f1))
        return noise.nu_of_gain(z0**2 - z1**2)

    def needed(self, k: int, m: int, nu: float = math.inf) -> float:
        """The chi-square reduction k extra parameters need to be significant under a
        noise estimated with ``nu`` degrees of freedom (infinite: the chi-square bar, the
        lower one, which the screen uses: it rules out only what could not pass even
        with the noise known)."""
        return chi2_needed(k, m, len(self.obs), self.alpha, self.bic_margin, nu)


# Shares of the Gauss-Newton step tried in turn by :func:`gls_step`
GLS_STEPS = (1.0, 0.5)


def gls_step(ctx: Context, noise, f: Fit) -> np.ndarray:
    """The prediction at the better (in z.z under ``noise``) of ``f`` and a step of its
    base parameters (``ctx.base_names``) toward their optimum under ``noise``: the
    Gauss-Newton step of generalised least squares, within the bounds, evaluated by one
    solve (halved once if it does not lower z.z); ``f.prediction`` where no step does.

    The fits weigh each row by its SD alone (diagonal: :func:`diagnosis.fitting.fit`);
    the comparisons whiten by the whole noise model, correlated in time.  A fit is then
    not the optimum of the metric it is judged in, and an effect's refit can gain what the
    base's own parameters would have gained under that metric (measured: a control of
    three torsion cycles with drift, its noise stated in full, where a 681 s relaxation
    gained 63 in chi-square, the bar 21, and the truth sat 52 below the base fit).  Every
    fit of a comparison takes the step, so both sides are judged nearer their optimum in
    that metric.  The step is evaluated, not predicted: from a fit its budget cut short
    (a round's candidates), a linear prediction credited 1000 in chi-square that no fit
    reached (real single tension ramps, 65 noise SD off the base model), while an
    evaluated point is a model the data were compared with.  An effect's own parameters
    stay as fitted."""
    z = noise.whiten(f.residual(ctx.obs))
    cols = [i for i, q in enumerate(f.names) if q in set(ctx.base_names)]
    if f.jacobian is None or not cols or not np.isfinite(z).all():
        return f.prediction
    J = np.asarray(f.jacobian, float)[:, cols]
    if not np.isfinite(J).all():
        return f.prediction
    names = [f.names[i] for i in cols]
    dx = np.linalg.lstsq(noise.whiten_jacobian(J), -z, rcond=None)[0]
    lo, hi = np.array([BASE_BOUNDS[q] for q in names], float).T
    x0 = np.array([f.values[q] for q in names], float)
    value = ctx.obs["value"].to_numpy(float)
    best, y_best = z, f.prediction
    for share in GLS_STEPS:
        x = np.clip(x0 + share * dx, lo, hi)
        if np.allclose(x, x0, rtol=1e-12, atol=0.0):
            break
        try:
            y = ctx.sim.predict({**f.values, **dict(zip(names, x, strict=True))}, ()).y
        except MODEL_FAILURES as exc:  # a point the model cannot follow: not taken
            log.info("GLS step of %s not solved (%s)", f.effect, exc)
            continue
        zs = noise.whiten(np.asarray(y, float) - value)
        if np.isfinite(zs).all() and zs @ zs < best @ best:
            best, y_best = zs, np.asarray(y, float)
            break
    return y_best


@dataclass
class Round:
    current: list  # effects of the model the round starts from
    scores: dict  # effect -> Score
    fits: dict  # effect -> Fit of current + effect
    table: list  # per candidate: chi2, lrt, p, bic, significant ...
    added: str | None = None
    dropped: list = field(default_factory=list)
    noise: object = None
    failed: list = field(default_factory=list)  # fitted but the model could not be solved
    unscored: list = field(default_factory=list)  # no design point could be solved
    # the candidates later rounds offer, read from the first round (fitted, failed, or
    # with a two-sided score that passes the screen: run_round)
    alive: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)  # wall time of the round's stages
    # when the recordings leave the noise undetermined (NoiseModel.rivals): the series,
    # and the effect the round adds under the chosen noise and under the rival (or None)
    noise_rival: dict = field(default_factory=dict)
    # where a series repeats and the candidate the round would add under its own noise
    # gains less than its BIC bar under the noise with only the current model's columns
    # kept out: it,
    # what the round adds instead (or None), its LRT under each and the BIC bar
    # (diagnosis.engine._blind_checked)
    noise_blind: dict = field(default_factory=dict)

    def timings(self) -> dict:
        """Wall time of the scores and fits [s] (with MPI: of the whole rank group) and
        the cost of each candidate's fit (on the rank that made it) with its evaluations."""
        return {**{k: round(v, 2) for k, v in self.seconds.items()},
                "fit_per_candidate": {e: {"s": round(f.seconds, 2), "evaluations": f.nfev}
                                      for e, f in self.fits.items()}}


def _fit(ctx: Context, start: dict, effects: list, label: str, nfev: int,
         fallback: dict | None = None):
    """The fit of ``effects`` from ``start``, or None when the model cannot follow the
    data.  ``fallback``: a point the model was solved at (a score's design point, with
    the current fit's values): when ``start`` cannot be solved, the fit starts part of
    the way back to it, then at it (:data:`BACK_OFF`).  A Gauss-Newton step from a design
    point can land where the model's Newton solver fails (a strong relaxation at a short
    time); the effect is then fitted from nearer where it was scored rather than left out
    of every round (open-world-32: seed 7's world043, a viscoelastic + Mullins pair whose
    viscoelastic fit failed at its start, answered ``unexplained``)."""
    names = parameter_names(ctx.lib, effects, ctx.base_names)
    tries = [start] + ([] if fallback is None else [_toward(fallback, start, s)
                                                     for s in BACK_OFF])
    for i, x0 in enumerate(tries):
        try:
            return fit(ctx.sim, ctx.obs, ctx.weights, x0, names, effect=label,
                       max_nfev=nfev, effect_def=Union(ctx.lib, effects))
        except UnsolvableStart as exc:
            if i + 1 < len(tries):
                log.info("fit of %s: %s; starting nearer the design point", label, exc)
                continue
            log.warning("fit of %s failed: %s", label, exc)
        except MODEL_FAILURES as exc:  # a model that cannot follow the data is reported
            log.warning("fit of %s failed: %s", label, exc)
        return None
    return None


# Where a fit starts when the Gauss-Newton start cannot be solved: the share of the step
# from the design point kept, in turn (0: the design point, solved already)
BACK_OFF = (0.5, 0.0)


def _toward(point: dict, start: dict, share: float) -> dict:
    """``start`` with each parameter ``point`` also holds moved back to ``point`` by
    1 - ``share`` of the way."""
    return {k: float(point[k]) + share * (float(v) - float(point[k])) if k in point
            else v for k, v in start.items()}


class Union:
    """The bounds of several effects' parameters, as one effect for :func:`fit`."""

    def __init__(self, lib, effects):
        self._by_name = {n: lib[e] for e in effects for n in lib[e].names}

    def bounds(self, name):
        return self._by_name[name].bounds(name)


def run_round(ctx: Context, current: Fit, current_effects: list, candidates: list,
              J_current: np.ndarray, progress=None, first: Round | None = None) -> Round:
    """Score and fit every candidate added to the current model.  After the first round
    (``first``), only the candidates it screened in are considered (fitted, failed to
    fit, or with a two-sided score that would have passed: ``alive``), each at the design
    point whose fit won there (:func:`second_start`; else the best scoring one), and at
    its neutral point when that one was of finite size: an effect with no score at the
    base fit is not unmasked by another effect in practice, and every later round follows
    the recorded path of a history model, where a score costs several seconds."""
    obs, sim = ctx.obs, ctx.sim
    t0 = time.perf_counter()
    names = parameter_names(ctx.lib, current_effects, ctx.base_names)
    if first is None:
        scales = design_scales(sim, obs, current.values)
        points = [(e, p) for e in candidates for p in design(ctx.lib[e], sim.nu0, scales)]
    else:
        # fitted there, or screened in and failed (the model could not follow it from
        # the base fit; from another effect's fit it may), or kept alive (run_round's
        # ``alive``)
        candidates = [e for e in candidates if e in first.alive]
        points = [(e, first.scores[e].point) for e in candidates]
        # and at its neutral point too when the one that won there is of finite size (a
        # lower nu0): beside another effect the current fit may ask for the effect where
        # the base fit did not, which the score at the neutral point sees and one step
        # from a finite point may not (an open-world compressibility beside a glue layer:
        # score 0 from nu0 0.45, LRT 37 when fitted from the assumed nu0)
        points += [(e, n) for e, p in points
                   if ctx.lib[e].of_finite_size(p, sim.nu0)
                   and (n := neutral_point(ctx.lib[e], sim.nu0)) is not None]

    def one_score(item):
        try:
            return score(sim, obs, ctx.weights, current, ctx.lib[item[0]], item[1], names,
                         J_current)
        except MODEL_FAILURES as exc:  # a model that cannot be solved there scores nothing
            log.warning("score of %s at %s failed: %s", item[0], item[1], exc)
            return None

    scored = ctx.share(points, one_score,
                       lambda it: HISTORY_COST if it[0] in HISTORY else 1.0)
    best: dict = {}  # per effect, its best design point: by the one-sided score, a tie
    # (none of its points can gain within the bounds) by the two-sided one
    free: dict = {}  # per effect, its best two-sided score
    for s in scored:
        if s is not None and (s.effect not in best or (s.lm, s.lm_free)
                              > (best[s.effect].lm, best[s.effect].lm_free)):
            best[s.effect] = s
        if s is not None:
            free[s.effect] = max(free.get(s.effect, 0.0), s.lm_free)
    m = max(len(candidates), 1)
    needed = {e: ctx.needed(len(ctx.lib[e].names), m) for e in best}
    to_fit = [e for e in candidates if e in best and best[e].lm >= SCREEN_FRACTION
              * needed[e]]
    # what later rounds offer: the candidates fitted here (or failed to be), and those
    # whose direction could gain were it not for the sign their bound forbids at the base
    # fit; beside another effect the sign may turn (Budday's CR: a second Ogden term that
    # asks for a negative mu_1 at the base fit gains 1121 beside the offsets)
    alive = [e for e in candidates if e in to_fit
             or (e in free and free[e] >= SCREEN_FRACTION * needed[e])]
    starts = [(e, best[e]) for e in to_fit]
    starts += [(e, s) for e in to_fit
               if (s := second_start(scored, best[e], needed[e])) is not None]
    t1 = time.perf_counter()
    if progress:
        progress(f"+{'+'.join(current_effects) or 'base'}: fitting {', '.join(to_fit) or '-'}")
    label = {e: "+".join([*current_effects, e]) for e in to_fit}
    results = ctx.share(starts, lambda it: _fit(ctx, it[1].start, [*current_effects, it[0]],
                                                label[it[0]], RANKING_NFEV,
                                                at_point(current.values, it[1].point)),
                        lambda it: it[1].seconds)
    fits: dict = {}
    for (e, sc), f in zip(starts, results, strict=True):  # the better of an effect's starts
        if f is not None and (e not in fits or f.chi2 < fits[e].chi2):
            fits[e] = f
            best[e] = sc  # later rounds start from the design point that won
    failed = [e for e in to_fit if e not in fits]
    seconds = {"scores": t1 - t0, "fits": time.perf_counter() - t1}
    log.info("round from %s: %d design points scored in %.1f s, %d candidates fitted in "
             "%.1f s", "+".join(current_effects) or "base", len(points), seconds["scores"],
             len(to_fit), seconds["fits"])
    unscored = [e for e in candidates if e not in best]
    if unscored:
        log.warning("no design point of %s could be solved: not scored, not fitted",
                    ", ".join(unscored))
    return Round(list(current_effects), best, fits, [], failed=failed, seconds=seconds,
                 unscored=unscored, alive=alive)


def second_start(scored: list, best, needed: float):
    """A second start for an effect whose best-scoring design point is far from linear (the
    Gauss-Newton step of one of its parameters too long to be trusted, so the fit starts
    at the point itself), or None: the best-scoring of its other design points that could
    earn a place by itself, one whose step was trusted first.  A far-from-linear point may
    promise gains its neighbourhood does not hold (a stiff glue layer, when the data need
    a soft one behind a ridge of the misfit), so the effect's fit is run from both starts
    and the better one stands.  Not for history effects, whose fits cost several elastic
    ones each (their design varies only the parameter a score cannot see)."""
    if not best.held or best.effect in HISTORY:
        return None
    other = [s for s in scored if s is not None and s.effect == best.effect
             and s is not best and s.lm >= SCREEN_FRACTION * needed]
    return max(other, key=lambda s: (not s.held, s.lm)) if other else None


def compare(ctx: Context, rnd: Round, current: Fit, m: int, noise) -> list:
    """The round's table under ``noise``: chi2, LRT p, BIC and significance per fit."""
    ctx.judge_all(noise, [current, *rnd.fits.values()])
    c0 = ctx.chi2(noise, current)
    n = len(ctx.obs)
    table = []
    for e, f in rnd.fits.items():
        k = len(ctx.lib[e].names)
        c1 = ctx.chi2(noise, f)
        lrt = c0 - c1
        p = lrt_p_value(lrt, k, ctx.nu(noise, current, f))
        dbic = (c1 + (current.k + k) * math.log(n)) - (c0 + current.k * math.log(n))
        table.append({"effect": e, "chi2": c1, "lrt": lrt, "p_value": p, "delta_bic": dbic,
                      "significant": bool(p < ctx.alpha / m and -dbic > ctx.bic_margin),
                      "score": rnd.scores[e].lm,
                      "parameters": {str(q): float(f.values[q]) for q in ctx.lib[e].names},
                      "stderr": {str(q): float(f.stderr.get(q, float("nan")))
                                 for q in ctx.lib[e].names}})
    def unfitted(e, score, why):  # a candidate in the table without a fit, and why
        return {"effect": e, "chi2": float("nan"), "lrt": float("nan"),
                "p_value": float("nan"), "delta_bic": float("nan"), "significant": False,
                "score": score, why: True, "parameters": {}, "stderr": {}}

    table += [unfitted(e, s.lm, "fit_failed" if e in rnd.failed else "screened_out")
              for e, s in rnd.scores.items() if e not in rnd.fits]
    # a candidate the model could not follow is said, not hidden
    table += [unfitted(e, float("nan"), "score_failed") for e in rnd.unscored]
    table.sort(key=lambda r: (math.isnan(r["delta_bic"]), r["delta_bic"],
                              -np.nan_to_num(r["score"], nan=-np.inf)))
    return table


def compatible(effect: str, chosen: list) -> bool:
    return not any(frozenset({effect, c}) in EXCLUSIVE for c in chosen)
