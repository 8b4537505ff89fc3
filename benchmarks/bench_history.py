"""Cost of one evaluation of a history update (the compiled ``fem.Expression`` of
:mod:`brain_fe.history`), compiled with FFCx's default C flags and with the project's
(:func:`brain_fe._compat.expression`: those of the forms, ``-O3 -ffast-math``).

A diagnosis evaluates the update after every converged (sub)step and once per parameter
direction of the path sensitivities: 13 529 evaluations in the one-rank profile of the
speed specimen. Per material with history (one Maxwell branch, a Mullins softening, both)
on the axisymmetric mesh of the speed specimen (radius 4 mm, height 5 mm) at refinements
1 and 2 (the diagnosis's working mesh and its correction), after the torsion ramp to 0.3
so that the state is not trivial: the median over ``--repeats`` blocks of the time per
evaluation, and the largest difference between the two kernels' values relative to the
largest value.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_history.py [--repeats 5]
"""

from __future__ import annotations

import numpy as np
from _machine import median_per_call, micro_arguments, run_script, write_result

DEFAULT_FLAGS = ["-O2", "-g0"]  # DOLFINx's default cffi_extra_compile_args
MATERIALS = {"maxwell": {"maxwell": 1}, "mullins": {"mullins": True},
             "maxwell+mullins": {"maxwell": 1, "mullins": True}}


def _model(refinement: int, kw: dict):
    from mpi4py import MPI

    from brain_fe import geometry, protocols
    from brain_fe.history import HistoryState
    from brain_fe.materials import MaterialParameters
    from brain_fe.model import ForwardModel

    kept = {}
    compile_update = HistoryState.compile_update

    def keep(self, update_ufl):  # the UFL of the update, to compile it a second way
        kept["ufl"] = update_ufl
        compile_update(self, update_ufl)

    HistoryState.compile_update = keep
    try:
        g = geometry.axisymmetric(4.0, 5.0, refinement=refinement, comm=MPI.COMM_SELF)
        m = ForwardModel(g, **kw)
    finally:
        HistoryState.compile_update = compile_update
    p = MaterialParameters(mu=(0.6,), alpha=(-16.0,),
                           **({"beta": (0.3,), "tau_s": (10.0,)} if kw.get("maxwell") else {}),
                           **({"softening": 0.3, "softening_m_kPa": 0.05} if kw.get("mullins")
                              else {}))
    m.run(protocols.torsion(0.3), p)
    return m, kept["ufl"]


def _per_call(evaluate, n: int, repeats: int) -> tuple[float, np.ndarray]:
    vals = np.asarray(evaluate()).copy()
    return median_per_call(evaluate, n, repeats), vals


def main():
    a = micro_arguments()
    from dolfinx import fem

    from brain_fe import _compat

    rows = []
    for name, kw in MATERIALS.items():
        for k in (1, 2):
            m, update = _model(k, kw)
            st = m.state
            # the project's JIT options with only the C flags changed
            plain = fem.Expression(update, st.points, **{_compat._EXPR_JITP: {
                **_compat._jit(), "cffi_extra_compile_args": DEFAULT_FLAGS}})
            t_plain, v_plain = _per_call(
                lambda e=plain, s=st: _compat.eval_expression(e, s.mesh, s.cells), 200,
                a.repeats)
            t_ours, v_ours = _per_call(st.evaluate, 200, a.repeats)
            rows.append({"material": name, "refinement": k,
                         "cells": int(len(st.cells)), "values": int(v_ours.size),
                         "default_flags": DEFAULT_FLAGS, "default_ms": 1e3 * t_plain,
                         "project_flags": _compat._jit()["cffi_extra_compile_args"],
                         "project_ms": 1e3 * t_ours, "ratio": t_ours / t_plain,
                         "rel_diff": float(np.abs(v_ours.ravel() - v_plain.ravel()).max()
                                           / np.abs(v_plain).max())})
            r = rows[-1]
            print(f"{name:16s} k={k} {r['cells']:4d} cells  default {r['default_ms']:.3f} ms"
                  f"  project {r['project_ms']:.3f} ms  ratio {r['ratio']:.2f}"
                  f"  rel diff {r['rel_diff']:.1e}")
    write_result(a.out, "history_update.json",
                 {"repeats": a.repeats, "evaluations_per_block": 200, "rows": rows})


if __name__ == "__main__":
    run_script(main)
