"""Re-diagnose stored open-world cases with the current engine, side by side with the
stored verdicts: what a change of the engine does to the same recordings.

    OPENBLAS_NUM_THREADS=1 mpirun -n 2 .venv/bin/python benchmarks/rediagnose_open.py \\
        --benchmark open/ --out rediag/ [world003 world017 ...]

``--benchmark`` is the folder of a ``brainmech benchmark-diagnosis --world open`` run
(its ``cases/`` and ``labels/``); without case names every case with a stored result is
taken.  The cases are handed out to whichever rank is free; each new result is written to
``--out`` as soon as it is done (a re-run skips the cases already there).  Rank 0 then
scores the stored and the new results of the same cases (``diagnosis.open_benchmark``)
and writes ``--out/compare.md`` with both summaries and one line per case.  ``--stated-white``: each
diagnosis is given the white noise SD per channel that its generator drew (``diagnose
--noise``), as a lab would state its instrument's; the other kinds of rig noise are still
estimated.  ``--stated-full``: each is given the whole noise its generator drew
(``diagnosis.open_world.noise_statement``), as a lab that measured its rig would state it,
and fits no noise: what the diagnosis does once the noise is not its to guess.
``--short-series N``: only the cases with a series too short to keep its
repeated-misfit columns and N more out of its noise model (open-world-24's change of what
short series keep out can move no other case; N = 12 took 58, 50 and 63 cases of seeds
1, 2 and 3).
"""

from __future__ import annotations

import argparse
import logging
import time
import types
from pathlib import Path

import numpy as np
from _machine import read_json, run_script
from mpi4py import MPI

from brain_fe.io import write_json_atomic, write_text_atomic
from brain_fe.parallel import SharedCounter, dynamic_items
from diagnosis.noise import MIN_REML_DOF
from diagnosis.open_benchmark import _diagnose, _rms_over_rig_noise, score, summary_markdown
from diagnosis.open_world import noise_statement
from diagnosis.remaining import reproducible_basis
from diagnosis.series import groups
from recordings.observations import observations
from recordings.tables import read_recordings, read_specimens


def read_case(src: Path, name: str):
    """A stored case of an open-world run: (its label, its observations)."""
    lab = read_json(src / "labels" / f"{name}.json")
    spec = read_specimens(src / "cases" / f"{name}_specimens.csv")
    obs = observations(read_recordings(src / "cases" / f"{name}_recordings.csv", spec))
    return lab, obs


def _has_short_series(obs, extra: int) -> bool:
    """Whether a series of ``obs`` would keep fewer than ``MIN_REML_DOF`` degrees of freedom
    with its repeated-misfit columns and ``extra`` more kept out of its noise."""
    obs = obs.reset_index(drop=True)
    B, _ = reproducible_basis(obs)
    for _, rows in groups(obs):
        Bs = B[rows][:, np.abs(B[rows]).max(axis=0) > 0]
        rank = np.linalg.matrix_rank(Bs) if Bs.shape[1] else 0
        if len(rows) - rank - extra < MIN_REML_DOF:
            return True
    return False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--benchmark", required=True, help="folder of an open-world benchmark")
    ap.add_argument("--out", required=True, help="folder of the new results")
    ap.add_argument("--stated-white", action="store_true",
                    help="give each diagnosis the white noise SD per channel its generator "
                    "drew, as a lab that knows its instrument states it (--noise)")
    ap.add_argument("--stated-full", action="store_true",
                    help="give each diagnosis the whole noise its generator drew (white, "
                    "filter, wander, drift, rounding), as a lab that measured its rig "
                    "states it (--noise JSON): no noise is fitted")
    ap.add_argument("--short-series", type=int, metavar="N", default=None,
                    help="only the cases with a series that keeps fewer than the noise "
                    "model's minimum degrees of freedom once its repeated-misfit columns "
                    "and N more (the trend and the parameters, at most) are kept out: the "
                    "only cases a change of what short series keep out can move")
    ap.add_argument("cases", nargs="*", help="case names (default: every stored result)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    comm = MPI.COMM_WORLD
    src, out = Path(a.benchmark), Path(a.out)
    names = a.cases or sorted(p.name.removesuffix("_result.json")
                              for p in (src / "cases").glob("*_result.json"))
    if a.short_series is not None:
        names = [n for n in names if _has_short_series(read_case(src, n)[1], a.short_series)]
    need = ("cases/{}_result.json", "cases/{}_specimens.csv", "cases/{}_recordings.csv",
            "labels/{}.json")
    missing = [n for n in names if not all((src / f.format(n)).is_file() for f in need)]
    if missing or not names:  # every rank finds the same, so every rank ends alike
        ap.error(f"{src}: no stored result, recordings and label of "
                 f"{', '.join(missing) or 'any case'}")
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    comm.Barrier()
    pending = [n for n in names if not (out / f"{n}_result.json").exists()]
    counter = SharedCounter(comm)
    for name in dynamic_items(pending, counter):
        lab, obs = read_case(src, name)
        t0 = time.perf_counter()
        stated = ({ch: float(n["white"]) for ch, n in lab["noise"].items()}
                  if a.stated_white else noise_statement(lab["noise"]) if a.stated_full
                  else None)
        res = _diagnose(obs, types.SimpleNamespace(**lab["specimen"]), 1, name, stated)
        res["rms_after_over_true_noise"] = _rms_over_rig_noise(obs, res, lab["noise"],
                                                               lab.get("noise_rms"))
        write_json_atomic(out / f"{name}_result.json", res, indent=1, default=str)
        old = read_json(src / "cases" / f"{name}_result.json")
        logging.getLogger("rediagnose").warning(
            "%s %s (%s): stored %s (%s) -> now %s (%s), %.0f s", name, lab["kind"],
            lab["expected"], old["verdict"], old["status"], res["verdict"], res["status"],
            time.perf_counter() - t0)
    counter.free()
    comm.Barrier()
    if comm.rank:
        return
    labels, old, new = {}, {}, {}
    for n in names:
        lab, obs = read_case(src, n)
        labels[n] = lab
        new[n] = read_json(out / f"{n}_result.json")
        o = read_json(src / "cases" / f"{n}_result.json")
        o["rms_after_over_true_noise"] = _rms_over_rig_noise(obs, o, lab["noise"],
                                                             lab.get("noise_rms"))
        old[n] = o
    so, sn = score(labels, old), score(labels, new)
    lines = ["# Stored results against the current engine, same recordings", "",
             "| case | kind | truth | stored verdict (status) | now (status) | "
             "now: after / true noise | now: seconds |", "|---|---|---|---|---|---|---|"]
    for n in names:
        o, r = old[n], new[n]
        lines.append(f"| {n} | {labels[n]['kind']} | {labels[n]['expected']} | "
                     f"{o['verdict']} ({o['status']}) | {r['verdict']} ({r['status']}) | "
                     f"{r.get('rms_after_over_true_noise', float('nan')):.2f} | "
                     f"{r.get('elapsed_s', float('nan')):.0f} |")
    text = ("\n".join(lines) + "\n\n## Stored\n\n" + summary_markdown(so)
            + "\n## Now\n\n" + summary_markdown(sn))
    write_text_atomic(out / "compare.md", text)
    write_json_atomic(out / "compare.json", {"stored": so, "now": sn}, indent=1, default=str)
    print(text)


if __name__ == "__main__":
    run_script(main)
