"""Two-stage identification vs FE-only fits, in one run, on synthetic FE recordings.

    .venv/bin/python benchmarks/bench_identification.py --surrogates MODEL_DIR

For each known parameter set (1 % noise, all tests, default mesh):
* two-stage: surrogate stage, then the FE stage with exact sensitivities;
* derivative-free FE-only fit (Nelder-Mead) from the same start as the FE stage (the
  surrogate optimum);
* derivative-free FE-only fit from a neutral start (mu = 1 kPa, alpha = -10), i.e. what
  one does without a surrogate.
Reports FE protocol solves, wall time (for the two-stage fit also that of each stage),
final objective and parameter errors, with the machine's CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

import numpy as np
import pandas as pd
from _machine import cpu_model, run_script
from scipy.optimize import minimize

TRUTH = [(0.8, -18.0), (2.0, -8.0), (0.4, -30.0), (1.2, -25.0)]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--surrogates", required=True)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    a = ap.parse_args()
    warnings.simplefilter("ignore")

    from brain_fe import geometry
    from brain_fe.model import ForwardModel
    from identification.fit import identify
    from identification.objective import identification_obs, residuals
    from recordings.synthetic import make_recordings
    from simulators.fe import FESimulator
    from simulators.surrogate import SurrogateSimulator
    from surrogate.persist import load_surrogates

    fm = ForwardModel(geometry.axisymmetric())
    models: dict = {}
    spec = pd.DataFrame({"specimen": [f"S{i}" for i in range(len(TRUTH))], "region": "R",
                         "brain": "B", "radius_mm": 4.0, "height_mm": 5.0})
    truth = pd.DataFrame({"specimen": spec.specimen, "mu_kPa": [t[0] for t in TRUTH],
                          "alpha": [t[1] for t in TRUTH]})
    rec = make_recordings(spec, truth, noise=0.01, seed=5, model_cache={(4.0, 5.0): fm})
    bundles = load_surrogates(a.surrogates)
    rows = []

    def fe_sim(obs):
        return FESimulator(obs, 4.0, 5.0, nu0=0.49, path="branches", geometry=fm.geometry,
                           models=models)

    for (mu, alpha), sid in zip(TRUTH, spec.specimen, strict=True):
        obs = identification_obs(rec[rec.specimen == sid])
        sur = SurrogateSimulator(obs, bundles, radius_mm=4.0, height_mm=5.0, nu0=0.49)
        fe = fe_sim(obs)
        t0 = time.perf_counter()
        res = identify(sur, fe, fit="all")
        rows.append({"truth": f"({mu}, {alpha})", "method": "two-stage (surrogate + FE TRF)",
                     "fe_solves": res.stage2.protocol_solves,
                     "wall_s": time.perf_counter() - t0, "objective": res.stage2.objective,
                     "surrogate_stage_s": res.stage1.wall_time_s,
                     "fe_stage_s": res.stage2.wall_time_s,
                     "mu_err_%": 100 * (res.mu_kPa / mu - 1),
                     "alpha_err_%": 100 * (res.alpha / alpha - 1)})
        for label, start in (("FE-only Nelder-Mead, same start", (res.stage1.mu_kPa,
                                                                  res.stage1.alpha)),
                             ("FE-only Nelder-Mead, neutral start", (1.0, -10.0))):
            fe = fe_sim(obs)

            def f(z, fe=fe, obs=obs):
                if z[1] >= -0.1:
                    return 1e3
                y = fe.predict({"mu_0": float(np.exp(z[0])), "alpha_0": float(z[1])}).y
                r = residuals(obs, y)
                return float(r @ r)

            t0 = time.perf_counter()
            o = minimize(f, [np.log(start[0]), start[1]], method="Nelder-Mead",
                         options={"xatol": 1e-5, "fatol": 1e-10, "maxfev": 400})
            rows.append({"truth": f"({mu}, {alpha})", "method": label,
                         "fe_solves": fe.solves, "wall_s": time.perf_counter() - t0,
                         "objective": o.fun, "mu_err_%": 100 * (np.exp(o.x[0]) / mu - 1),
                         "alpha_err_%": 100 * (o.x[1] / alpha - 1)})
        print(pd.DataFrame(rows[-3:]).to_string(index=False))
    df = pd.DataFrame(rows)
    os.makedirs(a.out, exist_ok=True)
    df.to_csv(os.path.join(a.out, "identification.csv"), index=False)
    summary = df.groupby("method")[["fe_solves", "wall_s", "objective"]].median()
    print(summary.to_string())
    with open(os.path.join(a.out, "identification.json"), "w") as fh:
        json.dump({"cpu": cpu_model(), "per_case": rows,
                   "median": summary.reset_index().to_dict("records")}, fh, indent=2)


if __name__ == "__main__":
    run_script(main)
