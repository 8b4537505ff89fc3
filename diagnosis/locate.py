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

1. :func:`diagnosis.noise.estimate_noise`: a noise level sigma per series from the
   residual's second differences, with its effective degrees of freedom.
2. :func:`segments`: the protocol's own axes (test, channel, branch, cycle, range) and a
   fine ``cell`` partition (curve, channel, branch, side/range) for the mismatch map.
3. :func:`locate`: on each segment, with ``z = r / sigma``, an excess-variance test
   (``chi2 = sum z^2``) and a Wald-Wolfowitz runs test on the signs of ``z`` in recording
   order; Bonferroni over the segments.  :func:`summary` condenses the table for JSON.
4. :func:`diagnosis.figures.mismatch_map`: z against control per curve/channel and a heat
   map of ``-log10 p`` over the cells.

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
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import special

from .noise import noise_dof
from .series import as_float, check, neutral_of, series_ids

log = logging.getLogger(__name__)

AXES = ("specimen", "test", "channel", "branch", "cycle", "range", "cell")
TABLE_COLUMNS = ("axis", "segment", "n", "mean_z", "rms_z", "chi2", "p_chi2", "runs_z",
                 "p_runs", "p_value", "systematic", "nu_sigma")
MIN_SEGMENT = 5  # smaller segments are listed but not tested (p = NaN)


# --------------------------------------------------------------------------- segments

@dataclass(frozen=True)
class Cell:
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


def cells(obs: pd.DataFrame) -> list[Cell]:
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
                        out.append(Cell(cv, ch, br, p, m))
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
    check(obs)
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
    for cell in cells(obs):
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
    check(obs)
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    n_rows = len(obs)
    r = as_float(residual, "residual", n_rows)
    s = as_float(np.broadcast_to(np.asarray(sigma, dtype=float), (n_rows,)), "sigma", n_rows)
    if np.any(s[np.isfinite(s)] <= 0.0):
        raise ValueError("sigma must be positive")
    if sigma_dof is None:
        nu = noise_dof(obs, r)
    else:
        nu = as_float(np.broadcast_to(np.asarray(sigma_dof, dtype=float), (n_rows,)),
                       "sigma_dof", n_rows)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        z = r / s
    finite = np.isfinite(z)
    sid = series_ids(obs) if n_rows else np.empty(0, dtype=int)
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
