"""Cost of each physics extension relative to the base solve, measured side by side.

Default protocol set (compression/tension A = 0.15, torsion 0.15 and 0.30, loading and
unloading), axisymmetric model at the default resolution (k = 2), one compiled model per
kind.  Configurations: base (glued, one-term Ogden), Maxwell with 1 and 2 branches,
Ogden-Roxburgh softening, two-term Ogden, interface springs, artefacts (stretch offset);
each without and with sensitivities for every parameter (the model constants, plus the five
artefact names for the artefact configuration).  After one warm-up pass over everything
(allocations, sensitivity forms), ``--repeats`` passes interleave the configurations so
that machine noise spreads evenly; the median is reported.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_physics.py [--repeats 3]

Prints a Markdown table and writes ``benchmarks/results/physics.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import statistics
import time

from _machine import cpu_model, run_script

HERE = os.path.dirname(os.path.abspath(__file__))


def configurations():
    from brain_fe.artefacts import NAMES, Artefacts
    from brain_fe.ends import Interface
    from brain_fe.materials import MaterialParameters

    base = {"mu": (1.0,), "alpha": (-20.0,), "nu0": 0.49}

    def p(**kw):
        d = dict(base)
        d.update(kw)
        return MaterialParameters(**d)

    # name -> (model kwargs, parameters, artefacts, extra sensitivity names)
    return {
        "base": ({}, p(), None, []),
        "maxwell 1 branch": ({"maxwell": 1}, p(beta=(0.5,), tau_s=(10.0,)), None, []),
        "maxwell 2 branches": ({"maxwell": 2}, p(beta=(0.5, 0.25), tau_s=(1.0, 10.0)), None,
                               []),
        "mullins": ({"mullins": True}, p(softening=0.5, softening_m_kPa=0.05), None, []),
        "ogden 2 terms": ({"n_terms": 2}, p(mu=(0.5, 0.5), alpha=(-20.0, 5.0)), None, []),
        "springs": ({"ends": "springs"}, p().values() | Interface(100.0, 100.0).values(), None,
                    []),
        "artefacts (stretch offset)": ({}, p(), Artefacts(stretch_offset=0.01), list(NAMES)),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--refinement", type=int, default=2)
    ap.add_argument("--out", default=os.path.join(HERE, "results"))
    a = ap.parse_args()
    logging.getLogger("ffcx").setLevel(logging.WARNING)
    os.makedirs(a.out, exist_ok=True)

    import dolfinx

    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import compression_tension, torsion

    geom = geometry.axisymmetric(refinement=a.refinement)
    prots = [compression_tension(0.15), torsion(0.15), torsion(0.30)]
    configs = configurations()
    models, compile_s = {}, {}
    for name, (kw, _, _, _) in configs.items():
        key = tuple(sorted(kw.items()))
        if key not in models:
            t0 = time.perf_counter()
            models[key] = ForwardModel(geom, **kw)
            compile_s[name] = time.perf_counter() - t0

    def one(name, sens):
        kw, params, art, extra = configs[name]
        m = models[tuple(sorted(kw.items()))]
        names = (list(m.constants) + extra) if sens else False
        its = 0
        t0 = time.perf_counter()
        for prot in prots:
            m.run(prot, params, sensitivities=names, artefacts=art)
            its += m.iterations
        return time.perf_counter() - t0, its, (len(names) if names else 0)

    cases = [(n, s) for n in configs for s in (False, True)]
    info = {}
    for case in cases:  # warm-up
        _, its, npar = one(*case)
        info[case] = {"newton_iterations": its, "n_sensitivities": npar, "times_s": []}
    for _ in range(a.repeats):
        for case in cases:
            info[case]["times_s"].append(one(*case)[0])
    for case in cases:
        info[case]["median_s"] = statistics.median(info[case]["times_s"])
    t_base = info["base", False]["median_s"]

    rows = []
    for name in configs:
        plain, sens = info[name, False], info[name, True]
        rows.append({
            "configuration": name,
            "solve_s": plain["median_s"], "solve_ratio_to_base": plain["median_s"] / t_base,
            "newton_iterations": plain["newton_iterations"],
            "n_sensitivities": sens["n_sensitivities"],
            "with_sensitivities_s": sens["median_s"],
            "with_sensitivities_ratio_to_base": sens["median_s"] / t_base,
            "sensitivity_overhead": sens["median_s"] / plain["median_s"],
            "solve_runs_s": plain["times_s"], "with_sensitivities_runs_s": sens["times_s"],
        })
    res = {"machine": f"{os.cpu_count()} cores, {cpu_model()}",
           "dolfinx": dolfinx.__version__, "python": platform.python_version(),
           "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
           "refinement": a.refinement, "repeats": a.repeats,
           "protocols": "compression_tension 0.15, torsion 0.15, torsion 0.30",
           "model_construction_s": compile_s, "rows": rows}
    with open(os.path.join(a.out, "physics.json"), "w") as fh:
        json.dump(res, fh, indent=2)

    print(f"machine: {res['machine']}; DOLFINx {res['dolfinx']}; k = {a.refinement}; "
          f"median of {a.repeats} after a warm-up\n")
    print("| configuration | solve [s] | / base | Newton its | with sensitivities [s] "
          "(n parameters) | / base | / own solve |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['configuration']} | {r['solve_s']:.2f} | {r['solve_ratio_to_base']:.2f} "
              f"| {r['newton_iterations']} | {r['with_sensitivities_s']:.2f} "
              f"({r['n_sensitivities']}) | {r['with_sensitivities_ratio_to_base']:.2f} "
              f"| {r['sensitivity_overhead']:.2f} |")


if __name__ == "__main__":
    run_script(main)
