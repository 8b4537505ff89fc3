"""The outside cases of each measured draw, split by what a library can mimic: a figure.

Reads the files ``benchmarks/mimicked_outside.py --summary`` writes (one per draw,
``seed<N>.json``) and draws, per draw and per bar it holds (white noise or the rig's whole
noise; one library effect, or pairs as well), the outside cases as a stacked bar: those a
library effect or pair mimics (out of any diagnosis's reach), those it does not that the
diagnosis answered `unexplained`, and its misses.  The line marks the issue's goal (90 %
of the outside cases).

    .venv/bin/python benchmarks/outside_ceiling_figure.py \\
        benchmarks/results/open_world/mimicked-outside/seed*.json \\
        --out benchmarks/results/open_world/mimicked-outside/ceiling.png
"""

from __future__ import annotations

import argparse
import logging
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from _machine import read_json, run_script  # noqa: E402

from brain_fe.io import write_figure_atomic  # noqa: E402

BARS = (("score", "white, one effect"),
        ("score_under_rig_noise", "rig's noise, one effect"),
        ("score_with_pairs", "white, with pairs"),
        ("score_with_pairs_under_rig_noise", "rig's noise, with pairs"))
GOAL = 0.9


def bars(files: list[Path]) -> list[dict]:
    """One row per (draw, bar) that a file holds: its label and the three counts."""
    rows = []
    for f in sorted(files, key=lambda p: int(re.sub(r"\D", "", p.stem) or 0)):
        d = read_json(f)
        for key, what in BARS:
            s = d.get(key)
            if not s:
                continue
            rows.append({"draw": f.stem, "bar": what, "mimicked": len(s["mimicked"]),
                         "right": s["not_mimicked_correct"],
                         "missed": s["not_mimicked"] - s["not_mimicked_correct"],
                         "cases": s["measured"]})
    return rows


def draw(rows: list[dict], out: Path) -> None:
    if not rows:
        raise ValueError("no bar to draw: the files hold no score (run mimicked_outside.py "
                         "with --summary)")
    fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(rows) + 4.0), 4.4))
    x = range(len(rows))
    m = [r["mimicked"] for r in rows]
    ok = [r["right"] for r in rows]
    miss = [r["missed"] for r in rows]
    ax.bar(x, m, color="0.7", label="a library effect or pair mimics it\n(no test can show "
           "it is outside)")
    ax.bar(x, ok, bottom=m, color="tab:green", label="not mimicked, `unexplained`")
    ax.bar(x, miss, bottom=[a + b for a, b in zip(m, ok, strict=True)], color="tab:red",
           label="not mimicked, missed")
    for i, r in enumerate(rows):
        ax.plot([i - 0.4, i + 0.4], [r["cases"] * (1 - GOAL)] * 2, color="k", lw=1)
        free = r["right"] + r["missed"]
        ax.text(i, r["cases"] + 0.2, f"{r['right']}/{free}", ha="center", fontsize=7)
    ax.set_xticks(list(x), [f"{r['draw']}\n{r['bar']}" for r in rows], rotation=60,
                  ha="right", fontsize=7)
    ax.set_ylabel("outside cases")
    ax.set_ylim(0, max(r["cases"] for r in rows) * 1.1)
    ax.set_title("Outside the library: the share out of reach, and the diagnosis's answers\n"
                 "(on top: `unexplained` of those not mimicked; grey above the black line:\n"
                 "the mimicked cases alone deny the goal of 90 %)",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    write_figure_atomic(fig, out, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+", type=Path, help="mimicked_outside.py outputs")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    rows = bars(a.files)
    draw(rows, a.out)
    logging.getLogger("ceiling").info("%d bars drawn to %s", len(rows), a.out)


if __name__ == "__main__":
    run_script(main)
