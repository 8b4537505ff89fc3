"""How much of each effect of a stored open-world pair its partner cannot mimic.

For every ``pair`` case of a ``brainmech benchmark-diagnosis --world open`` run, the
generator's rule of :func:`diagnosis.open_world.visible_beside` applied to its stored
truth and recorded times: the misfit (noise SDs, RMS) that the noiseless recordings leave
to the best model with the *other* effect, on the working mesh.  Runs made since write it
into every pair's label (the pair is kept); this script measures it for the pairs of an
earlier run.  ``not_separable``: the pairs with an effect below ``VISIBLE`` beside its
partner (:func:`diagnosis.open_benchmark.separable`; not measured: neither list).

    OPENBLAS_NUM_THREADS=1 mpirun -n 2 .venv/bin/python benchmarks/visible_beside.py \\
        --benchmark open/ --out beside.json
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import pandas as pd
from _machine import read_json, run_script
from mpi4py import MPI

from brain_fe.io import write_json_atomic
from brain_fe.parallel import SharedCounter, dynamic_items
from brain_fe.parameters import Param
from diagnosis.open_benchmark import separable
from diagnosis.open_world import VISIBLE, Specimen, Truth, visible_beside

OUTSIDE_FIELDS = {"stiffness_drift": "drift", "set_stretch": "set_stretch",
                  "set_shear": "set_shear"}


def stored(src: Path, name: str):
    """(label, specimen, truth, recorded times per protocol) of a stored case."""
    lab = read_json(src / "labels" / f"{name}.json")
    s = dict(lab["specimen"])
    s["torsion_amplitudes"] = tuple(s["torsion_amplitudes"])
    spec = Specimen(**s)
    truth = Truth({Param.parse(k): v for k, v in lab["truth"].items()
                   if k not in OUTSIDE_FIELDS},
                  **{OUTSIDE_FIELDS[k]: v for k, v in lab["truth"].items()
                     if k in OUTSIDE_FIELDS})
    rec = pd.read_csv(src / "cases" / f"{name}_recordings.csv")
    return lab, spec, truth, recorded_times(rec, spec)


def recorded_times(rec: pd.DataFrame, spec: Specimen) -> list:
    """The recorded times of each of ``spec``'s protocols in the recordings ``rec``."""
    return [rec[(rec.test == p.test) & (rec.amplitude.round(4) == round(p.amplitude, 4))]
            ["time_s"].to_numpy(float) for p in spec.protocols()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--benchmark", required=True)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    comm, src = MPI.COMM_WORLD, Path(a.benchmark)
    names = sorted(p.stem for p in (src / "labels").glob("world*.json")
                   if read_json(p)["kind"] == "pair")
    counter, mine, models = SharedCounter(comm), {}, {}
    for name in dynamic_items(names, counter):
        lab, spec, truth, times = stored(src, name)
        beside = visible_beside(lab["effects"], spec, truth, times, lab["noise_sd"], models)
        mine[name] = {"effects": lab["effects"], "alone": lab["base_misfit_over_noise"],
                      "beside": beside, "separable": separable(
                          {"misfit_beside_the_other_over_noise": beside})}
        logging.getLogger("beside").warning("%s %s: alone %s, beside the other %s", name,
                                            lab["effects"], mine[name]["alone"], beside)
    counter.free()
    every = {k: v for part in comm.allgather(mine) for k, v in part.items()}
    if comm.rank == 0:
        write_json_atomic(Path(a.out), {"visible": VISIBLE, "cases": every,
                                        "not_separable": sorted(
                                            n for n, r in every.items()
                                            if r["separable"] is False)},
                          indent=1, default=str)


if __name__ == "__main__":
    run_script(main)
