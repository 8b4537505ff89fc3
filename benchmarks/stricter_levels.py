"""What a stricter significance level for the tests of what remains would do, measured
on stored open-world runs without fitting again.

The status of a diagnosis (``none``/``explained`` against ``partially explained``/
``unexplained``) rests on the tests of :func:`diagnosis.remaining.remaining` on the final
model's residual: the located segments (:func:`diagnosis.locate.locate`, Bonferroni at
``0.01`` over the segments tested) and the repeated misfit, the stiffness trend and the
split (likelihood ratio at the selection's ``ALPHA`` and the BIC margin).  A control
answered ``unexplained`` is a false alarm of these tests; an outside case answered
``explained`` by a library name is a miss of them.  Both levels are scaled here by one
factor, every stored case's final tests are read again at it, and its status and verdict
decided again by the engine's own rule (:func:`diagnosis.engine.decide`) from the stored
RMS misfits.  The fits and the rounds of selection are the stored ones, so this is what
the decision at the end alone would do: a verdict of ``none``/``explained`` cannot change
(a stricter test finds nothing more), and what the stricter level would do to the
selection of effects is not measured.

    .venv/bin/python benchmarks/stricter_levels.py --benchmark run16/ run17/ \\
        --out stricter.md
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
from _machine import read_json, run_script
from rediagnose_open import read_case

from brain_fe.io import write_text_atomic
from diagnosis import locate as loc
from diagnosis.engine import decide
from diagnosis.open_benchmark import KINDS, score
from diagnosis.selection import ALPHA

LOCATE_ALPHA = 0.01  # the level remaining() gives locate(), before Bonferroni
FACTORS = (1.0, 0.3, 0.1, 0.03, 0.01)


def segments_tested(obs) -> int:
    """How many segments :func:`diagnosis.locate.locate` tests on ``obs`` (its Bonferroni
    divisor: it depends on the protocol only)."""
    obs = obs.reset_index(drop=True)
    return int(loc.locate(obs, np.ones(len(obs)), 1.0, sigma_dof=np.inf).attrs["m"])


def at_level(res: dict, m: int, factor: float) -> dict:
    """``res`` (a stored result) with its final status and verdict decided again with
    both levels of the tests of what remains times ``factor`` (``m``: segments tested)."""
    if res["status"] in ("none", "explained"):
        return res
    rem = res["remaining"]
    located = any(s["p_value"] < factor * LOCATE_ALPHA / m for s in rem["located"])
    sig = {k: bool(rem[k]["significant"] and rem[k]["p_value"] < factor * ALPHA)
           for k in ("reproducible", "trend", "split")}
    status, chosen, tried = decide(list(res["effects"]) or list(res["tried"]),
                                   located or any(sig.values()), res["rms_before"],
                                   res["rms_after"], trend=sig["trend"], split=sig["split"],
                                   slow=bool(res.get("slow_relaxation")))
    verdict = ("+".join(sorted(chosen)) if chosen else
               "none" if status == "none" else "unexplained")
    return dict(res, status=status, effects=chosen, tried=tried, verdict=verdict)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--benchmark", type=Path, nargs="+", required=True,
                    help="stored open-world runs (their labels/ and cases/)")
    ap.add_argument("--factors", type=float, nargs="+", default=list(FACTORS),
                    help="factors on both levels (1: the engine's)")
    ap.add_argument("--out", type=Path, required=True, help="the table (Markdown)")
    a = ap.parse_args()
    if any(not 0.0 < f <= 1.0 for f in a.factors):
        raise ValueError("--factors: each must lie in (0, 1]")
    logging.basicConfig(level=logging.WARNING)
    runs = []
    for src in a.benchmark:
        labels, results, m = {}, {}, {}
        rms = {}  # RMS after over the true noise, as the run scored it
        if (src / "summary.json").exists():
            rms = {c["case"]: c["rms_after_over_true_noise"]
                   for c in read_json(src / "summary.json", "by_case")["by_case"]}
        for p in sorted((src / "labels").glob("world*.json")):
            rp = src / "cases" / f"{p.stem}_result.json"
            if rp.exists():
                labels[p.stem], results[p.stem] = read_json(p), read_json(rp)
                results[p.stem]["rms_after_over_true_noise"] = rms.get(p.stem, np.nan)
                if results[p.stem]["status"] not in ("none", "explained"):
                    m[p.stem] = segments_tested(read_case(src, p.stem)[1])
        if not labels:
            raise ValueError(f"{src}: no case has both a label and a result")
        runs.append((src, labels, results, m))
    lines = ["| runs | factor | locate / others | controls, false alarms | singles | pairs "
             "| outside `unexplained` | outside explained by a library name "
             "| explained above 1.2x the true noise | changed |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for f in a.factors:
        tot = {k: [0, 0] for k in KINDS}
        alarms, wrong_names, above, changed = 0, 0, 0, []
        for src, labels, results, m in runs:
            now = {n: at_level(r, m.get(n, 1), f) for n, r in results.items()}
            s = score(labels, now)
            for k in KINDS:
                tot[k][0] += s[k]["correct"]
                tot[k][1] += s[k]["cases"]
            alarms += s["control"]["false_alarms"]
            above += len(s["explained_above_1.2"])
            wrong_names += sum(1 for c in s["by_case"] if c["kind"] == "outside"
                               and c["status"] == "explained")
            changed += [f"{src.name}/{n} {labels[n]['kind']}: {results[n]['verdict']} -> "
                        f"{now[n]['verdict']}" for n in sorted(now)
                        if now[n]["verdict"] != results[n]["verdict"]]
        lines.append(
            f"| {', '.join(src.name for src, *_ in runs)} | {f:g} | "
            f"{f * LOCATE_ALPHA:.2g} / {f * ALPHA:.2g} | {alarms} of {tot['control'][1]} | "
            f"{tot['single'][0]}/{tot['single'][1]} | {tot['pair'][0]}/{tot['pair'][1]} | "
            f"{tot['outside'][0]}/{tot['outside'][1]} | {wrong_names} | {above} | "
            f"{'; '.join(changed) or '-'} |")
    write_text_atomic(a.out, "\n".join(lines) + "\n")
    sys.stdout.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    run_script(main)
