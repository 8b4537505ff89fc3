"""The stated detection limit of a glue layer, checked by solving it again.

A diagnosis states below which glue stiffness k a glue layer would show beside its final
model (``detection_limits["imperfect_gluing"]``, found by Newton steps on log chi-square,
:class:`diagnosis.screen._GlueScan`).  Here the final model is solved again with a glue
layer at the stated stiffness, at half and at twice its compliance, outside the scan: the
chi-square the layer adds beyond what the final model's parameters can mimic (their
columns re-predicted at the final fit and projected out under the final noise model)
should be the bar at the stated stiffness, and it shows how far from linear in the
compliance 1/k the glue layer's misfit is (linear would scale it by 1/4 and 4).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/glue_limit.py \\
        --out benchmarks/results/glue_limit.json

The specimen is the one of ``compare_trees.py`` (full protocol, two cycles, a concealed
viscoelastic effect, seed 11); the diagnosis runs on one rank.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np
from scipy import stats

from brain_fe.io import write_json_atomic
from brain_fe.parameters import Param
from diagnosis.benchmark import full_protocols, make_case
from diagnosis.effects import library
from diagnosis.engine import diagnose
from recordings.observations import observations
from simulators.fe import FESimulator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rec, spec, _ = make_case(1, "viscoelastic", np.random.default_rng(a.seed), refinement=1,
                             truth_refinement=3, protocols=full_protocols(2, 0.03), models={})
    obs = observations(rec)
    R, H = float(spec.radius_mm.iloc[0]), float(spec.height_mm.iloc[0])
    sim = FESimulator(obs, R, H, refinement=1)
    res = diagnose(sim, obs, fine_sim=FESimulator(obs, R, H, refinement=2))
    limit = res.detection_limits["imperfect_gluing"]["log10_k"]
    final, noise = res.final, res.noise
    J = noise.whiten_jacobian(sim.predict(final.values, list(final.names)).jacobian)
    U, sv, _ = np.linalg.svd(J, full_matrices=False)
    U = U[:, sv > sv.max() * 1e-10]
    # the bar of the next round (diagnosis.selection.Context.needed): one parameter among
    # the candidates the final model has not taken, at the diagnosis's default alpha, margin
    m = len([e for e in library("fe") if e not in res.effects + res.tried])
    bar = max(float(stats.chi2.isf(1e-3 / max(m, 1), 1)), math.log(len(obs)) + 10.0)
    rows = []
    (k,) = limit["would_show_at"]
    for factor in (0.5, 1.0, 2.0):  # of the compliance 1/k at the stated stiffness
        lk = k - math.log10(factor)
        z = noise.whiten(sim.predict({**final.values, Param("log10_k"): lk}).y
                         - final.prediction)
        rows.append({"compliance_factor": factor, "log10_k": lk,
                     "chi2_beyond_model": float(np.sum((z - U @ (U.T @ z)) ** 2))})
    out = {"verdict": res.verdict, "stated": limit, "bar": bar,
           "candidates_with_limits": sorted(res.detection_limits), "resolved": rows}
    write_json_atomic(a.out, out, indent=1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
