"""Verification of the forward model (DESIGN.md section 3 references)."""

import contextlib
import math

import numpy as np
import pytest
from mpi4py import MPI
from references import homogeneous_uniaxial, rivlin_torque


def _params(**kw):
    from brain_fe.materials import MaterialParameters

    base = {"mu": (1.0,), "alpha": (-20.0,), "kappa": 100.0, "nu0": None}
    base.update(kw)
    return MaterialParameters(**base)


def test_slip_ends_match_homogeneous_solution(axi_slip):
    """Slip ends: every point of the full protocol (loading and unloading, compression and
    tension) within 0.1 % of the root-solved homogeneous uniaxial stress."""
    from brain_fe.protocols import compression_tension

    df = axi_slip.run(compression_tension(0.15), _params())
    assert len(df) == 41
    for lam, p in zip(df.stretch, df.nominal_stress_kPa, strict=True):
        assert p == pytest.approx(homogeneous_uniaxial(lam), rel=1e-3, abs=1e-9)


def test_torsion_approaches_rivlin(axi_glued):
    """Compressible torque -> Rivlin's incompressible torque, first order in mu/kappa."""
    from brain_fe.protocols import Protocol

    ref = rivlin_torque(0.30)
    prot = Protocol("torsion", (0.0, 0.30), max_increment=0.1)
    dev = []
    for kappa in (1e2, 1e3, 1e4):
        T = axi_glued.run(prot, _params(kappa=kappa)).torque_mNmm.iloc[-1]
        dev.append(abs(T - ref) / ref)
    assert dev[0] > dev[1] > dev[2]
    assert dev[2] < 5e-4
    assert 5.0 < dev[1] / dev[2] < 20.0  # ~10x closer per decade of kappa/mu


def _quadratic_constants(res, scale):
    """rho_{k+1} / rho_k^2 for the residuals relative to the force scale mu pi R^2, above
    the round-off floor (1e-11): bounded for quadratic convergence, while linear
    convergence gives c / rho_k -> inf."""
    rho = [x / scale for x in res]
    return [b / a**2 for a, b in zip(rho[:-1], rho[1:], strict=False) if b > 1e-11]


def test_newton_quadratic_through_reference_and_unloading(axi_glued):
    """Quadratic convergence in compression, on unloading through lambda = 1, in tension
    and in torsion: rho_{k+1} <= 100 rho_k^2 for every iteration of the default protocols,
    at most 5 iterations per step (the bound 100 is far below linear behaviour).  Full
    Newton (a fresh tangent every iteration): this checks that the tangent is consistent."""
    from brain_fe.protocols import compression_tension, torsion

    axi_glued.newton.reuse = False
    try:
        for prot in (compression_tension(0.15), torsion(0.30)):
            axi_glued.run(prot, _params(nu0=0.49, kappa=None))
            consts = [c for _, res in axi_glued.newton_log
                      for c in _quadratic_constants(res, math.pi * 16)]
            assert max(len(res) - 1 for _, res in axi_glued.newton_log) <= 5
            assert len(consts) >= 20
            assert max(consts) < 100.0  # linear convergence would give ~1e6 at rho ~ 1e-8
    finally:
        axi_glued.newton.reuse = True


def test_reused_factorisations_change_nothing(axi_glued):
    """Newton reusing its factorisation across iterations and load steps (the default)
    reaches the same states as full Newton (to 1e-9 of the peak, both converged to 1e-10
    of the first residual) with at most half the factorisations."""
    from brain_fe.protocols import compression_tension, torsion

    p = _params(nu0=0.49, kappa=None)
    for prot in (compression_tension(0.15), torsion(0.30)):
        runs, counts = [], []
        for reuse in (False, True):
            axi_glued.newton.reuse = reuse
            n0 = axi_glued.newton.factorisations
            runs.append(axi_glued.run(prot, p))
            counts.append(axi_glued.newton.factorisations - n0)
        axi_glued.newton.reuse = True
        for col in ("nominal_stress_kPa", "torque_mNmm", "axial_force_mN"):
            if col in runs[0]:
                a, b = runs[0][col].to_numpy(), runs[1][col].to_numpy()
                assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(a))
        assert counts[1] <= counts[0] / 2


@contextlib.contextmanager
def _primary_solver(newton, ksp):
    """``ksp`` as the Newton solver's own linear solver for the block, with no fall-back to
    MUMPS (as on several ranks or for a large system); the fixture's restored after it."""
    saved = newton.small, newton._primary
    newton.small, newton._primary, newton.ksp = False, ksp, ksp
    try:
        yield
    finally:
        newton.small, newton._primary = saved
        newton.ksp = newton._primary
        newton.forget()


def _same_states(ref, df, col: str = "nominal_stress_kPa") -> None:
    """Two runs of a protocol reach the same states: ``col`` to 1e-9 of its peak (both
    converged to 1e-10 of the first residual)."""
    a, b = ref[col].to_numpy(), df[col].to_numpy()
    assert len(a) == len(b)
    assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(a))


class _MumpsReport:
    """Stands in for a KSP's PC and its factor matrix: MUMPS's INFOG(1), INFOG(2) as the
    dict ``codes`` holds them when read (a test may change it between runs)."""

    def __init__(self, codes: dict):
        self.codes = codes

    def getFactorMatrix(self):
        return self

    def getFactorSolverType(self):
        return "mumps"

    def getMumpsInfog(self, i):
        return self.codes[i]


def test_failed_linear_solve_is_made_again_with_a_fresh_analysis(axi_glued, caplog):
    """A linear solve that fails (here: reported failed once, as MUMPS does when the
    workspace of its first analysis is too small for a later matrix, INFOG(1) = -9) is
    made again by a solver analysed afresh at the current Jacobian, with a warning: the
    run reaches the same states as one without the failure (to 1e-9 of the peak, both
    converged to 1e-10 of the first residual) instead of cutting its load steps back.  A
    singular Jacobian (INFOG(1) = -10) is not solved again: its load step is cut back, and
    the solver that failed is replaced (:func:`test_a_mumps_solver_that_failed_is_replaced`)."""
    from brain_fe.protocols import compression_tension
    from brain_fe.solver import ConvergenceError

    codes = {1: -9, 2: 1234}  # MUMPS's report of a workspace too small

    class FailsOnce:  # the real solver's answer, reported as a failed factorisation
        def __init__(self, ksp):
            self.ksp = ksp

        def getConvergedReason(self):
            return -11  # KSP_DIVERGED_PC_FAILED

        def getPC(self):
            return _MumpsReport(codes)

        def __getattr__(self, name):
            return getattr(self.ksp, name)

    p = _params(nu0=0.49, kappa=None)
    prot = compression_tension(0.15)
    newton = axi_glued.newton

    def failing(ksp):
        newton._primary = newton.ksp = FailsOnce(ksp)

    # MUMPS as the system's own solver (as on several ranks or for a large system)
    with _primary_solver(newton, newton._new_ksp()):
        newton.forget()
        ref = axi_glued.run(prot, p)
        n0 = newton.rebuilds
        failing(newton._primary)
        with caplog.at_level("WARNING", logger="brain_fe.solver"):
            df = axi_glued.run(prot, p)
        assert newton.rebuilds == n0 + 1
        assert not isinstance(newton.ksp, FailsOnce)
        assert not isinstance(newton._primary, FailsOnce)
        assert "analysing afresh" in caplog.text and "INFOG(1) = -9" in caplog.text
        _same_states(ref, df)
        # any other failure (a singular Jacobian, INFOG(1) = -10) is not solved again: the
        # load step is cut back, with a fresh solver in place of the one that failed
        codes.update({1: -10, 2: 77})
        failing(newton._primary)
        r0 = newton.renewed
        caplog.clear()
        with caplog.at_level("INFO", logger="brain_fe.stepper"):
            df = axi_glued.run(prot, p)
        assert "INFOG(1) = -10" in caplog.text and "cutting the step back" in caplog.text
        assert newton.rebuilds == n0 + 1 and newton.renewed == r0 + 1
        assert not isinstance(newton._primary, FailsOnce)
        _same_states(ref, df)
        newton.forget()
        # a sensitivity's tangent solve that fails again after the fresh analysis raises
        # (the model's failure, which the diagnosis reports) instead of returning a wrong z
        codes.update({1: -9, 2: 1234})
        real_new_ksp = newton._new_ksp
        newton._new_ksp = lambda *a: FailsOnce(real_new_ksp(*a))
        failing(newton._primary)
        x = newton.du.duplicate()
        try:
            with pytest.raises(ConvergenceError, match="tangent solve"):
                newton.solve_tangent(newton.b, x)
        finally:
            del newton._new_ksp


def test_a_zero_pivot_is_factorised_again_by_mumps(axi_glued):
    """A small system on one rank is factorised by PETSc's own LU, which does not pivot; a
    factorisation that meets a zero pivot (KSP reason -11), or whose solution is not one
    (NaN reported as converged), is made again by MUMPS for that matrix only: the run
    reaches the states of one without it (to 1e-9 of the peak, both converged to 1e-10 of
    the first residual), and the next factorisation is PETSc's again. Both solvers agree
    on the same Jacobian to 1e-12."""
    from brain_fe.protocols import torsion

    newton = axi_glued.newton
    if not newton.small:
        pytest.skip("several ranks: MUMPS throughout")
    assert newton._primary.getPC().getFactorSolverType() == "petsc"

    class FailsOnce:  # the first solve fails as PETSc's LU can: a zero pivot (KSP reason
        # -11), or NaN reported as converged (a Jacobian with entries that are not finite)
        def __init__(self, ksp, reason):
            self.ksp, self.first, self.reason = ksp, True, reason

        def solve(self, b, x):
            if self.first:
                self.first = False
                x.set(np.nan)
            else:
                self.reason = None
                self.ksp.solve(b, x)

        def getConvergedReason(self):
            return self.ksp.getConvergedReason() if self.reason is None else self.reason

        def __getattr__(self, name):
            return getattr(self.ksp, name)

    p = _params(nu0=0.49, kappa=None)
    prot = torsion(0.30)
    newton.forget()
    ref = axi_glued.run(prot, p)
    for reason in (-11, 4):
        _refactorised_by_mumps(axi_glued, newton, FailsOnce(newton._primary, reason), prot, p,
                               ref)


def _refactorised_by_mumps(model, newton, wrapped, prot, p, ref):
    n0, f0 = newton.pivoted, newton.factorisations
    newton._primary = newton.ksp = wrapped
    try:
        df = model.run(prot, p)
        assert newton.pivoted == n0 + 1
        assert newton._pivoting.getPC().getFactorSolverType() == "mumps"
        assert newton.ksp is newton._primary  # later factorisations: PETSc's LU again
        assert newton.factorisations - f0 >= 2
        for col in ("torque_mNmm", "axial_force_mN"):
            a, b = ref[col].to_numpy(), df[col].to_numpy()
            assert len(a) == len(b)
            assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(a))
        # the same Jacobian solved by either: the same answer to rounding
        x1, x2 = newton.du.duplicate(), newton.du.duplicate()
        newton.b.setRandom()
        wrapped.ksp.solve(newton.b, x1)
        newton._pivoting.setOperators(newton.A)
        newton._pivoting.setUp()
        newton._pivoting.solve(newton.b, x2)
        x2.axpy(-1.0, x1)
        assert x2.norm() <= 1e-12 * x1.norm()
    finally:
        newton._primary = newton.ksp = wrapped.ksp
        newton.forget()


def test_a_failed_factorisation_is_not_reused_after_the_cut_back(axi_glued):
    """A linear solve that fails (here a factorisation whose every solve fails, as a
    singular Jacobian's does: MUMPS INFOG(1) = -10) fails its Newton solve, and the step
    cut back from the converged state factorises afresh instead of reusing it (before,
    every cut-back reused it and the whole step failed): the run reaches the states of one
    without the failure (to 1e-9 of the peak)."""
    from brain_fe.protocols import compression_tension

    class BrokenFactorisation:  # the next factorisation fails every solve made with it
        def __init__(self, ksp):
            self.ksp, self.broken, self.failures = ksp, None, 0

        def setUp(self):
            self.broken = self.broken is None  # the first factorisation only
            self.ksp.setUp()

        def solve(self, b, x):
            if self.broken:
                self.failures += 1
                x.set(np.nan)
            else:
                self.ksp.solve(b, x)

        def getConvergedReason(self):
            return -11 if self.broken else self.ksp.getConvergedReason()

        def getPC(self):
            return _MumpsReport({1: -10, 2: 77}) if self.broken else self.ksp.getPC()

        def destroy(self):  # replaced after its failure; the fixture's solver stays
            pass

        def __getattr__(self, name):
            return getattr(self.ksp, name)

    newton = axi_glued.newton
    p = _params(nu0=0.49, kappa=None)
    prot = compression_tension(0.15)
    newton.forget()
    ref = axi_glued.run(prot, p)
    wrapped = BrokenFactorisation(newton._primary)
    with _primary_solver(newton, wrapped):  # no fall-back to MUMPS: the failure stands
        r0 = newton.renewed
        df = axi_glued.run(prot, p)
        assert wrapped.failures == 1 and newton.renewed == r0 + 1
        _same_states(ref, df)


def test_a_mumps_solver_that_failed_is_replaced(axi_glued):
    """PETSc 3.18's MUMPS interface never factorises again after a failed factorisation:
    it skips the numeric factorisation, and the next solve raises MUMPS's error -3 (an MPI
    rank of the open benchmark died of it, and the run hung).  A MUMPS solver whose
    factorisation failed (here of a Jacobian with a zero row: INFOG(1) = -10, numerically
    singular) is
    replaced, and the next run of the model reaches the states of a run without the
    failure (to 1e-9 of the peak).  Real solvers, no stand-ins."""
    from brain_fe.protocols import compression_tension

    newton = axi_glued.newton
    p = _params(nu0=0.49, kappa=None)
    prot = compression_tension(0.15)
    newton.forget()
    ref = axi_glued.run(prot, p)
    with _primary_solver(newton, newton._new_ksp()):  # MUMPS, as for large systems
        failed = newton._primary
        newton.factorise()  # analysed at the Jacobian, then given one with a zero row
        newton.A.zeroRows([5], diag=0.0)
        failed.setOperators(newton.A)
        failed.setUp()
        r0 = newton.renewed
        assert newton.linear_solve(newton.b, newton.du) < 0
        assert newton.renewed == r0 + 1 and "INFOG(1) = -10" in newton._failure
        assert newton._primary is not failed and newton.ksp is newton._primary
        df = axi_glued.run(prot, p)
        _same_states(ref, df)


def test_lifting_once_per_step_changes_nothing(axi_glued, monkeypatch):
    """On one rank the Dirichlet values are lifted only while u does not meet them (the
    first iteration of a step): the states equal those of lifting at every iteration to
    1e-12 of the peak, with at most one lifting per Newton solve instead of one per
    iteration."""
    from brain_fe import _compat
    from brain_fe.protocols import compression_tension, torsion

    calls = []
    lift = _compat.apply_lifting
    monkeypatch.setattr(_compat, "apply_lifting", lambda *a, **k: (calls.append(1),
                                                                   lift(*a, **k)))
    p = _params(nu0=0.49, kappa=None)
    for prot in (compression_tension(0.15), torsion(0.30)):
        runs, lifts = [], []
        for every in (True, False):
            axi_glued.newton.lift_every_iteration = every
            calls.clear()
            runs.append(axi_glued.run(prot, p))
            lifts.append(len(calls))
        axi_glued.newton.lift_every_iteration = False
        for col in ("nominal_stress_kPa", "torque_mNmm", "axial_force_mN"):
            if col in runs[0]:
                a, b = runs[0][col].to_numpy(), runs[1][col].to_numpy()
                assert np.max(np.abs(a - b)) <= 1e-12 * np.max(np.abs(a))
        solves = len(axi_glued.newton_log)
        # at most once per solve: not at all where the step's predictor already moved
        # the plate's dofs to their new values (test_only_the_moving_conditions_are_lifted)
        assert 0 < lifts[1] <= solves
        assert lifts[0] >= 2 * solves


def test_only_the_moving_conditions_are_lifted(axi_glued, monkeypatch):
    """On one rank a Dirichlet condition that u meets exactly adds A_e (g - u) = 0 to
    the lifting, so only the plate's conditions are lifted in a load step (4 of the cells
    touched by any condition on the working mesh): every output, sensitivities included,
    equals bit for bit a run that lifts every condition, and a residual lifted either way
    is the same vector."""
    from brain_fe import _compat
    from brain_fe.protocols import torsion
    from brain_fe.solver import NewtonSolver

    n = axi_glued.newton
    p = _params(nu0=0.49, kappa=None)
    prot = torsion(0.30)
    new = axi_glued.run(prot, p, sensitivities=["mu_0", "alpha_0"])
    monkeypatch.setattr(NewtonSolver, "_off_values", lambda self, x: self.bcs)
    old = axi_glued.run(prot, p, sensitivities=["mu_0", "alpha_0"])
    monkeypatch.undo()
    assert list(new.columns) == list(old.columns) and len(new.columns) > 5
    for col in new.select_dtypes("number"):
        assert np.array_equal(new[col].to_numpy(), old[col].to_numpy()), col
    # at the last converged state, the plate moved on: only its two conditions are off
    # (they share no dof with another; u_r = 0 on the axis, bottom and top do)
    x = _compat.petsc_vec(axi_glued.u)
    axi_glued.ends.set_top(0.05, 0.2)
    moving = n._off_values(x)
    assert moving == n.bcs[-2:]  # u_z and twist on top
    assert n._linked[0] == {0, 3, 4}  # the axis's u_r, with the bottom's and the top's
    lifted = n.assemble_residual().copy()
    monkeypatch.setattr(NewtonSolver, "_off_values", lambda self, x: self.bcs)
    every = n.assemble_residual().copy()
    assert np.array_equal(lifted.array, every.array)
    axi_glued.ends.set_top(0.0, 0.0)


def test_reactions_come_from_the_cells_at_the_top():
    """The reactions are the residual's rows of the top plate, so only the cells with a
    dof on the top face are assembled for them (4 of the 20 cells of the working mesh):
    a viscoelastic run with its path sensitivities (which take the reactions at every
    perturbed state) equals bit for bit the run that assembles the whole residual."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import torsion

    m = ForwardModel(geometry.axisymmetric(refinement=1, comm=MPI.COMM_SELF), maxwell=1)
    assert len(m.ends.top_cells()) == 4
    p = _params(nu0=0.49, kappa=None, beta=(0.3,), tau_s=(5.0,))
    prot = torsion(0.30)
    new = m.run(prot, p, sensitivities=["mu_0", "beta_0", "tau_0"])

    def whole(self):
        return self.ends.reactions(self.newton.assemble_residual(with_bcs=False), self.comm)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ForwardModel, "reactions", whole)
        old = m.run(prot, p, sensitivities=["mu_0", "beta_0", "tau_0"])
    assert len(new.columns) > 8
    for col in new.select_dtypes("number"):
        assert np.array_equal(new[col].to_numpy(), old[col].to_numpy()), col
    # a form whose cells are already split into regions is refused, not merged
    import ufl

    from brain_fe.model import on_cells
    dx1 = ufl.Measure("dx", domain=m.geometry.mesh, subdomain_id=1)
    with pytest.raises(ValueError, match="subdomains"):
        on_cells(ufl.inner(m.u, ufl.TestFunction(m.V)) * dx1, m.geometry.mesh,
                 m.ends.top_cells())


def test_small_systems_are_stored_by_blocks(axi_glued):
    """A small system's Jacobian is a block matrix (3 x 3: a node's displacement and
    twist): the same entries as the point-wise matrix DOLFINx makes by default, and its
    LU solves the same system to rounding (1e-12 relative)."""
    import dolfinx.fem.petsc as fem_petsc
    from petsc4py import PETSc

    n = axi_glued.newton
    assert n.small and n.A.getType() == "seqbaij" and n.A.getBlockSize() == 3
    axi_glued.set_parameters(axi_glued.parameter_values(_params(nu0=0.49, kappa=None)))
    axi_glued.u.x.array[:] = 1e-3 * np.sin(np.arange(axi_glued.u.x.array.size))
    n.factorise()
    A = fem_petsc.create_matrix(n.a)
    assert A.getType() == "seqaij"
    fem_petsc.assemble_matrix(A, n.a, bcs=n.bcs)
    A.assemble()
    dense = [M.convert("dense", PETSc.Mat()).getDenseArray() for M in (A, n.A)]  # copies
    assert np.array_equal(*dense)
    assert n.A.getType() == "seqbaij"
    ksp = PETSc.KSP().create(A.comm)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.setOperators(A)
    b = A.createVecLeft()
    b.setArray(np.cos(np.arange(b.getSize())))
    x, y = b.duplicate(), b.duplicate()
    ksp.solve(b, x)
    pivoted = n.pivoted
    assert n.linear_solve(b, y) > 0
    assert n.pivoted == pivoted and n.ksp is n._primary  # solved by PETSc's block LU
    assert n.ksp.getPC().getFactorSolverType() == "petsc"
    y.axpy(-1.0, x)
    assert y.norm() <= 1e-12 * x.norm()
    for obj in (ksp, A, b, x, y):
        obj.destroy()
    axi_glued.u.x.array[:] = 0.0
    n.forget()


def test_a_converged_state_is_evaluated_once(monkeypatch):
    """At a converged (sub)step the residual (Newton's own last one when it was assembled
    without lifting), the reactions and the history update are computed once and reused
    by the path sensitivities, which perturb the state and restore it: each equals a fresh
    evaluation at the state after the sensitivities, bit for bit, also in a run that
    follows another one on the same model (a kept residual must not outlive its state)."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import compression_tension, torsion
    from brain_fe.sensitivities import DirectSensitivities, PathSensitivities

    counts = {"kept": 0, "fresh": 0, "restored": 0}

    def at_state(real):
        def checked(self, record, base):
            m = self.model
            n = m.newton
            kept = n._free_of == n._state
            out = real(self, record, base)
            r = n.assemble_residual(with_bcs=False)  # afresh, after the perturbations
            if base.residual is not None:
                d = base.residual.copy()
                d.axpy(-1.0, r)
                assert d.norm(0) == 0.0  # max norm: bit for bit
                counts["kept" if kept else "fresh"] += 1
            if base.reactions is not None:
                assert m.ends.reactions(r, m.comm) == base.reactions
            if base.update is not None:
                np.testing.assert_array_equal(m.state.evaluate(), base.update)
                counts["restored"] += 1
            return out
        return checked

    for cls in (DirectSensitivities, PathSensitivities):
        monkeypatch.setattr(cls, "at_state", at_state(cls.at_state))
    g = geometry.axisymmetric(refinement=1, comm=MPI.COMM_SELF)
    elastic, maxwell = ForwardModel(g), ForwardModel(g, maxwell=1)
    p = _params(nu0=0.49, kappa=None)
    pv = _params(nu0=0.49, kappa=None, beta=(0.4,), tau_s=(5.0,))
    for m, q in ((elastic, p), (maxwell, pv)):
        for prot in (compression_tension(0.15), torsion(0.30)):
            m.run(prot, q)  # without sensitivities, then with them after it
            res = m.run(prot, q, sensitivities=True)
            assert np.abs(res.iloc[1:, 4:].to_numpy(float)).min() > 0
    assert counts["kept"] > 10 * counts["fresh"] and counts["restored"] > 50


def test_unloading_returns_to_the_loading_curve(axi_glued):
    """Hyperelastic: unloading retraces loading (to 1e-8 relative) and ends force-free."""
    from brain_fe.protocols import compression_tension, torsion

    p = _params(nu0=0.49, kappa=None)
    df = axi_glued.run(torsion(0.30), p)
    df["shear"] = df.shear.round(10)
    load = df[df.branch == "loading"].set_index("shear").torque_mNmm
    unload = df[df.branch == "unloading"].set_index("shear").torque_mNmm
    common = load.index.intersection(unload.index)
    assert len(common) >= 10
    np.testing.assert_allclose(unload[common], load[common], rtol=1e-8, atol=1e-9)
    df = axi_glued.run(compression_tension(0.15), p)
    assert abs(df.axial_force_mN.iloc[-1]) < 1e-9 * math.pi * 16


def test_axisymmetric_matches_3d_in_torsion():
    """Glued torsion to gamma = 0.15: torque and Poynting axial force of the
    axisymmetric model within 1 % of the 3D gmsh model (both converge fast in torsion)."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import Protocol

    prot = Protocol("torsion", (0.0, 0.15), max_increment=0.075)
    p = _params(nu0=0.49, kappa=None)
    m3 = ForwardModel(geometry.cylinder3d(refinement=1, comm=MPI.COMM_WORLD))
    ma = ForwardModel(geometry.axisymmetric(refinement=2, comm=MPI.COMM_WORLD))
    r3, ra = m3.run(prot, p).iloc[-1], ma.run(prot, p).iloc[-1]
    assert ra.torque_mNmm == pytest.approx(r3.torque_mNmm, rel=1e-2)
    assert ra.axial_force_mN == pytest.approx(r3.axial_force_mN, rel=1e-2)
    # the reactions of the cells at the top face alone are those of the whole residual
    # (under MPI too: the cells of each rank, summed into the owners' rows)
    for m in (m3, ma):
        full = m.ends.reactions(m.newton.assemble_residual(with_bcs=False), m.comm)
        assert m.reactions() == full and abs(full[1]) > 0.1


@pytest.mark.slow
def test_axisymmetric_matches_3d_in_compression_tension():
    """Glued compression/tension at lambda = 0.85 and 1.15: axisymmetric vs 3D within 1 %
    once the 3D rim is resolved. The 3D value is Richardson-extrapolated from k = 1, 2
    with the order observed on the axisymmetric sequence k = 2, 4, 8 (same singularity)."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import Protocol

    p = _params(nu0=0.49, kappa=None)
    prots = [Protocol("compression_tension", (1.0, lam), max_increment=0.05)
             for lam in (0.85, 1.15)]

    def stresses(m):
        return np.array([m.run(pr, p).nominal_stress_kPa.iloc[-1] for pr in prots])

    axi = [stresses(ForwardModel(geometry.axisymmetric(refinement=k))) for k in (2, 4, 8)]
    order = np.log2(np.abs(axi[1] - axi[0]) / np.abs(axi[2] - axi[1]))
    axi_lim = axi[2] + (axi[2] - axi[1]) / (2**order - 1)
    d3 = [stresses(ForwardModel(geometry.cylinder3d(refinement=k))) for k in (1, 2)]
    d3_lim = d3[1] + (d3[1] - d3[0]) / (2**order - 1)
    np.testing.assert_allclose(axi[2], axi_lim, rtol=1e-2)
    np.testing.assert_allclose(d3_lim, axi_lim, rtol=1e-2)


@pytest.mark.parametrize("nu0", [0.45, 0.49, 0.499])
def test_newton_succeeds_over_parameter_range(nu0):
    """Full default protocols for mu in {0.3, 1, 3} kPa and alpha in {-30, -10, -2, 2, 10}:
    Newton succeeds (cut-backs allowed), the unloaded end state is force-free and the
    small-strain stiffness is positive."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import compression_tension, torsion

    model = _sweep_model()
    for mu in (0.3, 1.0, 3.0):
        for alpha in (-30.0, -10.0, -2.0, 2.0, 10.0):
            p = _params(mu=(mu,), alpha=(alpha,), kappa=None, nu0=nu0)
            for prot in (compression_tension(0.15), torsion(0.15), torsion(0.30)):
                df = model.run(prot, p)
                scale = mu * math.pi * 16
                assert abs(df.axial_force_mN.iloc[-1]) < 1e-8 * scale
                col = "nominal_stress_kPa" if prot.test != "torsion" else "torque_mNmm"
                first = df[col].iloc[1] * (1 if prot.test == "torsion" else -1)
                assert first > 0
    del geometry, ForwardModel


_SWEEP = {}


def _sweep_model():
    from brain_fe import geometry
    from brain_fe.model import ForwardModel

    if "m" not in _SWEEP:
        _SWEEP["m"] = ForwardModel(geometry.axisymmetric(refinement=1, comm=MPI.COMM_WORLD))
    return _SWEEP["m"]


@pytest.mark.mpi
def test_distributed_equals_serial():
    """The same solve on COMM_WORLD (distributed under mpirun -n 2) and on COMM_SELF gives
    the same forces to 1e-8 relative."""
    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import Protocol

    p = _params(nu0=0.49, kappa=None)
    prot = Protocol("torsion", (0.0, 0.30), max_increment=0.1)
    prot_ct = Protocol("compression_tension", (1.0, 0.85, 1.15), max_increment=0.1)
    out = []
    for comm in (MPI.COMM_WORLD, MPI.COMM_SELF):
        m = ForwardModel(geometry.axisymmetric(refinement=1, comm=comm))
        t = m.run(prot, p)
        c = m.run(prot_ct, p)
        out.append(np.concatenate([t.torque_mNmm, t.axial_force_mN, c.axial_force_mN]))
    np.testing.assert_allclose(out[0], out[1], rtol=1e-8, atol=1e-10)


@pytest.mark.mpi
def test_a_curve_failing_on_one_rank_fails_the_shared_prediction():
    """With the curves of a prediction shared among the ranks, a curve that fails on one
    rank (here torsion between slip plates, refused) raises the same error on every rank;
    before, the other rank waited for the failed one's rows for ever (a real double
    compression that could not be solved hung `mpirun -n 2 brainmech diagnose`)."""
    import pandas as pd

    from simulators.fe import FESimulator

    comm = MPI.COMM_WORLD
    obs = pd.DataFrame({
        "curve": ["ct"] * 3 + ["tor"] * 3, "test": ["compression_tension"] * 3
        + ["torsion"] * 3, "amplitude": [0.1] * 3 + [0.2] * 3,
        "channel": ["stress"] * 3 + ["torque"] * 3, "branch": "loading", "cycle": 1,
        "control": [0.95, 0.92, 0.9, 0.05, 0.1, 0.2], "time_s": np.nan, "value": 0.0})
    sim = FESimulator(obs, 4.0, 5.0, ends="slip")
    assert [c for c, *_ in sim.curves] == ["ct", "tor"]  # one curve per rank
    with sim.sharing(comm), pytest.raises(ValueError, match="torsion needs glued ends"):
        sim.predict({"mu_0": 1.0, "alpha_0": -20.0, "nu0": 0.49})


def test_balanced_shares_the_costliest_item_first():
    """A static share of items of known costs: longest first, each to the least loaded
    rank. The default protocol's curves (compression/tension of 41 points, two torsions of
    21) go CT alone to one rank and both torsions to the other; before, the curves were
    dealt round-robin (CT and the second torsion on rank 0: 0.85 + 0.42 s against 0.36 s
    for one viscoelastic prediction, measured on the speed specimen)."""
    from brain_fe.parallel import balanced

    assert balanced([41.0, 21.0, 21.0], 2) == [[0], [1, 2]]
    assert balanced([0.85, 0.36, 0.42], 2) == [[0], [1, 2]]
    assert balanced([1.0, 1.0, 1.0], 2) == [[0, 2], [1]]
    assert balanced([], 3) == [[], [], []]
    # 9 | 4, then 3 (the tie of 4 and 4 to the lower rank) | 4, then 1: loads 9, 7, 5
    assert balanced([3.0, 9.0, 1.0, 4.0, 4.0], 3) == [[1], [0, 3], [2, 4]]


@pytest.mark.mpi
def test_a_shared_prediction_equals_the_unshared_one():
    """The curves of a prediction shared among the ranks by their cost (the longest alone
    on one rank) give the same values and sensitivities as one rank solving them all, and
    every rank holds the same costs afterwards (so the next prediction is shared alike)."""
    import pandas as pd

    from simulators.fe import FESimulator

    comm = MPI.COMM_WORLD
    ct = [0.97, 0.94, 0.91, 0.94, 0.97]
    obs = pd.DataFrame({
        "curve": ["ct"] * 5 + ["t1"] * 3 + ["t2"] * 3,
        "test": ["compression_tension"] * 5 + ["torsion"] * 6,
        "amplitude": [0.09] * 5 + [0.1] * 3 + [0.2] * 3,
        "channel": ["stress"] * 5 + ["torque"] * 6,
        "branch": ["loading"] * 3 + ["unloading"] * 2 + ["loading"] * 6, "cycle": 1,
        "control": ct + [0.03, 0.06, 0.1, 0.05, 0.1, 0.2], "time_s": np.nan, "value": 0.0})
    sim = FESimulator(obs, 4.0, 5.0)
    values = {"mu_0": 1.0, "alpha_0": -20.0}
    alone = sim.predict(values, list(values))
    with sim.sharing(comm):
        if comm.size == 2:  # by the number of recorded points before the first solve
            assert sim.share_of(True, comm) == [[0], [1, 2]][comm.rank]
        shared = sim.predict(values, list(values))
        again = sim.predict(values, list(values))
    np.testing.assert_allclose(shared.y, alone.y, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(shared.jacobian, alone.jacobian, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(again.y, alone.y, rtol=1e-10, atol=1e-12)
    if comm.size > 1:
        costs = comm.allgather(list(sim._cost[True]))
        assert all(c == costs[0] for c in costs) and all(x > 0 for x in costs[0])
        shares = comm.allgather(sim.share_of(True, comm))
        assert sorted(i for s in shares for i in s) == [0, 1, 2]


def test_a_prediction_does_not_depend_on_what_ran_before():
    """A specimen's prediction (values and sensitivities, a history law along the recorded
    path) is bit-identical whether it is the first of the process or comes after another
    specimen's models were built and solved (a batch diagnoses each specimen as if alone;
    docs/real-data.md: a flip once blamed on the predecessors came from the input's last
    digits)."""
    import pandas as pd

    from simulators.fe import FESimulator

    def obs(amplitude):
        ct = [1 - amplitude / 2, 1 - amplitude, 1 - amplitude / 2, 1.0]
        return pd.DataFrame({
            "curve": ["ct"] * 4 + ["t"] * 3, "test": ["compression_tension"] * 4
            + ["torsion"] * 3, "amplitude": [amplitude] * 4 + [0.2] * 3,
            "channel": ["stress"] * 4 + ["torque"] * 3,
            "branch": ["loading"] * 2 + ["unloading"] * 2 + ["loading"] * 3, "cycle": 1,
            "control": ct + [0.05, 0.1, 0.2], "time_s": [2.0, 4.0, 6.0, 8.0, 3.0, 6.0, 12.0],
            "value": 0.0})

    def predict(R, H, amplitude, values):
        return FESimulator(obs(amplitude), R, H, path="recorded").predict(values, list(values))

    mine = {"mu_0": 1.0, "alpha_0": -12.0, "beta_0": 0.5, "log10_tau_0": 0.5}
    first = predict(4.0, 5.0, 0.1, mine)
    predict(3.0, 6.0, 0.15, {"mu_0": 2.0, "alpha_0": 5.0, "softening": 0.3,
                             "log10_softening_m": -1.5})
    again = predict(4.0, 5.0, 0.1, mine)
    np.testing.assert_array_equal(again.y, first.y)
    np.testing.assert_array_equal(again.jacobian, first.jacobian)
    assert np.abs(first.jacobian).min() > 0  # every parameter moves every row


def test_cutback_recovers_then_fails_clearly(axi_slip):
    """One huge step (stretch 1 -> 0.4, alpha = -30) needs a cut-back and then matches the
    homogeneous solution to 0.1 %; with cut-backs disabled the error names the step."""
    from brain_fe.protocols import Protocol
    from brain_fe.solver import ConvergenceError

    prot = Protocol("compression_tension", (1.0, 0.4), max_increment=0.6)
    p = _params(alpha=(-30.0,), kappa=300.0)
    df = axi_slip.run(prot, p)
    assert axi_slip.cutbacks >= 1
    assert df.nominal_stress_kPa.iloc[-1] == pytest.approx(
        homogeneous_uniaxial(0.4, alpha=-30.0, kappa=300.0), rel=1e-3)
    with pytest.raises(ConvergenceError, match="Newton failed at stretch = 0.4"):
        axi_slip.run(prot, p, max_cutbacks=0)


def test_field_output_xdmf(tmp_path, axi_slip):
    """XDMF output for ParaView: one time step per output point."""
    from brain_fe.protocols import Protocol

    path = tmp_path / "u.xdmf"
    axi_slip.run(Protocol("compression_tension", (1.0, 0.9), max_increment=0.05), _params(),
                 field_output=str(path))
    text = path.read_text()
    assert text.count("<Time Value=") == 3
