"""Volumetric energies U(J) [kPa] and the bulk modulus from the initial Poisson ratio."""

from __future__ import annotations

import math
from dataclasses import dataclass

import ufl

from ..parameters import KAPPA, Param


def kappa_from_nu0(mu: float, nu0: float) -> float:
    """Bulk modulus [kPa] from the initial Poisson ratio:
    kappa = 2 mu (1 + nu0) / (3 (1 - 2 nu0))."""
    if not (math.isfinite(nu0) and 0.0 <= nu0 < 0.5):
        raise ValueError(f"nu0 must lie in [0, 0.5), got {nu0}")
    return 2.0 * mu * (1.0 + nu0) / (3.0 * (1.0 - 2.0 * nu0))


@dataclass(frozen=True)
class QuadraticVolumetric:
    """U(J) = kappa/2 (J - 1)^2."""

    name = "quadratic"

    def parameters(self) -> tuple[Param, ...]:
        return (KAPPA,)

    def strain_energy(self, J, p):
        return p[KAPPA] / 2 * (J - 1) ** 2


@dataclass(frozen=True)
class LogVolumetric:
    """U(J) = kappa/4 (J^2 - 1 - 2 ln J)."""

    name = "log"

    def parameters(self) -> tuple[Param, ...]:
        return (KAPPA,)

    def strain_energy(self, J, p):
        return p[KAPPA] / 4 * (J**2 - 1 - 2 * ufl.ln(J))
