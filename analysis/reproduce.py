"""``brainmech reproduce``: the whole study on the embedded (synthetic) brain bank.

Stages, each in its own folder of ``out`` and skipped on a re-run when its ``stage.json``
records the same configuration: ``samples`` (FE sample store), ``models`` (surrogates),
``fits_regions`` (region-averaged curves, both fit sets), ``fits_specimens`` (every
mechanics specimen, both fit sets; default and paper profiles), ``analysis`` (Kendall
tables and figures), then ``report.md`` and ``summary.json``. The ground truth
(``truth.json``) is read only here, by the report, never by the pipeline stages.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

from brain_fe.io import write_json_atomic, write_text_atomic

log = logging.getLogger(__name__)

BANK = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data",
                    "brain_bank")


@dataclass(frozen=True)
class ReproduceProfile:
    name: str
    n_samples: int
    sample_refinement: int | None
    train_profile: str
    trials: int
    executions: int
    specimens: bool  # also identify every specimen (the paper's 'both' level)
    fit_refinement: int | None = None


PROFILES = {
    "quick": ReproduceProfile("quick", 48, 1, "tiny", 4, 1, False),
    "default": ReproduceProfile("default", 160, None, "default", 10, 2, True),
    "paper": ReproduceProfile("paper", 512, None, "paper", 10, 2, True),
}

PLANTED_SIGN = {"mu_kPa": {"Iba1": 1, "Col_VI": 1, "GFAP": 1, "Col_IV": -1},
                "alpha": {"HA": 1, "FN": -1}}


def _stage(out: str, name: str, config: dict, run, progress_name: str | None = None) -> float:
    """Run ``run(folder)`` unless ``folder/stage.json`` records ``config``; wall time."""
    folder = os.path.join(out, name)
    marker = os.path.join(folder, "stage.json")
    if os.path.exists(marker):
        with open(marker) as fh:
            done = json.load(fh)
        if done.get("config") == config:
            log.info("stage %s: reusing %s", name, folder)
            return float(done.get("wall_time_s", 0.0))
    os.makedirs(folder, exist_ok=True)
    log.info("stage %s ...", progress_name or name)
    t0 = time.perf_counter()
    run(folder)
    wall = time.perf_counter() - t0
    write_json_atomic(marker, {"config": config, "wall_time_s": wall}, indent=1)
    return wall


def reproduce(out: str, profile: str = "quick", *, bank: str = BANK,
              custom: ReproduceProfile | None = None, progress: bool = True) -> dict:
    """Run (or resume) every stage; returns the summary also written to summary.json."""
    from mpi4py import MPI

    from brain_fe.sampling import SampleSpec, run_sampling
    from brain_fe.store import load_samples, read_manifest
    from identification.batch import identify_all
    from surrogate.train import train_all

    if custom is None and profile not in PROFILES:
        raise ValueError(f"profile must be one of {', '.join(PROFILES)}, got {profile!r}")
    prof = custom or PROFILES[profile]
    for f in ("recordings_regions.csv", "regions.csv", "composition.csv", "specimens.csv",
              "recordings.csv"):
        if not os.path.exists(os.path.join(bank, f)):
            raise FileNotFoundError(f"brain bank incomplete: {os.path.join(bank, f)} missing")
    os.makedirs(out, exist_ok=True)
    walls: dict[str, float] = {}
    sspec = SampleSpec(n=prof.n_samples, seed=0, refinement=prof.sample_refinement)
    walls["sample"] = _stage(out, "samples", sspec.as_dict(), lambda d: run_sampling(
        sspec, d, comm=MPI.COMM_WORLD, progress=progress))
    tcfg = {"profile": prof.train_profile, "trials": prof.trials,
            "executions": prof.executions, "samples": sspec.as_dict()}
    sdir = os.path.join(out, "samples")
    walls["train"] = _stage(out, "models", tcfg, lambda d: train_all(
        load_samples(sdir), read_manifest(sdir), d, profile=prof.train_profile,
        trials=prof.trials, executions=prof.executions, progress=progress))
    mdir = os.path.join(out, "models")
    icfg = {"train": tcfg, "bank": os.path.abspath(bank), "refinement": prof.fit_refinement}
    walls["identify_regions"] = _stage(out, "fits_regions", icfg, lambda d: identify_all(
        os.path.join(bank, "recordings_regions.csv"), os.path.join(bank, "regions.csv"),
        mdir, d, fits=("compression_tension", "all"), refinement=prof.fit_refinement,
        progress=progress))
    if prof.specimens:
        walls["identify_specimens"] = _stage(out, "fits_specimens", icfg, lambda d: (
            identify_all(os.path.join(bank, "recordings.csv"),
                         os.path.join(bank, "specimens.csv"), mdir, d,
                         fits=("compression_tension", "all"), refinement=prof.fit_refinement,
                         progress=progress)))
    comp = pd.read_csv(os.path.join(bank, "composition.csv"))

    def correlate_all(d):
        from . import correlate

        correlate(pd.read_csv(os.path.join(out, "fits_regions", "parameters.csv")), comp,
                  os.path.join(d, "regions"))
        if prof.specimens:
            correlate(pd.read_csv(os.path.join(out, "fits_specimens", "parameters.csv")),
                      comp, os.path.join(d, "specimens"))

    walls["correlate"] = _stage(out, "analysis", {**icfg, "specimens": prof.specimens},
                                correlate_all)
    t0 = time.perf_counter()
    summary = build_summary(out, bank, prof, walls)
    summary["wall_time_s"] = walls
    write_report(out, summary)
    walls["report"] = time.perf_counter() - t0
    write_json_atomic(os.path.join(out, "summary.json"), summary, indent=1, default=float)
    return summary


def _compare(params: pd.DataFrame, truth: pd.DataFrame, key: str) -> list[dict]:
    t = truth.set_index(key)
    rows = []
    for r in params.to_dict("records"):
        tr = t.loc[r[key]]
        rows.append({key: r[key], "fit": r["fit"], "mu_kPa": r["mu_kPa"], "alpha": r["alpha"],
                     "mu_se_kPa": r["mu_se_kPa"], "alpha_se": r["alpha_se"],
                     "true_mu_kPa": float(tr.mu_kPa), "true_alpha": float(tr.alpha),
                     "mu_rel_err": r["mu_kPa"] / float(tr.mu_kPa) - 1,
                     "alpha_rel_err": r["alpha"] / float(tr.alpha) - 1})
    return rows


def planted_recovery(kendall: pd.DataFrame, fit: str = "all", k: int = 4) -> dict:
    """Signs of tau for the planted components and overlap of the top-k |tau| components
    with the planted ones, per parameter (region level)."""
    out = {}
    tab = kendall[(kendall.level == "region") & (kendall.fit == fit)]
    for par, planted in PLANTED_SIGN.items():
        sub = tab[tab.parameter == par].set_index("component")
        signs = {c: bool(np.sign(sub.loc[c, "tau"]) == s) for c, s in planted.items()
                 if c in sub.index and np.isfinite(sub.loc[c, "tau"])}
        top = list(sub.assign(a=sub.tau.abs()).sort_values("a", ascending=False)
                   .index[:k])
        out[par] = {"signs_recovered": signs, "n_signs_recovered": int(sum(signs.values())),
                    "n_planted": len(planted), "top_components": top,
                    "planted_in_top": sorted(set(top) & set(planted))}
    return out


def build_summary(out: str, bank: str, prof: ReproduceProfile, walls: dict) -> dict:
    with open(os.path.join(out, "models", "metrics.json")) as fh:
        metrics = json.load(fh)
    with open(os.path.join(bank, "truth.json")) as fh:  # only the report reads the truth
        truth = json.load(fh)
    reg = pd.read_csv(os.path.join(out, "fits_regions", "parameters.csv"))
    summary = {"synthetic_data": True, "profile": asdict(prof),
               "metrics": {k: {kk: vv for kk, vv in v.items() if kk != "trials"}
                           if isinstance(v, dict) else v for k, v in metrics.items()},
               "regions": _compare(reg, pd.DataFrame(truth["region_truth"]), "region")}
    if prof.specimens:
        spe = pd.read_csv(os.path.join(out, "fits_specimens", "parameters.csv"))
        summary["specimens"] = _compare(spe, pd.DataFrame(truth["specimen_truth"]),
                                        "specimen")
    kend = pd.read_csv(os.path.join(out, "analysis", "regions", "kendall.csv"))
    summary["kendall"] = kend.to_dict("records")
    summary["planted_recovery"] = {f: planted_recovery(kend, f) for f in
                                   ("compression_tension", "all")}
    return summary


def _fig7(out: str) -> str:
    """CT-only vs all-tests parameters per region (the paper's Figure 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = pd.read_csv(os.path.join(out, "fits_regions", "parameters.csv"))
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    regions = list(dict.fromkeys(p.region))
    x = np.arange(len(regions))
    for ax, col, se in zip(axes, ("mu_kPa", "alpha"), ("mu_se_kPa", "alpha_se"), strict=True):
        for dx, fit in ((-0.18, "compression_tension"), (0.18, "all")):
            s = p[p.fit == fit].set_index("region").loc[regions]
            ax.errorbar(x + dx, s[col], yerr=s[se], fmt="o", capsize=2, label=fit)
        ax.set_xticks(x, regions)
        ax.set_ylabel(col)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Region parameters: compression/tension only vs all tests (+- 1 SE)",
                 fontsize=9)
    fig.tight_layout()
    path = os.path.join(out, "figure7_fit_sets.png")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return "figure7_fit_sets.png"


def write_report(out: str, s: dict) -> None:
    """report.md: surrogates, identification against the truth, correlations."""
    prof = s["profile"]
    L = ["# brainmech reproduce: report", "",
         "**Synthetic data.** The recordings and compositions are the embedded virtual brain "
         "bank made by this project's FE model (`data/brain_bank/`); the ground truth is "
         "compared here only.", "",
         f"Profile `{prof['name']}`: {prof['n_samples']} FE parameter sets, surrogate "
         f"profile `{prof['train_profile']}` ({prof['trials']} trials x {prof['executions']} "
         "executions). FE discretisation error of every simulated force <= 0.34 % "
         "(BENCHMARKS.md).", "", "## 1. Surrogates (paper Table 3, Figure 4)", "",
         "| test | R^2 mean | R^2 std | test curves | architecture |", "|---|---|---|---|---|"]
    for k in ("compression_tension", "torsion_0.15", "torsion_0.30"):
        m = s["metrics"].get(k)
        if m:
            hp = m["hyperparameters"]
            L.append(f"| {k} | {m['r2_mean']:.4f} | {m['r2_std']:.4f} | {m['n_test_curves']} "
                     f"| {hp['hidden1']}-{hp['hidden2']} {hp['activation']}, "
                     f"lr {hp['learning_rate_init']:g} |")
    L += ["", "Paper: 0.9234 +- 0.1230 (compression/tension), > 0.98 (torsion).", ""]
    L += [f"![{k}](models/{k}_test_curves.png)" for k in
          ("compression_tension", "torsion_0.15", "torsion_0.30")]
    L += ["", "## 2. Identified parameters against the ground truth", "",
          "Region-averaged curves (both fit sets). The 'true' region values are the planted "
          "region parameters; a fit to the average of curves of scattered specimens need not "
          "equal them (averaging nonlinear curves is not averaging parameters), so region "
          "errors mix that effect with identification error.", "",
          "| region | fit | mu [kPa] | true mu | error | alpha | true alpha | error |",
          "|---|---|---|---|---|---|---|---|"]
    for r in s["regions"]:
        L.append(f"| {r['region']} | {r['fit']} | {r['mu_kPa']:.4f} +- {r['mu_se_kPa']:.4f} "
                 f"| {r['true_mu_kPa']:.4f} | {100 * r['mu_rel_err']:+.1f} % | "
                 f"{r['alpha']:.2f} +- {r['alpha_se']:.2f} | {r['true_alpha']:.2f} | "
                 f"{100 * r['alpha_rel_err']:+.1f} % |")
    if "specimens" in s:
        sp = pd.DataFrame(s["specimens"])
        L += ["", "Specimen fits (every mechanics specimen, its own geometry): median |error| "
              "and 95th percentile:", "", "| fit | mu median | mu p95 | alpha median | "
              "alpha p95 |", "|---|---|---|---|---|"]
        for fit, g in sp.groupby("fit"):
            L.append(f"| {fit} | {100 * g.mu_rel_err.abs().median():.1f} % | "
                     f"{100 * g.mu_rel_err.abs().quantile(0.95):.1f} % | "
                     f"{100 * g.alpha_rel_err.abs().median():.1f} % | "
                     f"{100 * g.alpha_rel_err.abs().quantile(0.95):.1f} % |")
    L += ["", f"![fit sets]({_fig7(out)})", "",
          "![history](fits_regions/figures/history.png)", ""]
    first = s["regions"][0]["region"]
    L += [f"![example fit](fits_regions/figures/fit_{first}_all.png)", "",
          "## 3. Correlation with composition (paper Figure 8)", "",
          "Kendall tau-b at the region level (8 regions: with so few points only large |tau| "
          "reach p < 0.05; BH-adjusted p-values beside the raw ones in "
          "`analysis/regions/kendall.csv`).", ""]
    for fit, rec in s["planted_recovery"].items():
        for par, v in rec.items():
            L.append(f"- fit `{fit}`, {par}: planted signs recovered "
                     f"{v['n_signs_recovered']}/{v['n_planted']}; top-4 |tau| components "
                     f"{', '.join(v['top_components'])} (planted among them: "
                     f"{', '.join(v['planted_in_top']) or 'none'})")
    L += ["", "![heat map](analysis/regions/heatmap_region.png)", "",
          "![regression](analysis/regions/regression_all.png)", ""]
    if "specimens" in s:
        L += ["![heat map, specimens](analysis/specimens/heatmap_specimen.png)", ""]
    L += ["## Wall time per stage", "", "| stage | s |", "|---|---|"]
    L += [f"| {k} | {v:.1f} |" for k, v in s.get("wall_time_s", {}).items()]
    write_text_atomic(os.path.join(out, "report.md"), "\n".join(L) + "\n")


def summary_lines(s: dict, out: str) -> list[str]:
    """A few lines for the terminal: surrogate R^2, region errors, wall times."""
    lines = [f"{out}/report.md (profile {s['profile']['name']}, synthetic data)"]
    for k in ("compression_tension", "torsion_0.15", "torsion_0.30"):
        m = s["metrics"].get(k)
        if m:
            lines.append(f"  surrogate {k}: R^2 = {m['r2_mean']:.4f} +- {m['r2_std']:.4f}")
    for fit, g in pd.DataFrame(s["regions"]).groupby("fit"):
        lines.append(f"  regions, fit {fit}: median |error| mu "
                     f"{100 * g.mu_rel_err.abs().median():.1f} %, alpha "
                     f"{100 * g.alpha_rel_err.abs().median():.1f} %")
    lines.append("  wall time: " + ", ".join(f"{k} {v:.0f} s"
                                             for k, v in s["wall_time_s"].items()))
    return lines
