"""Forward-model cost on the default protocols, axisymmetric vs 3D, side by side.

* first-call JIT compile time of the axisymmetric and 3D forms (empty FFCx cache in a
  temporary directory, measured in a subprocess);
* the default full set (compression/tension A = 0.15, torsion 0.15 and 0.30, loading and
  unloading) on the axisymmetric model at its default resolution (k = 2, <= 1 % force error,
  see convergence.md), median of ``--repeats`` runs;
* the 3D model timed in the same run: torsion 0.15 and 0.30 at k = 1 (within 0.1 % of the
  converged torque, so at least the same accuracy), and the cost per Newton iteration at
  k = 1 and k = 2 from one compression branch, from which the cost of the full set at the
  3D resolution that reaches 1 % in compression/tension is projected (labelled as such).

    .venv/bin/python benchmarks/bench_forward.py [--repeats 5] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

from _machine import cpu_model, run_script

COMPILE_SNIPPET = """
import time, json, sys
from brain_fe import geometry
from brain_fe.model import ForwardModel
t = time.perf_counter(); g = geometry.{geom}(refinement=1)
t1 = time.perf_counter(); m = ForwardModel(g)
print(json.dumps({{"compile_s": m.compile_time_s}}))
"""


def first_call_compile(geom: str) -> float:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, XDG_CACHE_HOME=cache)
        out = subprocess.run([sys.executable, "-c", COMPILE_SNIPPET.format(geom=geom)],
                             env=env, capture_output=True, text=True, check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])["compile_s"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    ap.add_argument("--skip-compile", action="store_true")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)

    import dolfinx

    from brain_fe import geometry
    from brain_fe.materials import MaterialParameters
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import Protocol, compression_tension, torsion

    res = {"machine": f"{os.cpu_count()} cores, {cpu_model()}", "dolfinx": dolfinx.__version__,
           "python": platform.python_version()}
    if not a.skip_compile:
        res["compile_axisymmetric_s"] = first_call_compile("axisymmetric")
        res["compile_3d_s"] = first_call_compile("cylinder3d")

    p = MaterialParameters(mu=(1.0,), alpha=(-20.0,), nu0=0.49)
    default_set = [compression_tension(0.15), torsion(0.15), torsion(0.30)]

    axi = ForwardModel(geometry.axisymmetric())
    m3 = ForwardModel(geometry.cylinder3d(refinement=1))
    axi.run(torsion(0.15), p)  # warm caches (first assembly allocates)
    t_axi, t3_torsion, its_axi = [], [], 0
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        its_axi = 0
        for prot in default_set:
            axi.run(prot, p)
            its_axi += axi.iterations
        t_axi.append(time.perf_counter() - t0)
    t_axi_torsion = []
    for _ in range(max(1, a.repeats // 2)):
        t0 = time.perf_counter()
        for prot in default_set[1:]:
            axi.run(prot, p)
        t_axi_torsion.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        its3 = 0
        for prot in default_set[1:]:
            m3.run(prot, p)
            its3 += m3.iterations
        t3_torsion.append(time.perf_counter() - t0)
    res["axi_default_set_s"] = statistics.median(t_axi)
    res["axi_default_set_runs_s"] = t_axi
    res["axi_newton_iterations"] = its_axi
    res["axi_torsion_pair_s"] = statistics.median(t_axi_torsion)
    res["3d_k1_torsion_pair_s"] = statistics.median(t3_torsion)
    res["3d_k1_torsion_newton_iterations"] = its3
    res["ratio_3d_over_axi_torsion"] = res["3d_k1_torsion_pair_s"] / res["axi_torsion_pair_s"]
    res["axi_dofs"] = axi.V.dofmap.index_map.size_global * 3
    res["3d_k1_dofs"] = m3.V.dofmap.index_map.size_global * 3

    # 3D compression: cost per Newton iteration at k = 1 and 2 from one loading branch
    branch = Protocol("compression_tension", (1.0, 0.85), max_increment=0.015)
    per_it = {}
    for k, model in ((1, m3), (2, ForwardModel(geometry.cylinder3d(refinement=2)))):
        t0 = time.perf_counter()
        model.run(branch, p)
        per_it[k] = (time.perf_counter() - t0) / model.iterations
        res[f"3d_k{k}_dofs"] = model.V.dofmap.index_map.size_global * 3
    res["3d_k1_s_per_newton_iteration"] = per_it[1]
    res["3d_k2_s_per_newton_iteration"] = per_it[2]
    res["axi_s_per_newton_iteration"] = res["axi_default_set_s"] / its_axi
    # projected full default set with 3D at k = 2 (iteration count as on the axisymmetric)
    res["3d_k2_default_set_projected_s"] = per_it[2] * its_axi
    res["ratio_3d_k2_over_axi_projected"] = res["3d_k2_default_set_projected_s"] / res[
        "axi_default_set_s"]
    with open(os.path.join(a.out, "forward.json"), "w") as fh:
        json.dump(res, fh, indent=2)
    for k, v in res.items():
        print(f"{k}: {v}")


if __name__ == "__main__":
    run_script(main)
