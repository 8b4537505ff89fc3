"""Locate where the misfit of a fitted material model is systematic rather than noise.

Input is the *observation table* (one row per recorded value)::

    specimen  str    specimen id
    curve     str    e.g. ``compression_tension``, ``torsion_0.15``, ``tension``, ``simple_shear``
    channel   str    ``stress``, ``torque``, ``axial_force``, ...
    branch    str    ``loading`` | ``unloading`` (any other label is kept as its own branch)
    cycle     int    >= 1
    control   float  stretch (stretch curves) or amount of shear (``torsion*``,
                     ``simple_shear*``); neutral value 1 resp. 0
    time_s    float  may be NaN (not used: rows of one series are in recording order)
    value     float  recorded value

together with a residual ``r`` (recorded minus model, one per row).  A *series* is one
``(specimen, curve, channel)``; its rows are in recording (time) order.

The procedure, "with a statistic, not by eye":

1. :func:`estimate_noise`: a noise level sigma per series from the residual's second
   differences ``d_i = r_{i-1} - 2 r_i + r_{i+1}``, which for white noise have
   ``var d = 6 sigma^2`` and in which a smooth (systematic) misfit barely appears
   (``d_i ~ r''(t) dt^2``).  The effective degrees of freedom ``nu`` of each estimate
   (:func:`noise_dof`) are kept so that the tests below account for sigma being estimated.
2. :func:`segments`: the protocol's own axes (test, channel, branch, cycle, range) and a
   fine ``cell`` partition (curve, channel, branch, side/range) for the mismatch map.
3. :func:`locate`: on each segment, with ``z = r / sigma``, an excess-variance test
   (``chi2 = sum z^2``) and a Wald-Wolfowitz runs test on the signs of ``z`` in recording
   order; Bonferroni over the segments.  :func:`summary` condenses the table for JSON.
4. :func:`mismatch_map`: z against control per curve/channel and a heat map of
   ``-log10 p`` over the cells.

Why these two tests: sigma comes from second differences, so a smooth misfit leaves it
(almost) unchanged while it adds ``sum m_i^2 / sigma^2`` to ``chi2`` -- excess variance
over the local noise level is the signature of misfit.  A smooth misfit also makes
consecutive residuals share their sign, i.e. too *few* runs, which the runs test detects
even when the misfit is comparable to the noise in amplitude but long in extent; it is
conditional on the numbers of positive and negative signs, hence free of sigma.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import special

log = logging.getLogger(__name__)

__all__ = [
    "AXES",
    "REQUIRED_COLUMNS",
    "estimate_noise",
    "locate",
    "mismatch_map",
    "neutral_of",
    "noise_dof",
    "segments",
    "summary",
]

REQUIRED_COLUMNS = ("specimen", "curve", "channel", "branch", "cycle", "control", "value")
SERIES = ("specimen", "curve", "channel")
AXES = ("specimen", "test", "channel", "branch", "cycle", "range", "cell")
TABLE_COLUMNS = ("axis", "segment", "n", "mean_z", "rms_z", "chi2", "p_chi2", "runs_z",
                 "p_runs", "p_value", "systematic", "nu_sigma")

MAD_TO_SD = 1.4826  # 1 / Phi^{-1}(3/4): MAD of a normal sample -> its standard deviation
MIN_SERIES = 5  # shorter series borrow the pooled estimate of their channel
MIN_DIFFS = 3  # fewest second differences for a robust scale
REWEIGHT_C = 3.0  # hard-rejection cut (in robust SDs) of the reweighting step
# Effective degrees of freedom per second difference of the reweighted scale estimate:
# var(s^2 / sigma^2) = 2 / nu with nu = DOF_PER_DIFF * n_d.  The d_i are MA(2)-correlated
# (lag-1 and lag-2 correlations -2/3 and 1/6), so even the plain mean of d^2 has only
# n_d / (1 + 2 (4/9 + 1/36)) = 0.51 n_d; calibrated by simulation (N = 20..120 points,
# runs of 10..60) at 0.47-0.48.  The MAD alone would give 0.23 n_d.
DOF_PER_DIFF = 0.47
FLOOR_REL = 1e-12  # sigma floor, relative to the channel's peak |value|
FLOOR_ABS = 1e-300
_TRUNC_K = 1.0 - 2.0 * REWEIGHT_C * math.exp(-0.5 * REWEIGHT_C**2) / math.sqrt(2.0 * math.pi) \
    / math.erf(REWEIGHT_C / math.sqrt(2.0))  # k(c) = 1 - 2 c phi(c) / (2 Phi(c) - 1)
MIN_SEGMENT = 5  # smaller segments are listed but not tested (p = NaN)
SHEAR_PREFIXES = ("torsion", "simple_shear")


def neutral_of(curve: str) -> float:
    """Neutral control value: 0 for shear curves (``torsion*``, ``simple_shear*``), else 1."""
    return 0.0 if str(curve).startswith(SHEAR_PREFIXES) else 1.0


def _check(obs: pd.DataFrame, *arrays: tuple[str, np.ndarray | None]) -> None:
    missing = [c for c in REQUIRED_COLUMNS if c not in obs.columns]
    if missing:
        raise ValueError(f"observation table lacks column(s) {', '.join(missing)}")
    for name, a in arrays:
        if a is not None and len(a) != len(obs):
            raise ValueError(f"{name} has {len(a)} values, observation table has {len(obs)} rows")


def _as_float(a, name: str, n: int) -> np.ndarray:
    out = np.asarray(a, dtype=float).reshape(-1)
    if out.size != n:
        raise ValueError(f"{name} has {out.size} values, observation table has {n} rows")
    return out


def _series_ids(obs: pd.DataFrame, keys: Sequence[str] = SERIES) -> np.ndarray:
    """Integer id per row of the ``keys`` group, numbered by first appearance."""
    combined = np.zeros(len(obs), dtype=np.int64)
    for k in keys:
        codes, uniques = pd.factorize(obs[k], use_na_sentinel=False)
        combined = combined * max(len(uniques), 1) + codes
        combined = pd.factorize(combined)[0].astype(np.int64)  # keep the numbers small
    return combined


def _run_ids(obs: pd.DataFrame) -> np.ndarray:
    """Id per row of its *run*: consecutive rows (recording order) of one series with equal
    (branch, cycle); a turning point of the protocol starts a new run."""
    n = len(obs)
    sid = _series_ids(obs)
    bc = _series_ids(obs, ("branch", "cycle"))
    run = np.zeros(n, dtype=np.int64)
    for _, pos in _groups(obs):
        new = np.r_[True, bc[pos][1:] != bc[pos][:-1]]
        run[pos] = np.cumsum(new) - 1
    return _series_ids(pd.DataFrame({"s": sid, "r": run}), ("s", "r")) if n else run


def _groups(obs: pd.DataFrame, keys: Sequence[str] = SERIES) -> list[tuple[tuple, np.ndarray]]:
    """``[(key values, ascending row positions)]`` per group, in order of first appearance."""
    ids = _series_ids(obs, keys)
    order = np.argsort(ids, kind="stable")
    bounds = np.flatnonzero(np.diff(ids[order])) + 1
    cols = [obs[k].to_numpy() for k in keys]
    return [(tuple(c[pos[0]] for c in cols), pos) for pos in np.split(order, bounds)
            if pos.size]


def _second_differences(r: np.ndarray, run_key: np.ndarray) -> np.ndarray:
    """``d_i = r_{i-1} - 2 r_i + r_{i+1}`` within runs of equal ``run_key`` (consecutive rows
    of one (branch, cycle)); runs are also cut at non-finite residuals, so the kinks of the
    protocol's turning points never enter."""
    n = r.size
    if n < 3:
        return np.empty(0)
    ok = np.isfinite(r)
    same = (run_key[1:] == run_key[:-1]) & ok[1:] & ok[:-1]  # pair (i, i+1) in one run
    valid = same[:-1] & same[1:]  # triple (i, i+1, i+2) in one run
    d = r[:-2] - 2.0 * r[1:-1] + r[2:]
    return d[valid]


def _robust_sd(d: np.ndarray) -> float:
    """Noise SD from second differences, ``sigma = s_d / sqrt(6)``.

    ``s0 = 1.4826 * median|d - median d|`` (MAD, robust to the few d that straddle a kink or
    an outlier); then one reweighting step for efficiency (the MAD alone has 37 % Gaussian
    efficiency): ``s_d^2 = sum_{|d - med| <= c s0} (d - med)^2 / (n_kept * k(c))`` with
    ``c = 3`` and the truncated-normal consistency factor
    ``k(c) = 1 - 2 c phi(c) / (2 Phi(c) - 1)``.  Returns NaN if it cannot be formed and 0
    for identically flat differences (the caller floors it).
    """
    if d.size < MIN_DIFFS:
        return math.nan
    med = float(np.median(d))
    dev = np.abs(d - med)
    s0 = MAD_TO_SD * float(np.median(dev))
    if s0 <= 0.0:  # more than half of the d tie: fall back to the plain SD of d
        return float(np.sqrt(np.mean((d - med) ** 2)) / math.sqrt(6.0))
    keep = dev <= REWEIGHT_C * s0
    s = math.sqrt(float(np.sum(dev[keep] ** 2)) / (int(keep.sum()) * _TRUNC_K))
    return s / math.sqrt(6.0)


def _noise(obs: pd.DataFrame, residual) -> tuple[np.ndarray, np.ndarray]:
    """(sigma, nu) per row; see :func:`estimate_noise` and :func:`noise_dof`."""
    _check(obs)
    r = _as_float(residual, "residual", len(obs))
    n = len(obs)
    sigma = np.full(n, np.nan)
    nu = np.full(n, np.nan)
    if n == 0:
        return sigma, nu
    value = obs["value"].to_numpy(dtype=float)
    run_key = _series_ids(obs, ("branch", "cycle"))
    groups = _groups(obs)
    diffs: dict[tuple, np.ndarray] = {}
    for key, pos in groups:
        diffs[key] = _second_differences(r[pos], run_key[pos])
    by_channel: dict[str, list[np.ndarray]] = {}
    for key, d in diffs.items():
        by_channel.setdefault(key[2], []).append(d)
    pooled = {}
    for ch, ds in by_channel.items():
        d = np.concatenate(ds)
        pooled[ch] = (_robust_sd(d), DOF_PER_DIFF * d.size)
    channel = obs["channel"].to_numpy()
    for key, pos in groups:
        rr = r[pos]
        npts = int(np.isfinite(rr).sum())
        d = diffs[key]
        s = _robust_sd(d) if npts >= MIN_SERIES else math.nan
        dof = DOF_PER_DIFF * d.size
        if not math.isfinite(s):
            s, dof = pooled[key[2]]
            how = "pooled channel estimate"
            if not math.isfinite(s):
                fin = rr[np.isfinite(rr)]
                s = float(np.sqrt(np.mean(fin**2))) if fin.size else math.nan
                dof = float(fin.size)
                how = "RMS of the residual"
            log.debug("series %s: %d points, noise from the %s", key, npts, how)
        peak = np.nanmax(np.abs(value[channel == key[2]]), initial=0.0)
        floor = max(FLOOR_REL * (peak if math.isfinite(peak) else 0.0), FLOOR_ABS)
        if not math.isfinite(s) or s < floor:
            s = floor
        sigma[pos] = s
        nu[pos] = max(dof, 1.0)
    return sigma, nu


def estimate_noise(obs: pd.DataFrame, residual) -> np.ndarray:
    """Noise standard deviation per row, one value per (specimen, curve, channel) series.

    Within each run of consecutive rows with equal (branch, cycle) the second differences
    ``d_i = r_{i-1} - 2 r_i + r_{i+1}`` are formed (never across a turning point of the
    protocol).  For white noise of SD sigma, ``var d = (1 + 4 + 1) sigma^2 = 6 sigma^2``;
    a misfit that is smooth in recording order contributes only ``~ r''(t) dt^2`` (zero
    for a constant or linear misfit), so the estimate measures the noise, not the misfit::

        s0 = 1.4826 * MAD(d)                      (robust start)
        s_d^2 = mean_{|d - med| <= 3 s0} (d - med)^2 / k(3)     (one reweighting step)
        sigma = s_d / sqrt(6)

    ``k(c) = 1 - 2 c phi(c) / (2 Phi(c) - 1)`` makes the trimmed variance consistent.  The
    relative standard error of sigma is about ``1 / sqrt(2 nu)`` with ``nu = 0.47 n_d``
    (:func:`noise_dof`), i.e. 13-14 % for a 60-point series.

    Guards: a series with fewer than 5 finite residuals (or fewer than 3 differences) takes
    the pooled estimate over all second differences of its channel, failing that the RMS of
    its residual; sigma is floored at ``1e-12 * max |value|`` of the channel, so it is never
    0.  Residuals that are NaN stay NaN in ``z`` but do not break the estimate.
    """
    return _noise(obs, residual)[0]


def noise_dof(obs: pd.DataFrame, residual) -> np.ndarray:
    """Effective degrees of freedom ``nu`` of :func:`estimate_noise`'s sigma per row.

    ``nu = 2 / var(sigma_hat^2 / sigma^2)``; ``0.47 n_d`` for a series estimate from ``n_d``
    second differences (simulation-calibrated; see ``DOF_PER_DIFF``), the pooled count for a
    pooled estimate, the number of points for the RMS fallback.
    """
    return _noise(obs, residual)[1]


# --------------------------------------------------------------------------- segments

@dataclass(frozen=True)
class _Cell:
    curve: str
    channel: str
    branch: str
    part: str  # side (stretch curves) or range (shear curves)
    mask: np.ndarray

    @property
    def label(self) -> str:
        return f"{self.curve}/{self.channel}/{self.branch}/{self.part}"


def _ordered(values: Sequence) -> list:
    """Unique values in order of appearance, but ``loading`` before ``unloading``."""
    u = list(dict.fromkeys(values))
    rank = {"loading": 0, "unloading": 1}
    return sorted(u, key=lambda v: (rank.get(v, 2), u.index(v)))


def _geometry(obs: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per row: neutral value, deviation ``|control - neutral|``, curve max deviation and
    a tolerance for "at the neutral value"."""
    curve = obs["curve"].astype(str).to_numpy()
    control = obs["control"].to_numpy(dtype=float)
    neutral = np.array([neutral_of(c) for c in curve], dtype=float)
    dev = np.abs(control - neutral)
    maxdev = pd.Series(dev).groupby(curve).transform("max").to_numpy(dtype=float)
    tol = 1e-9 * np.where(np.isfinite(maxdev) & (maxdev > 0), maxdev, 1.0)
    return neutral, dev, maxdev, tol


def _parts(obs: pd.DataFrame) -> np.ndarray:
    """Cell part per row: ``compression`` / ``tension`` / ``neutral`` (stretch curves),
    ``small`` / ``large`` (shear curves, ``|control - neutral| <= max / 2``)."""
    control = obs["control"].to_numpy(dtype=float)
    neutral, dev, maxdev, tol = _geometry(obs)
    shear = neutral == 0.0
    small = dev <= 0.5 * maxdev
    side = np.where(control < neutral - tol, "compression",
                    np.where(control > neutral + tol, "tension", "neutral"))
    part = np.where(shear, np.where(small, "small", "large"), side)
    return np.where(np.isfinite(control), part, "unknown").astype(object)


def _cells(obs: pd.DataFrame) -> list[_Cell]:
    curve = obs["curve"].astype(str).to_numpy()
    channel = obs["channel"].astype(str).to_numpy()
    branch = obs["branch"].astype(str).to_numpy()
    part = _parts(obs)
    order = ["compression", "tension", "neutral", "small", "large", "unknown"]
    out = []
    for cv in dict.fromkeys(curve):
        for ch in dict.fromkeys(channel[curve == cv]):
            m_cc = (curve == cv) & (channel == ch)
            for br in _ordered(branch[m_cc]):
                m_b = m_cc & (branch == br)
                for p in order:
                    m = m_b & (part == p)
                    if m.any():
                        out.append(_Cell(cv, ch, br, p, m))
    return out


def segments(obs: pd.DataFrame) -> list[tuple[str, str, np.ndarray]]:
    """The protocol's own axes as ``(axis, label, boolean row mask)``.

    * ``specimen``: each specimen (only when the table holds more than one);
    * ``test``: each curve;
    * ``channel``: each ``curve/channel`` of curves with more than one channel, and each
      channel overall;
    * ``branch``: ``loading`` / ``unloading`` overall and ``curve/branch`` per curve;
    * ``cycle``: ``cycle k`` overall (only with more than one cycle);
    * ``range``: per curve, ``curve/compression`` (stretch < 1) and ``curve/tension``
      (stretch > 1) for stretch curves; ``curve/small`` (``|control - neutral| <= max/2``,
      the max over the curve) and ``curve/large`` for every curve;
    * ``cell``: the fine partition ``curve/channel/branch/part`` with part the side
      (``compression``, ``tension``, or ``neutral`` for stretch exactly 1) of stretch
      curves and the range (``small`` / ``large``) of shear curves.

    A non-cell segment whose rows equal those of an earlier one (e.g. the per-curve branch
    when there is a single curve) is dropped so that no test is counted twice; cells are
    always kept (they tile the map).  Masks are positional (``len(obs)``).
    """
    _check(obs)
    n = len(obs)
    out: list[tuple[str, str, np.ndarray]] = []
    if n == 0:
        return out
    seen: set[bytes] = set()

    def add(axis: str, label: str, mask: np.ndarray) -> None:
        if not mask.any():
            return
        key = np.packbits(mask).tobytes()
        if key in seen:
            return
        seen.add(key)
        out.append((axis, label, mask))

    specimen = obs["specimen"].astype(str).to_numpy()
    curve = obs["curve"].astype(str).to_numpy()
    channel = obs["channel"].astype(str).to_numpy()
    branch = obs["branch"].astype(str).to_numpy()
    cycle = obs["cycle"].to_numpy()
    control = obs["control"].to_numpy(dtype=float)
    curves = list(dict.fromkeys(curve))

    specimens = list(dict.fromkeys(specimen))
    if len(specimens) > 1:
        for sp in specimens:
            add("specimen", sp, specimen == sp)
    for cv in curves:
        add("test", cv, curve == cv)
    for cv in curves:
        chans = list(dict.fromkeys(channel[curve == cv]))
        if len(chans) > 1:
            for ch in chans:
                add("channel", f"{cv}/{ch}", (curve == cv) & (channel == ch))
    for ch in dict.fromkeys(channel):
        add("channel", ch, channel == ch)
    for br in _ordered(branch):
        add("branch", br, branch == br)
    for cv in curves:
        for br in _ordered(branch[curve == cv]):
            add("branch", f"{cv}/{br}", (curve == cv) & (branch == br))
    cycles = sorted(dict.fromkeys(cycle.tolist()))
    if len(cycles) > 1:
        for cy in cycles:
            name = int(cy) if float(cy).is_integer() else cy
            add("cycle", f"cycle {name}", cycle == cy)
    neutral, dev, maxdev, tol = _geometry(obs)
    for cv in curves:
        m_c = curve == cv
        if neutral_of(cv) == 1.0:
            add("range", f"{cv}/compression", m_c & (control < 1.0 - tol))
            add("range", f"{cv}/tension", m_c & (control > 1.0 + tol))
        small = m_c & np.isfinite(dev) & (dev <= 0.5 * maxdev)
        add("range", f"{cv}/small", small)
        add("range", f"{cv}/large", m_c & np.isfinite(dev) & ~small)
    for cell in _cells(obs):
        if cell.mask.any():
            out.append(("cell", cell.label, cell.mask))
    return out


# ------------------------------------------------------------------------------ tests

def runs_test(signs: np.ndarray) -> tuple[float, float, int]:
    """One-sided Wald-Wolfowitz runs test for *too few* runs.

    With ``n1`` positive and ``n2`` negative signs (zeros dropped), ``N = n1 + n2`` and
    ``R`` runs, under independence (conditional on n1, n2)::

        E R = 1 + 2 n1 n2 / N,   var R = 2 n1 n2 (2 n1 n2 - N) / (N^2 (N - 1))
        runs_z = (R - E R + 1/2) / sqrt(var R),   p = Phi(runs_z)

    (normal approximation with continuity correction).  If every sign is the same
    (``R = 1``, var R = 0) the conditional test is void and ``p = 2^(1 - N)``, the
    probability of a single run for independent fair signs.  Returns ``(runs_z, p, R)``.
    """
    s = np.asarray(signs, dtype=float)
    s = s[np.isfinite(s) & (s != 0)]
    big_n = s.size
    if big_n < 2:
        return math.nan, 1.0, big_n
    pos = s > 0
    n1 = int(pos.sum())
    n2 = big_n - n1
    runs = 1 + int(np.count_nonzero(pos[1:] != pos[:-1]))
    if n1 == 0 or n2 == 0:
        return -math.inf, min(1.0, 2.0 ** (1 - big_n)), runs
    mean = 1.0 + 2.0 * n1 * n2 / big_n
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - big_n) / (big_n**2 * (big_n - 1.0))
    if var <= 0.0:
        return 0.0, 1.0, runs
    z = (runs - mean + 0.5) / math.sqrt(var)
    return z, float(special.ndtr(z)), runs


def _chi2_p(chi2: float, n: int, nu_eff: float) -> float:
    """Upper tail of ``chi2 = sum z^2``: ``chi2 / n ~ F(n, nu_eff)`` when sigma is estimated
    with ``nu_eff`` degrees of freedom, ``chi2 ~ chi-square(n)`` when it is known."""
    if not math.isfinite(chi2):
        return 0.0
    if not math.isfinite(nu_eff) or nu_eff > 1e7:
        return float(special.chdtrc(n, chi2))
    return float(special.fdtrc(n, nu_eff, chi2 / n))


def locate(obs: pd.DataFrame, residual, sigma, alpha: float = 0.01, *,
           sigma_dof=None) -> pd.DataFrame:
    """Test every segment of :func:`segments` for systematic misfit.

    With ``z = residual / sigma`` (rows with non-finite ``z`` are ignored) and the ``n``
    rows of a segment:

    * ``mean_z``, ``rms_z = sqrt(mean z^2)``;
    * excess variance: ``chi2 = sum z^2``; for known sigma ``chi2 ~ chi-square(n)`` and
      ``p_chi2`` is its upper tail.  Sigma from :func:`estimate_noise` is itself estimated
      (``sigma_hat^2 / sigma^2 ~ chi-square(nu) / nu``), so by default
      ``chi2 / n ~ F(n, nu_eff)`` with ``1 / nu_eff = sum_s w_s^2 / nu_s`` over the series
      ``s`` in the segment, ``w_s = n_s / n`` (a weighted mean of independent
      ``sigma^2 / sigma_hat_s^2``).  Ignoring this would multiply the false alarms of
      whole-series segments several fold (sigma of a 60-point series has ~14 % error);
    * structure: Wald-Wolfowitz runs test on the signs of ``z`` in recording order
      (:func:`runs_test`; too few runs = systematic);
    * ``p_value = min(1, 2 min(p_chi2, p_runs))`` (Bonferroni over the two tests), and
      ``systematic = p_value < alpha / m`` (Bonferroni over the ``m`` tested segments).

    Why both: sigma comes from second differences, which a smooth misfit barely changes,
    so the misfit inflates ``chi2`` above ``n``; and a smooth misfit keeps its sign over
    many consecutive points, giving long runs.  The chi-square test also catches offsets
    (which do not change the sign pattern's independence); the runs test catches long,
    low-amplitude misfits and is independent of sigma.

    ``sigma_dof``: effective degrees of freedom of ``sigma`` per row (array or scalar);
    ``None`` assumes ``sigma`` came from :func:`estimate_noise` on these ``obs`` and
    ``residual`` (:func:`noise_dof`); ``numpy.inf`` for a known sigma (plain chi-square).
    Segments with fewer than 5 finite ``z`` are listed with NaN statistics and not tested.
    Returns one row per segment, columns ``axis, segment, n, mean_z, rms_z, chi2, p_chi2,
    runs_z, p_runs, p_value, systematic, nu_sigma``; ``table.attrs`` holds ``alpha``,
    ``m`` and ``threshold``.
    """
    _check(obs)
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    n_rows = len(obs)
    r = _as_float(residual, "residual", n_rows)
    s = _as_float(np.broadcast_to(np.asarray(sigma, dtype=float), (n_rows,)), "sigma", n_rows)
    if np.any(s[np.isfinite(s)] <= 0.0):
        raise ValueError("sigma must be positive")
    if sigma_dof is None:
        nu = noise_dof(obs, r)
    else:
        nu = _as_float(np.broadcast_to(np.asarray(sigma_dof, dtype=float), (n_rows,)),
                       "sigma_dof", n_rows)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        z = r / s
    finite = np.isfinite(z)
    sid = _series_ids(obs) if n_rows else np.empty(0, dtype=int)
    n_series = int(sid.max()) + 1 if n_rows else 0
    # nu of each series (constant within a series; the mean guards odd user input);
    # infinite (known sigma) contributes nothing to 1 / nu_eff
    ok = finite & np.isfinite(nu)
    cnt = np.bincount(sid[ok], minlength=n_series)
    nu_series = np.bincount(sid[ok], weights=nu[ok], minlength=n_series) / np.maximum(cnt, 1)
    inv_nu = np.where(cnt > 0, 1.0 / np.where(cnt > 0, nu_series, 1.0), 0.0)

    rows = []
    for axis, label, mask in segments(obs):
        m = mask & finite
        zz = z[m]
        n = int(zz.size)
        row = {"axis": axis, "segment": label, "n": n, "mean_z": math.nan, "rms_z": math.nan,
               "chi2": math.nan, "p_chi2": math.nan, "runs_z": math.nan, "p_runs": math.nan,
               "p_value": math.nan, "systematic": False, "nu_sigma": math.nan}
        if n >= 1:
            with np.errstate(over="ignore"):
                chi2 = float(np.sum(zz * zz))
            row.update(mean_z=float(np.mean(zz)), rms_z=math.sqrt(chi2 / n), chi2=chi2)
        if n >= MIN_SEGMENT:
            w = np.bincount(sid[m], minlength=n_series) / n
            inv = float(np.sum(w**2 * inv_nu))
            nu_eff = 1.0 / inv if inv > 0 else math.inf
            p_chi2 = _chi2_p(row["chi2"], n, nu_eff)
            runs_z, p_runs, _ = runs_test(np.sign(zz))
            row.update(p_chi2=p_chi2, runs_z=runs_z, p_runs=p_runs,
                       p_value=min(1.0, 2.0 * min(p_chi2, p_runs)), nu_sigma=nu_eff)
        rows.append(row)
    table = pd.DataFrame(rows, columns=list(TABLE_COLUMNS))
    tested = table["p_value"].notna()
    m_tests = int(tested.sum())
    threshold = alpha / m_tests if m_tests else math.nan
    if m_tests:
        table["systematic"] = tested & (table["p_value"] < threshold)
    table["systematic"] = table["systematic"].astype(bool)
    table["n"] = table["n"].astype(int)
    table.attrs.update(alpha=float(alpha), m=m_tests, threshold=float(threshold))
    log.info("locate: %d segments tested, %d systematic (p < %.3g)", m_tests,
             int(table["systematic"].sum()), threshold)
    return table


def summary(table: pd.DataFrame) -> dict:
    """JSON-ready digest of a :func:`locate` table (plain Python types only).

    ``systematic``: any systematic segment; ``worst``: label of the segment with the
    smallest ``p_value`` (``None`` if nothing was tested), with ``worst_axis`` and
    ``worst_p_value``; ``n_tested`` and ``threshold`` (``alpha / m``) when known;
    ``located``: ``{axis, segment, n, rms_z, p_value}`` of the systematic segments, sorted
    by ``p_value`` (then by table order).
    """
    tested = table[table["p_value"].notna()]
    out: dict = {"systematic": bool(table["systematic"].astype(bool).any())}
    if len(tested):
        i = tested["p_value"].to_numpy(dtype=float).argmin()
        worst = tested.iloc[int(i)]
        out.update(worst=str(worst["segment"]), worst_axis=str(worst["axis"]),
                   worst_p_value=float(worst["p_value"]))
    else:
        out.update(worst=None, worst_axis=None, worst_p_value=None)
    out["n_tested"] = int(len(tested))
    thr = table.attrs.get("threshold")
    out["threshold"] = float(thr) if thr is not None and math.isfinite(thr) else None
    sysm = table[table["systematic"].astype(bool)]
    sysm = sysm.assign(_order=np.arange(len(sysm))).sort_values(["p_value", "_order"],
                                                               kind="stable")

    def _f(x) -> float | None:
        x = float(x)
        return x if math.isfinite(x) else None

    out["located"] = [{"axis": str(r.axis), "segment": str(r.segment), "n": int(r.n),
                       "rms_z": _f(r.rms_z), "p_value": _f(r.p_value)}
                      for r in sysm.itertuples(index=False)]
    return out


# ------------------------------------------------------------------------------- map

def mismatch_map(obs: pd.DataFrame, residual, sigma, table: pd.DataFrame, path) -> str:
    """Figure of where the misfit is, written to ``path`` (PNG; parent directory must exist).

    One panel per (curve, channel): ``z = residual / sigma`` against the control value,
    loading and unloading in different colours (recording order joined by thin lines
    within each (branch, cycle) run), the band ``|z| <= 2`` shaded grey, and the control
    range of each systematic ``cell`` shaded red and named by its branch.  A last panel
    is a heat map of ``-log10 p_value`` over the cells (rows curve/channel, columns
    branch/part), systematic cells marked ``*`` and the Bonferroni level on the colour bar;
    untested cells are grey.  Returns ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _check(obs)
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise ValueError(f"{path}: output directory does not exist ({d})")
    n_rows = len(obs)
    r = _as_float(residual, "residual", n_rows)
    s = _as_float(np.broadcast_to(np.asarray(sigma, dtype=float), (n_rows,)), "sigma", n_rows)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = r / s
    curve = obs["curve"].astype(str).to_numpy()
    channel = obs["channel"].astype(str).to_numpy()
    branch = obs["branch"].astype(str).to_numpy()
    control = obs["control"].to_numpy(dtype=float)
    run_id = _run_ids(obs)

    cells = _cells(obs)
    ctab = table[table["axis"] == "cell"].set_index("segment")
    pairs = list(dict.fromkeys((c.curve, c.channel) for c in cells))
    colors = {"loading": "tab:blue", "unloading": "tab:orange"}

    n_panels = len(pairs) + 1
    ncols = min(3, n_panels)
    nrows = math.ceil(n_panels / ncols)
    fig, axes = plt.subplots(nrows, ncols, squeeze=False, layout="constrained",
                             figsize=(4.6 * ncols, 3.4 * nrows))
    flat = list(axes.ravel())
    for ax, (cv, ch) in zip(flat, pairs, strict=False):
        m_cc = (curve == cv) & (channel == ch) & np.isfinite(z) & np.isfinite(control)
        ax.axhspan(-2.0, 2.0, color="0.88", zorder=0, label=r"$|z| \leq 2$")
        ax.axhline(0.0, color="0.5", lw=0.6, zorder=1)
        for c in cells:
            if c.curve != cv or c.channel != ch or c.label not in ctab.index:
                continue
            if not bool(ctab.loc[c.label, "systematic"]):
                continue
            x = control[c.mask & np.isfinite(control)]
            if x.size:
                lo, hi = float(x.min()), float(x.max())
                if hi == lo:
                    pad = 0.01 * max(abs(lo), 1e-3)
                    lo, hi = lo - pad, hi + pad
                ax.axvspan(lo, hi, color="tab:red", alpha=0.13, zorder=0)
                ax.text(0.5 * (lo + hi), 1.0, f"{c.branch}\np={ctab.loc[c.label, 'p_value']:.1g}",
                        transform=ax.get_xaxis_transform(), ha="center", va="top", fontsize=7,
                        color="tab:red")
        shown = set()
        for rid in np.unique(run_id[m_cc]):
            m = m_cc & (run_id == rid)
            br = branch[m][0]
            col = colors.get(br, "0.4")
            ax.plot(control[m], z[m], "-", color=col, lw=0.5, alpha=0.6, zorder=2)
            ax.plot(control[m], z[m], "o", ms=2.8, color=col, zorder=3,
                    label=None if br in shown else br)
            shown.add(br)
        ax.axvline(neutral_of(cv), color="0.6", lw=0.6, ls=":")
        ax.set_title(f"{cv} - {ch}", fontsize=9)
        ax.set_xlabel("amount of shear [-]" if neutral_of(cv) == 0.0 else "stretch [-]")
        ax.set_ylabel(r"$z = r / \sigma$")
        ax.legend(fontsize=7, loc="lower left")

    hm = flat[len(pairs)]
    cols = list(dict.fromkeys((c.branch, c.part) for c in cells))
    # drop columns with nothing tested (e.g. the few points at stretch exactly 1)
    tested_cols = {(c.branch, c.part) for c in cells if c.label in ctab.index
                   and math.isfinite(float(ctab.loc[c.label, "p_value"]))}
    cols = [c for c in cols if c in tested_cols] or cols
    mat = np.full((len(pairs), len(cols)), np.nan)
    mark = np.zeros_like(mat, dtype=bool)
    for c in cells:
        if c.label in ctab.index and (c.branch, c.part) in cols:
            i, j = pairs.index((c.curve, c.channel)), cols.index((c.branch, c.part))
            p = float(ctab.loc[c.label, "p_value"])
            if math.isfinite(p):
                mat[i, j] = -math.log10(max(p, 1e-300))
            mark[i, j] = bool(ctab.loc[c.label, "systematic"])
    cmap = plt.get_cmap("magma_r").copy()
    cmap.set_bad("0.85")
    thr = table.attrs.get("threshold")
    finite_vals = mat[np.isfinite(mat)]
    vmax = max(float(finite_vals.max()) if finite_vals.size else 1.0,
               -math.log10(thr) if thr and math.isfinite(thr) else 1.0, 1.0)
    im = hm.imshow(np.ma.masked_invalid(mat), cmap=cmap, vmin=0.0, vmax=vmax, aspect="auto")
    for i, j in zip(*np.nonzero(mark), strict=True):
        hm.text(j, i, "*", ha="center", va="center", color="white", fontsize=12,
                fontweight="bold")
    hm.set_xticks(range(len(cols)), [f"{b}\n{p}" for b, p in cols], fontsize=6, rotation=90)
    hm.set_yticks(range(len(pairs)), [f"{cv}/{ch}" for cv, ch in pairs], fontsize=6)
    hm.set_title(r"$-\log_{10} p$ per cell (* systematic)", fontsize=9)
    cb = fig.colorbar(im, ax=hm, shrink=0.9)
    if thr and math.isfinite(thr):
        cb.ax.axhline(-math.log10(thr), color="tab:cyan", lw=1.5)
        cb.set_label(r"$-\log_{10} p$ (line: $\alpha / m$)", fontsize=7)
    for ax in flat[len(pairs) + 1:]:
        ax.set_visible(False)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    log.info("mismatch map written to %s", path)
    return path
