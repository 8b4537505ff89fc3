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

from .effects import separating_test

# Fixed generic design (see docstring), scaled by the data
TAU_OVER_RAMP = (0.1, 1.0, 10.0)  # relaxation time / duration of a ramp
M_OVER_ENERGY = (0.01, 0.1, 1.0)  # softening energy scale / energy reached
ALPHA_1 = (-20.0, -5.0, 5.0, 20.0)  # exponent of a second Ogden term
# Effects far from linear between neutral and realistic sizes are also scored away from
# the neutral point: a glue layer's stiffness relative to the specimen's shear stiffness
# per length mu / H (1e3: as glued), and Poisson ratios below the assumed one
GLUE_OVER_SHEAR = (1e3, 30.0, 1.0, 0.1)
NU0_BELOW = (0.45, 0.35)
FRICTIONLESS_LOG10_K = -3.0  # the glued-cube candidate's neutral end: no friction
CUBE_LOG10_K = (-3.0, -0.5, 1.0, 2.5)


@dataclass
class Score:
    effect: str
    lm: float  # predicted chi-square reduction (one-sided at a bound: _within_bounds)
    dof: int  # active effect parameters
    start: dict  # Gauss-Newton start of the effect's fit (all parameters)
    point: dict  # the neutral design point the score was taken at
    seconds: float = 0.0  # cost of the prediction (a guide to the cost of the fit)
    held: tuple = ()  # effect parameters whose step was too long: they start at the point
    # the reduction with no bound held (two-sided): what the effect's direction could do
    # beside another effect, where the sign the base fit asks for may turn
    lm_free: float = 0.0


def data_scales(obs: pd.DataFrame, values: dict, height_mm: float = 5.0) -> dict:
    """The scales the generic design is built on: the median duration of a ramp [s],
    mu (max strain)^2 [kPa] (the isochoric energy the specimen reaches) and mu / H
    [kPa/mm] (its shear stiffness per length, the scale of a glue layer's stiffness)."""
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
    return {"t_ramp": max(t_ramp, 1e-6), "energy": max(mu * float(np.max(strain)) ** 2, 1e-9),
            "glue": max(mu / height_mm, 1e-9)}


def design(effect, nu0: float, scales: dict) -> list[dict]:
    """Design points of an effect: its parameters at their neutral values, those that act
    only through another (listed in :data:`NUISANCE`) from the generic design; for the
    strongly nonlinear effects also points of realistic size (see the constants above)."""
    names = {str(n) for n in effect.names}
    lo, hi = effect.bounds(effect.names[0])
    if names == {"beta_0", "log10_tau_0"}:
        return [{"beta_0": 0.0, "log10_tau_0": math.log10(f * scales["t_ramp"])}
                for f in TAU_OVER_RAMP]
    if names == {"softening", "log10_softening_m"}:
        return [{"softening": 0.0, "log10_softening_m": math.log10(f * scales["energy"])}
                for f in M_OVER_ENERGY]
    if names == {"mu_1", "alpha_1"}:
        return [{"mu_1": 0.0, "alpha_1": a} for a in ALPHA_1]
    if names == {"nu0"}:
        return [{"nu0": nu0}] + [{"nu0": v} for v in NU0_BELOW if lo <= v < nu0]
    if names == {"log10_k"}:
        if effect.name == "glued_ends":
            return [{"log10_k": v} for v in CUBE_LOG10_K]
        ks = [float(np.clip(math.log10(f * scales["glue"]), lo, hi)) for f in GLUE_OVER_SHEAR]
        return [{"log10_k": k} for k in dict.fromkeys(ks)]
    return [{str(n): 0.0 for n in effect.names}]  # offsets: zero


def neutral_point(effect, nu0: float) -> dict | None:
    """The design point where ``effect`` *is* the current model, every parameter at its
    neutral value (``nu0`` for the assumed one), where its score is the score statistic
    proper; None when some parameter has no finite neutral value (a glue layer's is at
    infinity) or acts only through another (a relaxation time, a softening's m)."""
    point = {str(n): nu0 if v is None else v for n, v in effect.neutral.items()}
    if set(point) != {str(n) for n in effect.names} or not all(
            map(math.isfinite, point.values())):
        return None
    return point


MAX_STEP_OF_RANGE = 0.3  # a Gauss-Newton step longer than this share of the bounds is not
# trusted as a start


def _too_long(effect, name, step: float) -> bool:
    """Whether the step of an effect parameter is too long to be trusted as a start."""
    if name not in effect.names:
        return False
    lo, hi = effect.bounds(name)
    return abs(step) > MAX_STEP_OF_RANGE * (hi - lo)

# Parameters with no effect at the neutral point (they act through another): not scored
NUISANCE = {Param("log10_tau", 0), Param("log10_softening_m"), Param("alpha", 1)}


def at_point(values: dict, point: dict) -> dict:
    """The parameters ``values`` with a design ``point``'s in place (its names parsed):
    where a score is taken, and so where the model was solved."""
    return {**values, **{Param.parse(k): float(v) for k, v in point.items()}}


def score(sim, obs: pd.DataFrame, sigma: np.ndarray, current, effect, point: dict,
          base_names, base_jacobian: np.ndarray) -> Score:
    """The chi-square ``effect`` can remove from the ``current`` fit, predicted by one
    Gauss-Newton step from the design ``point`` (the current parameters ``base_names``
    move too).  At a neutral point, where the effect model *is* the current one, this is
    the score statistic, and ``base_jacobian`` (the current model's) serves for the base
    columns; elsewhere the point's own Jacobian is used.  Also the Gauss-Newton start."""
    values = at_point(current.values, point)
    scored = [n for n in effect.names if n not in NUISANCE]
    names = list(base_names) + scored
    data = obs["value"].to_numpy(float)
    z_cur = (current.prediction - data) / sigma
    t0 = time.perf_counter()
    # a point of finite size (a glue layer, a lower nu0) needs its own Jacobian: predicted
    # with it at once (a prediction and its columns do not depend on the other columns asked)
    own = effect.of_finite_size(point, sim.nu0)
    pred = sim.predict(values, names if own else scored)
    z = (pred.y - data) / sigma
    neutral = float(np.max(np.abs(z - z_cur))) < 1e-6
    if neutral:
        cols = pred.jacobian[:, len(base_names):] if own else pred.jacobian
        J = np.column_stack([base_jacobian, cols]) / sigma[:, None]
    else:
        if not own:
            pred = sim.predict(values, names)
        J = pred.jacobian / sigma[:, None]
    seconds = time.perf_counter() - t0
    nb = len(base_names)
    norms = np.linalg.norm(J, axis=0)
    scale = max(float(norms[:nb].max()) if nb else 1.0, 1e-300)
    active = [j for j in range(len(names)) if j < nb or norms[j] > 1e-9 * scale]
    scale_a = np.where(norms[active] > 0, norms[active], 1.0)  # of the active columns
    Ja = J[:, active] / scale_a
    # columns of Ja that take their Gauss-Newton step: an effect parameter at a bound
    # of its range (a relaxation, a softening or a second Ogden term of no strength) whose
    # step leaves the range is held there and the rest solved without it, so that the
    # score is the one-sided statistic of a parameter on its boundary: the gain the
    # effect can bring within its range, not one a fit clipped to the bound cannot have
    free, step = _within_bounds(effect, [names[j] for j in active], values, Ja, z,
                                scale_a, nb)
    predicted = float(np.sum((z + Ja[:, free] @ step) ** 2))
    if len(free) < len(active):  # else the step is the two-sided one already
        step_free, *_ = np.linalg.lstsq(Ja, -z, rcond=None)
        predicted_free = float(np.sum((z + Ja @ step_free) ** 2))
    else:
        predicted_free = predicted
    Jb = J[:, :nb] / np.where(norms[:nb] > 0, norms[:nb], 1.0)
    sb, *_ = np.linalg.lstsq(Jb, -z_cur, rcond=None)
    current_chi2 = float(np.sum((z_cur + Jb @ sb) ** 2))
    start = dict(values)
    held = []
    while True:
        d = step / scale_a[free]
        too_long = [k for k, dk in zip(free, d, strict=True) if _too_long(
            effect, names[active[k]], dk)]
        if not too_long:
            break
        # far beyond the linear model: such a parameter starts at the design point itself,
        # and the others take the step solved with it held there, not the one solved
        # jointly with its long step
        free = [k for k in free if k not in too_long]
        held += [str(names[active[k]]) for k in too_long]
        step, *_ = np.linalg.lstsq(Ja[:, free], -z, rcond=None)
    for k, dk in zip(free, d, strict=True):
        name = names[active[k]]
        start[name] = values[name] + float(dk)  # the fit clips it to the bounds
    return Score(effect.name, max(current_chi2 - predicted, 0.0), len(active) - nb, start,
                 point, seconds, tuple(held), max(current_chi2 - predicted_free, 0.0))


# Candidates whose neutral point is finite and whose every parameter acts there (no
# nuisance parameter), so that one Jacobian at the final fit says how large they would have
# to be to show: compressibility (from the assumed nu0) and the test artefacts (from zero)
LINEAR_AT_NEUTRAL = ("compressibility", "artefacts")
# Candidates whose amplitude acts at its neutral zero only through a nuisance parameter
# (beta with tau, mu_1 with alpha_1): their limits are stated at each point of the generic
# design, each point a further term of the same family on a free index (a Maxwell branch,
# an Ogden term of zero size), so that the same single prediction serves them all
AT_DESIGN = ("viscoelastic", "ogden_2term")
# Candidates like those AT_DESIGN but with no free term index (one Ogden-Roxburgh
# softening per model): one prediction per design point; with the amplitude at zero its
# path is the final fit's, so only the amplitude's column is new
PER_POINT = ("mullins",)
# Candidates whose neutral point is at infinity (a glue layer as stiff as glue can be): no
# derivative at a point says where they show (a glue layer's chi-square grows about as its
# compliance 1/k); stated from direct solves along their own coordinate (_compliance_limits)
IN_COMPLIANCE = ("imperfect_gluing",)


def _within_bounds(effect, names: list, values: dict, Ja: np.ndarray, z: np.ndarray,
                   scale: np.ndarray, nb: int) -> tuple[list, np.ndarray]:
    """The columns of ``Ja`` (parameters ``names``, the first ``nb`` the current model's)
    free to step, and their least-squares step on ``-z``: an effect parameter at a bound
    of its range whose step (``/ scale``) points out of it is held at the bound, and the
    step solved again without it, until no step leaves the range (the Kuhn-Tucker point
    of the linearised problem with those bounds, reached by dropping active ones)."""
    free = list(range(len(names)))
    while True:
        step, *_ = np.linalg.lstsq(Ja[:, free], -z, rcond=None)
        out = []
        for k, dk in zip(free, step / scale[free], strict=True):
            name = names[k]
            if k < nb or name not in effect.names:
                continue
            lo, hi = effect.bounds(name)
            if (values[name] <= lo and dk < 0) or (values[name] >= hi and dk > 0):
                out.append(k)
        if not out:
            return free, step
        free = [k for k in free if k not in out]


def design_scales(sim, obs: pd.DataFrame, values: dict) -> dict:
    """:func:`data_scales` of ``obs`` for the simulator's specimen (5 mm when unknown)."""
    geometry = getattr(sim, "geometry", None)
    return data_scales(obs, values, geometry.height_mm if geometry is not None else 5.0)


def _amplitude_and_nuisance(effect) -> tuple[Param, Param]:
    """The parameter of an effect that acts at its neutral zero, and the one that acts only
    through it (:data:`NUISANCE`)."""
    (amp,) = [n for n in effect.names if n not in NUISANCE]
    (nuis,) = [n for n in effect.names if n in NUISANCE]
    return amp, nuis


def _term_copies(effect, points: list[dict], values) -> tuple[Param, Param, list]:
    """The amplitude and the nuisance parameter of an :data:`AT_DESIGN` effect, and per
    design point (the point's coordinates on a free term index, the amplitude parameter
    there, the nuisance parameter there).  Free: beyond every index of the effect's
    families among ``values`` (the current model's terms)."""
    fams = {n.family for n in effect.names}
    k = 1 + max([p.index for p in map(Param.parse, values)
                 if p.family in fams and p.index is not None], default=-1)
    amp, nuis = _amplitude_and_nuisance(effect)
    out = []
    for i, pt in enumerate(points):
        a, q = Param(amp.family, k + i), Param(nuis.family, k + i)
        out.append(({a: 0.0, q: float(pt[str(nuis)])}, a, q))
    return amp, nuis, out


def detection_limits(sim, current, current_names, J_current: np.ndarray, effects: dict,
                     whiten, needed, points: dict | None = None,
                     named: dict | None = None) -> dict:
    """How large each candidate of ``effects`` (of :data:`LINEAR_AT_NEUTRAL` and, with
    their design ``points`` ({effect: [point, ...]}), of :data:`AT_DESIGN`,
    :data:`PER_POINT` and :data:`IN_COMPLIANCE` (solved: :func:`_compliance_limits`); not in the
    ``current`` model) would have to be to earn its place beside the current model, one
    parameter at a time, linearised at its neutral point: with the whitened Jacobians J_m
    of the current model and j of the parameter, the smallest step that removes
    ``needed(effect)`` of chi-square is sqrt(needed) / ||(I - P_{J_m}) j||.  What the
    current parameters can mimic does not count: an effect the named ones mask has a large
    limit, beyond its bounds when no allowed value would show.  An effect with a nuisance
    parameter has one limit of its amplitude per design point (tau, alpha_1, the softening
    scale m held there; :data:`PER_POINT` effects one prediction per point).
    ``whiten``: the noise model's whitening of Jacobian columns (``J_current``, the final
    fit's, serves the effects without design points; with them, the model's columns come
    from the same prediction).  Returns {effect: {label:
    {"parameter", "at" (the nuisance held, or {}), "from", "step", "step_alone" (beside
    nothing: what the tests can show at all), "would_show_at", "within_bounds"}}}, the label
    the parameter's name (with ``at ...`` for a design point).  With ``named`` ({effect:
    its parameter names} of effects in the current model), each limit of a linearised
    candidate also gets "step_without" ({effect: the step beside the model without that
    effect's columns}: :func:`hidden_behind`).  Raises ValueError when a Jacobian is not
    finite."""
    points = points or {}
    taken = set(current_names)

    def free(kind):  # the candidates of a kind that can be stated here
        return {e: eff for e, eff in effects.items() if e in kind and not set(eff.names) & taken
                and (kind is LINEAR_AT_NEUTRAL or points.get(e))}

    compliance = free(IN_COMPLIANCE)
    # another end condition (interface springs): solves of their own
    out = _compliance_limits(sim, current, J_current, compliance, whiten, needed,
                             points) if compliance else {}
    for e, eff in free(PER_POINT).items():
        out[e] = _per_point_limits(sim, current, current_names, J_current, eff, points[e],
                                   whiten, needed(eff), named)
    linear = free(LINEAR_AT_NEUTRAL)
    at_design = {e: _term_copies(eff, points[e], current.values)
                 for e, eff in free(AT_DESIGN).items()}
    if not linear and not at_design:
        return out
    values = {n: (sim.nu0 if str(n) == "nu0" else 0.0) for eff in linear.values()
              for n in eff.names}
    # (effect, label, parameter as the effect names it, coordinate predicted, "at")
    rows = [(e, str(n), n, n, {}) for e, eff in linear.items() for n in eff.names]
    for e, (amp, nuis, copies) in at_design.items():
        for coords, a, q in copies:
            values.update(coords)
            rows.append((e, _at_label(amp, nuis, coords[q]), amp, a, {str(nuis): coords[q]}))
    names = [r[3] for r in rows]
    point = {**current.values, **values}
    if at_design:  # further terms (a Maxwell branch brings the history along) put the
        # prediction on another path than the final fit's: the model's columns from it too
        own = sim.predict(point, list(current_names) + names).jacobian
        J_current, jac = own[:, :len(current_names)], own[:, len(current_names):]
    else:
        jac = sim.predict(point, names).jacobian
    (U, without), Jc = _spans(J_current, whiten, current_names, named), whiten(
        np.asarray(jac, float))
    if not np.isfinite(Jc).all():
        raise ValueError("a Jacobian at the final model is not finite")
    for col, (e, label, n, coord, at) in enumerate(rows):
        out.setdefault(e, {})[label] = _limit(Jc[:, col], U, math.sqrt(needed(effects[e])),
                                              n, values[coord], effects[e].bounds(n), at,
                                              without)
    return out


def _at_label(amp: Param, nuis: Param, x: float) -> str:
    """The label of an amplitude's limit at a design point of its nuisance parameter."""
    unit = {"log10_tau": " s", "log10_softening_m": " kPa"}.get(nuis.family, "")
    shown = (f"{str(nuis).removeprefix('log10_')} = {10.0 ** x:.3g}"
             if nuis.family.startswith("log10_") else f"{nuis} = {x:.3g}")
    return f"{amp} at {shown}{unit}"


def _limit(j: np.ndarray, U: np.ndarray, bar: float, n, x0: float, bounds: tuple,
           at: dict, without: dict | None = None) -> dict:
    """One entry of :func:`detection_limits`: the whitened column ``j`` of parameter ``n``
    at ``x0``, the model's span ``U``, the square root of the chi-square ``bar``;
    ``without``: {effect: the span of the model without that effect's columns}."""
    lo, hi = bounds

    def step_beside(V):
        left = float(np.linalg.norm(j - V @ (V.T @ j)))
        return bar / left if left > 0 else math.inf

    alone = float(np.linalg.norm(j))
    step = step_beside(U)
    show = [x for x in (x0 - step, x0 + step) if lo <= x <= hi]
    out = {"parameter": str(n), "at": at, "from": x0, "step": step,
           "step_alone": bar / alone if alone > 0 else math.inf,
           "would_show_at": show, "within_bounds": bool(show)}
    if without:
        out["step_without"] = {e: step_beside(V) for e, V in without.items()}
    return out


# A prediction within this many noise SDs of the final fit's (every row) is on its path,
# and the final fit's columns serve for the model: a softening switched on puts an elastic
# model on the recorded path, 0.003 SD off its faster one (open-world world000), which
# changes no limit beyond the precision it is stated with
SAME_PATH_SD = 0.01


def _per_point_limits(sim, current, current_names, J_current, effect, points: list[dict],
                      whiten, bar2: float, named: dict | None = None) -> dict:
    """:func:`detection_limits` of a :data:`PER_POINT` effect: its amplitude at zero and
    its nuisance parameter at each design point, one prediction each with the amplitude's
    column (and the model's columns too when the prediction leaves the final fit's path
    by more than :data:`SAME_PATH_SD`)."""
    amp, nuis = _amplitude_and_nuisance(effect)
    final = _spans(J_current, whiten, current_names, named)  # the final fit's, once
    out = {}
    for pt in points:
        x = float(pt[str(nuis)])
        values = {**current.values, amp: 0.0, nuis: x}
        pred = sim.predict(values, [amp])
        moved = whiten((pred.y - current.prediction)[:, None])
        if np.all(np.abs(moved) < SAME_PATH_SD):
            (U, without), j = final, pred.jacobian
        else:
            own = sim.predict(values, list(current_names) + [amp]).jacobian
            (U, without), j = _spans(own[:, :-1], whiten, current_names, named), own[:, -1:]
        Jc = whiten(np.asarray(j, float))
        if not np.isfinite(Jc).all():
            raise ValueError("a Jacobian at the final model is not finite")
        out[_at_label(amp, nuis, x)] = _limit(Jc[:, 0], U, math.sqrt(bar2), amp, 0.0,
                                              effect.bounds(amp), {str(nuis): x}, without)
    return out


def _span(J_current, whiten) -> np.ndarray:
    """An orthonormal basis of the span of the whitened model columns (zero and dependent
    columns add nothing); ValueError if they are not finite."""
    Jm = whiten(np.asarray(J_current, float))
    if not np.isfinite(Jm).all():
        raise ValueError("a Jacobian at the final model is not finite")
    U, sv, _ = np.linalg.svd(Jm, full_matrices=False)
    return U[:, sv > sv.max(initial=0.0) * 1e-10]


def _spans(J_model, whiten, names, named: dict | None) -> tuple[np.ndarray, dict]:
    """:func:`_span` of the model's columns (of parameters ``names``), and per effect of
    ``named`` ({effect: its parameter names}) the span without that effect's columns."""
    J_model = np.asarray(J_model, float)
    without = {e: _span(J_model[:, [i for i, n in enumerate(names) if n not in set(ns)]],
                        whiten) for e, ns in (named or {}).items()}
    return _span(J_model, whiten), without


def _compliance_limits(sim, current, J_current, effects: dict, whiten, needed,
                       points: dict) -> dict:
    """:func:`detection_limits` of the :data:`IN_COMPLIANCE` effects, by direct solves from
    the stiffest point of their design (:class:`_GlueScan`).  Stated in log10_k: ``from``
    its stiffest allowed value, ``would_show_at`` the stiffness below which a layer would
    show, ``step`` their difference, ``solved_at`` the stiffnesses solved."""
    U = _span(J_current, whiten)
    out: dict = {}
    for e, eff in effects.items():
        (n,) = eff.names
        lo, hi = eff.bounds(n)
        scan = _GlueScan(sim, current, n, (lo, hi), U, whiten, needed(eff))
        shows, shows_alone = scan.limits(max(float(p[str(n)]) for p in points[e]))
        show = [float(min(shows, hi))] if shows >= lo else []
        out[e] = {str(n): {"parameter": str(n), "at": {}, "from": hi, "step": hi - shows,
                           "step_alone": hi - shows_alone, "would_show_at": show,
                           "within_bounds": bool(show), "solved_at": sorted(scan.solved),
                           "in": "glue stiffness, solved"}}
    return out


class _GlueScan:
    """Where a glue layer of stiffness 10^log10_k shows beside the ``current`` model.  Its
    signature is far from linear in the compliance c = 10^-log10_k near zero (its
    chi-square grows about as c, not c^2: the interface takes the stress concentration at
    the glued edge), so no derivative at the neutral point can say where it shows; the
    logarithm of its chi-square is nearly linear in log10_k, though.  So: solved with its
    sensitivity at the design's stiffest point, then Newton steps on log(chi-square) =
    log(bar) until the chi-square at the step is within ``SCAN_TOLERANCE`` of the bar, on
    either side.  The chi-square counts what the model's parameters cannot mimic (the
    orthonormal basis ``U`` of their whitened columns projected out); alone, all of it."""

    def __init__(self, sim, current, name, bounds, U, whiten, bar2: float):
        self.sim, self.current, self.name, self.bounds = sim, current, name, bounds
        self.U, self.whiten, self.bar2 = U, whiten, bar2
        self.solved: dict = {}  # log10_k -> ((chi2, d chi2/d log10_k) beyond, alone)

    def solve(self, lk: float) -> tuple:
        lk = float(np.clip(lk, *self.bounds))
        if lk not in self.solved:
            p = self.sim.predict({**self.current.values, self.name: lk}, [self.name])
            zz = self.whiten(np.column_stack([p.y - self.current.prediction, p.jacobian[:, 0]]))
            if not np.isfinite(zz).all():
                raise ValueError("a prediction with a glue layer is not finite")
            U = self.U
            r = zz - U @ (U.T @ zz)
            self.solved[lk] = ((float(r[:, 0] @ r[:, 0]), 2.0 * float(r[:, 0] @ r[:, 1])),
                               (float(zz[:, 0] @ zz[:, 0]), 2.0 * float(zz[:, 0] @ zz[:, 1])))
        return lk, self.solved[lk]

    def newton(self, lk: float, col: int) -> float:
        """The Newton step on log(chi-square) - log(bar) from the solved ``lk`` (``col`` 0:
        beyond the model, 1: alone); -inf when it does not grow as the glue softens."""
        g, dg = self.solved[lk][col]
        if g <= 0 or dg >= 0:
            return -math.inf
        return lk + (math.log(self.bar2) - math.log(g)) / (dg / g)

    def limits(self, stiffest: float) -> tuple[float, float]:
        """(log10_k where the layer shows beside the model, where it shows alone: one Newton
        step from the solved point nearest to it)."""
        lo, hi = self.bounds
        lk = stiffest
        for _ in range(SCAN_SOLVES):
            at, ((g, _), _) = self.solve(lk)  # beyond the bounds: solved at the bound
            if g > 0 and abs(math.log(g / self.bar2)) < math.log(1.0 + SCAN_TOLERANCE):
                lk = at
                break
            lk = self.newton(at, 0)
            # the softest allowed glue solved and not showing (or the stiffest showing):
            # no allowed value is stated on an extrapolation alone
            if (at == lo and g < self.bar2 and lk <= at) or (at == hi and g > self.bar2
                                                              and lk >= at):
                break
        near = min(self.solved, key=lambda k: abs(math.log(
            max(self.solved[k][1][0], 1e-300) / self.bar2)))
        return lk, self.newton(near, 1)


SCAN_SOLVES = 4  # solves of a glue layer's scan at most
SCAN_TOLERANCE = 0.1  # a glue layer's stated stiffness: its chi-square within 10 % of the bar


# The variance inflation at which a candidate counts as hidden behind a named effect: the
# textbook bar of collinearity (a parameter's variance ten times what it is without the
# other; its detection step 3.2 times as long)
HIDDEN_INFLATION = 10.0


def hidden_behind(limits: dict, lib: dict) -> list[dict]:
    """The candidates a named effect hides: per (candidate, named effect), where some
    allowed value of the candidate would show beside the model without that effect while
    beside it the variance of the candidate's parameter is at least
    :data:`HIDDEN_INFLATION` times as large ((step / step_without)^2), the limit where it
    inflates most.  ``limits``: :func:`detection_limits` with ``named``."""
    out: dict = {}
    for e, d in limits.items():
        for v in d.values():
            n = Param.parse(v["parameter"])
            lo, hi = lib[e].bounds(n)
            for named, s0 in (v.get("step_without") or {}).items():
                shows = [x for x in (v["from"] - s0, v["from"] + s0) if lo <= x <= hi]
                infl = (v["step"] / s0) ** 2 if 0 < s0 < math.inf else 0.0
                if not shows or infl < HIDDEN_INFLATION or (
                        (e, named) in out and out[e, named]["inflation"] >= infl):
                    continue
                out[e, named] = {"effect": e, "behind": named, "parameter": v["parameter"],
                                 "at": v["at"], "inflation": infl,
                                 "would_show_without": shows,
                                 "would_show_at": v["would_show_at"],
                                 "separating_test": separating_test(e, named)}
    return list(out.values())


def masked_by_model(limit: dict, bounds: tuple[float, float]) -> bool:
    """Whether a parameter's detection limit (an entry of :func:`detection_limits`) says the
    current model masks it: alone some allowed value would show, beside the model none."""
    lo, hi = bounds
    x0, alone = limit["from"], limit["step_alone"]
    return not limit["within_bounds"] and (lo <= x0 - alone or x0 + alone <= hi)
