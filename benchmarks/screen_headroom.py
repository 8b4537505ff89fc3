"""Could the screen rule out more candidates before fitting them?  Measured on stored runs.

A round fits a candidate only when its score (the Lagrange-multiplier statistic at the
current fit, :mod:`diagnosis.screen`) reaches ``SCREEN_FRACTION`` of the chi-square
reduction it needs (:func:`diagnosis.selection.chi2_needed`).  A higher fraction skips
more fits, and so saves time, but only without changing a decision if no skipped fit is
one the round's decision uses: a *significant* fit (named, or a near tie beside the one
named) or the round's *best* fit (the lowest chi-square, whose residual gives the round's
noise model).  For every fitted candidate of the stored diagnoses this prints its score
over what it needs and its likelihood-ratio statistic over its score, and for each
fraction the fits it would skip, how many of them the decision used and the share of the
fitting time they took.  Reads ``*_result.json`` and the ``*_recordings.csv`` beside them
(a benchmark's ``cases/``); runs nothing.

    .venv/bin/python benchmarks/screen_headroom.py open/cases bench/cases [--out FILE.json]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import pandas as pd
from _machine import read_json, run_script

from brain_fe.io import write_json_atomic
from diagnosis.selection import SCREEN_FRACTION, chi2_needed

FRACTIONS = (SCREEN_FRACTION, 0.3, 0.35, 0.4, 0.5, 0.75, 1.0)


def fits(folder: Path) -> list[dict]:
    """One row per fitted candidate of every round of every diagnosis in ``folder``."""
    rows = []
    for res in sorted(folder.glob("*_result.json")):
        d = read_json(res)
        n = len(pd.read_csv(res.with_name(res.name.replace("_result.json",
                                                           "_recordings.csv"))))
        timing = d.get("timings_s", {}).get("rounds", [])
        for i, rnd in enumerate(d.get("rounds", [])):
            fitted = [r for r in rnd["table"] if not math.isnan(r["lrt"])]
            if not fitted:
                continue
            best = min(fitted, key=lambda r: r["chi2"])
            per = timing[i].get("fit_per_candidate", {}) if i < len(timing) else {}
            for r in fitted:
                k, m = len(r["parameters"]), len(rnd["table"])
                rows.append({"case": res.name.removesuffix("_result.json"), "round": i,
                             "effect": r["effect"], "score": r["score"], "lrt": r["lrt"],
                             "over_needed": r["score"] / chi2_needed(k, m, n),
                             "lrt_over_score": r["lrt"] / r["score"],
                             "significant": r["significant"], "best": r is best,
                             "seconds": per.get(r["effect"], {}).get("s", float("nan"))})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    df = pd.DataFrame([r for f in args.folders for r in fits(f)])
    used = df.significant | df.best
    total = df.seconds.sum()
    table = []
    for fr in FRACTIONS:
        skip = df.over_needed < fr
        table.append({"fraction": fr, "skipped": int(skip.sum()),
                      "skipped_significant": int((skip & df.significant).sum()),
                      "skipped_best": int((skip & df.best & ~df.significant).sum()),
                      "fit_time_share": float(df.seconds[skip].sum() / total)})
    sig = df[df.significant]
    out = {"diagnoses": int(df.case.nunique()), "fits": len(df),
           "used_by_the_decision": int(used.sum()),
           "lowest_over_needed_used": df[used].nsmallest(5, "over_needed").to_dict("records"),
           "highest_lrt_over_score_significant":
               sig.nlargest(5, "lrt_over_score").to_dict("records"),
           "fractions": table}
    print(f"{out['diagnoses']} diagnoses, {len(df)} fits, {out['used_by_the_decision']} "
          "used by a decision (significant or the round's best)\n")
    print("| fraction of what it needs | fits skipped | of them significant | of them the "
          "round's best | share of the fitting time |\n|---|---|---|---|---|")
    for t in table:
        print(f"| {t['fraction']:.2f} | {t['skipped']} | {t['skipped_significant']} | "
              f"{t['skipped_best']} | {100 * t['fit_time_share']:.0f} % |")
    cols = ["case", "round", "effect", "score", "lrt", "over_needed", "significant", "best"]
    print("\nused fits with the lowest score over what they need:\n"
          + df[used].nsmallest(5, "over_needed")[cols].to_string(index=False))
    print("\nsignificant fits with the highest LRT over score:\n"
          + sig.nlargest(5, "lrt_over_score")[cols + ["lrt_over_score"]]
          .to_string(index=False))
    if args.out:
        write_json_atomic(args.out, out)


if __name__ == "__main__":
    run_script(main)
