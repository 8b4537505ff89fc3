"""Could any selection rule have named it?  The *oracle* test of a missed open-world case.

For a stored case whose verdict named only part of the true set of effects, the model of
the true set is fitted from the true parameters (the oracle start, which no diagnosis
has) and compared with the model the diagnosis named, refitted from its own optimum, with
the diagnosis's base fit, discretisation correction and weights, under the noise model of
the oracle fit's residual (the round's rule: the best fit's residual).  The
likelihood-ratio statistic is set against what the diagnosis demands of the missing
parameters in that round (``Context.needed``: Bonferroni over the round's candidates and
the BIC margin).  A ratio below 1 means that even the true model does not earn its place
in these recordings: no selection rule at the diagnosis's significance could name it.

    OPENBLAS_NUM_THREADS=1 mpirun -n 2 .venv/bin/python benchmarks/oracle_open.py \\
        --benchmark open/ --results rediag/ --out oracle.json [world029 ...]

For an effect *outside* the library that a verdict called ``explained``, there is no true
model to fit; the question is then whether these recordings could tell the truth from the
named model at all: the named model (started at the diagnosis's refit) is fitted to the
noiseless recordings of the truth (the generator's path on the working mesh,
:func:`diagnosis.open_world.misfit_left`), and what it leaves, n r^2 in chi-square units
(r: RMS in noise SDs over the n points), is set against what even the most favourable
test of a systematic misfit, one parameter, would need.  Below it the named model *is*
the truth for these tests and noise; `unexplained` would have been a guess.

``--results``: the folder of the verdicts to test (``*_result.json`` of
``benchmarks/rediagnose_open.py`` or the benchmark's own ``cases/``); without case names,
every single or pair whose verdict named all of the truth but one effect (the one tested)
and every outside effect called ``explained``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from _machine import read_json, run_script
from mpi4py import MPI
from rediagnose_open import _case  # this folder is on the path when run as a script
from visible_beside import stored

from brain_fe.io import write_json_atomic
from brain_fe.parallel import SharedCounter, dynamic_items
from diagnosis.effects import BASE_NAMES, library, parameter_names
from diagnosis.engine import _base, _noise_of
from diagnosis.fitting import fit
from diagnosis.open_world import misfit_left
from diagnosis.selection import Context, Union, chi2_needed
from simulators.fe import FESimulator

ALPHA, BIC_MARGIN = 1e-3, 10.0  # the diagnosis's defaults (diagnosis.engine.diagnose)


def _load(src: Path, results: Path, name: str):
    lab, obs = _case(src, name)
    return lab, obs, read_json(results / f"{name}_result.json")


def missed_one(lab: dict, res: dict) -> bool:
    """A single or pair case whose verdict named all of the truth but one effect (the
    diagnosis adds one effect per round, so the oracle tests that one)."""
    named, truth = set(res.get("effects", [])), set(lab["effects"])
    return (lab["kind"] in ("single", "pair") and "error" not in res and named < truth
            and len(truth - named) == 1)


def missed_subsets(src: Path, results: Path) -> list[str]:
    """The stored cases of :func:`missed_one`."""
    out = []
    for p in sorted(results.glob("*_result.json")):
        name = p.name.removesuffix("_result.json")
        lab = read_json(src / "labels" / f"{name}.json")
        if missed_one(lab, read_json(p)):
            out.append(name)
    return out


def missed_outside(src: Path, results: Path) -> list[str]:
    """Outside effects whose verdict says ``explained``."""
    return [p.name.removesuffix("_result.json") for p in sorted(results.glob("*_result.json"))
            if read_json(src / "labels" / p.name.replace("_result", ""))
            ["kind"] == "outside" and read_json(p).get("status") == "explained"]


def outside_oracle(src: Path, name: str, res: dict, n: int) -> dict:
    lab, spec, truth, times = stored(src, name)
    named = tuple(res["effects"])
    r = misfit_left(spec, truth, times, lab["noise_sd"], {}, beside=named,
                    start=res["refit_parameters"])
    left = n * r**2
    need = chi2_needed(1, 1, n, ALPHA, BIC_MARGIN)  # the most favourable test: one parameter
    return {"named": "+".join(sorted(named)), "truth": lab["effects"][0],
            "rms_left_over_noise": r, "chi2_left": left, "needed_by_one_parameter": need,
            "ratio": left / need, "detectable": bool(left >= need)}


def oracle(lab: dict, obs, res: dict) -> dict:
    spec = lab["specimen"]
    sim = FESimulator(obs, spec["radius_mm"], spec["height_mm"], refinement=1)
    fine = FESimulator(obs, spec["radius_mm"], spec["height_mm"], refinement=2)
    lib = library(sim.kind)
    base, weights, _, _ = _base(sim, fine, obs, None)
    named, truth = list(res.get("effects", [])), list(lab["effects"])

    def run(effects, start):
        return fit(sim, obs, weights, start, parameter_names(lib, effects), effect="+".join(effects)
                   or "base", max_nfev=40, effect_def=Union(lib, effects) if effects else None)

    start_named = {**base.values, **res["refit_parameters"]}
    f_named = run(named, start_named) if named else base
    start_truth = {**base.values, **{k: v for k, v in lab["truth"].items()
                                     if k in {str(n) for n in parameter_names(lib, truth)}}}
    f_truth = run(truth, start_truth)
    if f_named.chi2 < f_truth.chi2:  # the named model's optimum is the better start
        f_truth = min(f_truth, run(truth, {**start_truth, **f_named.values}),
                      key=lambda f: f.chi2)
    noise = _noise_of(obs, f_truth, None)
    ctx = Context(sim, obs, weights, lib, list(BASE_NAMES), ALPHA, BIC_MARGIN, 40, None)
    k = len(parameter_names(lib, truth)) - len(parameter_names(lib, named))
    m = len(lib) - len(named)  # the round's candidates
    lrt = ctx.chi2(noise, f_named) - ctx.chi2(noise, f_truth)
    need = ctx.needed(k, m)
    return {"named": "+".join(sorted(named)) or "none", "truth": "+".join(sorted(truth)),
            "extra_parameters": k, "lrt": lrt, "needed": need, "ratio": lrt / need,
            "detectable": bool(lrt >= need),
            "oracle_parameters": {str(p): float(v) for p, v in f_truth.values.items()},
            "true_parameters": lab["truth"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--benchmark", required=True, help="folder of an open-world benchmark")
    ap.add_argument("--results", required=True, help="folder of the verdicts to test")
    ap.add_argument("--out", required=True, help="JSON file of the oracle tests")
    ap.add_argument("cases", nargs="*")
    a = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    comm = MPI.COMM_WORLD
    src, results = Path(a.benchmark), Path(a.results)
    names = a.cases or missed_subsets(src, results) + missed_outside(src, results)
    counter = SharedCounter(comm)
    mine = {}
    for name in dynamic_items(names, counter):
        lab, obs, res = _load(src, results, name)
        if lab["kind"] != "outside" and not missed_one(lab, res):
            logging.getLogger("oracle").error("%s: not a case with one effect missed "
                                              "(truth %s, named %s): skipped", name,
                                              lab["effects"], res.get("effects"))
            continue
        try:
            mine[name] = _one(src, name, lab, obs, res)
        except (RuntimeError, ValueError) as exc:  # this case, not the others' allgather
            logging.getLogger("oracle").error("%s: %s", name, exc)
    counter.free()
    every = {k: v for part in comm.allgather(mine) for k, v in part.items()}
    if comm.rank == 0:
        names = [n for n in names if n in every]
        write_json_atomic(Path(a.out), {"cases": {n: every[n] for n in names},
                                        "undetectable": sum(not every[n]["detectable"]
                                                            for n in names),
                                        "of": len(names)}, indent=1, default=str)


def _one(src: Path, name: str, lab: dict, obs, res: dict) -> dict:
    """The oracle test of one case (outside effect or one missed library effect)."""
    log = logging.getLogger("oracle")
    if lab["kind"] == "outside":
        r = outside_oracle(src, name, res, len(obs))
        log.warning("%s: named %s, truth %s (outside): left %.1f of %.1f needed (%.2f)", name,
                    r["named"], r["truth"], r["chi2_left"], r["needed_by_one_parameter"],
                    r["ratio"])
        return r
    r = oracle(lab, obs, res)
    log.warning("%s: named %s, truth %s: LRT %.1f of %.1f needed (%.2f)", name, r["named"],
                r["truth"], r["lrt"], r["needed"], r["ratio"])
    return r


if __name__ == "__main__":
    run_script(main)
