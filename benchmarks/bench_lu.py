"""Cost of one assembly, one LU factorisation and one back-substitution of the Newton
Jacobian, by matrix storage and direct solver, on one rank: the choice of
:data:`brain_fe.solver.SMALL_MATRIX` and :data:`brain_fe.solver.SMALL_SOLVER` below
:data:`brain_fe.solver.SMALL_MAX_DOFS` dofs and MUMPS above.

The Jacobian of the glued one-term Ogden model at a small random displacement, on the
axisymmetric mesh of the speed specimen (radius 4 mm, height 5 mm) at refinements 1-4
(the diagnosis works at 1 and corrects with 2; the open world's generator solves at 3) and
the 3D cylinder at refinement 1, stored point-wise (``aij``, DOLFINx's default) and by
3 x 3 blocks (``baij``: a node's three unknowns). Per storage: the median time of an
assembly (zeroed, assembled with the Dirichlet rows, finalised); per solver: the median
over ``--repeats`` blocks of the time per numeric factorisation (the symbolic one kept, as
Newton does) and per solve, and the largest difference of its solution from MUMPS's on
the point-wise matrix, relative to the solution's size.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_lu.py [--repeats 5]
"""

from __future__ import annotations

import statistics
import time

import numpy as np
from _machine import median_per_call, micro_arguments, run_script, write_result

SOLVERS = [("mumps", None), ("petsc", "nd"), ("petsc", "rcm"), ("petsc", "qmd"),
           ("umfpack", None)]
STORAGES = ("aij", "baij")


def _jacobian(kind: str, refinement: int, storage: str, n_assemble: int, repeats: int):
    """The Jacobian in ``storage`` and the median time of one assembly [s]."""
    import dolfinx.fem.petsc as fem_petsc
    from mpi4py import MPI

    from brain_fe import _compat, geometry
    from brain_fe.model import ForwardModel

    g = (geometry.cylinder3d(refinement=refinement, comm=MPI.COMM_SELF) if kind == "3d"
         else geometry.axisymmetric(4.0, 5.0, refinement=refinement, comm=MPI.COMM_SELF))
    m = ForwardModel(g)
    x = _compat.petsc_vec(m.u)
    x.array[:] = 1e-3 * np.random.default_rng(0).standard_normal(x.array.shape)
    A = fem_petsc.create_matrix(m.jacobian_form, storage)

    def assemble():
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, m.jacobian_form, bcs=m.bcs)
        A.assemble()

    assemble()
    return A, median_per_call(assemble, n_assemble, repeats)


def _time(A, solver, ordering, n_factor, n_solve, repeats):
    from petsc4py import PETSc

    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    pc.setFactorSolverType(solver)
    if ordering:
        pc.setFactorOrdering(ordering)
    ksp.setOperators(A)
    ksp.setUp()
    b = A.createVecLeft()
    b.setArray(np.random.default_rng(1).standard_normal(b.getLocalSize()))
    x = b.duplicate()
    ksp.solve(b, x)
    tf, ts = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n_factor):
            A.assemble()  # a new state of the same pattern: numeric factorisation only
            ksp.setOperators(A)
            ksp.setUp()
        tf.append((time.perf_counter() - t0) / n_factor)
        t0 = time.perf_counter()
        for _ in range(n_solve):
            ksp.solve(b, x)
        ts.append((time.perf_counter() - t0) / n_solve)
    return statistics.median(tf), statistics.median(ts), x.array.copy()


def main():
    a = micro_arguments()
    from brain_fe.solver import SMALL_MAX_DOFS

    rows = []
    for kind, k in [("axisymmetric", 1), ("axisymmetric", 2), ("axisymmetric", 3),
                    ("axisymmetric", 4), ("3d", 1)]:
        ref = None
        for storage in STORAGES:
            A, ta = _jacobian(kind, k, storage, 200 if kind != "3d" else 5, a.repeats)
            n = A.getSize()[0]
            small = n <= SMALL_MAX_DOFS  # many repetitions where a call takes well under 1 ms
            for solver, ordering in SOLVERS:
                if kind == "3d" and solver == "petsc" and (ordering == "rcm"
                                                           or storage == "baij"):
                    continue  # seconds per factorisation
                if solver == "umfpack" and storage == "baij":
                    continue  # point-wise matrices only
                tf, ts, x = _time(A, solver, ordering, 40 if small else 5,
                                  400 if small else 40, a.repeats)
                ref = x if ref is None else ref
                rows.append({"mesh": kind, "refinement": k, "dofs": n, "storage": storage,
                             "assemble_ms": 1e3 * ta, "solver": solver,
                             "ordering": ordering, "factorise_ms": 1e3 * tf,
                             "solve_ms": 1e3 * ts,
                             "rel_diff_from_mumps": float(np.abs(x - ref).max()
                                                          / np.abs(ref).max())})
                r = rows[-1]
                print(f"{kind:12s} k={k} {n:6d} dofs {storage:4s} assemble {r['assemble_ms']:8.3f}"
                      f" ms {solver:8s} {str(ordering):5s} "
                      f"factorise {r['factorise_ms']:9.3f} ms  solve {r['solve_ms']:8.3f} ms  "
                      f"rel diff {r['rel_diff_from_mumps']:.1e}")
    write_result(a.out, "lu.json",
                 {"repeats": a.repeats, "small_max_dofs": SMALL_MAX_DOFS, "rows": rows})


if __name__ == "__main__":
    run_script(main)
