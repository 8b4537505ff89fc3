"""Entry points of the diagnosis used by the CLI."""

from __future__ import annotations

import logging
from pathlib import Path

from mpi4py import MPI

from brain_fe.io import write_json_atomic

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
    from .homogeneous import HomogeneousSimulator

    obs_all = read_budday(path or DATA_PATH)
    out = Path(out)
    results = {}
    for region, obs in obs_all.groupby("specimen", sort=False):
        obs = obs.reset_index(drop=True)
        sim = HomogeneousSimulator(obs)
        sim.kind, sim.nu0 = "homogeneous", nu0
        d = diagnose(sim, obs)
        results[region] = report.write(d, out / str(region),
                                       title=f"Diagnosis of region {region} (Budday 2017)")
    summary = {r: {"verdict": v["verdict"], "one_term": v["base_parameters"],
                   "refit": v["refit_parameters"], "rms_before": v["rms_before"],
                   "rms_after": v["rms_after"], "located": v["located"][:3]}
               for r, v in results.items()}
    write_json_atomic(out / "diagnosis.json", summary, indent=1)
    return summary
