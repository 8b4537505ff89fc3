"""Identify every specimen (or region-averaged curve) of a recordings table, both stages.

Outputs in ``out_dir`` (each written through a temporary file and a rename, and only after
every fit succeeded, so bad input never leaves partial results):

* ``parameters.csv``: ``region`` (region-averaged input) or ``specimen`` (+ ``region``),
  ``fit``, ``mu_kPa``, ``alpha``, ``mu_se_kPa``, ``alpha_se``, ``objective``,
  ``fe_solves``, ``surrogate_mu_kPa``, ``surrogate_alpha`` and further diagnostics
  (``mu_alpha_correlation``, ``identifiable``, the FE objective at the surrogate optimum,
  per-test errors, wall times);
* ``history.csv``: the parameter history of both stages (the paper's Figure 5);
* ``figures/``: recorded vs identified curves per specimen and fit, and the histories.
"""

from __future__ import annotations

import logging
import os
import time
import warnings

import numpy as np
import pandas as pd

from .fit import IdentifiabilityWarning, Identification, identify
from .objective import CONTROL, STRESS, curves_from_recordings
from .recordings import read_recordings, read_specimens, write_table_atomic
from .simulators import FESimulator, SurrogateSimulator

log = logging.getLogger(__name__)

FITS = ("compression_tension", "all")


def identify_all(recordings: str, specimens: str, surrogates: str, out_dir: str, *,
                 fits=("all",), refinement: int | None = None,
                 surrogate_mismatch: str = "warn", progress: bool = False) -> pd.DataFrame:
    """Two-stage identification of every recorded specimen for each fit set."""
    from surrogate.persist import load_surrogates

    for f in fits:
        if f not in FITS:
            raise ValueError(f"fit must be one of {', '.join(FITS)}, got {f!r}")
    spec = read_specimens(specimens)
    rec = read_recordings(recordings, spec)
    bundles = load_surrogates(surrogates, keys=_available(surrogates))
    nu0 = next(iter(bundles.values())).conditions.get("nu0", 0.49)
    region_level = bool((spec["specimen"] == spec["region"]).all())
    ids = [s for s in spec["specimen"] if s in set(rec["specimen"])]
    rows, hist, figs = [], [], []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(ids) * len(fits), desc="identify", unit="fit", disable=None)
    fe_cache: dict = {}
    for sid in ids:
        srow = spec[spec["specimen"] == sid].iloc[0]
        R, H = float(srow.radius_mm), float(srow.height_mm)
        curves = curves_from_recordings(rec[rec["specimen"] == sid], R)
        with warnings.catch_warnings():
            # stage 1 only provides the start of the FE stage, which uses the specimen's own
            # geometry: a surrogate of the nominal geometry is acceptable there
            warnings.simplefilter("ignore" if surrogate_mismatch == "warn" else "error")
            sur = SurrogateSimulator(bundles, radius_mm=R, height_mm=H, nu0=nu0,
                                     on_mismatch=surrogate_mismatch)
        if (R, H) not in fe_cache:
            fe_cache[(R, H)] = FESimulator(R, H, nu0, refinement=refinement)
        fe = fe_cache[(R, H)]
        for fit in fits:
            t0 = time.perf_counter()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", IdentifiabilityWarning)
                res = identify(curves, sur, fe, fit=fit)
            for w in caught:
                log.warning("%s: %s", sid, w.message)
            rows.append(_row(sid, srow, region_level, res, time.perf_counter() - t0))
            hist.extend(_history(sid, res))
            figs.append((sid, fit, curves, res, fe))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    table = pd.DataFrame(rows)
    os.makedirs(os.path.join(out_dir, "figures"), exist_ok=True)
    write_table_atomic(table, os.path.join(out_dir, "parameters.csv"))
    write_table_atomic(pd.DataFrame(hist), os.path.join(out_dir, "history.csv"))
    for sid, fit, curves, res, fe in figs:
        plot_fit(sid, fit, curves, res, fe, os.path.join(out_dir, "figures",
                                                           f"fit_{sid}_{fit}.png"))
    plot_history(pd.DataFrame(hist), os.path.join(out_dir, "figures", "history.png"))
    return table


def _available(model_dir: str) -> list[str]:
    from surrogate.data import TEST_KEYS

    keys = [k for k in TEST_KEYS if os.path.exists(os.path.join(model_dir, f"{k}.joblib"))]
    if not keys:
        raise FileNotFoundError(f"no surrogates (<test>.joblib) in {model_dir}")
    return keys


def _row(sid, srow, region_level: bool, res: Identification, wall: float) -> dict:
    s1, s2 = res.stage1, res.stage2
    first = {"region": sid} if region_level else {"specimen": sid, "region": srow.region}
    fe_at_surrogate = s2.history[0][3] if s2.history else np.nan
    return {**first, "fit": res.fit, "mu_kPa": s2.mu_kPa, "alpha": s2.alpha,
            "mu_se_kPa": res.mu_se_kPa, "alpha_se": res.alpha_se, "objective": s2.objective,
            "fe_solves": s2.protocol_solves, "surrogate_mu_kPa": s1.mu_kPa,
            "surrogate_alpha": s1.alpha, "surrogate_objective": s1.objective,
            "fe_objective_at_surrogate_optimum": fe_at_surrogate,
            "mu_alpha_correlation": res.correlation, "identifiable": res.identifiable,
            "tests": " ".join(res.tests),
            **{f"error_{k}": v for k, v in s2.errors.items()},
            "surrogate_time_s": s1.wall_time_s, "fe_time_s": s2.wall_time_s,
            "wall_time_s": wall}


def _history(sid, res: Identification) -> list[dict]:
    out = []
    for st in (res.stage1, res.stage2):
        for ev, mu, alpha, obj in st.history:
            out.append({"id": sid, "fit": res.fit, "stage": st.name, "evaluation": ev,
                        "mu_kPa": mu, "alpha": alpha, "objective": obj})
    return out


def plot_fit(sid, fit, curves, res: Identification, fe: FESimulator, path: str) -> None:
    """Recorded points and the identified FE curve for every test (paper Figure 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sims = fe(curves, res.mu_kPa, res.alpha)
    fig, axes = plt.subplots(1, len(curves), figsize=(3.8 * len(curves), 3.3), squeeze=False)
    for ax, c, s in zip(axes[0], curves, sims, strict=True):
        used = c.key in res.tests
        for br, mk in (("loading", "o"), ("unloading", "s")):
            m = c.branch == br
            ax.plot(c.control[m], c.stress[m], mk, ms=3, mfc="none", label=f"recorded, {br}")
        order = np.argsort(c.control)
        ax.plot(c.control[order], s[order], "-", color="k",
                label="FE, identified" + ("" if used else " (not fitted)"))
        ax.set_title(f"{c.key}: eps = {np.sqrt(np.sum((s - c.stress)**2)) / c.norm:.3f}",
                     fontsize=9)
        ax.set_xlabel(CONTROL[c.test])
        ax.set_ylabel(STRESS[c.test])
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{sid}, fit '{fit}': mu = {res.mu_kPa:.3f} +- {res.mu_se_kPa:.3f} kPa, "
                 f"alpha = {res.alpha:.2f} +- {res.alpha_se:.2f} (FE discretisation "
                 "error <= 1 %)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_history(hist: pd.DataFrame, path: str, max_lines: int = 8) -> None:
    """Parameter history of both stages (paper Figure 5), for up to ``max_lines`` fits."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if hist.empty:
        return
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for n, ((sid, fit), g) in enumerate(hist.groupby(["id", "fit"], sort=False)):
        if n >= max_lines:
            break
        g = g.reset_index(drop=True)
        for ax, col in zip(axes, ("mu_kPa", "alpha"), strict=True):
            line, = ax.plot(g.index, g[col], "-", lw=1, label=f"{sid} ({fit})")
            fe = g.stage == "fe"
            ax.plot(g.index[fe], g[col][fe], "o", ms=3, color=line.get_color())
    for ax, lab in zip(axes, ("mu [kPa]", "alpha"), strict=True):
        ax.set_xlabel("evaluation (line: surrogate stage, dots: FE stage)")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
