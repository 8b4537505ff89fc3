"""Outputs of a diagnosis: DIR/diagnosis.json, DIR/report.md and its figures."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from brain_fe.io import write_json_atomic, write_text_atomic

from . import locate as loc
from .effects import EFFECTS

log = logging.getLogger(__name__)


def before_after(d, path: Path) -> None:
    """Recording, base fit and refit for every curve/channel, loading and unloading."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = list(d.obs.groupby(["curve", "channel"], sort=False))
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.6), squeeze=False)
    for ax, ((curve, ch), g) in zip(axes[0], groups, strict=True):
        i = g.index.to_numpy()
        for br, colour in (("loading", "tab:blue"), ("unloading", "tab:orange")):
            m = (g["branch"] == br).to_numpy()
            if not m.any():
                continue
            ax.plot(g["control"][m], g["value"][m], ".", ms=3, color=colour, alpha=0.6,
                    label=f"recorded, {br}")
        x = g["control"].to_numpy()
        ax.plot(x, d.base.prediction[i], "-", color="0.4", lw=1, label="base fit")
        if d.verdict != "none":
            ax.plot(x, d.winner.prediction[i], "-", color="tab:red", lw=1,
                    label=f"with {d.verdict}")
        rb = np.sqrt(np.mean(d.base.z[i] ** 2))
        ra = np.sqrt(np.mean(d.winner.z[i] ** 2))
        ax.set_title(f"{curve} / {ch}\nRMS/noise {rb:.2f} -> {ra:.2f}", fontsize=9)
        ax.set_xlabel("stretch" if "compression" in curve or "tension" in curve
                      else "amount of shear")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(d, out: str | Path, *, title: str = "diagnosis") -> dict:
    """Write DIR/diagnosis.json, DIR/report.md, DIR/mismatch_map.png, DIR/before_after.png."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    res = d.to_json()
    r = d.base.prediction - d.obs["value"].to_numpy(float)
    loc.mismatch_map(d.obs, r, d.sigma, d.located, out / "mismatch_map.png")
    before_after(d, out / "before_after.png")
    write_json_atomic(out / "diagnosis.json", res, indent=1, default=float)
    lines = [f"# {title}", "",
             f"**Verdict: {d.verdict}**"
             + (f" — {EFFECTS[d.verdict].description}" if d.verdict in EFFECTS else
                " — no candidate explains the misfit significantly better than the base model"),
             "", f"Residual RMS / noise: {res['rms_before']:.2f} (base) -> "
             f"{res['rms_after']:.2f} (after modelling); 1 = noise level.", "",
             "## Located mismatch", "",
             "| axis | segment | n | RMS/noise | p |", "|---|---|---|---|---|"]
    for s in res["located"][:12]:
        lines.append(f"| {s['axis']} | {s['segment']} | {s['n']} | {s['rms_z']:.2f} | "
                     f"{s['p_value']:.2g} |")
    if not res["located"]:
        lines.append("| - | no systematic segment | | | |")
    lines += ["", "![mismatch map](mismatch_map.png)", "", "## Ranking of explanations", "",
              "BIC = chi2 + k ln n; LRT p for chi2_base - chi2_effect ~ chi2(k_effect).", "",
              "| effect | dBIC vs base | LRT p | significant | parameters |",
              "|---|---|---|---|---|"]
    for e in res["ranking"]:
        pars = ", ".join(f"{k} = {v:.4g}" for k, v in e["parameters"].items())
        lines.append(f"| {e['effect']} | {e['delta_bic']:.1f} | {e['p_value']:.2g} | "
                     f"{'yes' if e['significant'] else 'no'} | {pars} |")
    for a in res["ambiguous"]:
        lines += ["", f"**Cannot tell apart** {a['effects'][0]} and {a['effects'][1]} "
                  f"(dBIC {a['delta_bic']:.1f}); would separate them: {a['separating_test']}."]
    lines += ["", "## Before and after", "", "![before/after](before_after.png)", "",
              "| parameter | base fit | refit | bias of the base fit |", "|---|---|---|---|"]
    for n, b in res["base_bias"].items():
        lines.append(f"| {n} | {b['base']:.4g} | {b['refit']:.4g} | {100 * b['relative']:+.1f} % |")
    disc = res["discretisation"]
    if disc.get("corrected"):
        lines += ["", f"Discretisation: the k = {disc['refinement']} mesh is corrected by its "
                  f"difference to k = {disc['reference_refinement']} at the base fit "
                  f"(max {disc['max_over_noise']:.2f}, RMS {disc['rms_over_noise']:.2f} noise "
                  "standard deviations)."]
    lines += ["", f"Elapsed: {res['elapsed_s']:.0f} s."]
    write_text_atomic(out / "report.md", "\n".join(lines) + "\n")
    return res
