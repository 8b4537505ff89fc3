r"""Symmetric spectral sums sum_i g(c_i) in UFL, smooth through repeated eigenvalues.

Used by the Ogden law (:mod:`brain_fe.materials.ogden`), DESIGN.md section 3:

.. math::

    W(C) = \sum_p \frac{2\mu_p}{\alpha_p^2}\,(\bar\lambda_1^{\alpha_p} + \bar\lambda_2^{\alpha_p}
           + \bar\lambda_3^{\alpha_p} - 3) + U(J), \qquad \bar\lambda_i = J^{-1/3}\lambda_i

Units: moduli in kPa, so W is in kPa (= mN/mm^2 = mJ/cm^3 ... energy per volume).
``mu = sum(mu_p)`` is the classical shear modulus.

Principal stretches: the energy only needs the symmetric sum
``S = sum_i g(c_i)`` over the eigenvalues ``c_i`` of ``Cbar = J^(-2/3) C`` with
``g(c) = c^(alpha/2)``.  Closed-form (trigonometric) eigenvalues are exact but their
derivatives are 0 * inf where eigenvalues coincide, which happens in the reference state
(triple), in uniaxial states and on the axis (double).  ``spectral_sum`` evaluates the
same smooth function through three exact representations, each switched on where the
others are singular:

* near a triple eigenvalue (``J2 < TOL_TRIPLE m^2``): the Taylor series of S about
  ``m = tr(Cbar)/3`` written with the deviatoric invariants (power sums from Newton's
  identities), truncated after order 6; its error is O(|dev Cbar|^7);
* elsewhere the eigenvalue that stays simple (the largest when ``det(dev) >= 0``, else
  the smallest) is ``m + 2 s sigma (1 - e)``, where ``e`` is an analytic function of
  ``y = 1 - |cos 3 theta|`` (series in y for ``y < TOL_DOUBLE``, trigonometric otherwise);
* the remaining pair enters only through its mean ``a`` and squared half gap ``beta``:
  ``g(a + sqrt(beta)) + g(a - sqrt(beta))``, replaced by its even Taylor series in beta for
  ``beta < TOL_PAIR a^2`` (error O(beta^4)).

Every branch is an exact representation up to its truncation error (<= 1e-12 relative in
the energy, <= 1e-8 in the tangent for |alpha| <= 40 at the switching points), so
``ufl.derivative`` of the energy gives a consistent tangent and Newton converges
quadratically through the reference state, on unloading and in torsion.
"""

from __future__ import annotations

from collections.abc import Callable
from math import factorial

import ufl

# Switching tolerances (see module docstring for the error budget behind them).
TOL_TRIPLE = 1e-6  # J2 / m^2: |dev Cbar| ~ 1e-3
TOL_DOUBLE = 1e-3  # y = 1 - |cos 3 theta|
TOL_PAIR = 1e-6  # beta / a^2: half-gap ~ 1e-3 of the mean

# e(y) = 1 - cos(acos(1 - y)/3): the simple root of 4c^3 - 3c = 1 - y about c = 1.
_E_SERIES = (1 / 9, 4 / 243, 28 / 6561, 80 / 59049, 2288 / 4782969)

GDeriv = Callable[[ufl.core.expr.Expr, int], ufl.core.expr.Expr]


def _falling(p, n: int):
    """p (p-1) ... (p-n+1), the coefficient of d^n/dc^n c^p."""
    out = 1.0
    for k in range(n):
        out = out * (p - k)
    return out


def power_derivative(p) -> GDeriv:
    """g(c) = c^p and its derivatives g^(n)(c) = p (p-1) ... (p-n+1) c^(p-n)."""

    def g(c, n: int = 0):
        return _falling(p, n) * c ** (p - n)

    return g


def spectral_sum(A, g: GDeriv):
    """sum_i g(a_i) over the eigenvalues a_i of the symmetric positive 3x3 UFL tensor A.

    ``g(c, n)`` must return the n-th derivative of g (n = 0..6). Smooth in A, including at
    repeated eigenvalues (see module docstring).
    """
    Id = ufl.Identity(3)
    m = ufl.tr(A) / 3
    D = A - m * Id
    J2 = ufl.inner(D, D) / 2
    J3 = ufl.det(D)

    # (1) Triple: sum_n g^(n)(m) p_n / n!, p_n = sum_i (a_i - m)^n from Newton's identities
    p = {2: 2 * J2, 3: 3 * J3, 4: 2 * J2**2, 5: 5 * J2 * J3, 6: 2 * J2**3 + 3 * J3**2}
    near_triple = 3 * g(m, 0)
    for n, pn in p.items():
        near_triple = near_triple + g(m, n) * pn / factorial(n)

    # (2) General: trigonometric form with the simple eigenvalue singled out.
    J2s = ufl.max_value(J2, TOL_TRIPLE * m**2 / 4)  # keeps the unused branch finite
    s = ufl.sqrt(J2s / 3)
    x = J3 / (2 * s**3)  # cos(3 theta)
    sigma = ufl.conditional(ufl.ge(x, 0), 1.0, -1.0)
    # y is left unclamped: rounding can put sigma x a hair above 1 at an exact double
    # eigenvalue, and the series (analytic in y) must keep the curvature there; only the
    # acos argument is clamped, in the branch used away from y = 0.
    y = 1 - sigma * x
    e_series = sum(c * y ** (k + 1) for k, c in enumerate(_E_SERIES))
    t = ufl.max_value(ufl.min_value(sigma * x, 1.0), -1.0)
    e_trig = 2 * ufl.sin(ufl.acos(t) / 6) ** 2
    e = ufl.conditional(ufl.lt(y, TOL_DOUBLE), e_series, e_trig)
    c_simple = m + 2 * s * sigma * (1 - e)
    a = m - s * sigma * (1 - e)
    beta = 3 * s**2 * e * (2 - e)
    pair_taylor = 2 * g(a, 0) + g(a, 2) * beta + g(a, 4) * beta**2 / 12 + g(a, 6) * beta**3 / 360
    b = ufl.sqrt(ufl.max_value(beta, TOL_PAIR * a**2 / 4))
    pair_exact = g(a + b, 0) + g(a - b, 0)
    pair = ufl.conditional(ufl.lt(beta, TOL_PAIR * a**2), pair_taylor, pair_exact)
    general = g(c_simple, 0) + pair

    return ufl.conditional(ufl.lt(J2, TOL_TRIPLE * m**2), near_triple, general)
