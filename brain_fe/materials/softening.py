r"""Ogden-Roxburgh pseudo-elastic softening (Mullins effect) of the isochoric stress.

.. math::  S_{iso} \to \eta S_{iso}, \qquad
           \eta = 1 - d\,\mathrm{erf}(\max(W_{max} - W_{iso}, 0) / m)

W_max is the largest isochoric energy reached so far (one internal variable per quadrature
point); d = 1/r in [0, 1) [-] (0: elastic), m > 0 [kPa].
"""

from __future__ import annotations

from dataclasses import dataclass

import ufl

from ..parameters import SOFTENING, SOFTENING_M, Param


@dataclass(frozen=True)
class OgdenRoxburgh:
    """Softening of the isochoric stress by the damage function eta."""

    name = "softening"
    state_size = 1

    def parameters(self) -> tuple[Param, ...]:
        return (SOFTENING, SOFTENING_M)

    def apply(self, S, S_iso, W_iso, state, p, dt):
        """(softened stress, new state components)."""
        W_max = state[0]
        eta = 1 - p[SOFTENING] * ufl.erf(ufl.max_value(W_max - W_iso, 0.0) / p[SOFTENING_M])
        return eta * S, [ufl.max_value(W_max, W_iso)]
