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


# MUMPS (with pivoting) on any number of ranks and for large systems.  Small systems on
# one rank (the diagnosis's axisymmetric models: ~300 dofs at its working refinement 1,
# ~1100 at the correction's 2, ~2300 at the generator's 3) are factorised by PETSc's own
# LU in a nested-dissection ordering (:data:`SMALL_SOLVER`, :data:`SMALL_ORDERING`):
# MUMPS's fixed cost per call dominates there (measured at 297 dofs: factorisation 0.81
# against 0.24 ms, back-substitution 0.143 against 0.012 ms; at 2325 dofs 10.9 against
# 9.3 and 0.88 against 0.44 ms; BENCHMARKS.md).  That LU does not pivot (but inside the
# 3 x 3 blocks of :data:`SMALL_MATRIX`): a factorisation
# that meets a zero pivot (KSP reason -11; a viscoelastic run with holds did) is made
# again by MUMPS, for that matrix only; so is one whose solution is not a solution to
# the rounding of a stable LU (normwise backward error above :data:`SMALL_BACKWARD_ERROR`,
# one product with the matrix per solve): without pivoting the elimination can grow, and
# on a Jacobian with entries that are not finite (assembled at a diverged iterate) it
# returns NaN as "converged" where MUMPS reports a failure (the closed benchmark's case011:
# a Mullins truth that MUMPS's failure and the step cut-back got past).  Above
# :data:`SMALL_MAX_DOFS` its fill grows fast (a 3D cylinder of 11 442 dofs: 1.7 s against
# MUMPS's 0.13 s per factorisation).
DIRECT_SOLVER = "mumps"
SMALL_SOLVER, SMALL_ORDERING = "petsc", "nd"
# Small systems are stored by 3 x 3 blocks (the displacement and twist of a node): an
# element matrix goes in by blocks and the LU works on them; assembly, factorisation and
# back-substitution of the glued Ogden Jacobian cost 0.33, 0.095 and 0.003 ms instead of
# 0.45, 0.097 and 0.004 at 297 dofs, 2.8, 3.1 and 0.045 instead of 4.0, 3.8 and 0.067 at
# 2325 (``benchmarks/bench_lu.py``); MUMPS factorises such a matrix too.
SMALL_MATRIX = "baij"
SMALL_MAX_DOFS = 3000
SMALL_BACKWARD_ERROR = 1e-10  # stable LU: ~1e-17 measured
KSP_DIVERGED_PC_FAILED = -11
# MUMPS sizes its workspace from the first (symbolic) analysis, which a solver keeps for
# every later factorisation; pivoting on a harder matrix of a later run can need more
# (its error -9, a failed linear solve, KSP reason -11), so that whether a solve succeeds
# depended on the runs before it.  Room for that fill-in, in per cent of the estimate
# (MUMPS ICNTL(14), default 20-35):
MUMPS_WORKSPACE_PERCENT = 200
SERIAL_PREFIX = "brainmech_newton_serial_"  # PETSc options of the one-rank solvers
# MUMPS's INFOG(1) when a workspace or buffer sized at the analysis was too small (-8, -9:
# factorisation; -11, -12, -14, -15: solution and refinement; -17, -20: send and receive
# buffers; -19: ICNTL(23)): a solver analysed afresh at the current matrix sizes them for it
MUMPS_WORKSPACE_ERRORS = frozenset({-8, -9, -11, -12, -14, -15, -17, -19, -20})


def ghost_forward(x) -> None:
    """The ghost values of x from their owners (nothing to exchange on one rank)."""
    if x.comm.size > 1:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)


def ghost_reverse(x) -> None:
    """What an assembly put into x's ghost entries, added to their owners (nothing to
    exchange on one rank)."""
    if x.comm.size > 1:
        x.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)


class NewtonSolver:
    """Newton for F(u; v) = 0 with Dirichlet conditions ``bcs`` applied by lifting, reusing
    a factorisation while it contracts (``reuse``; see :meth:`solve`).

    Converged when the free-dof residual norm drops below ``atol`` (a force, mN) or below
    ``rtol`` times the first residual of the step. The Jacobian is factorised by LU
    (MUMPS, :data:`DIRECT_SOLVER`); the symbolic factorisation is kept
    across iterations because the sparsity pattern never changes.
    """

    def __init__(self, comm, residual_form, jacobian_form, u, bcs, *, atol: float = 1e-10,
                 rtol: float = 1e-10, max_iterations: int = 15, reuse: bool = True,
                 contraction: float = 0.1):
        self.comm = comm
        self.L = residual_form
        self.a = jacobian_form
        self.u = u
        self.bcs = bcs
        self.atol, self.rtol, self.max_iterations = atol, rtol, max_iterations
        self.reuse, self.contraction = reuse, contraction
        # lift the Dirichlet values at every iteration even where u already meets them
        # (always under MPI: see :meth:`solve`)
        self.lift_every_iteration = False
        dofmap = u.function_space.dofmap
        n = dofmap.index_map.size_global * dofmap.index_map_bs
        self.small = comm.size == 1 and n <= SMALL_MAX_DOFS  # PETSc's LU, MUMPS if it fails
        self.A = fem_petsc.create_matrix(jacobian_form, SMALL_MATRIX if self.small else None)
        self.b = fem_petsc.create_vector(residual_form)
        self.du = self.b.duplicate()
        # the last residual assembled without lifting, before its Dirichlet rows were set
        # (they hold the plate's reactions), and the solve it converged (-1: none)
        self.b_free = self.b.duplicate()
        self._free_of = -1
        self._primary = self.ksp = self._new_ksp(SMALL_SOLVER if self.small else DIRECT_SOLVER)
        self._pivoting = None  # the MUMPS solver of a small system's zero pivots (made once)
        self._a_norm = np.inf  # infinity norm of the factorised Jacobian
        self._check = self.b.duplicate()
        # the conditions that share a dof with each other: DOLFINx gives a shared dof the
        # value of the last of them, so they are lifted together (see :meth:`_off_values`)
        dofs = [np.asarray(bc.dof_indices()[0]) for bc in bcs]
        self._linked = [{i} | {j for j, d in enumerate(dofs) if np.intersect1d(d, di).size}
                        for i, di in enumerate(dofs)]
        self._factorised = (-1, 0)  # (solve, iteration) the factorisation was made at
        self._state = self._iteration = 0
        self.factorisations = 0
        self.rebuilds = 0  # linear solvers made afresh after a failed solve
        self.pivoted = 0  # factorisations of a small system made again by MUMPS
        self.renewed = 0  # MUMPS solvers replaced after a failed factorisation
        self._failure = ""  # what the last failed linear solve reported

    def _new_ksp(self, solver: str = DIRECT_SOLVER):
        """LU by ``solver`` on ``self.A``, its analysis made at the next set-up."""
        ksp = PETSc.KSP().create(self.comm)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("lu")
        pc.setFactorSolverType(solver)
        if solver == SMALL_SOLVER:
            pc.setFactorOrdering(SMALL_ORDERING)
        elif self.comm.size == 1:  # where the diagnosis runs its models; distributed,
            # DOLFINx 0.9's MUMPS failed a Maxwell run with it (KSP -11): the default there
            ksp.setOptionsPrefix(SERIAL_PREFIX)  # one value for every such solver
            PETSc.Options()[f"{SERIAL_PREFIX}mat_mumps_icntl_14"] = MUMPS_WORKSPACE_PERCENT
            ksp.setFromOptions()  # read by the factor matrix when it is created
        ksp.setOperators(self.A)
        return ksp

    def linear_solve(self, b, x) -> int:
        """x from the current factorisation and right-hand side b.  A small system whose
        factorisation met a zero pivot (PETSc's LU does not pivot), or whose solution is
        not one (:meth:`_solves`), is factorised again by MUMPS and solved by it until the
        next factorisation.  A solve that fails
        because MUMPS's workspace, sized at the solver's first analysis, is too small for
        this matrix's pivoting (:data:`MUMPS_WORKSPACE_ERRORS`) is made once more with a
        solver analysed afresh at the Jacobian of the current u; any other failure (a
        numerically singular Jacobian, INFOG(1) = -10) is returned as it is, for the load
        step to be cut back, and the MUMPS solver that failed is replaced (:meth:`_renew`).
        Returns the KSP's converged reason (< 0: failed)."""
        reason = self._solve_with(b, x)
        if (self.small and self.ksp is self._primary
                and (reason == KSP_DIVERGED_PC_FAILED
                     or (reason >= 0 and not self._solves(b, x)))):
            log.debug("LU of a small system failed (%d) or inaccurate: factorised again by "
                      "MUMPS", reason)
            if self._pivoting is None:
                self._pivoting = self._new_ksp()
            self.ksp = self._pivoting
            self.ksp.setOperators(self.A)
            self.ksp.setUp()
            self.pivoted += 1
            reason = self._solve_with(b, x)
        if reason >= 0:
            return reason
        if self._mumps_error()[0] not in MUMPS_WORKSPACE_ERRORS:
            return self._renew(reason)
        log.warning("linear solver failed (%d%s): analysing afresh and solving again", reason,
                    self._factor_error())
        self._replace_ksp()
        self.rebuilds += 1
        self.factorise(self.ksp)
        reason = self._solve_with(b, x)
        return reason if reason >= 0 else self._renew(reason)

    def _solve_with(self, b, x) -> int:
        """x from the current solver; its converged reason, :data:`KSP_DIVERGED_PC_FAILED`
        where PETSc raises instead (kept for the message: :meth:`_factor_error`)."""
        self._failure = ""
        try:
            self.ksp.solve(b, x)
        except PETSc.Error as exc:
            self._failure = f"; PETSc error {exc.ierr}"
            log.debug("linear solve raised PETSc error %s", exc.ierr)
            return KSP_DIVERGED_PC_FAILED
        return self.ksp.getConvergedReason()

    def _renew(self, reason: int) -> int:
        """After a failed solve: a MUMPS solver is replaced by a fresh one, analysed at its
        next set-up.  PETSc 3.18's MUMPS interface never factorises again after a failed
        factorisation (it takes INFOG(1) < 0 for a failed analysis and skips the numeric
        factorisation, and the next solve raises MUMPS's error -3): a singular Jacobian,
        or a zero pivot of a small system that MUMPS could not take either, then failed
        every later run of the model, and the open benchmark's generator, which draws
        such truths, lost a whole MPI rank to the exception.  Returns ``reason``."""
        self._failure = self._failure or self._factor_error()
        if self.ksp.getPC().getFactorSolverType() != "mumps":
            return reason  # PETSc's own LU factorises the next matrix as usual
        self._replace_ksp()
        self._factorised = (-1, 0)
        self.renewed += 1
        return reason

    def _replace_ksp(self) -> None:
        """The current solver (the primary or the pivoting one) destroyed and replaced by a
        fresh MUMPS solver in its role, analysed at its next set-up."""
        fresh = self._new_ksp()
        if self.ksp is self._primary:
            self._primary = fresh
        else:
            self._pivoting = fresh
        self.ksp.destroy()
        self.ksp = fresh

    def _solves(self, b, x) -> bool:
        """Whether x solves A x = b to a normwise backward error of at most
        :data:`SMALL_BACKWARD_ERROR` (infinity norms; False when anything is not finite)."""
        r = self._check
        self.A.mult(x, r)
        r.axpy(-1.0, b)
        inf = PETSc.NormType.INFINITY
        scale = self._a_norm * x.norm(inf) + b.norm(inf)
        return bool(np.isfinite(scale) and r.norm(inf) <= SMALL_BACKWARD_ERROR * scale)

    def solve_tangent(self, b, x) -> None:
        """x = K^-1 b with the factorisation of the converged state (the sensitivities'
        solves); raises :class:`ConvergenceError` when the linear solve fails."""
        reason = self.linear_solve(b, x)
        if reason < 0:
            raise ConvergenceError(f"tangent solve of the sensitivities failed ({reason}"
                                   f"{self._failure})")

    def assemble_residual(self, *, with_bcs: bool = True, lift: bool = True):
        """Residual vector; with ``with_bcs`` the Dirichlet rows hold -(g - u).  ``lift``:
        add the lifting of the Dirichlet values (needless when u already meets them)."""
        x = _compat.petsc_vec(self.u)
        with self.b.localForm() as bl:
            bl.set(0.0)
        fem_petsc.assemble_vector(self.b, self.L)
        if with_bcs and lift:
            lifted = self._off_values(x)
            if lifted:
                _compat.apply_lifting(self.b, self.a, lifted, x, -1.0)
        ghost_reverse(self.b)
        if with_bcs:
            if not lift:  # the residual itself: what a later :meth:`free_residual` returns
                self.b.copy(self.b_free)
            _compat.set_bc(self.b, self.bcs, x, -1.0)
        return self.b

    def _off_values(self, x) -> list:
        """The Dirichlet conditions whose values u does not meet, with every condition
        that shares a dof with one of them (in their order): only these add to the lifting
        on one rank, where each condition that u meets exactly would add A_e (g - u) = 0
        on every cell it touches (the same bits without those cells: in a load step only
        the plate's conditions move, 4 of the 11 cells of the working mesh).  Under MPI
        every condition is lifted (see :meth:`solve`)."""
        if self.comm.size > 1 or self.lift_every_iteration:
            return self.bcs
        def met(bcs) -> bool:  # u meets every value of bcs (False when not finite)
            r = self._check
            with r.localForm() as rl:
                rl.set(0.0)
            _compat.set_bc(r, bcs, x, -1.0)  # -(g - u) on these conditions' rows only
            return r.norm(PETSc.NormType.INFINITY) == 0.0

        if met(self.bcs):  # most steps
            return []
        off = set()
        for i, bc in enumerate(self.bcs):
            if not met([bc]):
                off |= self._linked[i]  # with those sharing its dofs: the same values
        return [bc for i, bc in enumerate(self.bcs) if i in off]

    def free_residual(self):
        """The residual at the current u without the Dirichlet rows set (the rows of the
        reactions), in a vector of its own that no later assembly overwrites before the
        next :meth:`solve`.  Right after a converged solve it is that solve's own last
        residual when it was assembled without lifting (the same operations, so the same
        bits), otherwise it is assembled now.  Call it only while u, the parameters and
        the history are those the last solve converged at (or after :meth:`forget`)."""
        if self._free_of != self._state:
            self.assemble_residual(with_bcs=False).copy(self.b_free)
            self._free_of = self._state
        return self.b_free

    def factorise(self, ksp=None) -> None:
        """Assemble and factorise the Jacobian (Dirichlet rows = identity) at the current u,
        by the system's own solver (``ksp``: by that one)."""
        self.A.zeroEntries()
        fem_petsc.assemble_matrix(self.A, self.a, bcs=self.bcs)
        self.A.assemble()
        self._a_norm = self.A.norm(PETSc.NormType.INFINITY) if self.small else np.inf
        self.ksp = self._primary if ksp is None else ksp
        self.ksp.setOperators(self.A)
        self.ksp.setUp()
        self._factorised = (self._state, self._iteration)
        self.factorisations += 1

    def _mumps_error(self) -> tuple[int, int]:
        """MUMPS's INFOG(1), INFOG(2) of the last factorisation (0, 0 when there is none to
        read: another factorisation package, or none made yet)."""
        try:
            f = self.ksp.getPC().getFactorMatrix()
            return int(f.getMumpsInfog(1)), int(f.getMumpsInfog(2))
        except Exception:  # noqa: BLE001 - not MUMPS, or no factor matrix yet
            return 0, 0

    def _factor_error(self) -> str:
        """MUMPS's error code for a message ('' when there is none)."""
        e1, e2 = self._mumps_error()
        return f"; MUMPS INFOG(1) = {e1}, INFOG(2) = {e2}" if e1 else ""

    def forget(self) -> None:
        """Drop the factorisation: the next solve factorises afresh, so that a run's
        results do not depend on the runs before it (bit for bit)."""
        self._factorised = (-1, 0)
        self._free_of = -1  # u is about to change without a solve

    def ensure_factorised(self) -> None:
        """Make the factorisation belong to the current (converged) state.

        A factorisation made at the last or the last-but-one iterate of the converged
        solve is kept (the last update of a converged Newton solve is below 1e-8 of u);
        an older one (the chord steps reuse it) is renewed."""
        state, it = self._factorised
        if state != self._state or it < self._iteration - 1:
            self.factorise()

    def solve(self) -> NewtonReport:
        """Newton's method that reuses the last factorisation (from an earlier iterate or
        load step) while it contracts the residual at least ``contraction`` times per
        iteration, and factorises afresh otherwise: in small load steps the tangent
        barely changes, and assembling it costs ~10 residuals.  A step made with an old
        factorisation that does not reduce the residual is undone and made again with a
        fresh one, so the iteration never does worse than full Newton."""
        self._state += 1
        self._free_of = -1
        x = _compat.petsc_vec(self.u)
        rep = NewtonReport(False, 0)
        r0 = prev = None
        stale_step = False  # the last update was made with an old factorisation
        # Whether u meets the Dirichlet values (then the lifting, which costs about as much
        # as assembling the Jacobian, adds only rounding): after any update on one rank,
        # the identity rows of the Jacobian set them exactly.  Under MPI it is lifted at
        # every iteration: on DOLFINx 0.9 the ghosts of u need not hold the Dirichlet
        # values after an update (a distributed Maxwell run failed, KSP -11).
        serial = self.comm.size == 1 and not self.lift_every_iteration
        meets = before = False
        for it in range(self.max_iterations + 1):
            self._iteration = it
            b = self.assemble_residual(lift=not meets)
            rnorm = b.norm()
            redo = stale_step and not (rnorm < prev)  # also when rnorm is not finite
            if redo:  # undo the update, factorise at the iterate it was made from
                x.axpy(1.0, self.du)
                ghost_forward(x)
                meets = before
                b = self.assemble_residual(lift=not meets)
                rnorm = b.norm()
            rep.residuals.append(rnorm)
            if not np.isfinite(rnorm):
                rep.reason = "residual is not finite"
                return self._failed(rep)
            if r0 is None:
                r0 = rnorm
            if rnorm <= self.atol or rnorm <= self.rtol * r0:
                rep.converged, rep.iterations = True, it
                # b was assembled without lifting where u met the Dirichlet values
                self._free_of = self._state if meets else -1
                return rep
            if it == self.max_iterations:
                break
            fresh = (redo or self._factorised[0] < 0 or not self.reuse
                     or (prev is not None and rnorm > self.contraction * prev))
            if fresh:
                self.factorise()
            prev = rnorm
            reason = self.linear_solve(b, self.du)  # may factorise afresh
            if reason < 0:
                rep.reason = f"linear solver failed ({reason}{self._failure})"
                return self._failed(rep)
            stale_step = self._factorised != (self._state, it)
            x.axpy(-1.0, self.du)
            ghost_forward(x)
            before, meets = meets, serial
        rep.iterations = self.max_iterations
        rep.reason = f"no convergence in {self.max_iterations} iterations (|r| = {rnorm:.3e})"
        return self._failed(rep)

    def _failed(self, rep: NewtonReport) -> NewtonReport:
        """A failed solve drops its factorisation: the step cut back from the converged
        state factorises afresh there instead of reusing one that failed (every one of
        the cut-backs did, so that a failed factorisation failed the whole step)."""
        self._factorised = (-1, 0)
        return rep
