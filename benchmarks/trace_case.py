"""Where a stored open-world case's misfit comes from: the model or the noise.

For each named case of a ``brainmech benchmark-diagnosis --world open`` run, the
generator's noiseless recordings are made again from the stored truth and recorded times
(:func:`diagnosis.open_world.simulate`, the converged mesh and sub-steps of the run), so
that every recorded value splits into the noise actually added (recorded minus noiseless)
and the model's own misfit (the diagnosis's base and final fits minus noiseless).  The
diagnosis is run again blind (one rank, the benchmark's meshes), and per series (curve and
channel) the script reports

* the RMS of the noise added, and the SD the diagnosis's noise model gives it (with its
  white, correlated and drift parts and the degrees of freedom it was estimated from);
* the RMS of the base and of the final fit's gap to the noiseless recordings, in units of
  the noise added (what the model itself leaves: discretisation and the parameters'
  compromise, with no noise in it);
* the -2 log-likelihood (restricted, as the engine fits it) that the engine's noise model
  gains over a white-only one on the final residual (for its three parameters more);

and the tests of what remains (located segments, the repeated misfit, the trend, the
split) with their p values.  A control answered ``unexplained`` is then read at once: a
gap near zero with a noise model far below the noise added is the noise; a gap of a noise
SD or more is the model.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/trace_case.py \\
        --benchmark open/ --out trace.json world103 world112
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/trace_case.py \\
        --seed 3 --out trace.json world048
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import pandas as pd
from _machine import cpu_model, run_script
from noise_structure_choice import restricted_m2logl
from visible_beside import recorded_times, stored

from brain_fe.io import write_json_atomic
from diagnosis import noise as nz
from diagnosis.engine import diagnose, kept_out
from diagnosis.open_benchmark import draw_case
from diagnosis.open_world import SUBSTEPS, TRUTH_REFINEMENT, simulate
from recordings.observations import observations
from simulators.fe import FESimulator


def white_only_gain(obs: pd.DataFrame, fit, nm: nz.NoiseModel) -> dict:
    """Per series: -2 log L (restricted, with the columns the engine keeps out) of a
    white-only noise model minus that of ``nm`` (which has three parameters more: a
    correlated part, its time and a drift), and the white-only model's SD."""
    r = fit.residual(obs)
    kept = kept_out(obs, fit.prediction, fit.jacobian)
    white = nz.fit_noise(obs, r, systematic=kept, correlated=False, drift=False)
    return {f"{key[0]}/{key[1]}": {"gain_over_white": round(m2l["white"] - m2l["engine"], 2),
                                   "white_only_sd": round(white.params[key].white, 4)}
            for key, (_, m2l) in restricted_m2logl(
                obs, r, kept, {"white": white, "engine": nm}).items()}


def drawn(seed: int, name: str):
    """(label, specimen, truth, recorded times, recordings) of case ``name`` of ``seed``'s
    open world, drawn again (:func:`diagnosis.open_benchmark.draw_case`)."""
    rec, _, case = draw_case(int(name.removeprefix("world")), seed, {})
    return case.label(), case.spec, case.truth, recorded_times(rec, case.spec), rec


def trace(lab: dict, spec, truth, times: list, rec: pd.DataFrame, name: str) -> dict:
    clean = simulate(spec, truth, times, refinement=TRUTH_REFINEMENT, substeps=SUBSTEPS,
                     models={})
    obs, oc = observations(rec), observations(clean)
    if len(obs) != len(oc) or not np.allclose(obs["control"], oc["control"]):
        raise ValueError(f"{name}: the noiseless recordings made again do not match")
    sim = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=1)
    fine = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=2)
    d = diagnose(sim, obs, fine_sim=fine)
    o = d.obs
    value, noiseless = o["value"].to_numpy(float), oc["value"].to_numpy(float)
    added = value - noiseless
    # residual = prediction - recorded, so prediction - noiseless = residual + noise
    gaps = {k: f.residual(o) + added for k, f in (("base", d.base), ("final", d.final))}
    sd = d.noise.sd()
    per = {}
    described = d.noise.describe()
    for (c, ch), g in o.groupby(["curve", "channel"], sort=False):
        rows = g.index.to_numpy()
        rms = float(np.sqrt(np.mean(added[rows] ** 2)))
        per[f"{c}/{ch}"] = {
            "points": len(rows), "noise_added_rms": round(rms, 4),
            "noise_model_sd": round(float(np.median(sd[rows])), 4),
            "noise_model": {k: (round(v, 5) if isinstance(v, float) else v)
                            for k, v in described[f"{c}/{ch}"].items()},
            "noise_dof": float(np.median(d.noise.dof[rows])),
            **{f"{k}_gap_over_noise": round(float(np.sqrt(np.mean(v[rows] ** 2))) / rms, 3)
               for k, v in gaps.items()}}
    for key, v in white_only_gain(o, d.final, d.noise).items():
        per[key].update(v)
    rem = d.remaining
    j = d.to_json()
    return {"case": name, "kind": lab["kind"], "expected": lab["expected"],
            "noise_kinds": lab["noise_kinds"], "verdict": j["verdict"],
            "status": j["status"], "cannot_tell": bool(j["cannot_tell"]),
            "effects_fitted": [r.added for r in d.rounds if r.added],
            "series": per,
            "remains": {"located": [{k: s[k] for k in ("axis", "segment", "n", "p_value")}
                                    for s in rem["located"]],
                        **{k: {"gain": round(rem[k]["gain"], 2), "dof": rem[k]["dof"],
                               "p_value": rem[k]["p_value"],
                               "significant": rem[k]["significant"]}
                           for k in ("reproducible", "trend", "split")}},
            "notes": j.get("notes", [])}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    where = ap.add_mutually_exclusive_group(required=True)
    where.add_argument("--benchmark", type=Path, help="a run's directory")
    where.add_argument("--seed", type=int, help="draw the cases of this seed again")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("cases", nargs="+")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    for name in a.cases:
        if a.benchmark and not (a.benchmark / "labels" / f"{name}.json").exists():
            raise ValueError(f"{a.benchmark}: no stored case {name}")
        if not (name.startswith("world") and name.removeprefix("world").isdigit()):
            raise ValueError(f"{name}: not a case name (world and its number, e.g. world048)")

    def case(name):
        if a.benchmark:
            lab, spec, truth, times = stored(a.benchmark, name)
            return lab, spec, truth, times, pd.read_csv(
                a.benchmark / "cases" / f"{name}_recordings.csv")
        return drawn(a.seed, name)

    out = {"machine": cpu_model(), "source": str(a.benchmark) if a.benchmark
           else f"seed {a.seed}, drawn again", "cases": [trace(*case(n), n) for n in a.cases]}
    write_json_atomic(a.out, out)


if __name__ == "__main__":
    run_script(main)
