"""Entry points of the diagnosis used by the CLI."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from mpi4py import MPI

from brain_fe.io import write_json_atomic, write_text_atomic

from . import report
from .engine import diagnose
from .observations import observations

log = logging.getLogger(__name__)
BASES = ("one-term-ogden", "homogeneous-ogden")


def progress_callback(progress, comm, desc: str, unit: str):
    """(bar, callback): a tqdm bar on rank 0 when ``progress`` is True, a callable passed
    through otherwise."""
    if progress is not True:
        return None, progress
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit=unit, disable=None if comm.rank == 0 else True)

    def step(what: str) -> None:
        bar.set_postfix_str(what)
        bar.update()

    return bar, step


def diagnose_recordings(recordings: str, specimens: str, out: str, *,
                        specimen: str | None = None, refinement: int = 1,
                        effects=None, nu0: float = 0.49, comm=MPI.COMM_WORLD,
                        progress=None) -> dict:
    """Diagnose every specimen of a recordings table (FE base model, one-term Ogden).

    One specimen: DIR/diagnosis.json, report.md and figures. Several: one subfolder each
    and DIR/diagnosis.json mapping specimen -> verdict. The candidate fits of a specimen are
    shared among the MPI ranks of ``comm``.
    """
    from identification.recordings import read_recordings, read_specimens

    from .simulators import FESimulator

    specs = read_specimens(specimens)
    rec = read_recordings(recordings, specs)  # validated before any output is written
    names = list(dict.fromkeys(rec["specimen"]))
    if specimen is not None:
        if specimen not in names:
            raise ValueError(f"{recordings}: no recordings of specimen {specimen!r}")
        names = [specimen]
    out = Path(out)
    results = {}
    for name in names:
        row = specs.set_index("specimen").loc[name]
        obs = observations(rec[rec.specimen == name])
        obs.attrs["radius_mm"] = float(row.radius_mm)
        R, H = float(row.radius_mm), float(row.height_mm)
        sim = FESimulator(obs, R, H, refinement=refinement, nu0=nu0)
        fine = FESimulator(obs, R, H, refinement=refinement + 1, nu0=nu0)
        bar, step = progress_callback(progress, comm, f"diagnose {name}", "fit")
        d = diagnose(sim, obs, fine_sim=fine, effects=effects, comm=comm, progress=step)
        if bar is not None:
            bar.close()
        target = out if len(names) == 1 else out / str(name)
        if comm.rank == 0:
            res = report.write(d, target, title=f"Diagnosis of specimen {name}")
            results[name] = res
        log.info("%s: verdict %s", name, d.verdict)
    if comm.rank == 0 and len(names) > 1:
        summary = {n: {"verdict": r["verdict"], "rms_before": r["rms_before"],
                       "rms_after": r["rms_after"]} for n, r in results.items()}
        write_json_atomic(out / "diagnosis.json", summary, indent=1)
    comm.Barrier()
    return results


def diagnose_budday(path: str | None, out: str, *, nu0: float = 0.49) -> dict:
    """The homogeneous analytical base model on the averaged human-brain curves of Budday
    et al. (2017): one diagnosis per region, plus the one-term fit of all tests together."""
    from .budday import DATA_PATH, read_budday
    from .glued_cube import GluedCubeSimulator

    obs_all = read_budday(path or DATA_PATH)
    out = Path(out)
    results, by_test = {}, {}
    for region, obs in obs_all.groupby("specimen", sort=False):
        obs = obs.reset_index(drop=True)
        sim = GluedCubeSimulator(obs, nu0=nu0)
        d = diagnose(sim, obs)
        results[region] = report.write(d, out / str(region),
                                       title=f"Diagnosis of region {region} (Budday 2017)")
        by_test[region] = _fits_by_test(obs, d)
    summary = {r: {"verdict": v["verdict"], "one_term": v["base_parameters"],
                   "one_term_by_test": by_test[r],
                   "refit": v["refit_parameters"], "rms_before": v["rms_before"],
                   "rms_after": v["rms_after"], "located": v["located"][:3]}
               for r, v in results.items()}
    write_json_atomic(out / "diagnosis.json", summary, indent=1)
    write_text_atomic(out / "summary.md", _budday_table(summary))
    return summary


def _fits_by_test(obs, d) -> dict:
    """One-term fits of each test alone (same noise weights), started from the all-tests
    fit: how far the tests disagree when each is fitted on its own."""
    from .effects import BASE_NAMES
    from .engine import fit
    from .homogeneous import HomogeneousSimulator

    out = {}
    for curve, sub in obs.groupby("curve", sort=False):
        rows = sub.index.to_numpy()
        sub = sub.reset_index(drop=True)
        f = fit(HomogeneousSimulator(sub), sub, d.sigma[rows], d.base.values,
                list(BASE_NAMES), max_nfev=60)
        out[str(curve)] = {"mu_0": float(f.values["mu_0"]),
                           "alpha_0": float(f.values["alpha_0"]),
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
