r"""What a model leaves unexplained, told apart from the rig's noise.

Two tests on the residual of the final model, whitened with the noise model estimated from
it (white noise, wander correlated over at most half a ramp, or one cycle in a series of
several, drift from the tare):

* **located**: the protocol's segments (:mod:`diagnosis.locate`) with chi-square and runs
  tests on the whitened residual, which is standard white noise where the model is right;
* **reproducible**: a generic smooth misfit, the same at every repetition of a ramp (a
  piecewise-linear function of the control value per curve, channel and branch, shared by
  all cycles; with one cycle, shared by loading and unloading), fitted to the whitened
  residual.  Wander is independent between repetitions, so it cannot make this term
  significant; a systematic misfit the model lacks is the same every time and does.
  Significant when its likelihood-ratio statistic has p < ``alpha`` and beats BIC by the
  margin.  Data without repetitions (loading only, one pass) cannot be tested this way,
  and the report says so;
* **trend**: the stiffness changing with time within the tests of several cycles (the
  prediction scaled by time at one rate for every test), which no library effect does;
  its size is reported as the relative change of the stiffness over the longest such
  test (``change`` +- ``change_se`` over ``span_s`` seconds);
* **split**: whether the shear tests ask for other material parameters than
  compression/tension (:func:`split_test`, a score test on the final fit's Jacobian): an
  isotropic material and every library effect describe both with one set, a fibre family
  along the axis, a stiffness changing between the tests or a set left by the first do not.

The noise model is estimated by restricted ML with these columns and the model's own
parameters projected out (:func:`systematic_basis`, :func:`diagnosis.noise.fit_noise`), so
it cannot absorb the misfit the tests look for; on short series that leaves few degrees of
freedom, so every test here is an F test with the noise's own (``NoiseModel.dof``),
weighted by the series that carry the test's gain (:func:`diagnosis.noise.nu_gain`)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
from scipy import stats

from . import locate as loc
from .noise import lrt_p_value, nu_gain
from .series import neutral_of

KNOTS = 5  # knots of the generic misfit per curve/channel/branch (plus the neutral value)


def _hat_basis(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Piecewise-linear hat functions on ``knots`` evaluated at ``x`` (n x len(knots))."""
    B = np.zeros((len(x), len(knots)))
    for j, k in enumerate(knots):
        left = knots[j - 1] if j > 0 else None
        right = knots[j + 1] if j + 1 < len(knots) else None
        b = np.zeros(len(x))
        if left is not None:
            m = (x >= left) & (x <= k)
            b[m] = (x[m] - left) / (k - left)
        if right is not None:
            m = (x >= k) & (x <= right)
            b[m] = np.maximum(b[m], (right - x[m]) / (right - k))
        if left is None:
            b[x <= k] = np.maximum(b[x <= k], 1.0)
        if right is None:
            b[x >= k] = np.maximum(b[x >= k], 1.0)
        B[:, j] = b
    return B


def reproducible_basis(obs: pd.DataFrame) -> tuple[np.ndarray, str]:
    """Columns of the generic reproducible misfit, and how it repeats (``cycles``,
    ``branches`` or ``none``)."""
    cols, how = [], "none"
    for (curve, _), g in obs.groupby(["curve", "channel"], sort=False):
        cycles = g["cycle"].nunique()
        branches = set(g["branch"]) - {"hold"}
        if cycles >= 2:
            groups, how = list(g.groupby("branch", sort=False)), "cycles"
        elif len(branches) >= 2:
            groups = [(None, g)]
            how = how if how == "cycles" else "branches"
        else:
            continue
        for _, gg in groups:
            x = gg["control"].to_numpy(float)
            knots = np.unique(np.r_[np.linspace(x.min(), x.max(), KNOTS), neutral_of(curve)])
            knots = knots[(knots >= x.min()) & (knots <= x.max())]
            if len(knots) < 2:
                continue
            col = np.zeros((len(obs), len(knots)))
            col[gg.index.to_numpy()] = _hat_basis(x, knots)
            cols.append(col)
    return (np.hstack(cols) if cols else np.zeros((len(obs), 0))), how


def trend_basis(obs: pd.DataFrame, prediction: np.ndarray) -> np.ndarray:
    """One column: the model's prediction times time (centred on each curve's mid-time, in
    units of the longest curve's duration), over every curve of several cycles: the
    response of a specimen whose stiffness drifts during the session (tissue degrading,
    drying, warming up) at one rate, the same in every test.  No effect of the library
    changes with time alone, so a trend the final model leaves is a misfit, whatever its
    cause.  One rate, not one per curve: a drift of the tissue is the tissue's, and a
    single column needs the least evidence to be seen (open-world-10)."""
    col, curves = np.zeros(len(obs)), list(_trend_curves(obs))
    for rows, tt in curves:
        col[rows] = prediction[rows] * (tt - 0.5 * (tt.min() + tt.max()))
    span = _span(curves)
    return (col / span)[:, None] if span > 0 else np.zeros((len(obs), 0))


def _trend_curves(obs: pd.DataFrame):
    """(rows, times) of every curve of several cycles with a usable clock."""
    t = obs["time_s"].to_numpy(float) if "time_s" in obs else np.full(len(obs), np.nan)
    for _, g in obs.groupby("curve", sort=False):
        rows = g.index.to_numpy()
        tt = t[rows]
        if g["cycle"].nunique() >= 2 and np.isfinite(tt).all() and np.ptp(tt) > 0:
            yield rows, tt


def trend_rows(obs: pd.DataFrame) -> np.ndarray:
    """Positions of the rows :func:`trend_basis` covers (the curves of several cycles)."""
    parts = [rows for rows, _ in _trend_curves(obs.reset_index(drop=True))]
    return np.concatenate(parts) if parts else np.zeros(0, int)


def trend_span(obs: pd.DataFrame) -> float:
    """The time unit of :func:`trend_basis` [s]: the longest curve of several cycles (0
    when there is none): its coefficient is the relative change of the stiffness over
    that time."""
    return _span(_trend_curves(obs))


def _span(curves) -> float:
    """The longest time span of ``curves`` ((rows, times) of :func:`_trend_curves`) [s]."""
    return max((float(np.ptp(tt)) for _, tt in curves), default=0.0)


def trend_change(trend: dict) -> str:
    """The modelled trend of :func:`remaining` in words: '-12 +- 2 % over 65 s'."""
    return (f"{100 * trend['change']:+.0f} +- {100 * trend['change_se']:.0f} % over "
            f"{trend['span_s']:.0f} s")


def systematic_basis(obs: pd.DataFrame, prediction: np.ndarray | None = None) -> np.ndarray:
    """Columns of every misfit these tests call systematic (the reproducible misfit and,
    with a ``prediction``, the stiffness trend), to be kept out of the noise model
    (:func:`diagnosis.noise.fit_noise`'s ``systematic``).  Wander slower than a ramp is
    nearly the same on both sides of a turn and is then partly kept out as well: beyond
    the noise model's contract (correlation over at most half a ramp, or one cycle in a
    series of several), it may be reported as misfit."""
    obs = obs.reset_index(drop=True)
    B, _ = reproducible_basis(obs)
    if prediction is not None:
        B = np.hstack([B, trend_basis(obs, np.asarray(prediction, float))])
    return B


def _lrt(Bw: np.ndarray, z: np.ndarray, n: int, alpha: float, bic_margin: float,
         nu_of) -> dict:
    """Gain of the columns ``Bw`` on the whitened residual ``z``: an F test with the
    noise's degrees of freedom ``nu_of(per-row gain)`` (:func:`diagnosis.noise.nu_gain`;
    a chi-square test where it is infinite, the noise known)."""
    return _lrt_and_coef(Bw, z, n, alpha, bic_margin, nu_of)[0]


def _lrt_and_coef(Bw: np.ndarray, z: np.ndarray, n: int, alpha: float, bic_margin: float,
                  nu_of) -> tuple[dict, np.ndarray]:
    """:func:`_lrt` and the columns' least-squares coefficients."""
    coef, _, rank, _ = np.linalg.lstsq(Bw, z, rcond=None)
    fitted = Bw @ coef
    gain = float(z @ z - np.sum((z - fitted) ** 2))
    p = lrt_p_value(gain, rank, nu_of(fitted**2)) if rank else 1.0
    return {"gain": gain, "dof": int(rank), "p_value": p, "significant": bool(
        rank and p < alpha and gain > rank * math.log(n) + bic_margin)}, coef


# Parameters that are the rig's, not the material's: one per channel already, never split
RIG_PARAMETERS = ("stretch_offset", "force_offset", "torque_offset")


def shear_rows(obs: pd.DataFrame) -> np.ndarray:
    """Per row, whether it belongs to a shear test (torsion, simple shear) rather than to
    compression/tension: the two kinds of test a consistent material must both explain."""
    return obs["curve"].astype(str).str.startswith(("torsion", "simple_shear")).to_numpy()


def split_test(obs: pd.DataFrame, z: np.ndarray, noise, jacobian: np.ndarray, names: list,
               alpha: float, bic_margin: float, nu_of,
               prediction: np.ndarray | None = None,
               smooth: np.ndarray | None = None) -> dict:
    """Whether the shear tests ask for other material parameters than compression/tension:
    the score (Lagrange-multiplier) test of the final model against the same model whose
    material parameters (``names`` but the rig's offsets) take other values in the shear
    tests, linearised at the fit (one Gauss-Newton step: no solve).  An isotropic material
    and a library effect describe every test with one set of parameters; a fibre family
    along the axis, a stiffness drifting between the tests or a set left by the first one
    do not, and a misfit each test's own fit hides shows here.  ``z``: the whitened
    residual; the gain is what the split columns remove beyond the model's own (the
    F test of :func:`_lrt`'s kind, with ``nu_of`` of the gain's rows).  Not applicable
    (dof 0) with only one kind of test.  ``steps``: per split parameter, its first-order
    shear value minus the joint one (ill-conditioned where parameters nearly mimic each
    other, as two Ogden terms do); with the model's ``prediction``, what the split does to
    the shear tests' response, which is well determined (a fit to their residual): the
    split model's response there minus the final model's, to first order, as a
    least-squares factor on the final model's response (``scale``, +0.1: the shear tests
    ask for a response 10 % stiffer than the fit of both gives them) and the RMS of the
    rest relative to the response's (``shape``).

    ``smooth``: whitened columns of the repeated misfit (:func:`reproducible_basis`) when
    its own test found nothing systematic there.  The split's columns are smooth along
    each ramp, as those are, and the noise model, fitted by restricted ML with those
    columns kept out, never saw the noise in that part of the residual: a low-pass
    filtered noise or a wander puts more there than the model says (measured, seed 7 of
    the open benchmark: two single effects whose split gains of 30 and 36 on 3-4 columns
    came from a noise 1.8-2 times the model's in variance).  The split is then also
    tested against the noise those columns show beyond the split's own
    (``smooth_noise``: that F test's p, whether it passes, and the columns' gain and
    degrees of freedom), reported beside the decision, which stays the first test's
    (:func:`diagnosis.notes.split_doubt` says when the second would reverse it)."""
    out = {"gain": 0.0, "dof": 0, "p_value": 1.0, "significant": False, "steps": {}}
    shear = shear_rows(obs)
    if jacobian is None or not shear.any() or shear.all():
        return out
    J = np.asarray(jacobian, float)
    cols = [j for j, n in enumerate(names) if str(n) not in RIG_PARAMETERS
            and np.any(J[shear, j] != 0) and np.any(J[~shear, j] != 0)]
    if not cols or not np.isfinite(J).all():
        return out
    Jw = noise.whiten_jacobian(J)
    Sw = noise.whiten_jacobian(J[:, cols] * shear[:, None])
    # the split columns and the residual beyond the model's own columns
    q, _ = np.linalg.qr(Jw)
    r = z - q @ (q.T @ z)
    S = Sw - q @ (q.T @ Sw)
    test, coef = _lrt_and_coef(S, r, len(z), alpha, bic_margin, nu_of)
    out.update(test, steps={str(names[j]): -float(c) for j, c in zip(cols, coef, strict=True)})
    if smooth is not None and smooth.shape[1] and test["dof"]:
        against = _against_smooth_noise(test, S, smooth - q @ (q.T @ smooth), r, alpha)
        if against is not None:
            out["smooth_noise"] = against
    if prediction is not None:  # the split model's Gauss-Newton step from the fit: its
        # split coefficients are ``coef`` (Frisch-Waugh), the model's follow from them
        base, *_ = np.linalg.lstsq(Jw, z - Sw @ coef, rcond=None)
        y = np.asarray(prediction, float)[shear]
        dy = J[shear] @ (-base) + J[np.ix_(shear, cols)] @ (-coef)
        yy = float(y @ y)
        if yy > 0:
            scale = float(dy @ y) / yy
            out.update(scale=scale, shape=float(np.linalg.norm(dy - scale * y))
                       / math.sqrt(yy))
    return out


def _against_smooth_noise(test: dict, S: np.ndarray, B: np.ndarray, r: np.ndarray,
                          alpha: float) -> dict | None:
    """The split's gain on the columns ``S`` (``test``) as an F test against the gain of
    the columns ``B`` beyond ``S`` on the residual ``r`` (all three whitened and beyond the
    model's own columns): numerator the split's gain per column, denominator what the
    smooth columns take besides it per column, both chi-square under the same noise
    whatever its true level in those directions.  ``{"p_value", "significant" (p <
    alpha and the first test significant), "gain", "dof"}`` (the last two the
    reference's), or None when ``B`` adds no column."""
    both = np.hstack([S, B])
    coef, _, rank, _ = np.linalg.lstsq(both, r, rcond=None)
    extra = float(r @ r - np.sum((r - both @ coef) ** 2)) - test["gain"]
    dof = int(rank) - test["dof"]
    if dof <= 0 or extra <= 0.0:
        return None
    p = float(stats.f.sf((test["gain"] / test["dof"]) / (extra / dof), test["dof"], dof))
    return {"p_value": p, "significant": bool(test["significant"] and p < alpha),
            "gain": extra, "dof": dof}


def split_words(split: dict) -> str:
    """The split test of :func:`split_test` in words: 'to first order a response 0.31 %
    softer and 1.2 % of it in shape; gain 57.1 on 4 columns, p = 4.3e-08'."""
    stats = f"gain {split['gain']:.1f} on {split['dof']} columns, p = {split['p_value']:.2g}"
    if "scale" not in split:
        return stats
    c = split["scale"]
    return (f"to first order a response {100 * abs(c):.2g} % "
            f"{'stiffer' if c >= 0 else 'softer'} and {100 * split['shape']:.2g} % of it in "
            f"shape; {stats}")


def remaining(obs: pd.DataFrame, residual: np.ndarray, noise, *, alpha: float = 1e-3,
              bic_margin: float = 10.0, prediction: np.ndarray | None = None,
              jacobian: np.ndarray | None = None, names: list = ()) -> dict:
    """The tests on ``residual`` (model minus recorded) under ``noise``; with the model's
    ``prediction``, also whether the stiffness trends with time (:func:`trend_basis`);
    with its ``jacobian`` (columns ``names``), whether the kinds of test ask for other
    parameters (:func:`split_test`)."""
    obs = obs.reset_index(drop=True)
    z = noise.whiten(np.asarray(residual, float))
    table = loc.locate(obs, z, 1.0, sigma_dof=noise.dof)
    located = loc.summary(table)["located"]
    dof = np.asarray(noise.dof, float)

    def nu(gain: np.ndarray) -> float:  # weighted by the series that carry the gain
        return nu_gain(obs, dof, gain)

    B, how = reproducible_basis(obs)
    Bw = noise.whiten_jacobian(B) if B.shape[1] else B
    rep = {"repeats": how, "gain": 0.0, "dof": 0, "p_value": 1.0, "significant": False}
    if B.shape[1]:
        rep.update(_lrt(Bw, z, len(obs), alpha, bic_margin, nu))
    trend = {"gain": 0.0, "dof": 0, "p_value": 1.0, "significant": False}
    if prediction is not None:
        T = trend_basis(obs, np.asarray(prediction, float))
        if T.shape[1]:
            Tw = noise.whiten_jacobian(T)
            trend = _lrt(Tw, z, len(obs), alpha, bic_margin, nu)
            # the trend modelled: the recorded stiffness is the model's times
            # 1 + change (t - mid) / span (the residual is model minus recorded), with
            # its standard error (the whitened residual has unit variance)
            tt = float(Tw[:, 0] @ Tw[:, 0])
            if tt > 0:
                trend.update(change=-float(Tw[:, 0] @ z) / tt, change_se=1.0 / math.sqrt(tt),
                             span_s=trend_span(obs))
    split = split_test(obs, z, noise, jacobian, list(names), alpha, bic_margin, nu,
                       prediction, smooth=None if rep["significant"] or not B.shape[1]
                       else Bw)
    out = {"located": located, "reproducible": rep, "trend": trend, "split": split,
           "table": table}
    out["systematic"] = systematic(out)
    return out


def systematic(rem: dict, besides: tuple = ()) -> bool:
    """Whether what :func:`remaining` found leaves a systematic misfit: a located one, or
    a significant repeated misfit, stiffness trend or split, those tests named in
    ``besides`` left out (what the status would be without them)."""
    return bool(rem["located"]) or any(rem[k]["significant"] for k in (
        "reproducible", "trend", "split") if k not in besides)
