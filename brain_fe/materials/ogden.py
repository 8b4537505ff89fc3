r"""Isochoric N-term Ogden law (DESIGN.md section 3):

.. math::  W_{iso}(\bar C) = \sum_p \frac{2\mu_p}{\alpha_p^2}
           (\bar\lambda_1^{\alpha_p} + \bar\lambda_2^{\alpha_p} + \bar\lambda_3^{\alpha_p} - 3)

mu_p in kPa, alpha_p dimensionless and non-zero; mu = sum mu_p is the classical shear
modulus.  The eigenvalues enter only through the smooth spectral sum of
:mod:`brain_fe.materials.spectral`, so stresses and tangents are exact UFL derivatives.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..parameters import Param, alpha, mu
from .spectral import GDeriv, power_derivative, spectral_sum


@dataclass(frozen=True)
class Ogden:
    """``terms`` Ogden terms; parameters mu_p [kPa], alpha_p [-] for p = 0..terms-1."""

    terms: int = 1
    name = "ogden"

    def __post_init__(self):
        if int(self.terms) < 1:
            raise ValueError("Ogden needs at least one term")

    def parameters(self) -> tuple[Param, ...]:
        return tuple(q for p in range(self.terms) for q in (mu(p), alpha(p)))

    def _g(self, p) -> GDeriv:
        """Combined spectral function sum_p 2 mu_p / alpha_p^2 c^(alpha_p/2)."""
        terms = [(2 * p[mu(i)] / p[alpha(i)] ** 2, power_derivative(p[alpha(i)] / 2))
                 for i in range(self.terms)]

        def g(c, n: int = 0):
            return sum(coef * gp(c, n) for coef, gp in terms)

        return g

    def strain_energy(self, Cbar, p):
        """W_iso [kPa] of the isochoric right Cauchy-Green tensor; ``p`` maps Param -> UFL."""
        offset = sum(6 * p[mu(i)] / p[alpha(i)] ** 2 for i in range(self.terms))
        return spectral_sum(Cbar, self._g(p)) - offset
