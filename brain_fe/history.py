"""Internal variables of history-dependent materials at the quadrature points.

The state (one vector per quadrature point of the geometry's measure) lives in a quadrature
space; its update G(u, state, parameters) is a compiled ``fem.Expression`` evaluated after
every converged (sub)step.
"""

from __future__ import annotations

import numpy as np
import ufl
from dolfinx import fem

from . import _compat


class HistoryState:
    """Quadrature-point state of ``size`` components per point on ``geometry``."""

    def __init__(self, geometry, size: int):
        msh = geometry.mesh
        self.space, self.points = _compat.quadrature_space(msh, geometry.quadrature_degree,
                                                           size)
        self.function = fem.Function(self.space, name="history")
        dm = _compat.dofmap_array(self.space)
        bs = self.space.dofmap.bs
        self.index = (bs * dm[:, :, None] + np.arange(bs)).reshape(dm.shape[0], -1)
        self.cells = np.arange(_compat.num_local_cells(msh), dtype=np.int32)
        self.mesh = msh
        self._expr = None

    @property
    def array(self) -> np.ndarray:
        return self.function.x.array

    def compile_update(self, update_ufl) -> None:
        self._expr = _compat.expression(update_ufl, self.points)

    def reset(self) -> None:
        self.array[:] = 0.0

    def evaluate(self) -> np.ndarray:
        """The update G at every quadrature point, shaped (cells, points * components)."""
        vals = _compat.eval_expression(self._expr, self.mesh, self.cells)
        return np.asarray(vals).reshape(len(self.cells), -1)

    def scatter(self, values: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Per-cell ``values`` (as :meth:`evaluate`) into a state-shaped array."""
        out = self.array if out is None else out
        out[self.index] = values
        return out


def history_residual(material, geometry, u, v, state: HistoryState, p, dt):
    """int (1/2 S : dC + U'(J) dJ) w dx with the material's history stress S; sets the
    state's update expression."""
    F = geometry.deformation_gradient(u)
    S, update = material.history_stress(F, state.function, p, dt)
    state.compile_update(update)
    J = ufl.det(F)
    dF = ufl.derivative(F, u, v)
    dC = dF.T * F + F.T * dF
    w, dx = geometry.volume_weight(), geometry.dx
    U = material.volumetric.strain_energy(J, p)
    return 0.5 * ufl.inner(S, dC) * w * dx + ufl.derivative(U * w * dx, u, v)
