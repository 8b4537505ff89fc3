r"""Maxwell branches on the isochoric stress (finite-strain viscoelasticity, Simo 1987 type).

.. math::  S = S_{vol} + S_{iso} + \sum_i Q_i, \qquad
           \dot Q_i + Q_i / \tau_i = \beta_i \dot S_{iso}

integrated by the recurrence ``Q_i(n+1) = exp(-x) Q_i(n) + beta_i (1 - exp(-x))/x
(S_iso(n+1) - S_iso(n))``, ``x = dt / tau_i``, exact for piecewise-linear histories of
S_iso.  beta_i >= 0 [-] (0: elastic), tau_i > 0 [s].  State per quadrature point: the
previous S_iso and every Q_i (3x3 each).
"""

from __future__ import annotations

from dataclasses import dataclass

import ufl

from ..parameters import Param, beta, tau

TENSOR_SIZE = 9  # a 3x3 stress per quadrature point (full, for simple indexing)


@dataclass(frozen=True)
class Maxwell:
    """``branches`` Maxwell branches; wraps the isochoric stress of an elastic law."""

    branches: int = 1
    name = "maxwell"

    def parameters(self) -> tuple[Param, ...]:
        return tuple(q for i in range(self.branches) for q in (beta(i), tau(i)))

    @property
    def state_size(self) -> int:
        return TENSOR_SIZE * (1 + self.branches) if self.branches else 0

    def apply(self, S, S_iso, W_iso, state, p, dt):
        """(stress with the branches added, new state components)."""

        def tensor(k0):
            return ufl.as_matrix([[state[k0 + 3 * i + j] for j in range(3)] for i in range(3)])

        S_prev = tensor(0)
        new = [S_iso]
        for i in range(self.branches):
            xi = dt / p[tau(i)]
            gamma = p[beta(i)] * (1 - ufl.exp(-xi)) / xi
            Q_new = ufl.exp(-xi) * tensor(TENSOR_SIZE * (i + 1)) + gamma * (S_iso - S_prev)
            S = S + Q_new
            new.append(Q_new)
        return S, [t[i, j] for t in new for i in range(3) for j in range(3)]
