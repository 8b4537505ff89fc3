"""Two runs of the open-world benchmark side by side, on the cases both scored.

    .venv/bin/python benchmarks/compare_open_runs.py OLD/summary.json NEW/summary.json

The cases of ``brainmech benchmark-diagnosis --world open`` depend only on (seed, index),
so two runs with the same seed hold the same recordings and differ only by the engine
that diagnosed them (or, with the same engine, by the machine: rounding).  Prints, per
kind of case, how many each run got right, every case whose verdict, status, *cannot
tell* or correctness changed, and how closely the numbers agree (relative differences of
the RMS before and after modelling and of the generator's calibration misfit: median,
largest and where), and the ratio of the per-case diagnosis times (new / old): its median
and spread over all cases, over the first, middle and last third of the run's order and
over the shorter and longer half of the cases.  A slowdown of the host (or of another job
sharing it) moves every case alike; a cache that is cold at the start of a run slows the
first cases; an engine that does more in some cases slows those.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from _machine import read_json, run_script


def by_case(path: Path) -> dict:
    return {c["case"]: c for c in read_json(path)["by_case"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    a = ap.parse_args()
    old, new = by_case(a.old), by_case(a.new)
    both = sorted(set(old) & set(new))
    kinds: dict = {}
    changed = ["| case | kind | right answer | old verdict (status) | new verdict (status) |",
               "|---|---|---|---|---|"]  # ", cannot tell" after a status that carried it
    for c in both:
        o, n = old[c], new[c]
        k = kinds.setdefault(n["kind"], [0, 0, 0])
        k[0] += 1
        k[1] += bool(o["correct"])
        k[2] += bool(n["correct"])
        if any(o.get(f) != n.get(f) for f in ("correct", "verdict", "status", "cannot_tell")):
            changed.append(f"| {c} | {n['kind']} | {n['expected']} | {_said(o)} | "
                           f"{_said(n)} |")
    print(f"{len(both)} cases in both runs\n")
    print("| kind | cases | right, old | right, new |\n|---|---|---|---|")
    for kind, (n, r_old, r_new) in kinds.items():
        print(f"| {kind} | {n} | {r_old} | {r_new} |")
    print("\n" + "\n".join(changed))
    print("\n" + "\n".join(agreement(old, new, both)))
    print("\n" + "\n".join(timing(old, new, both)))


def _said(case: dict) -> str:
    """A run's answer on one case: the verdict, its status and whether it said *cannot
    tell*, so that a row whose only change is the doubt shows it."""
    doubt = ", cannot tell" if case.get("cannot_tell") else ""
    return f"{case['verdict']} ({case['status']}{doubt})"


NUMBERS = ("rms_before", "rms_after", "misfit")


def agreement(old: dict, new: dict, cases: list) -> list[str]:
    """Markdown rows: per number of :data:`NUMBERS`, the relative differences between the
    runs over ``cases`` (0 where both are equal, including both zero)."""
    rows = ["| number | cases | equal | median rel. difference | largest (case) |",
            "|---|---|---|---|---|"]
    for key in NUMBERS:
        diffs = []
        for c in cases:
            a, b = old[c].get(key), new[c].get(key)
            if isinstance(a, (int, float)) and isinstance(b, (int, float)):
                diffs.append((0.0 if a == b else abs(b - a) / max(abs(a), abs(b)), c))
        if not diffs:
            continue
        diffs.sort()
        rows.append(f"| {key} | {len(diffs)} | {sum(d == 0.0 for d, _ in diffs)} | "
                    f"{statistics.median(d for d, _ in diffs):.1e} | "
                    f"{diffs[-1][0]:.1e} ({diffs[-1][1]}) |")
    return rows


def timing(old: dict, new: dict, cases: list) -> list[str]:
    """Markdown rows: the per-case diagnosis time ratio new / old (``elapsed_s``) over
    ``cases`` in the run's order (case names sort in it), and over its parts."""
    pairs = [(c, old[c].get("elapsed_s"), new[c].get("elapsed_s")) for c in cases]
    pairs = [(c, a, b) for c, a, b in pairs if a and b]
    if not pairs:
        return []
    third = max(len(pairs) // 3, 1)
    by_length = sorted(pairs, key=lambda p: p[1])
    half = len(by_length) // 2
    parts = [("all cases", pairs), ("first third of the run", pairs[:third]),
             ("middle third", pairs[third:-third]), ("last third", pairs[-third:]),
             ("shorter half (old time)", by_length[:half]),
             ("longer half (old time)", by_length[half:])]
    rows = ["| diagnosis time, new / old | cases | median | 10-90 % | sum new / sum old |",
            "|---|---|---|---|---|"]
    for name, part in parts:
        if not part:
            continue
        q = [b / a for _, a, b in part]
        lo, *_, hi = statistics.quantiles(q, n=10, method="inclusive") if len(q) > 1 else q * 2
        rows.append(f"| {name} | {len(q)} | {statistics.median(q):.2f} | {lo:.2f}-{hi:.2f} | "
                    f"{sum(b for *_, b in part) / sum(a for _, a, _ in part):.2f} |")
    return rows


if __name__ == "__main__":
    run_script(main)
