"""Side-by-side timings of this working tree against another checkout (an earlier commit).

    git worktree add /tmp/old <commit>
    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/compare_trees.py --old /tmp/old \\
        [--repeats 5] [--diagnosis-repeats 3] [--ranks 2] [--out FILE.json]

Both trees run the same workloads in fresh subprocesses with the same interpreter and JIT
cache, alternating old/new in every repeat, so machine load affects both alike:

* ``forward``: the default protocol set (compression/tension 0.15, torsion 0.15 and 0.30,
  loading and unloading) on the axisymmetric k = 2 model, timed inside the process after a
  warm-up run (solve time only);
* ``forward_sens``: the same with every parameter's sensitivities;
* ``diagnose``: ``brainmech diagnose`` of one synthetic specimen (full protocol, two
  cycles, a concealed viscoelastic effect) under ``mpirun -n RANKS``, wall time of the
  whole command.

Prints a Markdown table (medians, ratio new/old) and writes ``--out`` (default
``benchmarks/results/compare_trees.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import read_json, run_script

HERE = Path(__file__).resolve().parent
NEW = HERE.parent

FORWARD = r"""
import json, time, sys
from brain_fe import geometry
from brain_fe.model import ForwardModel, MaterialParameters  # both trees
from brain_fe.protocols import compression_tension, torsion
sens = sys.argv[1] == "1"
m = ForwardModel(geometry.axisymmetric(refinement=2))
p = MaterialParameters(mu=(1.0,), alpha=(-20.0,), nu0=0.49)
prots = [compression_tension(0.15), torsion(0.15), torsion(0.30)]
for pr in prots:
    m.run(pr, p, sensitivities=sens)
t0 = time.perf_counter()
for pr in prots:
    m.run(pr, p, sensitivities=sens)
print(json.dumps({"s": time.perf_counter() - t0}))
"""

SPECIMEN = r"""
import sys
import numpy as np
from mpi4py import MPI
from brain_fe import geometry
from diagnosis.benchmark import full_protocols, make_case
rng = np.random.default_rng(11)
rec, spec, case = make_case(1, "viscoelastic", rng, refinement=1, truth_refinement=3,
                            protocols=full_protocols(2, 0.03), models={})
rec.to_csv(sys.argv[1] + "/rec.csv", index=False)
spec.to_csv(sys.argv[1] + "/spec.csv", index=False)
print(case)
"""


STAGES: dict = {}  # tree -> the diagnosis's own stage timings of every run (new trees)


def _env(tree: Path) -> dict:
    env = dict(os.environ)
    env.update(PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", PYTHONDONTWRITEBYTECODE="1")
    return env


def _cli_module(tree: Path) -> str:
    return "brainmech" if (tree / "brainmech").is_dir() else "brain_fe.cli"


def forward(tree: Path, sens: bool) -> float:
    out = subprocess.run([sys.executable, "-c", FORWARD, "1" if sens else "0"],
                         env=_env(tree), capture_output=True, text=True, check=True,
                         cwd=tree)
    return json.loads(out.stdout.strip().splitlines()[-1])["s"]


def diagnose(tree: Path, data: Path, ranks: int) -> float:
    out = Path(tempfile.mkdtemp(prefix="diag-"))
    cmd = ["mpirun", "-n", str(ranks), sys.executable, "-m", _cli_module(tree), "diagnose",
           "--recordings", str(data / "rec.csv"), "--specimens", str(data / "spec.csv"),
           "--out", str(out / "d")]
    t0 = time.perf_counter()
    subprocess.run(cmd, env=_env(tree), capture_output=True, text=True, check=True, cwd=tree)
    wall = time.perf_counter() - t0
    res = read_json(out / "d" / "diagnosis.json")
    STAGES.setdefault(str(tree), []).append(res.get("timings_s"))  # where the time went
    return wall, res["verdict"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, type=Path)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--diagnosis-repeats", type=int, default=3)
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--skip", default="", help="comma list of workloads to skip")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "compare_trees.json",
                    help="where the times, verdicts and stage timings go (JSON)")
    a = ap.parse_args()
    skip = set(filter(None, a.skip.split(",")))
    trees = {"old": a.old.resolve(), "new": NEW}
    times: dict = {k: {"old": [], "new": []} for k in ("forward", "forward_sens", "diagnose")}
    verdicts = {"old": [], "new": []}
    for _ in range(a.repeats):
        for label, tree in trees.items():
            if "forward" not in skip:
                times["forward"][label].append(forward(tree, False))
            if "forward_sens" not in skip:
                times["forward_sens"][label].append(forward(tree, True))
    if "diagnose" not in skip:
        data = Path(tempfile.mkdtemp(prefix="spec-"))
        subprocess.run([sys.executable, "-c", SPECIMEN, str(data)], env=_env(NEW),
                       check=True, capture_output=True, cwd=NEW)
        diagnose(NEW, data, a.ranks)  # warm the JIT cache of every candidate's forms
        diagnose(trees["old"], data, a.ranks)
        for _ in range(a.diagnosis_repeats):
            for label, tree in trees.items():
                wall, verdict = diagnose(tree, data, a.ranks)
                times["diagnose"][label].append(wall)
                verdicts[label].append(verdict)
    rows = ["| workload | old median [s] | new median [s] | new / old | runs |",
            "|---|---|---|---|---|"]
    for k, d in times.items():
        if d["old"]:
            mo, mn = statistics.median(d["old"]), statistics.median(d["new"])
            rows.append(f"| {k} | {mo:.2f} | {mn:.2f} | {mn / mo:.2f} | {len(d['old'])} |")
    print("\n".join(rows))
    if verdicts["old"]:
        print(f"verdicts: old {verdicts['old']}, new {verdicts['new']}")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(
        {"old": str(a.old), "times": times, "verdicts": verdicts, "stages": STAGES},
        indent=1))


if __name__ == "__main__":
    run_script(main)
