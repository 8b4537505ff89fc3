"""Which outside-the-library cases of an open-world draw a library effect mimics.

For every ``outside`` case of a ``brainmech benchmark-diagnosis --world open`` draw, the
generator's rule of :func:`diagnosis.open_world.closest_library`: the misfit (noise SDs,
RMS) that the noiseless recordings leave to the best base model with each library effect
alone, on the working mesh.  Where one leaves less than even the most favourable test,
one parameter, needs (:func:`diagnosis.open_benchmark.mimicked`), that effect mimics the
outside one in the specimen's tests, and no diagnosis can tell from the recordings that
something outside the library is at work.  The cases come from a stored run
(``--benchmark``: its labels and recorded times) or are drawn again from the seed
(``--seed``: the generator is deterministic, so a draw's outside cases can be measured
after its case data are gone; only the outside cases are made, no diagnosis is run), or
judged again from a file this script wrote (``--rescore``: no fit).
Two bars: white noise at the rig's SD (optimistic: the most any test could see), and the
rig's whole noise, wander, filter and drift included (``mimicked_under_rig_noise``: a
misfit as slow as the rig's wander hides in it).  With ``--pairs``, every pair of library
effects as well, each fitted from its two effects' best fits alone (``*_with_pairs``: a
verdict of two effects is one the diagnosis may give).  With ``--summary`` (the run's
``summary.json``), the outside score is split by each
(:func:`diagnosis.open_benchmark.outside_ceiling`).

    OPENBLAS_NUM_THREADS=1 mpirun -n 2 .venv/bin/python benchmarks/mimicked_outside.py \\
        --seed 10 --pairs --summary open/summary.json --out mimicked.json
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from _machine import read_json, run_script
from mpi4py import MPI
from visible_beside import recorded_times, stored

from brain_fe.io import write_json_atomic
from brain_fe.parallel import SharedCounter, dynamic_items
from diagnosis.open_benchmark import (
    draw_case,
    mimicked,
    mimicked_by,
    outside_ceiling,
    plan,
    singles_of,
)
from diagnosis.open_world import closest_library, noise_sd


def _outside_case(a, name: str, models: dict):
    """(truth effects, base misfit alone, specimen, truth, recorded times, noise SD, the
    rig's noise per channel)."""
    if a.benchmark:
        lab, spec, truth, times = stored(Path(a.benchmark), name)
        return lab["effects"], lab["base_misfit_over_noise"], spec, truth, times, \
            lab["noise_sd"], lab["noise"]
    made = draw_case(int(name[5:]), a.seed, models)
    if made is None:
        return None
    rec, _, case = made
    return case.effects, case.misfits, case.spec, case.truth, recorded_times(rec, case.spec), \
        noise_sd(case.noise), case.noise


def judged(closest: dict) -> dict:
    """One case's flags: mimicked by one effect (white, rig) and, where pairs were
    measured, the effect or pair that mimics it."""
    single = singles_of(closest)
    out = {"mimicked": mimicked(single), "mimicked_under_rig_noise": mimicked(single, "rig")}
    if closest.get("pairs"):
        out.update(mimicked_with_pairs=mimicked_by(closest),
                   mimicked_with_pairs_under_rig_noise=mimicked_by(closest, "rig"))
    return out


def result(every: dict, summary: str | None) -> dict:
    """The file written: every case, the cases each bar flags and, with the run's
    ``summary``, its outside score split by each."""
    pairs = any(r["closest"].get("pairs") for r in every.values())
    out = {"cases": every,
           "mimicked": sorted(n for n, r in every.items() if r["mimicked"]),
           "mimicked_under_rig_noise": sorted(
               n for n, r in every.items() if r["mimicked_under_rig_noise"])}
    if pairs:
        for key in ("mimicked_with_pairs", "mimicked_with_pairs_under_rig_noise"):
            out[key] = {n: r[key] for n, r in sorted(every.items()) if r.get(key)}
    if summary:
        by_case = read_json(summary, "by_case")["by_case"]
        closest = {n: r["closest"] for n, r in every.items()}
        out["score"] = outside_ceiling(by_case, closest, pairs=False)
        out["score_under_rig_noise"] = outside_ceiling(by_case, closest, "rig", pairs=False)
        if pairs:
            out["score_with_pairs"] = outside_ceiling(by_case, closest)
            out["score_with_pairs_under_rig_noise"] = outside_ceiling(by_case, closest, "rig")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--benchmark", help="a stored open-world run (its labels/ and cases/)")
    src.add_argument("--seed", type=int, help="draw the outside cases of this seed again")
    src.add_argument("--rescore", help="a file this script wrote: judge its measured cases "
                     "again (no fit; the flags and scores of the current rules)")
    ap.add_argument("--cases", type=int, default=122, help="the draw's number of cases "
                    "(with --seed; default 122)")
    ap.add_argument("--pairs", action="store_true",
                    help="measure every pair of library effects too (one fit each)")
    ap.add_argument("--summary", help="the run's summary.json: split its outside score")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    comm = MPI.COMM_WORLD
    if a.rescore:
        every = read_json(a.rescore, "cases")["cases"]
        every = {n: {**r, **judged(r["closest"])} for n, r in every.items()}
        if comm.rank == 0:
            write_json_atomic(Path(a.out), result(every, a.summary), indent=1, default=str)
        return
    if a.benchmark:
        names = sorted(p.stem for p in (Path(a.benchmark) / "labels").glob("world*.json")
                       if read_json(p)["kind"] == "outside")
    else:
        names = [f"world{i:03d}" for i in range(a.cases) if plan(i, a.seed)[0] == "outside"]
    counter, mine, models = SharedCounter(comm), {}, {}
    for name in dynamic_items(names, counter):
        made = _outside_case(a, name, models)
        if made is None:
            continue
        effects, alone, spec, truth, times, sd, rig = made
        closest = closest_library(spec, truth, times, sd, models, rig=rig, pairs=a.pairs)
        mine[name] = {"effects": effects, "alone": alone, "closest": closest,
                      **judged(closest)}
        logging.getLogger("mimicked").warning(
            "%s %s: alone %s, closest library %s", name, effects, alone,
            {k: round(v, 2) for k, v in closest["rms_left_over_noise"].items()})
    counter.free()
    every = {k: v for part in comm.allgather(mine) for k, v in part.items()}
    if comm.rank == 0:
        write_json_atomic(Path(a.out), result(every, a.summary), indent=1, default=str)


if __name__ == "__main__":
    run_script(main)
