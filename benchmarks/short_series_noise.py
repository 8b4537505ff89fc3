"""The noise model of short series on stored open-world cases: what the engine fits, what
plain ML or one noise per channel would, and what the tests of what remains say under each.

For each case of a ``brainmech benchmark-diagnosis --world open`` run, the diagnosis is
run again (one rank, the benchmark's working and correction meshes) and its final
residual is given three noise models:

* ``engine``: the diagnosis's own (restricted ML per curve and channel, the repeated
  misfit, the stiffness trend and the final model's columns kept out);
* ``plain``: maximum likelihood per curve and channel, nothing kept out;
* ``channel``: the engine's restricted ML, one noise model per channel shared by every
  curve of it (the rig's transducer), with the degrees of freedom of all of them; beside
  it the BIC of the shared against the per-curve model.

Per model: the SD per series against the RMS of the noise actually added (the label's
``noise_rms``), and :func:`diagnosis.remaining.remaining` (located segments, the repeated
misfit, the trend, the split test, systematic or not).  Also the RMS of the working model
at the *true* parameters against the recordings (library truths only), beside the final
fit's, both over the noise actually added per series: whether the model could have fitted
within the noise.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/short_series_noise.py \\
        --benchmark open/ --out noise.json world048 world061
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import numpy as np
import pandas as pd
from _machine import read_json, run_script
from visible_beside import stored

from brain_fe.io import write_json_atomic
from diagnosis import noise as nz
from diagnosis.engine import diagnose
from diagnosis.remaining import remaining, systematic_basis
from recordings.observations import observations
from simulators.fe import FESimulator


def per_channel(obs: pd.DataFrame, r: np.ndarray, B: np.ndarray,
                engine: nz.NoiseModel) -> tuple[nz.NoiseModel, dict]:
    """One restricted-ML noise model per channel over all its curves, and per channel the
    BIC of that shared model and of the engine's per-curve ones (-2 log L + k ln n)."""
    series = nz.noise_series(obs)
    for s in series:
        s.restrict(B)
    dt, ramp = nz.time_scales(obs)
    sd0 = nz.estimate_noise(obs, r)
    params, dof, bic = {}, np.asarray(engine.dof, float).copy(), {}
    for ch in dict.fromkeys(s.key[1] for s in series):
        mine = [s for s in series if s.key[1] == ch]
        curves = list(dict.fromkeys(s.key[0] for s in mine))
        rows = np.concatenate([s.rows for s in mine])
        shared, _ = nz.fit_channel(mine, r, float(np.median(sd0[rows])), None, dt, ramp,
                                    True, True)
        n = int(sum(engine.dof[s.rows[0]] for s in mine))  # the same projection as the engine's
        k = 4  # white, correlated, its time, drift
        bic[ch] = {"shared": sum(s.nll(shared, r[s.rows]) for s in mine) + k * math.log(n),
                   "per_curve": sum(s.nll(engine.params[s.key], r[s.rows]) for s in mine)
                   + k * len(curves) * math.log(n)}
        for c in curves:
            params[(c, ch)] = shared
        dof[rows] = n
    return nz.NoiseModel(obs, params, dof), bic


def _tests(obs, r, model, final) -> dict:
    out = remaining(obs, r, model, prediction=final.prediction, jacobian=final.jacobian,
                    names=final.names)
    return {"located": len(out["located"]),
            "repeated_p": out["reproducible"]["p_value"], "trend_p": out["trend"]["p_value"],
            "split_p": out["split"]["p_value"], "systematic": bool(out["systematic"])}


def _rms_over(obs, resid, realised) -> dict:
    z = resid / np.array([realised[f"{c}/{ch}"] for c, ch in zip(obs["curve"], obs["channel"],
                                                                   strict=True)])
    out = {"all": float(np.sqrt(np.mean(z**2)))}
    for (c, ch), g in obs.groupby(["curve", "channel"], sort=False):
        out[f"{c}/{ch}"] = float(np.sqrt(np.mean(z[g.index] ** 2)))
    return out


def study(src: Path, name: str) -> dict:
    lab, spec, truth, _ = stored(src, name)
    obs = observations(pd.read_csv(src / "cases" / f"{name}_recordings.csv"))
    obs = obs.reset_index(drop=True)
    refinement = read_json(src / "config.json").get("refinement", 1)
    sim = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=refinement)
    fine = FESimulator(obs, spec.radius_mm, spec.height_mm, refinement=refinement + 1)
    d = diagnose(sim, obs, fine_sim=fine)  # sets sim.correction as the engine does
    final, r = d.final, d.final.residual(obs)
    B = systematic_basis(obs, final.prediction)
    if final.jacobian is not None and np.isfinite(final.jacobian).all():
        B = np.hstack([B, final.jacobian])
    models = {"engine": d.noise, "plain": nz.fit_noise(obs, r)}
    models["channel"], bic = per_channel(obs, r, B, d.noise)
    realised = lab["noise_rms"]
    first = {k: int(g.index[0]) for k, g in obs.groupby(["curve", "channel"], sort=False)}
    # the library model at the true parameters (an outside effect has none in the library)
    at_truth = (None if lab["kind"] == "outside"
                else sim.predict(truth.values, []).y - obs["value"].to_numpy(float))
    return {"kind": lab["kind"], "truth": lab["expected"], "verdict": d.effects or "none",
            "status": d.status,
            "noise_added_rms": realised,
            "noise_sd": {name_: {f"{c}/{ch}": float(m.sd()[i]) for (c, ch), i in first.items()}
                         for name_, m in models.items()},
            "tests": {name_: _tests(obs, r, m, final) for name_, m in models.items()},
            "bic_channel": bic,
            "rms_over_noise_added": {"final_fit": _rms_over(obs, r, realised),
                                     "true_parameters": None if at_truth is None
                                     else _rms_over(obs, at_truth, realised)}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--benchmark", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("cases", nargs="+")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    src = Path(a.benchmark)
    if not (src / "config.json").is_file():
        ap.error(f"{src}: not an open-world benchmark (no config.json)")
    missing = [n for n in a.cases if not ((src / "cases" / f"{n}_recordings.csv").is_file()
                                          and (src / "labels" / f"{n}.json").is_file())]
    if missing:
        ap.error(f"{src}: no recordings and label of {', '.join(missing)}")
    out = {name: study(src, name) for name in a.cases}
    write_json_atomic(Path(a.out), out, indent=1, default=str)


if __name__ == "__main__":
    run_script(main)
