"""Diagnose the specimens of a recordings table: shared among MPI ranks, resumable.

* One specimen: its results go to ``DIR`` itself, and the candidate fits are shared among
  the ranks of ``comm``.
* Several: one folder per specimen (``DIR/<specimen>/``), each written atomically when its
  diagnosis is complete; the specimens are handed out one at a time to whichever rank is
  free (:func:`brain_fe.parallel.dynamic_items`), each rank working alone, so the same
  command scales from 2 cores to a cluster under ``mpirun``/``srun``.  ``DIR/config.json``
  records the settings; a re-run with the same settings (after an interruption, say)
  diagnoses only the specimens without a result, and one with other settings is refused.
  ``DIR/diagnosis.json`` and ``DIR/summary.md`` gather the verdicts.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from mpi4py import MPI

from brain_fe.io import write_json_atomic, write_text_atomic
from brain_fe.parallel import Progress, SharedCounter, as_progress, dynamic_items, gather_all
from recordings.observations import observations
from recordings.tables import read_recordings, read_specimens
from simulators.fe import FESimulator

from . import report
from .engine import diagnose

log = logging.getLogger(__name__)


def _diagnose_one(name, rec, specs, target: Path, *, refinement, effects, nu0, noise, comm,
                  progress) -> dict:
    row = specs.set_index("specimen").loc[name]
    obs = observations(rec[rec.specimen == name])
    obs.attrs["radius_mm"] = float(row.radius_mm)
    R, H = float(row.radius_mm), float(row.height_mm)
    sim = FESimulator(obs, R, H, refinement=refinement, nu0=nu0)
    fine = FESimulator(obs, R, H, refinement=refinement + 1, nu0=nu0)
    with as_progress(progress, None, f"diagnose {name}", "fit", comm) as bar:
        d = diagnose(sim, obs, fine_sim=fine, effects=effects, comm=comm, noise=noise,
                     progress=lambda what: bar.update(1, what))
    log.info("%s: verdict %s", name, d.verdict)
    if comm.rank == 0:
        return report.write(d, target, title=f"Diagnosis of specimen {name}")
    return {}


def diagnose_recordings(recordings: str, specimens: str, out: str, *,
                        specimen: str | None = None, refinement: int = 1,
                        effects=None, nu0: float = 0.49, noise: dict | None = None,
                        comm=MPI.COMM_WORLD, progress=None) -> dict:
    """Diagnose every specimen of a recordings table (see the module docstring).

    Returns ``{specimen: diagnosis.json content}`` on rank 0 (every specimen, reused or
    new; each with ``"reused": bool``) and ``{}`` on the other ranks."""
    specs = read_specimens(specimens)
    rec = read_recordings(recordings, specs)  # validated before any output is written
    names = list(dict.fromkeys(rec["specimen"]))
    if specimen is not None:
        if specimen not in names:
            raise ValueError(f"{recordings}: no recordings of specimen {specimen!r}")
        names = [specimen]
    out = Path(out)
    kw = dict(refinement=refinement, effects=effects, nu0=nu0, noise=noise)
    if len(names) == 1:
        res = _diagnose_one(names[0], rec, specs, out, comm=comm, progress=progress, **kw)
        comm.Barrier()
        return {names[0]: dict(res, reused=False)} if comm.rank == 0 else {}
    config = {"refinement": refinement, "effects": sorted(effects) if effects else None,
              "nu0": nu0, "noise": noise, "recordings": str(Path(recordings).resolve())}
    error = None
    if comm.rank == 0:
        error = _claim(out, config)
    error = comm.bcast(error, root=0)
    if error:
        raise ValueError(error)
    pending = [n for n in names if not (out / str(n) / "diagnosis.json").exists()]
    log.info("%s: %d of %d specimens to diagnose on %d rank(s)", out, len(pending),
             len(names), comm.size)
    counter = SharedCounter(comm, slots=2)
    done_here = []
    self_comm = MPI.COMM_SELF
    with Progress(len(names), "diagnose", "specimen", enabled=bool(progress), comm=comm,
                  initial=len(names) - len(pending)) as bar:
        for name in dynamic_items(pending, counter):
            t0 = time.perf_counter()
            res = _diagnose_one(name, rec, specs, out / str(name), comm=self_comm,
                                progress=None, **kw)
            done_here.append(name)
            counter.add(1)
            bar.update(1, f"{name}: {res['verdict']} ({time.perf_counter() - t0:.0f} s)")
        if comm.rank == 0:
            seen = counter.read(1)
            while seen < len(pending):  # keep the bar moving while the others finish
                time.sleep(0.2)
                now = counter.read(1)
                bar.update(now - seen, None)
                seen = now
    new = set(gather_all(comm, done_here))
    counter.free()
    if comm.rank != 0:
        return {}
    results = {n: dict(json.loads((out / str(n) / "diagnosis.json").read_text()),
                       reused=n not in new) for n in names}
    write_json_atomic(out / "diagnosis.json", {n: _digest(r) for n, r in results.items()},
                      indent=1)
    write_text_atomic(out / "summary.md", summary_markdown(results))
    return results


def _claim(out: Path, config: dict) -> str | None:
    """Create ``out`` with its config, or check that an existing one has the same."""
    path = out / "config.json"
    if path.exists():
        old = json.loads(path.read_text())
        diff = [k for k in config if old.get(k) != config[k]]
        if diff:
            return (f"{out} holds diagnoses made with another {diff[0]} ({old.get(diff[0])!r}"
                    f", now {config[diff[0]]!r}); use another output directory")
        return None
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, config, indent=1)
    return None


def _digest(r: dict) -> dict:
    keys = ("verdict", "effects", "status", "rms_before", "rms_after")
    return {k: r[k] for k in keys if k in r}


def summary_markdown(results: dict) -> str:
    """One line per specimen: verdict, RMS before and after, the worst located segment."""
    lines = ["# Diagnosis of every specimen", "",
             "| specimen | verdict | status | RMS/noise before -> after | where the base model "
             "misfits | what remains |", "|---|---|---|---|---|---|"]
    for n, r in results.items():
        where = r["located"][0]["segment"] if r.get("located") else "-"
        left = r.get("remaining", {}).get("located") or []
        lines.append(f"| {n} | {r['verdict']} | {r.get('status', '-')} | "
                     f"{r['rms_before']:.2f} -> {r['rms_after']:.2f} | {where} | "
                     f"{left[0]['segment'] if left else '-'} |")
    counts: dict[str, int] = {}
    for r in results.values():
        counts[r["verdict"]] = counts.get(r["verdict"], 0) + 1
    lines += ["", "Verdicts: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))]
    return "\n".join(lines) + "\n"
