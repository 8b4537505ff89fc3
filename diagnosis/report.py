"""Outputs of a diagnosis: DIR/diagnosis.json, DIR/report.md and its figures."""

from __future__ import annotations

import logging
from pathlib import Path

from brain_fe.io import staged_directory, write_json_atomic, write_text_atomic

from .effects import EFFECTS
from .figures import before_after, mismatch_map

log = logging.getLogger(__name__)


def write(d, out: str | Path, *, title: str = "diagnosis") -> dict:
    """Write DIR/diagnosis.json, DIR/report.md, DIR/mismatch_map.png, DIR/before_after.png,
    all at once (staged, then moved into place: a result is complete or absent)."""
    with staged_directory(out) as stage:
        return _write(d, stage, title)


def _write(d, out: Path, title: str) -> dict:
    res = d.to_json()
    r = d.base.prediction - d.obs["value"].to_numpy(float)
    mismatch_map(d.obs, r, d.sigma, d.located, out / "mismatch_map.png")
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
