"""Identify every specimen (or region-averaged curve) of a recordings table, both stages.

Outputs in ``out_dir``, written only after every fit succeeded (staged, then moved into
place), so bad input never leaves partial results:

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

from brain_fe import geometry as geo
from brain_fe.io import staged_directory, write_figure_atomic, write_table_atomic
from brain_fe.parallel import Progress
from brain_fe.vocabulary import CHANNELS, CONTROL
from recordings.tables import read_recordings, read_specimens
from simulators.fe import FESimulator
from simulators.surrogate import SurrogateSimulator

from .fit import FITS, IdentifiabilityWarning, Identification, identify, select
from .objective import identification_obs

log = logging.getLogger(__name__)


def identify_all(recordings: str, specimens: str, surrogates: str, out_dir: str, *,
                 fits=("all",), refinement: int | None = None,
                 surrogate_mismatch: str = "warn", progress: bool = False) -> pd.DataFrame:
    """Two-stage identification of every recorded specimen for each fit set."""
    from surrogate.persist import available_surrogates, load_surrogates

    for f in fits:
        if f not in FITS:
            raise ValueError(f"fit must be one of {', '.join(FITS)}, got {f!r}")
    spec = read_specimens(specimens)
    rec = read_recordings(recordings, spec)
    bundles = load_surrogates(surrogates, keys=available_surrogates(surrogates))
    nu0 = next(iter(bundles.values())).conditions.get("nu0", 0.49)
    region_level = bool((spec["specimen"] == spec["region"]).all())
    ids = [s for s in spec["specimen"] if s in set(rec["specimen"])]
    rows, hist, figs = [], [], []
    geometries: dict = {}
    with Progress(len(ids) * len(fits), "identify", "fit", enabled=progress) as bar:
        for sid in ids:
            srow = spec[spec["specimen"] == sid].iloc[0]
            R, H = float(srow.radius_mm), float(srow.height_mm)
            obs_all = identification_obs(rec[rec["specimen"] == sid])
            if (R, H) not in geometries:
                geometries[(R, H)] = (geo.make("axisymmetric", R, H, refinement,
                                               comm=_self()), {})
            g, models = geometries[(R, H)]
            for fit in fits:
                obs = select(obs_all, fit)
                with warnings.catch_warnings():
                    # stage 1 only provides the start of the FE stage, which uses the
                    # specimen's own geometry: a surrogate of the nominal geometry is fine
                    warnings.simplefilter("ignore" if surrogate_mismatch == "warn"
                                          else "error")
                    sur = SurrogateSimulator(obs, bundles, radius_mm=R, height_mm=H, nu0=nu0,
                                             on_mismatch=surrogate_mismatch)
                fe = FESimulator(obs, R, H, nu0=nu0, path="branches", geometry=g,
                                 models=models)
                t0 = time.perf_counter()
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", IdentifiabilityWarning)
                    res = identify(sur, fe, fit=fit)
                for w in caught:
                    log.warning("%s: %s", sid, w.message)
                rows.append(_row(sid, srow, region_level, res, time.perf_counter() - t0))
                hist.extend(_history(sid, res))
                figs.append((sid, fit, obs_all, res, FESimulator(
                    obs_all, R, H, nu0=nu0, path="branches", geometry=g, models=models)))
                bar.update(1, f"{sid} [{fit}]")
    table = pd.DataFrame(rows)
    with staged_directory(out_dir) as stage:
        os.makedirs(stage / "figures")
        write_table_atomic(table, stage / "parameters.csv")
        write_table_atomic(pd.DataFrame(hist), stage / "history.csv")
        for sid, fit, obs, res, fe in figs:
            plot_fit(sid, fit, obs, res, fe, stage / "figures" / f"fit_{sid}_{fit}.png")
        plot_history(pd.DataFrame(hist), stage / "figures" / "history.png")
    return table


def _self():
    from mpi4py import MPI

    return MPI.COMM_SELF


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


def plot_fit(sid, fit, obs: pd.DataFrame, res: Identification, fe: FESimulator, path) -> None:
    """Recorded points and the identified FE curve for every test (paper Figure 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    y = fe.predict({"mu_0": res.mu_kPa, "alpha_0": res.alpha, "nu0": fe.nu0}).y
    groups = list(obs.groupby("curve", sort=False))
    fig, axes = plt.subplots(1, len(groups), figsize=(3.8 * len(groups), 3.3), squeeze=False)
    for ax, (key, g) in zip(axes[0], groups, strict=True):
        i = g.index.to_numpy()
        e, s, x = g["value"].to_numpy(), y[i], g["control"].to_numpy()
        for br, mk in (("loading", "o"), ("unloading", "s")):
            m = (g["branch"] == br).to_numpy()
            ax.plot(x[m], e[m], mk, ms=3, mfc="none", label=f"recorded, {br}")
        order = np.argsort(x)
        used = key in res.tests
        ax.plot(x[order], s[order], "-", color="k",
                label="FE, identified" + ("" if used else " (not fitted)"))
        eps = np.sqrt(np.sum((s - e) ** 2) / np.sum(e ** 2))
        ax.set_title(f"{key}: eps = {eps:.3f}", fontsize=9)
        ax.set_xlabel(CONTROL[g["test"].iloc[0]])
        ch = CHANNELS[g["channel"].iloc[0]]
        ax.set_ylabel(f"{ch.column}")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{sid}, fit '{fit}': mu = {res.mu_kPa:.3f} +- {res.mu_se_kPa:.3f} kPa, "
                 f"alpha = {res.alpha:.2f} +- {res.alpha_se:.2f} (FE discretisation "
                 "error <= 1 %)", fontsize=9)
    fig.tight_layout()
    write_figure_atomic(fig, path, dpi=100)
    plt.close(fig)


def plot_history(hist: pd.DataFrame, path, max_lines: int = 8) -> None:
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
    write_figure_atomic(fig, path, dpi=100)
    plt.close(fig)
