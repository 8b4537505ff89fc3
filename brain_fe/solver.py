"""Newton's method on PETSc objects with a direct solver and a residual convergence test."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import dolfinx.fem.petsc as fem_petsc
import numpy as np
from petsc4py import PETSc

from . import _compat

log = logging.getLogger(__name__)


class ConvergenceError(RuntimeError):
    """Newton did not converge (after all load-step cut-backs)."""


@dataclass
class NewtonReport:
    converged: bool
    iterations: int
    residuals: list[float] = field(default_factory=list)
    reason: str = ""


def _direct_solver_type(comm) -> str:
    """MUMPS in parallel; PETSc's own LU on one rank, where it factorises the small systems
    of the axisymmetric model ~15 % faster than MUMPS (whose per-call set-up dominates)."""
    return "mumps" if comm.size > 1 else "petsc"


class NewtonSolver:
    """Full Newton for F(u; v) = 0 with Dirichlet conditions ``bcs`` applied by lifting.

    Converged when the free-dof residual norm drops below ``atol`` (a force, mN) or below
    ``rtol`` times the first residual of the step. The Jacobian is factorised by LU
    (MUMPS when PETSc has it, required in parallel); the symbolic factorisation is kept
    across iterations because the sparsity pattern never changes.
    """

    def __init__(self, comm, residual_form, jacobian_form, u, bcs, *, atol: float = 1e-10,
                 rtol: float = 1e-10, max_iterations: int = 15):
        self.comm = comm
        self.L = residual_form
        self.a = jacobian_form
        self.u = u
        self.bcs = bcs
        self.atol, self.rtol, self.max_iterations = atol, rtol, max_iterations
        self.A = fem_petsc.create_matrix(jacobian_form)
        self.b = fem_petsc.create_vector(residual_form)
        self.du = self.b.duplicate()
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setType("preonly")
        pc = self.ksp.getPC()
        pc.setType("lu")
        pc.setFactorSolverType(_direct_solver_type(comm))
        self.ksp.setOperators(self.A)
        self._factorised_state = -1  # id of the state the factorisation belongs to
        self._state = 0

    def assemble_residual(self, *, with_bcs: bool = True):
        """Residual vector; with ``with_bcs`` the Dirichlet rows hold -(g - u)."""
        x = _compat.petsc_vec(self.u)
        with self.b.localForm() as bl:
            bl.set(0.0)
        fem_petsc.assemble_vector(self.b, self.L)
        if with_bcs:
            _compat.apply_lifting(self.b, self.a, self.bcs, x, -1.0)
        self.b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        if with_bcs:
            _compat.set_bc(self.b, self.bcs, x, -1.0)
        return self.b

    def factorise(self) -> None:
        """Assemble and factorise the Jacobian (Dirichlet rows = identity) at the current u."""
        self.A.zeroEntries()
        fem_petsc.assemble_matrix(self.A, self.a, bcs=self.bcs)
        self.A.assemble()
        self.ksp.setOperators(self.A)
        self.ksp.setUp()
        self._factorised_state = self._state

    def ensure_factorised(self) -> None:
        """Make the factorisation belong to the current (converged) state.

        After convergence the last factorisation is one Newton update old; with quadratic
        convergence that update is below 1e-8 of u, so it is reused unless the step
        converged without any iteration (then the factorisation is a step old)."""
        if self._factorised_state != self._state:
            self.factorise()

    def solve(self) -> NewtonReport:
        self._state += 1
        x = _compat.petsc_vec(self.u)
        rep = NewtonReport(False, 0)
        r0 = None
        for it in range(self.max_iterations + 1):
            b = self.assemble_residual()
            rnorm = b.norm()
            rep.residuals.append(rnorm)
            if not np.isfinite(rnorm):
                rep.reason = "residual is not finite"
                return rep
            if r0 is None:
                r0 = rnorm
            if rnorm <= self.atol or rnorm <= self.rtol * r0:
                rep.converged, rep.iterations = True, it
                return rep
            if it == self.max_iterations:
                break
            self.factorise()
            self.ksp.solve(b, self.du)
            if self.ksp.getConvergedReason() < 0:
                rep.reason = f"linear solver failed ({self.ksp.getConvergedReason()})"
                return rep
            x.axpy(-1.0, self.du)
            x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        rep.iterations = self.max_iterations
        rep.reason = f"no convergence in {self.max_iterations} iterations (|r| = {rnorm:.3e})"
        return rep
