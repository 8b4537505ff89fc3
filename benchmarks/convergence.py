"""Mesh convergence of the reported forces (axisymmetric model, glued ends).

Quantities: nominal stress at stretch 0.85 and 1.15, torque and axial force at shear 0.30
(mu = 1 kPa, alpha = -20, nu0 = 0.49, R = 4 mm, H = 5 mm). For each quantity the observed
order p comes from the three finest levels (k, 2k, 4k... refinement doubles), the limit
from Richardson extrapolation, and the error of every level relative to that limit.

    .venv/bin/python benchmarks/convergence.py [--levels 1,2,3,4,6,8,12,16] [--out DIR]

Writes DIR/convergence.csv, DIR/convergence.md and DIR/convergence.png.
"""

from __future__ import annotations

import argparse
import logging
import os
import time

import numpy as np
import pandas as pd
from _machine import run_script

from brain_fe import geometry
from brain_fe.materials import MaterialParameters
from brain_fe.model import ForwardModel
from brain_fe.protocols import Protocol

QUANTITIES = {
    "P(0.85) kPa": ("compression_tension", (1.0, 0.85), "nominal_stress_kPa"),
    "P(1.15) kPa": ("compression_tension", (1.0, 1.15), "nominal_stress_kPa"),
    "T(0.30) mN mm": ("torsion", (0.0, 0.30), "torque_mNmm"),
    "Fz(0.30) mN": ("torsion", (0.0, 0.30), "axial_force_mN"),
}


def measure(levels):
    params = MaterialParameters(mu=(1.0,), alpha=(-20.0,), nu0=0.49)
    rows = []
    for k in levels:
        m = ForwardModel(geometry.axisymmetric(refinement=k))
        t0 = time.perf_counter()
        row = {"k": k, "dofs": m.V.dofmap.index_map.size_global * 3}
        for name, (test, wp, col) in QUANTITIES.items():
            df = m.run(Protocol(test, wp, max_increment=0.05), params)
            row[name] = float(df[col].iloc[-1])
        row["solve_s"] = time.perf_counter() - t0
        rows.append(row)
        logging.info("k=%d done", k)
    return pd.DataFrame(rows)


def richardson(df):
    """Observed order from levels (k, 2k, 4k) at the fine end; limit and errors."""
    ks = list(df.k)
    fine = max(k for k in ks if k % 4 == 0 and k // 4 in ks and k // 2 in ks)
    out = {}
    for name in QUANTITIES:
        f1, f2, f4 = (df.set_index("k").loc[k, name] for k in (fine // 4, fine // 2, fine))
        p = np.log2(abs(f2 - f1) / abs(f4 - f2))
        lim = f4 + (f4 - f2) / (2**p - 1)
        out[name] = (p, lim)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--levels", default="1,2,3,4,6,8,12,16")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    for noisy in ("ffcx", "UFL", "root"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    os.makedirs(a.out, exist_ok=True)
    df = measure([int(x) for x in a.levels.split(",")])
    rr = richardson(df)
    for name, (_, lim) in rr.items():
        df[f"err {name}"] = (df[name] - lim) / abs(lim)
    df.to_csv(os.path.join(a.out, "convergence.csv"), index=False)

    lines = ["| quantity | observed order | Richardson limit | error at k=1 | k=2 (default) "
             "| k=4 |", "|---|---|---|---|---|---|"]
    e = df.set_index("k")
    for name, (p, lim) in rr.items():
        lines.append(f"| {name} | {p:.2f} | {lim:.6g} | {100 * e.loc[1, 'err ' + name]:+.3f} % "
                     f"| {100 * e.loc[2, 'err ' + name]:+.3f} % "
                     f"| {100 * e.loc[4, 'err ' + name]:+.3f} % |")
    lines += ["", "| k | dofs | solve time of the four single-branch runs (s) |", "|---|---|---|"]
    lines += [f"| {r.k} | {r.dofs} | {r.solve_s:.2f} |" for r in df.itertuples()]
    with open(os.path.join(a.out, "convergence.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2))
    for name, (p, _) in rr.items():
        ax.loglog(df.dofs, np.abs(df[f"err {name}"]), "o-", label=f"{name} (order {p:.2f} in k)")
    ax.axhline(1e-2, color="k", lw=0.8, ls="--")
    ax.text(df.dofs.min(), 1.1e-2, "1 % target", fontsize=8)
    ax.set_xlabel("degrees of freedom (axisymmetric, Q2)")
    ax.set_ylabel("|relative error| vs Richardson limit")
    ax.set_title("Mesh convergence, glued ends (default k = 2)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "convergence.png"), dpi=120)
    logging.info("wrote %s", a.out)


if __name__ == "__main__":
    run_script(main)
