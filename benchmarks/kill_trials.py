"""``kill -9`` at random moments of ``brainmech sample`` and of a batch ``brainmech diagnose``:
nothing lost, nothing duplicated, at most one unit of work (per rank) repeated.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/kill_trials.py [--trials 10]
        [--ranks 2] [--seed 0] [--only sample|diagnose]

Each trial starts the command (under ``mpirun -n RANKS``) on a fresh output, kills the whole
process group with SIGKILL at a random moment (uniform over the duration of an
uninterrupted run, start-up included), then runs the same command again to completion and
checks the output against a reference run that was never interrupted:

* ``sample`` (n = 16, refinement 1): every (sample, test) stored exactly once, the values
  equal the reference store bit for bit, and the second run computed at most as many
  samples as the first had not finished plus one per rank;
* ``diagnose`` (6 synthetic specimens, 1 cycle): every specimen's ``diagnosis.json``
  present once with the reference verdict, and the second run diagnosed only the specimens
  without a result (at most one per rank was in progress when killed).

Prints one line per trial and a summary; writes ``benchmarks/results/kill_trials.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _machine import read_json, run_script

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def _env() -> dict:
    env = dict(os.environ)
    env.update(OPENBLAS_NUM_THREADS="1", OMPI_ALLOW_RUN_AS_ROOT="1",
               OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMPI_MCA_rmaps_base_oversubscribe="1",
               PYTHONDONTWRITEBYTECODE="1")
    return env


def _cmd(ranks: int, args: list[str]) -> list[str]:
    return ["mpirun", "-n", str(ranks), sys.executable, "-m", "brainmech", *args]


def _run(cmd) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, env=_env(), capture_output=True, text=True, cwd=ROOT)


def _session(sid: int) -> list[int]:
    """Pids of the processes of session ``sid`` (mpirun puts each rank in a process group
    of its own, but in mpirun's session)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[3]) == sid and fields[0] != "Z":  # zombies are dead already
                out.append(int(d.name))
    return out


def _kill_session(sid: int) -> None:
    """SIGKILL every process of the session and wait until none is left."""
    for _ in range(500):
        pids = _session(sid)
        if not pids:
            return
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.02)
    raise RuntimeError(f"processes of session {sid} survive SIGKILL")


def _kill_at(cmd, delay: float) -> bool:
    """Start ``cmd`` in a session of its own and SIGKILL every process of it (mpirun and
    all ranks) ``delay`` s later. True when the kill landed before the run ended."""
    p = subprocess.Popen(cmd, env=_env(), cwd=ROOT, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        end = time.monotonic() + delay
        while time.monotonic() < end:
            if p.poll() is not None:
                return False
            time.sleep(0.01)
        _kill_session(p.pid)
        return True
    finally:
        _kill_session(p.pid)
        p.wait()


# ------------------------------------------------------------------------------ sample
def sample_trials(trials: int, ranks: int, rng: random.Random, work: Path) -> list[dict]:
    from brain_fe import store

    n = 16
    args = ["sample", "--n", str(n), "--seed", "3", "--refinement", "1",
            "--tests", "compression_tension,torsion:0.30"]
    ref = work / "sample-ref"
    t0 = time.perf_counter()
    r = _run(_cmd(ranks, args + ["--out", str(ref)]))
    assert r.returncode == 0, r.stderr
    duration = time.perf_counter() - t0
    reference = store.load_samples(ref)
    out = []
    for k in range(trials):
        d = work / f"sample-{k}"
        delay = rng.uniform(0.0, duration)
        killed = _kill_at(_cmd(ranks, args + ["--out", str(d)]), delay)
        before = store.summarize(d).done if (d / "manifest.json").exists() else 0
        r = _run(_cmd(ranks, args + ["--out", str(d)]))
        assert r.returncode == 0, r.stderr
        computed = int(r.stdout.split("computed ")[1].split(" ")[0])
        raw = store.read_chunks(d, with_file=True)
        copies = raw.groupby(["sample", "test"]).chunk.nunique()
        df = store.load_samples(d)
        same = df.drop(columns="wall_time_s").equals(reference.drop(columns="wall_time_s"))
        res = {"trial": k, "killed": killed, "delay_s": round(delay, 2),
               "stored_before": before, "computed_after": computed,
               "repeated": before + computed - n, "all_once": bool((copies == 1).all())
               and len(copies) == 2 * n, "identical": bool(same)}
        res["ok"] = res["all_once"] and res["identical"] and res["repeated"] <= ranks
        out.append(res)
        print("sample", res, flush=True)
        shutil.rmtree(d)
    return out


# ------------------------------------------------------------------------------ diagnose
def _diagnosis_data(work: Path, n: int) -> tuple[Path, Path]:
    script = f"""
import numpy as np, pandas as pd
from diagnosis.benchmark import full_protocols, make_case
rng = np.random.default_rng(5)
recs, specs = [], []
for i in range({n}):
    effect = ["none", "viscoelastic", "artefacts"][i % 3]
    rec, spec, case = make_case(i, effect, rng, refinement=1, truth_refinement=2,
                                protocols=full_protocols(1, 0.05), models={{}})
    recs.append(rec); specs.append(spec)
pd.concat(recs).to_csv("{work}/rec.csv", index=False)
pd.concat(specs).to_csv("{work}/spec.csv", index=False)
"""
    subprocess.run([sys.executable, "-c", script], env=_env(), cwd=ROOT, check=True,
                   capture_output=True)
    return work / "rec.csv", work / "spec.csv"


def _verdicts(d: Path) -> dict:
    out = {}
    for p in sorted(d.glob("*/diagnosis.json")):
        out[p.parent.name] = read_json(p)["verdict"]
    return out


def diagnose_trials(trials: int, ranks: int, rng: random.Random, work: Path) -> list[dict]:
    n = 6
    rec, spec = _diagnosis_data(work, n)
    args = ["diagnose", "--recordings", str(rec), "--specimens", str(spec)]
    ref = work / "diag-ref"
    t0 = time.perf_counter()
    r = _run(_cmd(ranks, args + ["--out", str(ref)]))
    assert r.returncode == 0, r.stderr
    duration = time.perf_counter() - t0
    reference = _verdicts(ref)
    out = []
    for k in range(trials):
        d = work / f"diag-{k}"
        delay = rng.uniform(0.0, duration)
        killed = _kill_at(_cmd(ranks, args + ["--out", str(d)]), delay)
        before = len(_verdicts(d))
        r = _run(_cmd(ranks, args + ["--out", str(d)]))
        assert r.returncode == 0, r.stderr
        done_now = r.stdout.count("diagnosed in this run")
        verdicts = _verdicts(d)
        res = {"trial": k, "killed": killed, "delay_s": round(delay, 2),
               "done_before": before, "diagnosed_after": done_now,
               "repeated": before + done_now - n, "complete": len(verdicts) == n,
               "same_verdicts": verdicts == reference}
        res["ok"] = res["complete"] and res["same_verdicts"] and res["repeated"] <= ranks
        out.append(res)
        print("diagnose", res, flush=True)
        shutil.rmtree(d)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", choices=["sample", "diagnose"], default=None)
    a = ap.parse_args()
    rng = random.Random(a.seed)
    work = Path(tempfile.mkdtemp(prefix="kill-"))
    results = {}
    if a.only in (None, "sample"):
        results["sample"] = sample_trials(a.trials, a.ranks, rng, work)
    if a.only in (None, "diagnose"):
        results["diagnose"] = diagnose_trials(a.trials, a.ranks, rng, work)
    for k, rows in results.items():
        print(f"{k}: {sum(r['ok'] for r in rows)}/{len(rows)} trials ok, "
              f"{sum(r['killed'] for r in rows)} killed mid-run, max repeated "
              f"{max(r['repeated'] for r in rows)}")
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "kill_trials.json").write_text(json.dumps(results, indent=1))
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    run_script(main)
