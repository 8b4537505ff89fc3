"""Diagnose the specimens of a recordings table with the FE base model (one-term Ogden)."""

from __future__ import annotations

import logging
from pathlib import Path

from mpi4py import MPI

from brain_fe.io import write_json_atomic
from brain_fe.parallel import as_progress
from recordings.observations import observations
from recordings.tables import read_recordings, read_specimens
from simulators.fe import FESimulator

from . import report
from .engine import diagnose

log = logging.getLogger(__name__)


def diagnose_recordings(recordings: str, specimens: str, out: str, *,
                        specimen: str | None = None, refinement: int = 1,
                        effects=None, nu0: float = 0.49, comm=MPI.COMM_WORLD,
                        progress=None) -> dict:
    """Diagnose every specimen of a recordings table.

    One specimen: DIR/diagnosis.json, report.md and figures. Several: one subfolder each
    and DIR/diagnosis.json mapping specimen -> verdict. The candidate fits of a specimen are
    shared among the MPI ranks of ``comm``.
    """
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
        with as_progress(progress, None, f"diagnose {name}", "fit", comm) as bar:
            d = diagnose(sim, obs, fine_sim=fine, effects=effects, comm=comm,
                         progress=lambda what: bar.update(1, what))
        target = out if len(names) == 1 else out / str(name)
        if comm.rank == 0:
            results[name] = report.write(d, target, title=f"Diagnosis of specimen {name}")
        log.info("%s: verdict %s", name, d.verdict)
    if comm.rank == 0 and len(names) > 1:
        summary = {n: {"verdict": r["verdict"], "rms_before": r["rms_before"],
                       "rms_after": r["rms_after"]} for n, r in results.items()}
        write_json_atomic(out / "diagnosis.json", summary, indent=1)
    comm.Barrier()
    return results
