"""Locate the mismatch, name the missing physics, model it, say what remains.

1. **Base fit** (one-term Ogden, nu0 fixed) by trust-region least squares, weighted by the
   noise of each (curve, channel) (the stated instrument noise, or estimated from second
   differences, which a smooth misfit hardly changes).  The FE model's discretisation
   error is estimated against the next finer mesh at the base optimum and added to every
   prediction (deferred correction, scaled to the Richardson limit of the observed order),
   so that it is never mistaken for physics.
2. **Name**: rounds of forward selection (:mod:`diagnosis.selection`): every candidate
   (:mod:`diagnosis.effects`) is scored at the current fit, the promising ones are fitted
   with FE in the loop, and their gains are compared under a noise model of the rig
   (white noise, wander, drift: :func:`diagnosis.noise.fit_noise`) estimated from the
   best fit's residual: likelihood-ratio test (p < ``alpha`` / candidates) and BIC margin.
   An effect is added while one earns its place; in a model of two or more, each
   (the new one too) is re-tested beside the others from the joint fit's values.  Two
   effects within the BIC margin are reported as indistinguishable, with the test that
   would separate them; before such a near tie is decided, every fit of it that the
   ranking budget stopped short is run to the end.
3. **Locate and check**: the base residual and the final residual, whitened by the final
   noise model (each at its evaluated GLS step under it, as every comparison reads a fit:
   :func:`diagnosis.selection.gls_step`), are located along the protocol's axes
   (:mod:`diagnosis.locate`); what the
   final model leaves systematic (located, or reproducible across repetitions:
   :mod:`diagnosis.remaining`) decides the status.
4. **What would show**: how large each candidate not named would have to be to earn its
   place beside the final model (:func:`diagnosis.screen.detection_limits`), and those the
   named effects mask.

Outcome: ``verdict`` is ``none``, an effect, effects joined by ``+`` (alphabetical), or
``unexplained``;
``status`` is ``none`` (nothing systematic), ``explained`` (the named effects leave noise),
``partially explained`` (they leave a systematic misfit, having at least halved the RMS
misfit, and no stiffness trend with time) or ``unexplained`` (a systematic misfit no
candidate removes, that the best model of the library does not halve, or that holds a
trend no library effect makes, or shear tests that ask for other material parameters than
compression/tension: then ``tried`` holds that model's effects and the closest candidates
are listed).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from brain_fe.ends import resolve
from brain_fe.parameters import Param, Parameters
from simulators.coordinates import NU0

from . import locate as loc
from .drift import drift_model
from .effects import BASE_NAMES, check_effects, library, parameter_names, separating_test
from .fitting import Fit, fit, initial_guess, sigma_guess, solvable_start
from .noise import ChannelNoise, NoiseModel, estimate_noise, fit_noise, stated_sd
from .notes import (
    blind_doubt,
    contact_event_notes,
    contact_notes,
    edge_notes,
    lookalike_notes,
    noise_doubt,
    offset_doubt,
    one_kind_doubt,
    slow_doubt,
    slowest_wander_doubt,
    split_doubt,
    threshold_doubt,
    tie_doubt,
    wander_doubt,
)
from .remaining import (
    remaining,
    reproducible_basis,
    split_words,
    systematic,
    systematic_basis,
    trend_basis,
    trend_change,
    trend_rows,
)
from .screen import (
    AT_DESIGN,
    IN_COMPLIANCE,
    LINEAR_AT_NEUTRAL,
    PER_POINT,
    SCAN_SOLVES,
    design,
    design_scales,
    detection_limits,
    hidden_behind,
    masked_by_model,
)
from .selection import (
    ALPHA,
    BIC_MARGIN,
    HISTORY,
    MODEL_FAILURES,
    Context,
    Union,
    compare,
    compatible,
    run_round,
)
from .sharing import share_with, sharing

log = logging.getLogger(__name__)

# Bump when a change can alter a verdict: stored benchmark results of another version are
# diagnosed again instead of reused
ENGINE_VERSION = "2026.12-open-world-43"
RICHARDSON_ORDER = 3.0  # observed order of the axisymmetric model in k (BENCHMARKS.md)
MAX_EFFECTS = 3
RELAXATION = "viscoelastic"  # the effect whose relaxation time :func:`slow_relaxation` reads
ARTEFACTS = "artefacts"  # the offsets that :func:`diagnosis.notes.offset_doubt` judges
# Effects that leave a systematic misfit are named ("partially explained") only when they at
# least halve the RMS misfit (in units of the noise) and what they leave holds no stiffness
# trend with time (physics no library effect makes, which they may stand in for); otherwise
# the verdict is ``unexplained``, with the library's closest model beside it
EXPLAINS_FRACTION = 0.5


@dataclass
class Diagnosis:
    base: Fit
    final: Fit
    effects: list
    status: str
    rounds: list
    noise: NoiseModel  # estimated from the final model's residual
    located: pd.DataFrame  # the base model's misfit, whitened by ``noise``
    remaining: dict  # what the final model leaves (diagnosis.remaining)
    ambiguous: list
    discretisation: dict
    elapsed_s: float
    obs: pd.DataFrame
    notes: list = field(default_factory=list)
    # effects fitted that explain too little, or beside a stiffness trend (``decide``)
    tried: list = field(default_factory=list)
    cannot_tell: str = ""  # why the verdict may not be what the recordings determine
    timings: dict = field(default_factory=dict)  # wall time of each stage [s]
    # how large the candidates not named would have to be to show beside the final model
    detection_limits: dict = field(default_factory=dict)  # (diagnosis.screen.detection_limits)
    masked: list = field(default_factory=list)  # candidates no allowed value of would show
    # evaluations that failed for a reason other than the model (a verdict that may be
    # incomplete; the notes say so)
    internal_errors: list = field(default_factory=list)
    # the verdict of a second diagnosis with the recorded numbers changed in their last
    # digits ({} when not checked; diagnosis.determinacy)
    last_digits: dict = field(default_factory=dict)
    # where the recordings leave the noise undetermined: per place (a round, the final
    # model), the two noise models and what each decides (diagnosis.noise.NOISE_TIE)
    noise_rivals: list = field(default_factory=list)
    # a candidate for the left-out physics when the final model leaves a stiffness trend: the
    # base model with its stiffness drifting (a rate within tests, a level per test), fitted
    # jointly (:func:`diagnosis.drift.drift_model`)
    drift: dict = field(default_factory=dict)
    # candidates a named effect hides: they would show beside the model without it, and
    # beside it their parameter's variance is inflated HIDDEN_INFLATION times or more
    # (:func:`diagnosis.screen.hidden_behind`)
    hidden: list = field(default_factory=list)
    # a relaxation slower than the longest test in the final model (:func:`slow_relaxation`)
    # and what it gains over the fit without it under that fit's noise ({} when none)
    slow: dict = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        if self.effects:  # alphabetical: one spelling per set (``effects`` keeps the order
            return "+".join(sorted(self.effects))  # in which they were added)
        return "unexplained" if self.status == "unexplained" else "none"

    @property
    def ranking(self) -> list:
        """The first round: every candidate against the base model."""
        return self.rounds[0].table if self.rounds else []

    @property
    def winner(self) -> Fit:
        return self.final

    @property
    def sigma(self) -> np.ndarray:
        """Per row, the stationary SD of the noise."""
        return self.noise.sd()

    def rms(self, fit: Fit) -> dict:
        """Residual RMS per (curve, channel) in recording units and in units of the noise."""
        out = {}
        r = fit.residual(self.obs)
        sd = self.sigma
        for (c, ch), g in self.obs.groupby(["curve", "channel"], sort=False):
            i = g.index.to_numpy()
            out[f"{c}/{ch}"] = {"rms": float(np.sqrt(np.mean(r[i] ** 2))),
                                "noise": float(np.sqrt(np.mean(sd[i] ** 2))),
                                "rms_over_noise": float(np.sqrt(np.mean((r[i] / sd[i]) ** 2)))}
        return out

    def _rms_total(self, fit: Fit) -> float:
        return fit.rms(self.obs, self.sigma)

    def closest(self, k: int = 2) -> list:
        """The candidates that came closest to explaining the misfit (first round)."""
        rows = [r for r in self.ranking if not math.isnan(r["lrt"])]
        rows.sort(key=lambda r: -r["lrt"])
        return [{"effect": r["effect"], "lrt": r["lrt"], "delta_bic": r["delta_bic"]}
                for r in rows[:k]]

    def to_json(self) -> dict:
        w = self.final
        bias = {str(n): {"base": self.base.values[n], "refit": w.values[n],
                         "relative": (self.base.values[n] - w.values[n]) / abs(w.values[n])}
                for n in BASE_NAMES}
        rem = {k: v for k, v in self.remaining.items() if k != "table"}
        return {
            "verdict": self.verdict,
            "effects": list(self.effects),
            "status": self.status,
            "located": loc.summary(self.located)["located"],
            "remaining": rem,
            "closest": self.closest() if self.status == "unexplained" else [],
            "tried": list(self.tried),
            "cannot_tell": self.cannot_tell,
            "last_digits": self.last_digits,
            "ranking": self.ranking,
            "rounds": [{"from": "+".join(r.current) or "base", "added": r.added,
                        "dropped": r.dropped, "noise_dof": _finite(r.noise.nu_level())
                        if r.noise is not None else None, "table": r.table,
                        "noise_blind": r.noise_blind}
                       for r in self.rounds],
            "ambiguous": self.ambiguous,
            "detection_limits": self.detection_limits,
            "masked": self.masked,
            "hidden": self.hidden,
            "internal_errors": self.internal_errors,
            "notes": self.notes,
            "rms_before": self._rms_total(self.base),
            "rms_after": self._rms_total(w),
            "rms_unit": "noise standard deviations (1 = fit at the noise level)",
            "noise": {k: v["noise"] for k, v in self.rms(self.base).items()},
            "noise_model": self.noise.describe(),
            "noise_rivals": self.noise_rivals,
            "drift_model": self.drift,
            "slow_relaxation": self.slow,
            "rms_by_curve_before": self.rms(self.base),
            "rms_by_curve_after": self.rms(w),
            "base_parameters": _plain(self.base.values),
            "refit_parameters": _plain(w.values),
            "refit_stderr": _plain(w.stderr),
            "fits": {label: {"evaluations": f.nfev, "refused": f.refused}
                     for label, f in (("base", self.base), ("final", w))},
            "base_bias": bias,
            "discretisation": self.discretisation,
            "elapsed_s": self.elapsed_s,
            "timings_s": self.timings,
        }


def _finite(x: float) -> float | None:
    """``x``, or None where it is infinite (JSON has no infinity)."""
    return float(x) if math.isfinite(x) else None


def _plain(d: dict) -> dict:
    return {str(k): float(v) for k, v in d.items()}


def diagnose(sim, obs: pd.DataFrame, *, fine_sim=None, effects=None, alpha: float = ALPHA,
             bic_margin: float = BIC_MARGIN, max_nfev: int = 15, comm=None, progress=None,
             noise: dict | None = None, max_effects: int = MAX_EFFECTS) -> Diagnosis:
    """Diagnose one specimen.  ``sim``/``fine_sim``: simulators on the working mesh and on
    the next finer one (None: no discretisation correction, e.g. analytical models);
    ``noise``: the stated noise per channel ({"stress": white SD in kPa, ...}, or a
    channel's whole noise, :func:`diagnosis.noise.statement`), else estimated.  With
    ``comm`` (MPI) the work of every stage is shared among the ranks."""
    t0 = time.perf_counter()
    obs = obs.reset_index(drop=True)
    check_effects(effects, sim.kind)
    with sharing(sim, comm), sharing(fine_sim, comm):  # the ranks share every curve
        base, weights, disc, J_base = _base(sim, fine_sim, obs, noise)
    timings = {"base_fit_and_correction": round(time.perf_counter() - t0, 2), "rounds": []}
    if progress:
        progress("base")
    lib = library(sim.kind, getattr(sim, "nu0", None))  # compressibility: below nu0
    errors: list = []  # internal errors (not the model's failures) met on any rank
    ctx = Context(sim, obs, weights, lib, list(BASE_NAMES), alpha, bic_margin, max_nfev,
                  share_with(comm, sim, errors), noise, errors)
    rounds, current, chosen, J = [], base, [], J_base
    ambiguous, notes = [], []
    while len(chosen) < max_effects:
        # an effect dropped by the re-test right after being added is not tried again
        lost = {r.added for r in rounds if r.added in r.dropped}
        cands = [e for e in (effects or lib)
                 if e not in chosen and e not in lost and compatible(e, chosen)]
        if not cands:
            break
        t_round = time.perf_counter()
        rnd = run_round(ctx, current, chosen, cands, J, progress,
                        first=rounds[0] if rounds else None)
        rounds.append(rnd)
        timings["rounds"].append(entry := rnd.timings())
        try:
            if not rnd.fits:
                rnd.noise = _noise_of(obs, current, noise)
                rnd.table = compare(ctx, rnd, current, len(cands), rnd.noise)
                break
            sig = _judge(ctx, rnd, current, len(cands), noise)
            completed = _complete_contenders(ctx, rnd, chosen, sig)
            if completed:  # the order may change
                entry["near_tie_completion"] = {
                    e: {"s": round(rnd.fits[e].seconds, 2), "evaluations": rnd.fits[e].nfev}
                    for e in completed}
                sig = _judge(ctx, rnd, current, len(cands), noise)
            if not sig:
                break
            added = sig[0]["effect"]
            ties = [{"effects": [added, r["effect"]], "delta_bic": r["delta_bic"]
                     - sig[0]["delta_bic"], "separating_test": separating_test(
                         added, r["effect"])} for r in sig[1:]
                    if r["delta_bic"] - sig[0]["delta_bic"] < bic_margin]
            with sharing(sim, comm):  # one fit at a time: the ranks share its curves
                new = _completed(ctx, rnd.fits[added], [*chosen, added])
                rnd.added = added
                chosen = [*chosen, added]
                current, chosen, dropped, doubts = _retest(ctx, new, chosen, rnd.noise)
                if doubts:  # re-test decisions the rival noise would reverse
                    rnd.noise_rival["retest"] = doubts
            rnd.dropped = dropped
            if added not in dropped:
                ambiguous += ties
            # no stop at "nothing systematic remains": the noise model of this fit's
            # residual may take a second effect's smooth misfit for wander; the next
            # round judges every candidate under the noise of its own best fit
            J = _jacobian(sim, comm, current, parameter_names(lib, chosen))
        finally:  # every round, the one that stops too
            entry["whole_round"] = round(time.perf_counter() - t_round, 2)
    t_end = time.perf_counter()
    current, chosen, with_offsets, weak_offsets = _weigh_offsets(
        ctx, comm, rounds, base, current, chosen, noise)
    if with_offsets:
        J = _jacobian(sim, comm, current, parameter_names(lib, chosen))
    final_noise, rem = _what_remains(ctx, current, noise, also=[base])
    located = loc.locate(obs, ctx.judged(final_noise, base), 1.0,
                          sigma_dof=final_noise.dof)
    in_model = list(chosen)  # the effects of ``current``, named or not
    (status, chosen, tried), (rms_base, rms_final) = _status_under(
        obs, base, current, in_model, final_noise, rem)
    if status == "unexplained" and _unexplained_with(ctx, base, with_offsets, noise):
        # unexplained with the offsets too: they decide nothing, a note says what they gained
        notes.append(offset_doubt(rounds, [ARTEFACTS], len(obs), bic_margin, wording="note"))
        weak_offsets = ""
    trend, sd = rem["trend"]["significant"], final_noise.sd()
    if tried:
        notes.append(f"the library's closest model ({'+'.join(sorted(tried))}) leaves "
                     f"{100 * rms_final / rms_base:.0f} % of the base RMS misfit"
                     + ("; an effect is named only when it at least halves it"
                        if rms_final > EXPLAINS_FRACTION * rms_base else "")
                     + ("; what it leaves holds a stiffness change with time ("
                        f"{trend_change(rem['trend'])}, p = {rem['trend']['p_value']:.2g}) "
                        "that no effect of the library "
                        "makes, and the effects fitted beside it may stand in for part of "
                        "it, so none is named" if trend else ""))
    slow = slow_relaxation(obs, current) if tried else {}
    if slow:  # judged again under the noise of the fit without it, which may hold the
        # rig's drift that the relaxation takes up
        with sharing(sim, comm):
            without = _without(ctx, base, current, in_model, RELAXATION)
        slow["without"] = None if without is None else without.effect  # None: its fit failed
        if without is not None:
            slow.update(_gain_under_noise_of(ctx, without, current, noise))
        notes.append(f"the closest model holds a relaxation slower than the longest test "
                     f"(tau {slow['tau_s']:.3g} s, the test {slow['longest_test_s']:.3g} s): "
                     "over the test it is a slow change of the stress with time, which a "
                     "drift of the stiffness, a set left by the loading or the rig's drift "
                     "make alike, so none is named; a hold longer than tau tells them apart")
    if rem["split"]["significant"]:
        notes.append("the shear tests ask for other material parameters than compression/"
                     f"tension (with their own, {split_words(rem['split'])}): one isotropic "
                     "material of the library does not describe both kinds of test (a fibre "
                     "family, a stiffness changing between the tests or a set left by the "
                     "first may)" + (", and an effect fitted to both would stand in for "
                                     "what tells them apart, so none is named" if tried
                                     else ""))
    drift = {}
    if trend:  # the physics the library left out, modelled: does it take the misfit?
        with sharing(sim, comm):
            drift = drift_model(sim, obs, base, sd)
        if drift and drift["rms_after"] < rms_final:
            notes.append(f"modelled: the base model with its stiffness drifting during the "
                         f"session ({trend_change(drift)}, a level per test) takes the RMS "
                         f"misfit from {rms_base:.2f} to {drift['rms_after']:.2f} with "
                         f"{drift['extra_parameters']} parameter(s) more (the library's best "
                         f"model: {rms_final:.2f}); a candidate for what the library "
                         "lacks, not a verdict: other physics may leave a trend too")
        elif drift:
            notes.append("a stiffness drifting during the session does not explain the trend "
                         f"either: fitted, it leaves RMS {drift['rms_after']:.2f} (the "
                         f"library's best model: {rms_final:.2f})")
    doubt = wander_doubt(status, rem, final_noise, noise)
    undetermined, rivals = noise_doubt(rounds, status, chosen, _rival_outcome(
        ctx, base, current, in_model, final_noise))
    doubt = "; ".join(filter(None, [doubt, slowest_wander_doubt(status, rem, final_noise),
                                    threshold_doubt(status, rem, alpha), undetermined,
                                    one_kind_doubt(chosen, obs, current),
                                    weak_offsets,
                                    tie_doubt(ambiguous, chosen),
                                    blind_doubt(rounds, chosen),
                                    slow_doubt(slow),
                                    split_doubt(status, rem, _status_under(
                                        obs, base, current, in_model, final_noise, rem,
                                        besides=("split",))[0][0])]))
    if rivals and not undetermined:
        notes.append("the recordings leave the slow part of the noise undetermined in "
                     f"{', '.join(p['where'] for p in rivals)} (two noise models neither "
                     "of which they rule out); every decision is the same under both")
    limits, masked, hidden = _limits(ctx, comm, current, in_model, chosen, J, final_noise,
                                     effects)
    if rem["reproducible"]["repeats"] == "none":
        notes.append("no repeated ramp (one pass of each): wander and a smooth misfit cannot "
                     "be told apart by repetition; only the located test applies")
    for a in ambiguous:
        log.warning("%s and %s cannot be told apart with these tests (dBIC %.1f); %s",
                    *a["effects"], a["delta_bic"], a["separating_test"])
    if rounds and rounds[0].unscored:
        notes.append(f"{', '.join(rounds[0].unscored)} could not be scored: the FE model "
                     "could not follow the recorded path at any of its design points, so "
                     "the verdict does not test "
                     + ("it" if len(rounds[0].unscored) == 1 else "them"))
    if errors:
        notes.append(f"incomplete: {len(errors)} evaluation(s) failed for a reason other "
                     f"than the model ({'; '.join(errors[:3])}); what they concern was left "
                     "out, so the verdict may miss what it would have shown")
    notes += lookalike_notes(chosen, status)
    notes += edge_notes(base, current)
    lift_off = resolve(getattr(sim, "ends", "glued"))[1]
    notes += contact_notes(obs, base, current, sd, lift_off=lift_off)
    if lift_off and "in_contact" in obs and not obs["in_contact"].all():
        notes += contact_event_notes(obs, sim, current)
    timings["noise_locate_decide"] = round(time.perf_counter() - t_end, 2)
    return Diagnosis(base, current, chosen, status, rounds, final_noise, located, rem,
                     ambiguous, disc, time.perf_counter() - t0, obs, notes, tried, doubt,
                     timings, limits, masked, list(errors), noise_rivals=rivals,
                     drift=drift, hidden=hidden, slow=slow)


def _limits(ctx: Context, comm, current: Fit, in_model: list, named: list, J: np.ndarray,
            nm: NoiseModel, effects) -> tuple[dict, list, list]:
    """The detection limits of the candidates that could join the final model ``current``
    (of effects ``in_model``, named or merely tried) under the final noise model and the
    next round's bar (:func:`diagnosis.screen.detection_limits`), those of them the
    ``named`` effects mask (some allowed value would show alone, none beside them), and
    those one named effect hides (:func:`diagnosis.screen.hidden_behind`)."""
    lib = ctx.lib
    cands = {e: lib[e] for e in (effects or lib)
             if e not in in_model and compatible(e, in_model)}
    m = max(len(cands), 1)
    nu = nm.nu_level()  # the bar of the next round's F test under the final noise
    scales = design_scales(ctx.sim, ctx.obs, current.values)
    points = {e: design(lib[e], ctx.sim.nu0, scales) for e in cands
              if e in AT_DESIGN + PER_POINT + IN_COMPLIANCE}

    # compressibility and the offsets (on the final fit's own path: when it cannot be
    # followed there, nothing is stated), the effects with a time or an exponent (a Maxwell
    # branch or Ogden term per design point, in one prediction), a softening (one per
    # model) at each design point and a glue layer (interface springs): independent
    # solves, each group on whichever rank is free; the elastic ones alone again if the
    # branches' history cannot be followed
    def attempt(group: dict, pts=points) -> dict | None:
        if not group:
            return {}
        try:
            return detection_limits(ctx.sim, current, parameter_names(lib, in_model), J,
                                    group, nm.whiten_jacobian,
                                    lambda eff: ctx.needed(len(eff.names), m, nu), pts,
                                    {e: lib[e].names for e in named})
        except MODEL_FAILURES as exc:  # a note is not worth a failed diagnosis
            log.warning("detection limits at the final model: %s: %s",
                        type(exc).__name__, exc)
            return None

    def kind(k):
        return {e: v for e, v in cands.items() if e in k}

    at_design = kind(AT_DESIGN)
    groups = [(kind(LINEAR_AT_NEUTRAL), points), (at_design, points)]
    groups += [({e: v}, {e: [p]}) for e, v in kind(PER_POINT).items() for p in points[e]]
    groups += [(kind(IN_COMPLIANCE), points)]
    solves = {**dict.fromkeys(AT_DESIGN, 2.0), **dict.fromkeys(IN_COMPLIANCE, SCAN_SOLVES)}
    found = ctx.share(groups, lambda g: attempt(*g),
                      lambda g: max([solves.get(e, 1.0) for e in g[0]], default=0.0))
    limits = None
    if found[0] is not None:
        limits = {}
        elastic = {e: v for e, v in at_design.items() if e not in HISTORY}
        if found[1] is None and elastic != at_design:
            found[1] = ctx.share([elastic], attempt, lambda g: 1.0)[0]  # all ranks
        for part in found:  # in the order of the groups, a softening's points in turn
            for e, d in (part or {}).items():
                limits.setdefault(e, {}).update(d)
    if not limits:
        return {}, [], []
    masked = [{"effect": e, "beside": sorted(named), "separating_test": " / ".join(
        dict.fromkeys(separating_test(e, c) for c in named))}
        for e, d in limits.items()
        if named and not any(v["within_bounds"] for v in d.values())
        and any(masked_by_model(v, lib[e].bounds(Param.parse(v["parameter"])))
                for v in d.values())]
    return limits, masked, hidden_behind(limits, lib)


def decide(chosen: list, systematic: bool, rms_before: float, rms_after: float, *,
           trend: bool = False, split: bool = False,
           slow: bool = False) -> tuple[str, list, list]:
    """Status, named effects and merely tried effects of a diagnosis from the effects
    selected, whether the final model leaves a systematic misfit (and among it a
    stiffness ``trend`` with time), and the RMS misfit (in noise SDs) of the base and the
    final model.  Effects that leave a systematic misfit are named only when
    ``rms_after <= EXPLAINS_FRACTION * rms_before`` and that misfit holds no trend: a
    stiffness changing with time is physics outside the library (no effect of it changes
    with time alone), and the history effects and offsets fitted beside it may stand in
    for part of it (softening between cycles, relaxation), so none of them is named.  The
    same when the shear tests ask for other material parameters than compression/tension
    (``split``, :func:`diagnosis.remaining.split_test`): every effect of the library
    describes all tests with one set of parameters, so the physics that tells them apart
    is not among them, and a named effect would stand in for it.  The same, systematic
    misfit left or not, when the final model holds a relaxation slower than the longest
    test (``slow``, :func:`slow_relaxation`); the *cannot tell* notes that apply only to
    ``none`` and ``explained`` then fall away with the names."""
    if not chosen:
        return ("unexplained" if systematic else "none"), [], []
    if slow:
        return "unexplained", [], list(chosen)
    if not systematic:
        return "explained", list(chosen), []
    if rms_after <= EXPLAINS_FRACTION * rms_before and not trend and not split:
        return "partially explained", list(chosen), []
    return "unexplained", [], list(chosen)


def _status_under(obs, base: Fit, current: Fit, in_model: list, nm: NoiseModel,
                  rem: dict, besides: tuple = ()
                  ) -> tuple[tuple[str, list, list], tuple[float, float]]:
    """:func:`decide` for the final model ``current`` (effects ``in_model``) under the
    noise model ``nm`` and what it leaves (``rem``; the tests named in ``besides`` left
    out, :func:`diagnosis.remaining.systematic`: the status without them), with the RMS
    misfits of the base and the final model in ``nm``'s SDs."""
    sd = nm.sd()
    rms_base, rms_final = base.rms(obs, sd), current.rms(obs, sd)
    return (decide(in_model, systematic(rem, besides), rms_base, rms_final,
                   trend=rem["trend"]["significant"] and "trend" not in besides,
                   split=rem["split"]["significant"] and "split" not in besides,
                   slow=bool(slow_relaxation(obs, current))),
            (rms_base, rms_final))


def stated_in_full(obs: pd.DataFrame, noise: dict | None) -> bool:
    """Whether every channel of ``obs`` has its whole noise stated (``--noise`` JSON with
    its slow parts, :func:`diagnosis.noise.statement`): then no slow part is fitted, and
    the noise model cannot miss one (:func:`diagnosis.notes.offset_doubt` does not apply)."""
    return bool(noise) and all(isinstance(noise.get(ch), ChannelNoise)
                               for ch in obs["channel"].unique())


def slow_relaxation(obs: pd.DataFrame, f: Fit) -> dict:
    """``{"tau_s", "longest_test_s"}`` when ``f`` holds a relaxation slower than the
    longest test of ``obs`` (the span of its recorded times), else {}.  Over a test shorter
    than its time, a relaxation has not decayed to a third: it is a slow, nearly steady
    change of the stress with time, which a drift of the stiffness, a set left by the
    loading or the rig's own drift make alike, and the recordings do not tell which (a hold
    longer than the relaxation time does).  A relaxation of no strength (beta 0) is none;
    a curve's span is that of its finite times.  Measured on the open benchmark's five draws
    (open-world-25/26, written after seeing them): of 147 final models with a relaxation,
    the 106 of viscoelastic specimens had it at most 0.65 of the longest test; 8 others had
    it slower than the test and named it (4 permanent sets and 1 axial fibre family,
    outside the library; 2 single effects given a spurious relaxation beside them; a
    compressibility named viscoelastic), and 20 more that were already unexplained."""
    vals = Parameters(f.values)
    if ("log10_tau_0" not in vals or not vals.get("beta_0", 0.0) > 0.0
            or "time_s" not in obs or "curve" not in obs):
        return {}
    t = pd.to_numeric(obs["time_s"], errors="coerce")
    spans = t.groupby(obs["curve"]).agg(
        lambda x: float(x.max() - x.min()) if x.notna().sum() >= 2 else 0.0)
    longest, tau = float(spans.max()) if len(spans) else 0.0, 10.0 ** vals["log10_tau_0"]
    if not (longest > 0 and np.isfinite(tau) and tau > longest):
        return {}
    return {"tau_s": tau, "longest_test_s": longest}


def _refit_without(ctx: Context, current: Fit, in_model: list, effect: str) -> Fit:
    """``current``'s model (effects ``in_model``) less ``effect``, refitted from
    ``current``'s values less its parameters; the model's failures are raised."""
    rest = [e for e in in_model if e != effect]
    start = {k: v for k, v in current.values.items() if k not in ctx.lib[effect].names}
    return fit(ctx.sim, ctx.obs, ctx.weights, start, parameter_names(ctx.lib, rest),
               effect="+".join(rest), max_nfev=ctx.max_nfev, effect_def=_union(ctx, rest))


def _weigh_offsets(ctx: Context, comm, rounds: list, base: Fit, current: Fit, chosen: list,
                   noise) -> tuple[Fit, list, tuple[Fit, list] | None, str]:
    """Offsets (``artefacts``) named with a gain the rig's slow noise could make
    (:func:`diagnosis.notes.offset_doubt`; not when every channel's noise is stated in
    full, :func:`stated_in_full`) are said, not named: the final fit and effects without
    them, the fit and effects with them (None when they stay), and the doubt's words.
    When the fit without them fails, they stay named with the doubt."""
    n, margin = len(ctx.obs), ctx.bic_margin
    doubt = "" if stated_in_full(ctx.obs, noise) else offset_doubt(rounds, chosen, n, margin)
    if not doubt:
        return current, chosen, None, ""
    with sharing(ctx.sim, comm):
        without = _without(ctx, base, current, chosen, ARTEFACTS)
    if without is None:
        return current, chosen, None, doubt
    return (without, [e for e in chosen if e != ARTEFACTS], (current, list(chosen)),
            offset_doubt(rounds, [ARTEFACTS], n, margin, wording="dropped"))


def _unexplained_with(ctx: Context, base: Fit, with_offsets: tuple[Fit, list] | None,
                      noise) -> bool:
    """Whether the fit with the offsets not named (:func:`_weigh_offsets`) would be
    ``unexplained`` too, judged under the noise model of its own residual."""
    if not with_offsets:
        return False
    f, effects = with_offsets
    return _status_under(ctx.obs, base, f, effects,
                         *_what_remains(ctx, f, noise, also=[base]))[0][0] == "unexplained"


def _without(ctx: Context, base: Fit, current: Fit, in_model: list, effect: str) -> Fit | None:
    """The fit of ``current``'s model (effects ``in_model``) without ``effect``: ``base``
    when it is the only one, else :func:`_refit_without` (as the re-test does); None when
    that fit fails."""
    if all(e == effect for e in in_model):
        return base
    try:
        return _refit_without(ctx, current, in_model, effect)
    except MODEL_FAILURES as exc:  # no reference to judge it against: no doubt is raised
        log.warning("the fit without %s failed: %s", effect, exc)
        return None


def _gain_under_noise_of(ctx: Context, without: Fit, current: Fit, stated) -> dict:
    """``current``'s gain in -2 log L over ``without`` (its model less some effects) under
    the noise model of ``without``'s residual (:func:`_noise_of`), and the gain its extra
    parameters need there as one candidate (:func:`diagnosis.selection.chi2_needed`).  The
    selection judges an effect under the noise its own fit leaves; an effect that takes up
    a slow part of the noise (the rig's drift) empties that noise of it, and only the noise
    of the fit without the effect shows it."""
    nb = _noise_of(ctx.obs, without, stated)
    ctx.judge_all(nb, [without, current])
    z0, z1 = ctx.judged(nb, without), ctx.judged(nb, current)
    return {"gain_under_noise_without": float(z0 @ z0 - z1 @ z1),
            "needed": ctx.needed(current.k - without.k, 1, ctx.nu(nb, without, current))}


def _what_remains(ctx: Context, current: Fit, stated, also: list = ()):
    """The noise model of ``current``'s residual and what that model leaves systematic;
    the GLS steps of ``current`` and of the fits ``also`` judged under it are shared
    among the ranks first (each would otherwise be solved by every rank)."""
    nm = _noise_of(ctx.obs, current, stated)
    ctx.judge_all(nm, [current, *also])
    return nm, _remains_under(ctx, current, nm)


def _remains_under(ctx: Context, current: Fit, nm: NoiseModel) -> dict:
    """What ``current`` leaves systematic under the noise model ``nm``, read where every
    comparison reads it: at its evaluated GLS step under ``nm`` (:meth:`Context.judged`),
    so that what the base's own parameters would take in that metric is not called a
    misfit."""
    y = ctx.judged_prediction(nm, current)
    return remaining(ctx.obs, y - ctx.obs["value"].to_numpy(float), nm, alpha=ctx.alpha,
                     bic_margin=ctx.bic_margin, prediction=y, jacobian=current.jacobian,
                     names=current.names)


def _noise_of(obs, f: Fit, stated, columns: np.ndarray | None = None) -> NoiseModel:
    """The noise model of ``f``'s residual by restricted ML: every misfit the tests of
    :mod:`diagnosis.remaining` call systematic (repeated at every cycle or branch, a
    stiffness trend) and ``f``'s own parameters (its Jacobian's columns; ``columns``
    instead when given) are kept out of it, so that a smooth misfit the model lacks is
    never taken for wander.  On short
    series this leaves few degrees of freedom; the model carries them (``dof``) and the
    located tests are F tests with them.  A series of several cycles too short to keep
    out all of them keeps out the stiffness trend and ``f``'s parameters: kept whole, its
    noise would take up a drift of the stiffness (measured: an open-world stiffness drift
    on two torsions of 17 points each, answered `none` with the noise put at 2.3 times
    the true one).  A short series of one pass keeps nothing out, as before: no test
    tells a smooth misfit from wander there, and keeping the model's columns out only
    moves which of the two its noise takes (measured: a pair answered with a third,
    spurious effect)."""
    J = f.jacobian if columns is None else columns
    return fit_noise(obs, f.residual(obs), stated=stated,
                     systematic=kept_out(obs, f.prediction, J))


def kept_out(obs, prediction: np.ndarray, J: np.ndarray | None) -> list:
    """The column sets :func:`_noise_of` keeps out of the noise model of a fit with this
    ``prediction`` and Jacobian ``J`` (its parameters' columns; None when it has none),
    the fullest first (:func:`diagnosis.noise.fit_noise`'s ``systematic``)."""
    B = systematic_basis(obs, prediction)
    T = trend_basis(obs, prediction)
    if J is None or not np.isfinite(J).all():
        return [B, T]
    cycled = np.zeros(len(obs), bool)
    cycled[trend_rows(obs)] = True
    return [np.hstack([B, J]), np.hstack([T, J * cycled[:, None]])]


def _jacobian(sim, comm, f: Fit, names: list) -> np.ndarray:
    """The Jacobian of the model at ``f`` with respect to ``names``: the fit's own when it
    was taken with respect to the same parameters (no second solve along the path)."""
    if f.jacobian is not None and list(map(str, f.names)) == list(map(str, names)):
        return f.jacobian
    with sharing(sim, comm):
        return sim.predict(f.values, names).jacobian


def _complete(ctx: Context, f: Fit, effects: list) -> Fit:
    """Run a fit that the ranking budget cut short to the end."""
    if f.converged:
        return f
    more = fit(ctx.sim, ctx.obs, ctx.weights, f.values, f.names, effect=f.effect,
               max_nfev=ctx.max_nfev, effect_def=_union(ctx, effects))
    return more if more.chi2 <= f.chi2 else f


def _completed(ctx: Context, f: Fit, effects: list) -> Fit:
    """:func:`_complete`, or ``f`` itself where the model fails in the completion: the
    ranking fit stands (a real double compression was once lost whole to a Newton failure
    in completing the winner's fit)."""
    try:
        return _complete(ctx, f, effects)
    except MODEL_FAILURES as exc:
        log.warning("completing the fit of %s failed: %s", effects[-1], exc)
        return f


def _judge(ctx: Context, rnd, current: Fit, m: int, stated) -> list:
    """The round's noise model (from its best fit's residual) and table; returns the
    significant rows, best first.

    Where a series repeats (cycles or branches), a candidate's gain must also stay above
    its BIC bar under the noise of the same residual with only ``current``'s columns kept
    out (:func:`_blind_checked`)."""
    leader = min(rnd.fits.values(), key=lambda f: f.chi2)
    rnd.noise = _noise_of(ctx.obs, leader, stated)
    rnd.table = compare(ctx, rnd, current, m, rnd.noise)
    sig = _blind_checked(ctx, rnd, current, m, stated, leader,
                         [r for r in rnd.table if r["significant"]])
    rival = rnd.noise.rival()
    rnd.noise_rival = {}
    if rival is not None:  # what the round would add under the other noise
        alt = [r for r in compare(ctx, rnd, current, m, rival) if r["significant"]]
        rnd.noise_rival = {"series": rnd.noise.describe_rivals(),
                           "adds": sig[0]["effect"] if sig else None,
                           "rival_adds": alt[0]["effect"] if alt else None}
    return sig


def _blind_checked(ctx: Context, rnd, current: Fit, m: int, stated, leader: Fit,
                   sig: list) -> list:
    """``sig`` less the candidates whose gain falls below their BIC bar (the size one
    candidate needs: ``bic_margin`` more than k ln n) under the noise of ``leader``'s
    residual with only ``current``'s columns kept out (the round's own keeps ``leader``'s
    extra columns out too), where a series repeats; the decision this moves is kept in
    ``rnd.noise_blind``.

    Kept out, a candidate's own columns make the noise blind along its direction: a
    wander that looks like it is then counted whole as its gain, and under the other
    noise the gain collapses (controls: seed 15's world063 a Mullins softening at LRT
    35.1 under its own fit's noise, 5.0 with only the base columns kept out, the bar
    20.5; seed 10's world012 a relaxation 31.5 -> -2.0; seed 11's world083 28.4 -> -5.6).
    Not kept out, a smooth misfit the candidate makes can be taken for wander instead:
    where a series repeats the systematic basis keeps out what repeats at every cycle or
    branch, not a hysteresis of one cycle, which differs between its branches.  So the
    other noise only asks that the gain not collapse below the bar, not the whole test
    again (open-world-42 asked for the test: three stand-ins for what the library lacks,
    at LRT 20.3, 20.9 and 18.5 there against bars of 19.1, 18.6 and 13.7, were dropped,
    and two outside cases of seed 14 were then named by the relaxation left; chosen after
    seeing seeds 14 and 15).  On one pass nothing is kept out but the candidate's columns
    (open-world-41, the shared noise alone: 10 of 24 real single ramps and Budday's CR
    moved, 8 of them to ``none``): there the round's own noise decides alone."""
    rnd.noise_blind = {}
    J = current.jacobian
    if not sig or J is None or len(J) != len(ctx.obs) \
            or reproducible_basis(ctx.obs)[1] == "none":
        return sig
    shared = _noise_of(ctx.obs, leader, stated, columns=J)
    # only the significant candidates' fits are judged again (a GLS solve each)
    mine = replace(rnd, fits={r["effect"]: rnd.fits[r["effect"]] for r in sig})
    passed = {r["effect"]: r for r in compare(ctx, mine, current, m, shared)}
    kept = [r for r in sig if -passed[r["effect"]]["delta_bic"] > ctx.bic_margin]
    if kept[:1] != sig[:1]:  # the decision moved: what the round would have added lost
        r, q = sig[0], passed[sig[0]["effect"]]
        rnd.noise_blind = {"would_add": r["effect"], "adds": kept[0]["effect"] if kept
                           else None, "lrt": r["lrt"], "lrt_shared": q["lrt"],
                           "bic_bar": r["lrt"] + r["delta_bic"] + ctx.bic_margin}
    return kept


def _rival_outcome(ctx: Context, base: Fit, current: Fit, in_model: list,
                   nm: NoiseModel) -> dict:
    """The status and named effects of the final model under ``nm``'s rival noise (the
    other optimum the recordings do not rule out), or {} when the noise is determined."""
    rival = nm.rival()
    if rival is None:
        return {}
    ctx.judge_all(rival, [current])
    rem = _remains_under(ctx, current, rival)
    (status, named, _), _ = _status_under(ctx.obs, base, current, in_model, rival, rem)
    return {"series": nm.describe_rivals(), "status": status, "effects": sorted(named)}


def _complete_contenders(ctx: Context, rnd, chosen: list, sig: list) -> list:
    """When several significant candidates are within the BIC margin of the best, run every
    one of their fits that the ranking budget cut short to the end (shared among the
    ranks): a competitor stopped early is judged on a worse fit than the leader's and
    would lose a near tie for that reason alone.  Returns the effects completed."""
    near = [r["effect"] for r in sig if r["delta_bic"] - sig[0]["delta_bic"] < ctx.bic_margin]
    short = [e for e in near if not rnd.fits[e].converged] if len(near) > 1 else []
    if short:
        def run(e):
            return _completed(ctx, rnd.fits[e], [*chosen, e])

        done = ctx.share(short, run, lambda e: rnd.fits[e].seconds)
        rnd.fits.update((e, f if f is not None else rnd.fits[e])  # None: internal error
                        for e, f in zip(short, done, strict=True))
        log.info("near tie between %s: completed the fits of %s", near, short)
    return short


def _union(ctx, effects):
    return Union(ctx.lib, effects)


def _retest(ctx: Context, current: Fit, chosen: list, noise) -> tuple[Fit, list, list, list]:
    """Re-test every effect chosen in the presence of the others: refit without it from the
    joint fit's values, drop it when it no longer earns its place.  Returns (fit, effects,
    dropped, doubts).  Where ``noise`` has a rival (:meth:`NoiseModel.rival`) each decision
    is made under it too; ``doubts`` lists those it reverses (effect, whether dropped, the
    LRT under each noise model and the LRT needed).

    The one just added too, once the model holds two or more: its likelihood ratio was
    measured against the previous model's fit, which may sit in a worse optimum than the
    previous model can reach from the joint fit's values; then the extra parameter's gain
    is only the better optimum's (open-benchmark world040: nu0 added with LRT 126 and
    fitted to 0.4902 +- 0.005, its neutral 0.49).  The first effect needs no such re-test:
    the base fit it is measured against has no previous round's start to inherit."""
    dropped, doubts = [], []
    rival = noise.rival() if noise is not None else None
    for e in list(chosen if len(chosen) > 1 else ()):
        rest = [c for c in chosen if c != e]
        try:
            without = _refit_without(ctx, current, chosen, e)
        except MODEL_FAILURES as exc:  # cannot do without it: it stays
            log.warning("re-test without %s failed: %s", e, exc)
            continue
        except Exception as exc:  # noqa: BLE001 - an internal error: it stays, and is said
            log.error("internal error in the re-test without %s: %s: %s", e,
                      type(exc).__name__, exc)
            ctx.errors.append(f"{type(exc).__name__}: {exc}")
            continue
        k = len(ctx.lib[e].names)
        lrt = ctx.chi2(noise, without) - ctx.chi2(noise, current)
        needed = ctx.needed(k, max(len(chosen), 1), ctx.nu(noise, without, current))
        if rival is not None:
            lrt_rival = ctx.chi2(rival, without) - ctx.chi2(rival, current)
            if (lrt_rival < needed) != (lrt < needed):
                doubts.append({"effect": e, "dropped": bool(lrt < needed), "lrt": lrt,
                               "rival_lrt": lrt_rival, "needed": needed})
        if lrt < needed:
            log.info("%s no longer earns its place next to %s (LRT %.1f)", e, rest, lrt)
            current, chosen = without, rest
            dropped.append(e)
    return current, chosen, dropped, doubts


def _base(sim, fine_sim, obs, stated):
    """Base fit, discretisation correction, noise weights, refit and the base Jacobian."""
    names = list(BASE_NAMES)
    sigma = sigma_guess(obs)
    start = solvable_start(sim, {**initial_guess(obs), NU0: sim.nu0})
    base = fit(sim, obs, sigma, start, names, max_nfev=40)
    disc = {"corrected": False}
    try:
        y_fine = None if fine_sim is None else fine_sim.predict(base.values, [])[0]
    except RuntimeError as exc:  # the finer mesh cannot follow (e.g. its glued corner
        # at large compression): diagnosed uncorrected, and the report says so
        log.warning("no discretisation correction: mesh k = %d cannot be solved at the "
                    "base fit (%s)", fine_sim.refinement, exc)
        disc["not_corrected_because"] = (f"mesh k = {fine_sim.refinement} cannot be solved "
                                         f"at the base fit: {exc}")
        y_fine = fine_sim = None
    if fine_sim is not None:
        sim.correction = np.zeros(len(obs))
        y_coarse, _ = sim.predict(base.values, [])
        factor = 2 ** RICHARDSON_ORDER / (2 ** RICHARDSON_ORDER - 1)
        sim.correction = factor * (y_fine - y_coarse)
        disc = {"corrected": True, "refinement": sim.refinement,
                "reference_refinement": fine_sim.refinement, "richardson_factor": factor}
    sigma = estimate_noise(obs, base.residual(obs))
    if stated:
        sigma = np.array([stated_sd(stated[c]) if c in stated else s
                          for c, s in zip(obs["channel"], sigma, strict=True)], dtype=float)
    base = fit(sim, obs, sigma, base.values, names, max_nfev=20)
    if fine_sim is not None:
        rel = np.abs(sim.correction) / sigma
        disc.update(max_over_noise=float(rel.max()), rms_over_noise=float(
            np.sqrt(np.mean(rel**2))))
    return base, sigma, disc, base.jacobian

