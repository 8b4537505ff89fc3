r"""A fibre family along the specimen axis (Holzapfel-Gasser-Ogden type, tension only):

.. math::  W_f = \frac{k_1}{2 k_2}\left(\exp\left(k_2 \langle \bar I_4 - 1\rangle^2\right)
           - 1\right), \qquad \bar I_4 = a_0 \cdot \bar C a_0, \quad a_0 = E_Z

with ``<x> = max(x, 0)``: the fibres carry load only when stretched (they buckle in
compression).  k1 > 0 [kPa] (``fibre_k1``), k2 > 0 [-] (``fibre_k2``).  W_f is C1 at
I4 = 1 (its tangent jumps there, as in every tension-only fibre model).  E_Z is the
specimen axis in both geometries (component 2 of the axisymmetric (R, Theta, Z) and of the
3D (x, y, z) frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import ufl

from ..parameters import Param

K1, K2 = Param("fibre_k1"), Param("fibre_k2")


@dataclass(frozen=True)
class AxialFibres:
    """Tension-only fibres along the specimen axis; parameters fibre_k1, fibre_k2."""

    name = "axial_fibres"

    def parameters(self) -> tuple[Param, ...]:
        return (K1, K2)

    def strain_energy(self, Cbar, p):
        x = ufl.max_value(Cbar[2, 2] - 1.0, 0.0)
        return p[K1] / (2 * p[K2]) * (ufl.exp(p[K2] * x**2) - 1.0)
