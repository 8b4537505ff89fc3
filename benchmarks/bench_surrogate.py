"""Surrogate cost vs the FE protocol solve it replaces, measured side by side.

    .venv/bin/python benchmarks/bench_surrogate.py --surrogates MODEL_DIR [--repeats 200]

MODEL_DIR comes from `brainmech train` (see BENCHMARKS.md for the commands). For each test:
the median wall time of one whole-curve prediction (21 or 41 points, the numpy forward
pass used by the identification and the scikit-learn pipeline path), and of one FE solve
of the same protocol on the default mesh; their ratio is the speed-up.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np
from _machine import run_script


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--surrogates", required=True)
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--fe-repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    a = ap.parse_args()

    from brain_fe import geometry
    from brain_fe.materials import MaterialParameters
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import compression_tension, torsion
    from surrogate.persist import load_surrogates

    bundles = load_surrogates(a.surrogates)
    fm = ForwardModel(geometry.axisymmetric())
    p = MaterialParameters(mu=(1.0,), alpha=(-20.0,), nu0=0.49)
    prots = {"compression_tension": compression_tension(0.15), "torsion_0.15": torsion(0.15),
             "torsion_0.30": torsion(0.30)}
    res = {}
    for key, b in bundles.items():
        prot = prots[key]
        ctrl = np.array([s.value for s in prot.steps()])
        X = np.column_stack([np.full_like(ctrl, 1.0), np.full_like(ctrl, -20.0), ctrl])
        fast, pipe = [], []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            b.predict(1.0, -20.0, ctrl)
            fast.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            b.estimator.predict_pipeline(X)
            pipe.append(time.perf_counter() - t0)
        fe = []
        fm.run(prot, p)
        for _ in range(a.fe_repeats):
            t0 = time.perf_counter()
            fm.run(prot, p)
            fe.append(time.perf_counter() - t0)
        res[key] = {"points": len(ctrl), "surrogate_curve_ms": 1e3 * statistics.median(fast),
                    "pipeline_curve_ms": 1e3 * statistics.median(pipe),
                    "fe_protocol_s": statistics.median(fe),
                    "speedup": statistics.median(fe) / statistics.median(fast)}
        print(key, res[key])
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "surrogate.json"), "w") as fh:
        json.dump(res, fh, indent=2)


if __name__ == "__main__":
    run_script(main)
