"""Signatures of the physics extensions on the default protocols (docs/physics.md).

One figure per extension, base model (glued, one-term Ogden mu = 1 kPa, alpha = -20,
nu0 = 0.49, quadratic U) against the extension at 2-3 effect sizes, default mesh (k = 2):

* compression/tension A = 0.15, two cycles (history effects show in the second cycle);
* torsion 0.30, two cycles: torque-derived shear stress AND axial (Poynting) force.

Each title carries the discretisation error of the base curves: max |f(k=2) - f(k=4)| /
max |f(k=4)| per channel.  A summary of every curve (peaks, loop work, residual force) is
printed as Markdown and written to ``--json``.

    .venv/bin/python benchmarks/physics_signatures.py [--out docs/figures] [--refinement 2]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _machine import run_script

from brain_fe import geometry  # noqa: E402
from brain_fe.artefacts import Artefacts  # noqa: E402
from brain_fe.ends import Interface  # noqa: E402
from brain_fe.materials import MaterialParameters  # noqa: E402
from brain_fe.model import ForwardModel  # noqa: E402
from brain_fe.protocols import compression_tension, torsion  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
BASE = {"mu": (1.0,), "alpha": (-20.0,), "nu0": 0.49}


def _p(**kw) -> MaterialParameters:
    d = dict(BASE)
    d.update(kw)
    return MaterialParameters(**d)


# name -> (title, [(label, model kwargs, params, artefacts or None, tests)])
# ``tests`` restricts a curve to some protocols (slip ends cannot twist).
BOTH = ("compression_tension", "torsion")
EXTENSIONS = {
    "viscoelastic": ("Maxwell viscoelasticity (one branch, tau = 10 s; rate 0.01/s)", [
        (f"beta = {b:g}", {"maxwell": 1}, _p(beta=(b,), tau_s=(10.0,)), None, BOTH)
        for b in (0.25, 0.5, 1.0)]),
    "mullins": ("Ogden-Roxburgh softening (m = 0.05 kPa)", [
        (f"d = {d:g}", {"mullins": True}, _p(softening=d, softening_m_kPa=0.05), None, BOTH)
        for d in (0.2, 0.5, 0.8)]),
    "ogden2": ("Two-term Ogden, mu_0 + mu_1 = 1 kPa, alpha = (-20, 5)", [
        (f"mu_1 = {f:g} kPa", {"n_terms": 2}, _p(mu=(1 - f, f), alpha=(-20.0, 5.0)), None,
         BOTH) for f in (0.2, 0.5, 0.8)]),
    "compressibility": ("Compressibility (initial Poisson ratio nu0, volumetric law)", [
        ("nu0 = 0.45", {}, _p(nu0=0.45), None, BOTH),
        ("nu0 = 0.499", {}, _p(nu0=0.499), None, BOTH),
        ("nu0 = 0.45, U = log", {"volumetric": "log"}, _p(nu0=0.45), None, BOTH)]),
    "gluing": ("Compliant glue layer (k_r = k_theta = k) and frictionless plates", [
        (f"springs k = {k:g} kPa/mm", {"ends": "springs"},
         _p().values() | Interface(k, k).values(), None, BOTH) for k in (10.0, 100.0, 1000.0)]
        + [("slip (frictionless)", {"ends": "slip"}, _p(), None, ("compression_tension",))]),
    "artefacts": ("Measurement artefacts (machine assumes H = 5 mm, R = 4 mm, zero offsets)", [
        ("height_rel = +0.05", {}, _p(), Artefacts(height_rel=0.05), BOTH),
        ("radius_rel = +0.05", {}, _p(), Artefacts(radius_rel=0.05), BOTH),
        ("stretch_offset = +0.01", {}, _p(), Artefacts(stretch_offset=0.01), BOTH),
        ("force 0.5 mN, torque 2 mN mm offsets", {}, _p(),
         Artefacts(force_offset_mN=0.5, torque_offset_mNmm=2.0), BOTH)]),
}


def protocols():
    return {"compression_tension": compression_tension(0.15, cycles=2),
            "torsion": torsion(0.30, cycles=2)}


CHANNELS = {"compression_tension": ("nominal_stress_kPa",),
            "torsion": ("shear_stress_kPa", "axial_force_mN")}


def discretisation_error(refinement: int, fine: int) -> dict[str, float]:
    """max |f(k) - f(fine)| / max |f(fine)| of the base curves per channel."""
    prots = protocols()
    runs = {}
    for k in (refinement, fine):
        m = ForwardModel(geometry.axisymmetric(refinement=k))
        runs[k] = {t: m.run(p, _p()) for t, p in prots.items()}
    out = {}
    for t, chans in CHANNELS.items():
        for c in chans:
            a, b = runs[refinement][t][c].to_numpy(), runs[fine][t][c].to_numpy()
            out[f"{t}:{c}"] = float(np.abs(a - b).max() / np.abs(b).max())
    return out


def summarise(df, test) -> dict[str, float]:
    """Numbers a reader can compare with data (second cycle where it matters)."""
    if test == "compression_tension":
        s, lam = df.nominal_stress_kPa.to_numpy(), df.stretch.to_numpy()
        c1, c2 = (df.cycle == 1).to_numpy(), (df.cycle == 2).to_numpy()
        i1, i2 = np.flatnonzero(c1), np.flatnonzero(c2)
        i2 = np.concatenate([[i1[-1]], i2])  # cycle 2 starts from the end of cycle 1

        def work(idx):
            return float(np.sum(0.5 * (s[idx][1:] + s[idx][:-1]) * np.diff(lam[idx])))

        return {"P_min_cycle1_kPa": float(s[c1].min()), "P_min_cycle2_kPa": float(s[c2].min()),
                "P_max_cycle1_kPa": float(s[c1].max()),
                "loop_work_cycle1_kPa": work(i1), "loop_work_cycle2_kPa": work(i2),
                "P_end_kPa": float(s[-1])}
    tau, fz = df.shear_stress_kPa.to_numpy(), df.axial_force_mN.to_numpy()
    return {"tau_max_kPa": float(tau.max()), "Fz_min_mN": float(fz.min()),
            "tau_end_kPa": float(tau[-1]), "Fz_end_mN": float(fz[-1])}


def plot(name, title, curves, base_runs, err, out_dir):
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.2))
    styles = ["-", "--", "-.", ":"]
    colours = ["C1", "C2", "C3", "C4"]

    def draw(runs, label, ls, col, lw):
        if "compression_tension" in runs:
            d = runs["compression_tension"]
            ax[0].plot(d.stretch, d.nominal_stress_kPa, ls, color=col, lw=lw, label=label)
        if "torsion" in runs:
            d = runs["torsion"]
            ax[1].plot(d.shear, d.shear_stress_kPa, ls, color=col, lw=lw, label=label)
            ax[2].plot(d.shear, d.axial_force_mN, ls, color=col, lw=lw, label=label)

    draw(base_runs, "base", "-", "k", 2.2)
    for i, (label, runs) in enumerate(curves):
        draw(runs, label, styles[i % 4], colours[i % 4], 1.4)
    ax[0].set(xlabel="stretch", ylabel="nominal stress [kPa]",
              title="compression/tension A = 0.15, 2 cycles")
    ax[1].set(xlabel="amount of shear at R", ylabel="shear stress 2T/(pi R^3) [kPa]",
              title="torsion 0.30, 2 cycles")
    ax[2].set(xlabel="amount of shear at R", ylabel="axial force [mN]",
              title="torsion 0.30: axial (Poynting) force")
    for a in ax:
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    e_ct = err["compression_tension:nominal_stress_kPa"]
    e_t = err["torsion:shear_stress_kPa"]
    e_f = err["torsion:axial_force_mN"]
    fig.suptitle(f"{title}\nbase-curve discretisation error (k = 2 vs k = 4, max relative): "
                 f"stress {100 * e_ct:.2f} %, shear stress {100 * e_t:.3f} %, "
                 f"axial force {100 * e_f:.3f} %", fontsize=10)
    fig.tight_layout()
    path = os.path.join(out_dir, f"physics_{name}.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.path.join(HERE, "..", "docs", "figures"))
    ap.add_argument("--refinement", type=int, default=2)
    ap.add_argument("--fine", type=int, default=4)
    ap.add_argument("--json", default=None, help="summary JSON (default: not written)")
    ap.add_argument("--only", default=None, help="comma list of extensions to draw")
    a = ap.parse_args()
    logging.getLogger("ffcx").setLevel(logging.WARNING)
    os.makedirs(a.out, exist_ok=True)
    t0 = time.perf_counter()
    err = discretisation_error(a.refinement, a.fine)
    geom = geometry.axisymmetric(refinement=a.refinement)
    models: dict[tuple, ForwardModel] = {}

    def model(**kw):
        key = tuple(sorted(kw.items()))
        if key not in models:
            models[key] = ForwardModel(geom, **kw)
        return models[key]

    prots = protocols()
    base_runs = {t: model().run(p, _p()) for t, p in prots.items()}
    summary = {"discretisation_error": err,
               "base": {t: summarise(d, t) for t, d in base_runs.items()}}
    names = a.only.split(",") if a.only else list(EXTENSIONS)
    for name in names:
        title, spec = EXTENSIONS[name]
        curves = []
        summary[name] = {}
        for label, kw, params, art, tests in spec:
            m = model(**kw)
            runs = {t: m.run(prots[t], params, artefacts=art) for t in tests}
            curves.append((label, runs))
            summary[name][label] = {t: summarise(d, t) for t, d in runs.items()}
        print(f"wrote {plot(name, title, curves, base_runs, err, a.out)}", flush=True)
    summary["elapsed_s"] = time.perf_counter() - t0
    errs = ", ".join(f"{k} {100 * v:.3f} %" for k, v in err.items())
    print(f"\ndiscretisation error of the base curves (k = {a.refinement} vs {a.fine}): {errs}")
    for name in ["base"] + names:
        print(f"\n### {name}\n")
        rows = {"base": {"base": summary["base"]}}.get(name, summary[name])
        keys = sorted({f"{t}:{k}" for r in rows.values() for t, s in r.items() for k in s})
        print("| curve | " + " | ".join(keys) + " |")
        print("|---" * (len(keys) + 1) + "|")
        for label, r in rows.items():
            vals = []
            for key in keys:
                t, k = key.split(":")
                vals.append(f"{r[t][k]:.4g}" if t in r else "-")
            print(f"| {label} | " + " | ".join(vals) + " |")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(summary, fh, indent=2)
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    run_script(main)
