"""The stated detection limits of a glue layer and a softening, checked by solving them again.

A diagnosis states how large each candidate it did not name would have to be to show beside
its final model (``detection_limits``): a glue layer's stiffness found by Newton steps on
log chi-square (:class:`diagnosis.screen._GlueScan`), a softening's amplitude d linearised
at d = 0 at each point of its design (:func:`diagnosis.screen._per_point_limits`).  Here
each is checked outside the diagnosis's code for limits: the final model is solved with
the effect at its stated size, at half and at twice it, and its own parameters are then
refitted to that prediction by Gauss-Newton steps under the final noise model (columns
re-predicted at every step), so what is left is the chi-square the effect adds beyond
what the final model can mimic, not linearised.  At the stated size it should be the bar
of the next round; half and twice show how far from linear the effect is (a glue layer in
its compliance 1/k, a softening in d; linear: x1/4 and x4).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/limits_solved.py \\
        --out benchmarks/results/limits_solved.json

The specimen is the one of ``compare_trees.py`` (full protocol, two cycles, a concealed
viscoelastic effect, seed 11; ``--effect none``: a control, whose final model is elastic);
the diagnosis runs on one rank.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np
from _machine import run_script

from brain_fe.io import write_json_atomic
from brain_fe.parameters import Param
from diagnosis.benchmark import full_protocols, make_case
from diagnosis.effects import library
from diagnosis.engine import diagnose
from diagnosis.selection import chi2_needed
from recordings.observations import observations
from simulators.fe import FESimulator

GAUSS_NEWTON_STEPS = 3


def beyond_model(sim, noise, final, extra: dict) -> list[float]:
    """Chi-square of the final model refitted to its own prediction with ``extra``
    parameter values added: after 0, 1, ... Gauss-Newton steps of its parameters."""
    names = list(final.names)
    target = sim.predict({**final.values, **extra}).y
    theta = np.array([final.values[n] for n in names], float)
    out = []
    for it in range(GAUSS_NEWTON_STEPS + 1):
        p = sim.predict(dict(zip(names, theta, strict=True)),
                        names if it < GAUSS_NEWTON_STEPS else [])
        z = noise.whiten(p.y - target)
        out.append(float(z @ z))
        if it < GAUSS_NEWTON_STEPS:
            step, *_ = np.linalg.lstsq(noise.whiten_jacobian(p.jacobian), -z, rcond=None)
            theta = theta + step
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--effect", default="viscoelastic",
                    help="the effect concealed in the specimen ('none': a control)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rec, spec, _ = make_case(1, a.effect, np.random.default_rng(a.seed), refinement=1,
                             truth_refinement=3, protocols=full_protocols(2, 0.03), models={})
    obs = observations(rec)
    R, H = float(spec.radius_mm.iloc[0]), float(spec.height_mm.iloc[0])
    sim = FESimulator(obs, R, H, refinement=1)
    res = diagnose(sim, obs, fine_sim=FESimulator(obs, R, H, refinement=2))
    lib = library("fe")
    # the bar of the next round: among the candidates the final model has not taken
    m = max(len([e for e in lib if e not in res.effects + res.tried]), 1)
    out = {"verdict": res.verdict, "candidates_with_limits": sorted(res.detection_limits),
           "gauss_newton_steps": GAUSS_NEWTON_STEPS, "checks": []}
    cases = []  # (effect, limit, its entry, factor, the parameters solved with)
    glue = res.detection_limits["imperfect_gluing"]["log10_k"]
    for k in glue["would_show_at"]:  # none when no allowed glue would show
        cases += [("imperfect_gluing", "log10_k", glue, f, {Param("log10_k"):
                   k - math.log10(f)}) for f in (0.5, 1.0, 2.0)]  # of the compliance 1/k
    for label, lim in res.detection_limits["mullins"].items():
        for d in lim["would_show_at"]:
            cases += [("mullins", label, lim, f, {Param("softening"): f * d, **{
                Param.parse(q): v for q, v in lim["at"].items()}}) for f in (0.5, 1.0, 2.0)]
    for effect, label, lim, factor, extra in cases:
        chi2 = beyond_model(sim, res.noise, res.final, extra)
        out["checks"].append({
            "effect": effect, "limit": label, "stated": lim, "factor": factor,
            "values": {str(q): v for q, v in extra.items()},
            "bar": chi2_needed(len(lib[effect].names), m, len(obs)),
            "chi2_beyond_model_by_step": chi2})
    write_json_atomic(a.out, out, indent=1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    run_script(main)
