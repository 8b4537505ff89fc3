"""False alarms of the tests of what remains on pure rig noise, with the engine's noise
model and with its structure chosen by a penalised likelihood.

The engine fits every series' noise with all its parts (white, one Ornstein-Uhlenbeck
part with its time, a drift: :func:`diagnosis.noise.fit_noise`), by restricted ML with the
columns the diagnosis keeps out (:func:`diagnosis.engine.kept_out`).  On a short series
(8 degrees of freedom left, two cycles of five points a ramp) that can put most of a
white noise into the slow parts and the white SD at a fraction of the truth (seed 16's
control world103: 0.035 against 0.163, `benchmarks/trace_case.py`), and the located tests
then read noise as misfit.  The alternative measured here keeps a slow part only when it
earns it: per series, the structure (white; white + drift; white + correlated part; all)
with the least -2 log L + ``penalty`` x its parameters, the penalty 2 (AIC) or the log of
the series' degrees of freedom (BIC).

A table of one torsion test (torque and axial force, ``--per-ramp`` points a ramp,
``--cycles`` cycles, one sample every ``--dt`` seconds), whose residual is pure rig noise
of each kind (:func:`recordings.noise.rig_noise`, white SD 1) on a smooth stand-in
prediction with two parameter columns; :func:`diagnosis.remaining.remaining` decides
whether it leaves a systematic misfit (a false alarm: there is none).  Each kind draws
from its own seeded generator, so the three noise models see the same draws.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/noise_structure_choice.py \\
        --per-ramp 5 --cycles 2 --dt 3 --draws 30 --out choice.md
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _machine import cpu_model, run_script

from brain_fe.io import write_text_atomic
from diagnosis import noise as nz
from diagnosis.engine import kept_out
from diagnosis.remaining import remaining
from recordings.noise import RigNoise, rig_noise

KINDS = {
    "white": {},
    "white, quantised (0.75 SD)": {"quantum": 0.75},
    "filter (0.7 SD, 2.8 s)": {"filtered": 0.7, "filter_s": 2.8},
    "wander (0.6 SD, 30 s)": {"wander": 0.6, "wander_s": 30.0},
    "filter + wander (0.4 SD, 15 s) + drift": {"filtered": 0.7, "filter_s": 2.8,
                                               "wander": 0.4, "wander_s": 15.0,
                                               "drift": 0.01},
    "drift (0.02 SD/s)": {"drift": 0.02},
}
CHANNELS = ("torque", "axial_force")
STRUCTURES = {"white": ({"correlated": False, "drift": False}, 1),
              "white + drift": ({"correlated": False}, 2),
              "white + correlated": ({"drift": False}, 3),
              "all (the engine's)": ({}, 4)}


def table(per_ramp: int, cycles: int, dt: float) -> pd.DataFrame:
    """One torsion test of ``cycles`` cycles to 0.2, both channels, every value 0."""
    up = np.linspace(0.01, 0.2, per_ramp)
    rows = []
    for ch in CHANNELS:
        t = 0.0
        for c in range(cycles):
            for branch, xs in (("loading", up), ("unloading", up[::-1] - 0.01)):
                for x in xs:
                    t += dt
                    rows.append({"specimen": "s", "curve": "torsion_0.20", "test": "torsion",
                                 "amplitude": 0.2, "channel": ch, "branch": branch,
                                 "cycle": c + 1, "control": x, "time_s": t, "value": 0.0})
    return pd.DataFrame(rows)


def restricted_m2logl(obs: pd.DataFrame, r: np.ndarray, kept: list,
                      models: dict) -> dict:
    """Per series key (curve, channel): its degrees of freedom and the -2 log L of ``r``
    under each of ``models`` (name -> noise model), restricted with the column sets
    ``kept`` as :func:`diagnosis.noise.fit_noise` restricts them."""
    series = nz.noise_series(obs)
    for s in series:
        s.restrict(kept)
    out = {}
    for key in dict.fromkeys(s.key for s in series):
        mine = [s for s in series if s.key == key]
        out[key] = (sum(len(s.rows) - (0 if s.basis is None else s.basis.shape[1])
                        for s in mine),
                    {name: sum(s.nll(m.params[key], r[s.rows]) for s in mine)
                     for name, m in models.items()})
    return out


def penalised(obs: pd.DataFrame, r: np.ndarray, kept: list, fits: dict,
              penalty: float | None) -> nz.NoiseModel:
    """Per series, the structure of ``fits`` (name -> noise model) with the least
    restricted -2 log L + penalty x parameters (``None``: the log of its degrees of
    freedom)."""
    params = {}
    for key, (dof, m2l) in restricted_m2logl(obs, r, kept, fits).items():
        p = math.log(dof) if penalty is None else penalty
        score = {name: m2l[name] + p * STRUCTURES[name][1] for name in fits}
        params[key] = fits[min(score, key=score.get)].params[key]
    return nz.NoiseModel(obs, params, fits["all (the engine's)"].dof)


def run(per_ramp: int, cycles: int, dt: float, draws: int) -> list[dict]:
    obs = table(per_ramp, cycles, dt)
    x = obs["control"].to_numpy()
    torque = (obs["channel"] == "torque").to_numpy()
    pred = np.where(torque, 10 * x + 300 * x**3, -5 * x**2 - 100 * x**4)
    J = np.c_[pred, np.where(torque, 300 * x**3, -100 * x**4) * np.log1p(x)]
    kept = kept_out(obs, pred, J)  # as the engine keeps them out of a fit's noise
    t = obs["time_s"].to_numpy(float)
    rows = []
    for kind, levels in KINDS.items():
        rng = np.random.default_rng(7)
        alarms = {"engine": 0, "AIC": 0, "BIC": 0}
        for _ in range(draws):
            r = np.empty(len(obs))
            for ch in CHANNELS:
                m = (obs["channel"] == ch).to_numpy()
                n = RigNoise(white=1.0, **levels)
                e = rig_noise(t[m], n, rng)
                if n.quantum:  # rounding of the recorded value, as recordings.noise does
                    e = n.quantum * np.round((pred[m] + e) / n.quantum) - pred[m]
                r[m] = e
            fits = {name: nz.fit_noise(obs, r, systematic=kept, **kw)
                    for name, (kw, _) in STRUCTURES.items()}
            for name, nm in (("engine", fits["all (the engine's)"]),
                             ("AIC", penalised(obs, r, kept, fits, 2.0)),
                             ("BIC", penalised(obs, r, kept, fits, None))):
                rem = remaining(obs, r, nm, prediction=pred, jacobian=J, names=["mu", "alpha"])
                alarms[name] += bool(rem["systematic"])
        rows.append({"kind": kind, **alarms})
    return rows


def markdown(a: argparse.Namespace, rows: list[dict], seconds: float) -> str:
    lines = [f"One torsion test, {a.cycles} cycle(s) of {a.per_ramp} points a ramp, one "
             f"sample every {a.dt:g} s, torque and axial force; {a.draws} draws of pure rig "
             f"noise per kind. False alarms (a systematic misfit found where there is "
             f"none) per noise model of the residual:", "",
             "| rig noise | engine (all parts) | structure by AIC | structure by BIC |",
             "|---|---|---|---|"]
    lines += [f"| {r['kind']} | {r['engine']} | {r['AIC']} | {r['BIC']} |" for r in rows]
    lines.append(f"\n{cpu_model()}, {math.ceil(seconds)} s")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-ramp", type=int, default=5)
    ap.add_argument("--cycles", type=int, default=2)
    ap.add_argument("--dt", type=float, default=3.0)
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    if a.per_ramp < 2 or a.cycles < 1 or a.dt <= 0 or a.draws < 1:
        raise ValueError("--per-ramp >= 2, --cycles >= 1, --dt > 0 and --draws >= 1")
    t0 = time.perf_counter()
    rows = run(a.per_ramp, a.cycles, a.dt, a.draws)
    write_text_atomic(a.out, markdown(a, rows, time.perf_counter() - t0))


if __name__ == "__main__":
    run_script(main)
