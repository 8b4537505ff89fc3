"""Two runs of the open-world benchmark side by side, on the cases both scored.

    .venv/bin/python benchmarks/compare_open_runs.py OLD/summary.json NEW/summary.json

The cases of ``brainmech benchmark-diagnosis --world open`` depend only on (seed, index),
so two runs with the same seed hold the same recordings and differ only by the engine
that diagnosed them.  Prints, per kind of case, how many each run got right, and every
case whose verdict or correctness changed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def by_case(path: Path) -> dict:
    return {c["case"]: c for c in json.loads(path.read_text())["by_case"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    a = ap.parse_args()
    old, new = by_case(a.old), by_case(a.new)
    both = sorted(set(old) & set(new))
    kinds: dict = {}
    changed = ["| case | kind | right answer | old verdict (status) | new verdict (status) |",
               "|---|---|---|---|---|"]
    for c in both:
        o, n = old[c], new[c]
        k = kinds.setdefault(n["kind"], [0, 0, 0])
        k[0] += 1
        k[1] += bool(o["correct"])
        k[2] += bool(n["correct"])
        if o["correct"] != n["correct"] or o["verdict"] != n["verdict"]:
            changed.append(f"| {c} | {n['kind']} | {n['expected']} | {o['verdict']} "
                           f"({o['status']}) | {n['verdict']} ({n['status']}) |")
    print(f"{len(both)} cases in both runs\n")
    print("| kind | cases | right, old | right, new |\n|---|---|---|---|")
    for kind, (n, r_old, r_new) in kinds.items():
        print(f"| {kind} | {n} | {r_old} | {r_new} |")
    print("\n" + "\n".join(changed))


if __name__ == "__main__":
    main()
