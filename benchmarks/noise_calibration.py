"""How well the fitted noise model calibrates the test of an offset on a short cycled
series, per kind of rig noise: the gain of a constant column (chi-square with one degree
of freedom under a right noise model: mean 1, above 3.84 in 5 % of draws) under the noise
model the diagnosis fits, against its gain under the true covariance of the same draw.

An offset is what a load cell's zero error adds, and a slow part of the noise imitates it;
it lies in the span of the misfit repeated at every cycle, which the diagnosis keeps out of
its noise fit (restricted ML), so the noise model learns the noise's slow power only from
what differs between cycles.  Three noise models of each draw:

* ``engine``: :func:`diagnosis.noise.fit_noise` as the diagnosis calls it (restricted ML,
  the repeated misfit kept out; white + one Ornstein-Uhlenbeck part + drift);
* ``plain``: the same without keeping anything out (maximum likelihood);
* ``two parts``: restricted ML with a second Ornstein-Uhlenbeck part (a filter and a
  wander side by side), fitted here only: what a richer noise model would give.

Series: ``--cycles`` cycles of ramps of ``--per-ramp`` points at one sampling interval
(the unit of time); noise levels in units of the white SD.  The kinds: the model's own
shape (a filter of 1.4 intervals), a slower filter (2.8 intervals), that filter with a
wander (SD 0.2, 40 intervals), with a drift (SD 0.0065 per interval), and all of them:
the levels of seed 7's control world062 (46 points over two cycles), whose torque offset
the diagnosis named; and a wander larger than the white noise (SD 1.15, 13 intervals)
beside that filter, the axial force of seed 8's world113 (three cycles of 5 points a ramp),
named `artefacts` beside its right `viscoelastic` (BENCHMARKS.md, "Noise calibration of
short series").

    .venv/bin/python benchmarks/noise_calibration.py --out noise_calibration.md
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.linalg as sl
from _machine import run_script
from scipy.optimize import minimize

from brain_fe.io import write_text_atomic
from diagnosis import noise as nz
from diagnosis.remaining import systematic_basis
from recordings.noise import RigNoise, rig_noise

KINDS = {
    "white": {},
    "filter 1.4 (the model's shape)": {"filtered": 0.7, "filter_s": 1.4},
    "filter 2.8": {"filtered": 0.7, "filter_s": 2.8},
    "filter 2.8 + wander": {"filtered": 0.7, "filter_s": 2.8, "wander": 0.2, "wander_s": 40.0},
    "filter 2.8 + drift": {"filtered": 0.7, "filter_s": 2.8, "drift": 0.0065},
    "filter 2.8 + wander + drift": {"filtered": 0.7, "filter_s": 2.8, "wander": 0.2,
                                    "wander_s": 40.0, "drift": 0.0065},
    "filter 2.8 + strong wander": {"filtered": 0.77, "filter_s": 2.8, "wander": 1.15,
                                   "wander_s": 13.0},
}
CHI2_95 = 3.84


def series(per_ramp: int, cycles: int) -> pd.DataFrame:
    """One (curve, channel) series: loading and unloading ramps 0 -> 0.2 -> 0, one sample
    per unit of time."""
    n = 2 * per_ramp * cycles
    k = np.arange(n) // per_ramp
    up = np.linspace(0.0, 0.2, per_ramp)
    return pd.DataFrame({"specimen": "s", "curve": "torsion", "test": "torsion",
                         "amplitude": 0.2, "channel": "torque",
                         "branch": np.where(k % 2, "unloading", "loading"),
                         "cycle": k // 2 + 1, "control": np.where(k % 2, np.tile(
                             up[::-1], 2 * cycles), np.tile(up, 2 * cycles)),
                         "time_s": np.arange(float(n)), "value": 0.0})


def covariance(t: np.ndarray, white=1.0, filtered=0.0, filter_s=1.0, wander=0.0,
               wander_s=1.0, drift=0.0) -> np.ndarray:
    lag = np.abs(t[:, None] - t[None, :])
    ramp = t - t[0]
    return (white**2 * np.eye(len(t)) + filtered**2 * np.exp(-lag / filter_s)
            + wander**2 * np.exp(-lag / wander_s) + drift**2 * np.outer(ramp, ramp))


def offset_gain(cov: np.ndarray, r: np.ndarray) -> float:
    one = np.ones(len(r))
    a = sl.cho_solve(sl.cho_factor(cov, lower=True), one)
    return float((a @ r) ** 2 / (a @ one))


def two_parts(obs: pd.DataFrame, r: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Restricted-ML covariance with white, two Ornstein-Uhlenbeck parts (each between
    half an interval and the longest correlation the engine allows) and a drift."""
    t = obs["time_s"].to_numpy(float)
    (s,) = nz.noise_series(obs)
    s.restrict([B])
    dt, ramp = nz.time_scales(obs)
    longest = nz.longest_correlation_s(dt, ramp, nz.cycle_duration(obs, np.arange(len(t))))
    sc, span = float(np.sqrt(np.mean(r**2))), float(t[-1] - t[0])
    lo = np.log([1e-6 * sc, 1e-6 * sc, 0.5 * dt, 1e-6 * sc, 0.5 * dt, 1e-8 * sc / span])
    hi = np.log([10 * sc, 10 * sc, longest, 10 * sc, longest, 10 * sc / span])

    def cov(x):
        w, c1, s1, c2, s2, d = np.exp(x)
        return covariance(t, w, c1, s1, c2, s2, d)

    def nll(x):  # the engine's restricted likelihood, with this covariance
        try:
            c = sl.cho_factor(cov(x), lower=True)
        except np.linalg.LinAlgError:
            return 1e300
        value = 2.0 * np.sum(np.log(np.diag(c[0]))) + r @ sl.cho_solve(c, r)
        Lb = sl.solve_triangular(c[0], s.basis, lower=True)
        q, rr = np.linalg.qr(Lb)
        zr = sl.solve_triangular(c[0], r, lower=True)
        return value + 2.0 * np.sum(np.log(np.abs(np.diag(rr)))) - np.sum((q.T @ zr) ** 2)

    best = None
    for x0 in ([sc, 0.3 * sc, 2 * dt, 0.3 * sc, longest, 0.01 * sc / span],
               [sc, 0.3 * sc, 2 * dt, 0.01 * sc, longest, 0.3 * sc / span]):
        res = minimize(nll, np.clip(np.log(x0), lo, hi), method="L-BFGS-B",
                       bounds=list(zip(lo, hi, strict=True)))
        best = res if best is None or res.fun < best.fun else best
    return cov(best.x)


def run(per_ramp: int, cycles: int, draws: int) -> list[dict]:
    obs = series(per_ramp, cycles)
    t = obs["time_s"].to_numpy(float)
    B = systematic_basis(obs)
    (one,) = nz.noise_series(obs)  # the engine's covariance of a fitted noise: one.covariance
    rows = []
    for kind, levels in KINDS.items():
        true = covariance(t, **levels)
        gains = {"engine": [], "plain": [], "two parts": [], "true": []}
        for seed in range(draws):
            r = rig_noise(t, RigNoise(white=1.0, **levels), np.random.default_rng(seed))
            (cn,) = nz.fit_noise(obs, r, systematic=B).params.values()
            (cp,) = nz.fit_noise(obs, r).params.values()
            gains["engine"].append(offset_gain(one.covariance(cn), r))
            gains["plain"].append(offset_gain(one.covariance(cp), r))
            gains["two parts"].append(offset_gain(two_parts(obs, r, B), r))
            gains["true"].append(offset_gain(true, r))
        rows.append({"kind": kind, **{k: (float(np.mean(v)), float(np.mean(np.asarray(v)
                                                                            > CHI2_95)))
                                      for k, v in gains.items()}})
    return rows


def markdown(per_ramp: int, cycles: int, draws: int, rows: list[dict]) -> str:
    lines = [f"Series of {cycles} cycle{'s' if cycles > 1 else ''}, {per_ramp} points a ramp "
             f"({2 * per_ramp * cycles} "
             f"points), {draws} draws. Offset gain: mean (share above {CHI2_95})",
             "", "| rig noise | engine | plain ML | two parts | true covariance |",
             "|---|---|---|---|---|"]
    for r in rows:
        cells = [f"{r[k][0]:.2f} ({100 * r[k][1]:.0f} %)"
                 for k in ("engine", "plain", "two parts", "true")]
        lines.append(f"| {r['kind']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-ramp", type=int, default=11)
    ap.add_argument("--cycles", type=int, nargs="+", default=[2, 8])
    ap.add_argument("--draws", type=int, default=40)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    parts = [markdown(args.per_ramp, c, args.draws, run(args.per_ramp, c, args.draws))
             for c in args.cycles]
    parts.append(f"\n{math.ceil(time.perf_counter() - t0)} s\n")
    write_text_atomic(args.out, "\n".join(parts))


if __name__ == "__main__":
    run_script(main)
