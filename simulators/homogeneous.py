r"""Homogeneous (analytical) compressible N-term Ogden model: a fast base model for cube
specimens in uniaxial tension/compression and simple shear.

Material (the same as ``brain_fe/materials``, DESIGN.md section 3):

.. math::

    W = \sum_p \frac{2\mu_p}{\alpha_p^2}(\bar\lambda_1^{\alpha_p} + \bar\lambda_2^{\alpha_p}
        + \bar\lambda_3^{\alpha_p} - 3) + U(J), \qquad \bar\lambda_i = J^{-1/3}\lambda_i,

with ``U = kappa/2 (J - 1)^2`` ("quadratic") or ``U = kappa/4 (J^2 - 1 - 2 ln J)`` ("log")
and ``kappa = 2 mu (1 + nu0) / (3 (1 - 2 nu0))``, ``mu = sum mu_p``. Moduli in kPa.

For ``F = diag(l1, l2, l3)`` the principal Kirchhoff stresses are
``tau_i = l_i dW/dl_i = sum_p 2 mu_p/alpha_p (lbar_i^alpha_p - 1/3 sum_j lbar_j^alpha_p)
+ J U'(J)``.

*Uniaxial* (``F = diag(lambda, s, s)``): with ``r = lambda / s`` the deviatoric part is
``D(r) = sum_p 2 mu_p/alpha_p (r^(2 alpha_p/3) - r^(-alpha_p/3))``, and
``tau_1 = 2/3 D + J U'``, ``tau_2 = -1/3 D + J U'``. The lateral stretch solves
``tau_2 = 0``, i.e. ``J U'(J) = D(r)/3`` with ``J = lambda s^2``; then
``P11 = tau_1 / lambda = D(r) / lambda`` [kPa]. The root is found by a vectorised Newton
iteration in ``x = ln s`` safeguarded by bisection on a sign-change bracket.

*Simple shear* (``F = I + g e1 (x) e2``, ``J = 1``): ``lambda_1 = g/2 + sqrt(1 + g^2/4)``,
``lambda_2 = 1/lambda_1``, ``lambda_3 = 1``, ``W(g) = sum_p 2 mu_p/alpha_p^2
(lambda_1^alpha_p + lambda_1^-alpha_p - 2)`` and
``P12 = dW/dg = sum_p 2 mu_p/alpha_p (lambda_1^alpha_p - lambda_1^-alpha_p) / (2 sqrt(1 +
g^2/4))`` [kPa] (U does not contribute since U'(1) = 0).

Derivatives with respect to the parameters are analytic (implicit function theorem for the
lateral stretch).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from brain_fe.parameters import KAPPA, Param

from .base import Prediction

logger = logging.getLogger(__name__)

VOLUMETRIC = ("quadratic", "log")
UNIAXIAL_CURVES = ("tension", "compression")
SHEAR_CURVES = ("simple_shear",)
MAX_TERMS = 4  # Ogden terms listed in HomogeneousSimulator.names_available

_NEWTON_MAXITER = 100
_NEWTON_XTOL = 1e-14  # on ln(s): after a quadratic step the root is exact to rounding


def bulk_modulus(mu_total: float, nu0: float) -> float:
    """kappa = 2 mu (1 + nu0) / (3 (1 - 2 nu0)) [kPa] from mu = sum mu_p [kPa] and the
    initial Poisson ratio nu0 (-1 < nu0 < 0.5)."""
    if not -1.0 < nu0 < 0.5:
        raise ValueError(f"nu0 must lie in (-1, 0.5), got {nu0}")
    return 2.0 * mu_total * (1.0 + nu0) / (3.0 * (1.0 - 2.0 * nu0))


def _dkappa_dnu0(mu_total: float, nu0: float) -> float:
    """d kappa / d nu0 = 2 mu / (1 - 2 nu0)^2 [kPa]."""
    return 2.0 * mu_total / (1.0 - 2.0 * nu0) ** 2


def _terms(mu: Sequence[float], alpha: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Ogden moduli and exponents as (N, 1) columns for broadcasting against points."""
    m = np.atleast_1d(np.asarray(mu, dtype=float))
    a = np.atleast_1d(np.asarray(alpha, dtype=float))
    if m.ndim != 1 or m.shape != a.shape or m.size == 0:
        raise ValueError(f"mu and alpha must be equal-length sequences, got {mu!r}, {alpha!r}")
    if np.any(a == 0.0) or not (np.all(np.isfinite(a)) and np.all(np.isfinite(m))):
        raise ValueError(f"alpha_p must be finite and nonzero and mu_p finite: {mu!r}, {alpha!r}")
    return m[:, None], a[:, None]


def _check_volumetric(volumetric: str) -> None:
    if volumetric not in VOLUMETRIC:
        raise ValueError(f"volumetric must be one of {VOLUMETRIC}, got {volumetric!r}")


def _pressure(J: np.ndarray, kappa: float, volumetric: str) -> tuple[np.ndarray, np.ndarray]:
    """p = J U'(J) [kPa] and dp/dJ: kappa J (J - 1) (quadratic), kappa/2 (J^2 - 1) (log)."""
    if volumetric == "quadratic":
        return kappa * J * (J - 1.0), kappa * (2.0 * J - 1.0)
    return 0.5 * kappa * (J * J - 1.0), kappa * J


def _deviatoric(r: np.ndarray, m: np.ndarray, a: np.ndarray):
    """Per-term powers and D(r) = sum_p 2 mu_p/alpha_p (r^(2a/3) - r^(-a/3)),
    r dD/dr = sum_p 2 mu_p/3 (2 r^(2a/3) + r^(-a/3))."""
    p1 = r ** (2.0 * a / 3.0)
    p2 = r ** (-a / 3.0)
    c = 2.0 * m / a
    D = np.sum(c * (p1 - p2), axis=0)
    rDr = np.sum(2.0 * m / 3.0 * (2.0 * p1 + p2), axis=0)
    return p1, p2, D, rDr


def _residual(x, lam, m, a, kappa, volumetric):
    """f(x) = J U'(J) - D(r)/3 with s = e^x, J = lam s^2, r = lam/s, and df/dx."""
    J = lam * np.exp(2.0 * x)
    r = lam * np.exp(-x)
    p, dp = _pressure(J, kappa, volumetric)
    _, _, D, rDr = _deviatoric(r, m, a)
    return p - D / 3.0, 2.0 * J * dp + rDr / 3.0


def _solve_log_lateral(lam: np.ndarray, m, a, kappa: float, volumetric: str) -> np.ndarray:
    """x = ln s solving the lateral equilibrium tau_2 = 0, elementwise in lam (1-D)."""
    x = -0.5 * np.log(lam)  # incompressible guess (J = 1)
    lo = x - 0.5
    hi = x + 0.5
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        # f -> -inf as x -> -inf and f -> +inf as x -> +inf (mu_p > 0): widen to a sign change
        for width in 2.0 ** np.arange(12):
            flo, _ = _residual(lo, lam, m, a, kappa, volumetric)
            fhi, _ = _residual(hi, lam, m, a, kappa, volumetric)
            bad_lo = ~(flo <= 0.0)
            bad_hi = ~(fhi >= 0.0)
            if not (bad_lo.any() or bad_hi.any()):
                break
            lo = np.where(bad_lo, lo - width, lo)
            hi = np.where(bad_hi, hi + width, hi)
        else:
            raise RuntimeError("uniaxial: no sign change of the lateral stress found "
                               f"(mu={m.ravel()}, alpha={a.ravel()}, kappa={kappa})")
        for _ in range(_NEWTON_MAXITER):
            f, df = _residual(x, lam, m, a, kappa, volumetric)
            neg = f < 0.0
            lo = np.where(neg, x, lo)
            hi = np.where(neg, hi, x)
            dx = f / df
            xn = x - dx
            # a Newton step is taken when it stays in the bracket (or is already below the
            # tolerance, where rounding may put it an ulp outside); otherwise bisect
            newton = (xn >= lo) & (xn <= hi) | (np.abs(dx) <= _NEWTON_XTOL)
            xn = np.where(newton, xn, 0.5 * (lo + hi))
            step = float(np.max(np.abs(xn - x))) if xn.size else 0.0
            x = xn
            if step <= _NEWTON_XTOL:
                break
        else:
            if step > 1e-10:
                raise RuntimeError(f"uniaxial: lateral stretch did not converge (step {step:g})")
            logger.debug("uniaxial: Newton stopped at step %g (rounding level)", step)
    return x


def _uniaxial(stretch, mu, alpha, kappa, volumetric, stretch_offset, gradient: bool):
    """Core of the uniaxial model: P11 and (optionally) its partial derivatives."""
    _check_volumetric(volumetric)
    m, a = _terms(mu, alpha)
    kappa = float(kappa)
    if not kappa > 0.0:
        raise ValueError(f"kappa must be positive, got {kappa}")
    lam_in = np.asarray(stretch, dtype=float)
    lam = lam_in.ravel() + float(stretch_offset)
    if np.any(~(lam > 0.0)):
        raise ValueError("uniaxial: stretch + stretch_offset must be positive")
    x = _solve_log_lateral(lam, m, a, kappa, volumetric)
    s = np.exp(x)
    J = lam * s * s
    r = lam / s
    p1, p2, D, rDr = _deviatoric(r, m, a)
    y = D / lam
    if not gradient:
        return y.reshape(lam_in.shape), s.reshape(lam_in.shape)
    p, dp = _pressure(J, kappa, volumetric)
    Fx = 2.0 * J * dp + rDr / 3.0
    c = 2.0 * m / a
    dD_dm = (2.0 / a) * (p1 - p2)  # (N, n)
    dD_da = -c / a * (p1 - p2) + c * np.log(r) * (2.0 / 3.0 * p1 + 1.0 / 3.0 * p2)
    # implicit function theorem on f(x; theta) = p(J) - D(r)/3 = 0: dx = -f_theta / f_x;
    # P11 = D(r)/lam with dr = -r dx (+ r/lam dlam), r dD/dr = rDr
    dx_dm = (dD_dm / 3.0) / Fx
    dx_da = (dD_da / 3.0) / Fx
    dx_dk = -(p / kappa) / Fx
    dx_dl = -(dp * J / lam - rDr / (3.0 * lam)) / Fx
    dy_dm = (dD_dm - rDr * dx_dm) / lam
    dy_da = (dD_da - rDr * dx_da) / lam
    dy_dk = -rDr * dx_dk / lam
    dy_dl = (rDr * (1.0 / lam - dx_dl)) / lam - D / lam**2
    return y, s, dy_dm, dy_da, dy_dk, dy_dl


def uniaxial_nominal_stress(
    stretch: float | np.ndarray,
    mu: Sequence[float],
    alpha: Sequence[float],
    kappa: float,
    volumetric: str = "quadratic",
    stretch_offset: float = 0.0,
) -> np.ndarray:
    """Homogeneous uniaxial nominal stress P11 [kPa], F = diag(lambda, s, s), lateral
    stretch s from P22 = 0.

    ``lambda = stretch + stretch_offset`` (contact-point zero offset of the recording);
    ``P11 = D(r)/lambda`` with ``r = lambda/s`` and
    ``D(r) = sum_p 2 mu_p/alpha_p (r^(2 alpha_p/3) - r^(-alpha_p/3))``.

    Args:
        stretch: recorded stretch(es) h/H [-], any shape.
        mu, alpha: Ogden moduli mu_p [kPa] and exponents alpha_p [-] (N terms each).
        kappa: bulk modulus [kPa].
        volumetric: "quadratic" (kappa/2 (J-1)^2) or "log" (kappa/4 (J^2-1-2 ln J)).
        stretch_offset: added to ``stretch`` [-].

    Returns:
        P11 [kPa], same shape as ``stretch`` (tension positive).
    """
    y, _ = _uniaxial(stretch, mu, alpha, kappa, volumetric, stretch_offset, gradient=False)
    return y


def uniaxial_lateral_stretch(
    stretch: float | np.ndarray,
    mu: Sequence[float],
    alpha: Sequence[float],
    kappa: float,
    volumetric: str = "quadratic",
    stretch_offset: float = 0.0,
) -> np.ndarray:
    """Lateral stretch s [-] of the homogeneous uniaxial state, the root of P22(lambda, s, s)
    = 0 (equivalently ``J U'(J) = D(lambda/s)/3``, ``J = lambda s^2``); arguments as
    :func:`uniaxial_nominal_stress`."""
    _, s = _uniaxial(stretch, mu, alpha, kappa, volumetric, stretch_offset, gradient=False)
    return s


def _shear(g, mu, alpha, gradient: bool):
    m, a = _terms(mu, alpha)
    g_in = np.asarray(g, dtype=float)
    g = g_in.ravel()
    q = np.sqrt(1.0 + 0.25 * g * g)
    l1 = 0.5 * g + q
    la = l1**a
    lma = l1 ** (-a)
    c = 2.0 * m / a
    y = np.sum(c * (la - lma), axis=0) / (2.0 * q)
    if not gradient:
        return y.reshape(g_in.shape)
    dy_dm = (2.0 / a) * (la - lma) / (2.0 * q)
    dy_da = (-c / a * (la - lma) + c * np.log(l1) * (la + lma)) / (2.0 * q)
    return y, dy_dm, dy_da


def simple_shear_stress(
    shear: float | np.ndarray,
    mu: Sequence[float],
    alpha: Sequence[float],
    kappa: float | None = None,
    volumetric: str = "quadratic",
) -> np.ndarray:
    """Simple-shear nominal stress P12 = dW/dg [kPa] for F = [[1, g, 0], [0, 1, 0], [0, 0, 1]].

    J = 1, so U (and kappa, ``volumetric``) do not contribute:
    ``P12 = sum_p 2 mu_p/alpha_p (l^alpha_p - l^-alpha_p) / (2 sqrt(1 + g^2/4))`` with
    ``l = g/2 + sqrt(1 + g^2/4)``. For alpha = 2 this is mu g (neo-Hooke).

    Args:
        shear: amount of shear g [-], any shape.
        mu, alpha: Ogden moduli mu_p [kPa] and exponents alpha_p [-].
        kappa, volumetric: accepted for a uniform signature; unused.

    Returns:
        P12 [kPa], same shape as ``shear``.
    """
    _check_volumetric(volumetric)
    return _shear(shear, mu, alpha, gradient=False)


_SCALARS = ("nu0", "kappa", "stretch_offset", "stress_offset", "shear_offset")
OBS_COLUMNS = ("specimen", "curve", "channel", "branch", "cycle", "control", "time_s", "value")
NU0 = Param("nu0")
STRETCH_OFFSET, STRESS_OFFSET, SHEAR_OFFSET = (Param("stretch_offset"), Param("stress_offset"),
                                               Param("shear_offset"))


class HomogeneousSimulator:
    """Predicted stresses and their parameter Jacobian for an observation table.

    ``obs`` has the columns ``specimen, curve, channel, branch, cycle, control, time_s,
    value``; ``curve`` is tension | compression | simple_shear, ``channel`` is ``stress``,
    ``control`` the stretch [-] (tension/compression) or amount of shear [-].

    Parameters: ``mu_p`` [kPa] and ``alpha_p`` [-] for p = 0..N-1 (N = number of ``mu_p`` in
    the values), ``nu0`` [-] (kappa = 2 mu (1+nu0)/(3(1-2 nu0)), mu = sum mu_p; derivatives
    with respect to mu_p are taken at fixed nu0), or ``kappa`` [kPa] directly when ``nu0`` is
    absent, ``stretch_offset`` [-] (added to the stretch of tension/compression rows),
    ``stress_offset`` [kPa] (added to tension/compression predictions), ``shear_offset``
    [kPa] (added to simple-shear predictions). Offsets default to 0.
    """

    kind = "homogeneous"
    names_available: tuple[str, ...] = tuple(
        f"{k}_{p}" for p in range(MAX_TERMS) for k in ("mu", "alpha")) + _SCALARS

    def __init__(self, obs: pd.DataFrame, volumetric: str = "quadratic",
                 nu0: float = 0.49) -> None:
        _check_volumetric(volumetric)
        missing = [c for c in OBS_COLUMNS if c not in obs.columns]
        if missing:
            raise ValueError(f"observation table: missing column(s) {missing}")
        curve = obs["curve"].astype(str).to_numpy()
        known = np.isin(curve, UNIAXIAL_CURVES + SHEAR_CURVES)
        if not known.all():
            i = int(np.flatnonzero(~known)[0])
            raise ValueError(f"observation table: row {i}, column curve: unknown curve "
                             f"{curve[i]!r} (expected one of {UNIAXIAL_CURVES + SHEAR_CURVES})")
        channel = obs["channel"].astype(str).to_numpy()
        if np.any(channel != "stress"):
            i = int(np.flatnonzero(channel != "stress")[0])
            raise ValueError(f"observation table: row {i}, column channel: only 'stress' is "
                             f"modelled, got {channel[i]!r}")
        control = pd.to_numeric(obs["control"], errors="coerce").to_numpy(dtype=float)
        if not np.all(np.isfinite(control)):
            i = int(np.flatnonzero(~np.isfinite(control))[0])
            raise ValueError(f"observation table: row {i}, column control: not a finite number")
        self.obs = obs.reset_index(drop=True)
        self.nu0 = nu0
        self.volumetric = volumetric
        self.n_obs = len(obs)
        self._uni = np.flatnonzero(np.isin(curve, UNIAXIAL_CURVES))
        self._shr = np.flatnonzero(np.isin(curve, SHEAR_CURVES))
        self._stretch = control[self._uni]
        self._gamma = control[self._shr]
        if np.any(self._stretch <= 0.0):
            raise ValueError("observation table: column control: stretches must be positive")

    @staticmethod
    def _parse(values: dict[Param, float]) -> tuple[list[float], list[float]]:
        unknown = [str(k) for k in values
                   if not (k.family in ("mu", "alpha") and k.index is not None
                           or str(k) in _SCALARS)]
        if unknown:
            raise ValueError(f"unknown parameter name(s) {unknown}; "
                             "expected mu_p, alpha_p, nu0, kappa or offsets")
        idx = sorted(k.index for k in values if k.family == "mu")
        n = len(idx)
        if n == 0 or idx != list(range(n)):
            raise ValueError(f"Ogden terms must be mu_0..mu_(N-1), got "
                             f"{sorted(map(str, values))}")
        missing = [f"alpha_{p}" for p in range(n) if Param("alpha", p) not in values]
        extra = [str(k) for k in values if k.family == "alpha" and k.index >= n]
        if missing or extra:
            raise ValueError(f"need exactly alpha_0..alpha_{n - 1} with mu_0..mu_{n - 1}; "
                             f"missing {missing}, without mu: {extra}")
        return ([float(values[Param("mu", p)]) for p in range(n)],
                [float(values[Param("alpha", p)]) for p in range(n)])

    def predict(self, values: Mapping, wrt: Sequence = ()) -> Prediction:
        """Stresses y [kPa] at every row of ``obs`` (row order) and J = dy/d(wrt),
        shape (n_obs, len(wrt)) (analytic derivatives)."""
        values = {Param.parse(k): float(v) for k, v in values.items()}
        names = tuple(Param.parse(q) for q in wrt)
        if NU0 not in values and KAPPA not in values:
            raise ValueError("values need 'nu0' (or 'kappa')")
        mu, alpha = self._parse(values)
        n = len(mu)
        mu_total = float(np.sum(mu))
        if NU0 in values and KAPPA in values:
            raise ValueError("give nu0 or kappa, not both")
        if NU0 in values:
            nu0 = values[NU0]
            kappa = bulk_modulus(mu_total, nu0)
            dk_dmu = kappa / mu_total if mu_total != 0.0 else 0.0
            if KAPPA in names:
                raise ValueError("'kappa' cannot be a free parameter when 'nu0' is given")
        else:
            nu0 = None
            kappa = values[KAPPA]
            dk_dmu = 0.0
            if NU0 in names:
                raise ValueError("'nu0' is a free parameter but only 'kappa' is given")
        for name in names:
            if not (str(name) in _SCALARS
                    or (name.family in ("mu", "alpha") and (name.index or 0) < n)):
                raise ValueError(f"cannot differentiate with respect to {str(name)!r} "
                                 f"({n} Ogden term(s) in the values)")
        st_off = values.get(STRETCH_OFFSET, 0.0)
        y = np.empty(self.n_obs)
        jac = np.zeros((self.n_obs, len(names)))
        col = {name: j for j, name in enumerate(names)}
        if self._uni.size:
            yu, _, dm, da, dk, dl = _uniaxial(self._stretch, mu, alpha, kappa,
                                              self.volumetric, st_off, gradient=True)
            y[self._uni] = yu + values.get(STRESS_OFFSET, 0.0)
            for p in range(n):
                if Param("mu", p) in col:
                    jac[self._uni, col[Param("mu", p)]] = dm[p] + dk_dmu * dk
                if Param("alpha", p) in col:
                    jac[self._uni, col[Param("alpha", p)]] = da[p]
            if NU0 in col:
                jac[self._uni, col[NU0]] = _dkappa_dnu0(mu_total, nu0) * dk
            if KAPPA in col:
                jac[self._uni, col[KAPPA]] = dk
            if STRETCH_OFFSET in col:
                jac[self._uni, col[STRETCH_OFFSET]] = dl
            if STRESS_OFFSET in col:
                jac[self._uni, col[STRESS_OFFSET]] = 1.0
        if self._shr.size:
            ys, dm, da = _shear(self._gamma, mu, alpha, gradient=True)
            y[self._shr] = ys + values.get(SHEAR_OFFSET, 0.0)
            for p in range(n):
                if Param("mu", p) in col:
                    jac[self._shr, col[Param("mu", p)]] = dm[p]
                if Param("alpha", p) in col:
                    jac[self._shr, col[Param("alpha", p)]] = da[p]
            if SHEAR_OFFSET in col:
                jac[self._shr, col[SHEAR_OFFSET]] = 1.0
        return Prediction(y, jac, names)
