"""Is a diagnosis determined by the recordings?  Change their last digits and look.

``perturb``: a copy of a recordings table (CSV) whose measured numbers are each multiplied
by ``1 + 4e-16 g`` (g standard normal, seeded): one to two units in the last place of a
double, far below any instrument's resolution.  The protocol columns (specimen, test,
amplitude, cycle, branch) and columns holding only integers (flags such as
``in_contact``) are left alone; every number is written exactly (``repr``).

``compare``: two ``brainmech diagnose`` output folders of the same specimens, side by side:
verdict, status, RMS before and after, and the largest relative change of a base
parameter; a markdown table of the specimens that differ and the counts.

A verdict that moves when only the last digits do is not a property of the data: the
likelihood has two (near-)equal optima, and which one a fit ends in is a matter of
rounding.  docs/real-data.md reports the measurement on the rheometer exports::

    python benchmarks/last_digits.py perturb rheo/recordings.csv ulp/recordings.csv
    brainmech diagnose --recordings rheo/recordings.csv ... --out exact
    brainmech diagnose --recordings ulp/recordings.csv ... --out ulp
    python benchmarks/last_digits.py compare exact ulp
"""

from __future__ import annotations

import argparse
import csv
import random
import sys
from pathlib import Path

from _machine import read_json, run_script

from diagnosis.determinacy import RELATIVE_SD  # the size `diagnose --check-digits` uses

PROTOCOL = ("specimen", "test", "amplitude", "cycle", "branch")


def _is_int(cell: str) -> bool:
    try:
        return float(cell).is_integer()
    except ValueError:
        return False


def perturb(src: Path, dst: Path, seed: int = 1) -> int:
    """Write the perturbed copy; returns the number of cells changed."""
    rows = list(csv.reader(src.open(newline="", encoding="utf-8-sig")))
    header, body = rows[0], rows[1:]
    flags = {h for j, h in enumerate(header)
             if all(_is_int(r[j]) for r in body if r[j])}
    keep = set(PROTOCOL) | flags
    rng = random.Random(seed)
    changed = 0
    with dst.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(header)
        for r in body:
            out = []
            for h, cell in zip(header, r, strict=True):
                if h not in keep and cell:
                    x = float(cell)
                    y = x * (1 + RELATIVE_SD * rng.gauss(0, 1))
                    changed += y != x
                    cell = repr(y)
                out.append(cell)
            w.writerow(out)
    return changed


def _load(folder: Path) -> dict:
    return {str(f.parent.relative_to(folder)): read_json(f)
            for f in sorted(folder.glob("**/diagnosis.json")) if f.parent != folder}


def compare(a: Path, b: Path) -> str:
    x, y = _load(a), _load(b)
    names = sorted(set(x) & set(y))
    lines = [f"| specimen | {a.name} | {b.name} | base parameters, largest relative change |",
             "|---|---|---|---|"]
    same_verdict = identical = 0
    for n in names:
        p, q = x[n], y[n]
        same = (p["verdict"], p["status"]) == (q["verdict"], q["status"])
        bit = (p["base_parameters"], p["refit_parameters"]) == (q["base_parameters"],
                                                                q["refit_parameters"])
        same_verdict += same
        identical += bit
        if same and bit:
            continue
        rel = max((abs(p["base_parameters"][k] - v) / max(abs(p["base_parameters"][k]),
                                                             1e-300)
                   for k, v in q["base_parameters"].items() if k in p["base_parameters"]),
                  default=float("nan"))

        def cell(d):
            return (f"{d['verdict']}, {d['status']} ({d['rms_before']:.3g} -> "
                    f"{d['rms_after']:.3g})")
        lines.append(f"| {n} | {cell(p)} | {cell(q)} | {rel:.1e} |")
    return "\n".join(lines + [
        "", f"{len(names)} specimens: the same verdict and status in {same_verdict}, "
        f"bit-identical base and final parameters in {identical}."])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    p = sub.add_parser("perturb")
    p.add_argument("src", type=Path)
    p.add_argument("dst", type=Path)
    p.add_argument("--seed", type=int, default=1)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    if args.what == "perturb":
        n = perturb(args.src, args.dst, args.seed)
        sys.stdout.write(f"{args.dst}: {n} cells changed in their last digits\n")
    else:
        sys.stdout.write(compare(args.a, args.b) + "\n")
    return 0


if __name__ == "__main__":
    run_script(main)
