"""The averaged human-brain curves of Budday et al. (2017), diagnosed region by region with
the homogeneous analytical base model (the cube tests were reduced as if homogeneous) and
the glued-end candidate (:mod:`simulators.glued_cube`)."""

from __future__ import annotations

import logging

import numpy as np

from brain_fe.io import staged_directory, write_json_atomic, write_text_atomic
from recordings.budday import DATA_PATH, read_budday
from simulators.glued_cube import GluedCubeSimulator
from simulators.homogeneous import HomogeneousSimulator

from . import report
from .effects import BASE_NAMES
from .engine import diagnose
from .fitting import fit

log = logging.getLogger(__name__)


def diagnose_budday(path: str | None, out: str, *, nu0: float = 0.49) -> dict:
    """One diagnosis per region, plus the one-term fit of each test alone."""
    obs_all = read_budday(path or DATA_PATH)
    results, by_test = {}, {}
    with staged_directory(out) as stage:
        for region, obs in obs_all.groupby("specimen", sort=False):
            obs = obs.reset_index(drop=True)
            sim = GluedCubeSimulator(obs, nu0=nu0)
            d = diagnose(sim, obs)
            results[region] = report.write(d, stage / str(region),
                                           title=f"Diagnosis of region {region} (Budday 2017)")
            by_test[region] = _fits_by_test(obs, d, nu0)
        summary = {r: {"verdict": v["verdict"], "one_term": v["base_parameters"],
                       "one_term_by_test": by_test[r],
                       "refit": v["refit_parameters"], "rms_before": v["rms_before"],
                       "rms_after": v["rms_after"], "located": v["located"][:3]}
                   for r, v in results.items()}
        write_json_atomic(stage / "diagnosis.json", summary, indent=1)
        write_text_atomic(stage / "summary.md", _budday_table(summary))
    return summary


def _fits_by_test(obs, d, nu0: float) -> dict:
    """One-term fits of each test alone (same noise weights), started from the all-tests
    fit: how far the tests disagree when each is fitted on its own."""
    out = {}
    mu0, a0 = BASE_NAMES
    for curve, sub in obs.groupby("curve", sort=False):
        rows = sub.index.to_numpy()
        sub = sub.reset_index(drop=True)
        f = fit(HomogeneousSimulator(sub, nu0=nu0), sub, d.sigma[rows], d.base.values,
                list(BASE_NAMES), max_nfev=60)
        out[str(curve)] = {"mu_0": float(f.values[mu0]), "alpha_0": float(f.values[a0]),
                           "rms_over_noise": float(np.sqrt(np.mean(f.z**2)))}
    return out


def _budday_table(summary: dict) -> str:
    tests = sorted({t for v in summary.values() for t in v["one_term_by_test"]})
    head = ("| region | all tests: mu [kPa], alpha | "
            + " | ".join(f"{t} alone" for t in tests)
            + " | verdict | RMS/noise before -> after |")
    lines = ["# One-term Ogden fits of the Budday et al. (2017) regions", "",
             "Homogeneous analytical base model (nu0 fixed); each test alone next to the fit "
             "of all tests together.", "", head, "|" + "---|" * (len(tests) + 4)]
    for r, v in summary.items():
        a = v["one_term"]
        cells = [f"{v['one_term_by_test'][t]['mu_0']:.2f}, "
                 f"{v['one_term_by_test'][t]['alpha_0']:.1f}"
                 if t in v["one_term_by_test"] else "-" for t in tests]
        lines.append(f"| {r} | {a['mu_0']:.2f}, {a['alpha_0']:.1f} | " + " | ".join(cells)
                     + f" | {v['verdict']} | {v['rms_before']:.1f} -> {v['rms_after']:.1f} |")
    return "\n".join(lines) + "\n"
