"""Figures of the composition analysis: Kendall tau heat map and the paper's Figure 8
regression plots (component concentration [-] against mu [kPa] and alpha [-]).

Figures use the non-interactive Agg backend (no display needed) and are written to the
given path (format from its extension); the parent directory must exist.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from .correlation import PARAMETERS, joined, kendall_pair, require_columns  # noqa: E402

log = logging.getLogger(__name__)

LABELS = {"mu_kPa": r"$\mu$ [kPa]", "alpha": r"$\alpha$ [-]"}
BH_MARK = "\u2020"  # dagger: BH-adjusted p < 0.05


def _check_dir(path: str) -> str:
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise ValueError(f"{path}: output directory does not exist ({d})")
    return path


def heatmap(table: pd.DataFrame, path: str, level: str = "region",
            threshold: float = 0.05) -> str:
    """Kendall tau-b of parameters (rows: mu, alpha) x components (columns), one panel per
    fit, diverging colormap fixed to [-1, 1] so that white is tau = 0.

    Each cell shows tau; ``*`` marks a raw p < ``threshold``, a dagger marks a
    Benjamini-Hochberg adjusted p < ``threshold`` (when the table has ``p_bh``); NaN
    cells (too few pairs) are grey.  Returns ``path``.
    """
    require_columns(table, ["fit", "parameter", "component", "tau", "p_value"], "Kendall")
    path = _check_dir(path)
    tab = table[table["level"] == level] if "level" in table.columns else table
    if tab.empty:
        raise ValueError(f"Kendall table has no rows for level {level!r}")
    fits = list(dict.fromkeys(tab["fit"]))
    comps = list(dict.fromkeys(tab["component"]))
    pars = [p for p in PARAMETERS if p in set(tab["parameter"])]
    cmap = plt.get_cmap("RdBu_r").copy()
    cmap.set_bad("0.85")
    fig, axes = plt.subplots(len(fits), 1, squeeze=False, sharex=True, layout="constrained",
                             figsize=(max(6.0, 0.9 * len(comps) + 2.0), 1.9 * len(fits) + 1.2))
    im = None
    for ax, fit in zip(axes[:, 0], fits, strict=True):
        sub = tab[tab["fit"] == fit].set_index(["parameter", "component"])
        tau = np.full((len(pars), len(comps)), np.nan)
        for i, p in enumerate(pars):
            for j, c in enumerate(comps):
                if (p, c) not in sub.index:
                    continue
                r = sub.loc[(p, c)]
                tau[i, j] = r["tau"]
                if np.isnan(r["tau"]):
                    text = "n/a"
                else:
                    text = f"{r['tau']:.2f}"
                    if r["p_value"] < threshold:
                        text += "*"
                    if "p_bh" in sub.columns and r["p_bh"] < threshold:
                        text += BH_MARK
                dark = np.isfinite(tau[i, j]) and abs(tau[i, j]) > 0.6
                ax.text(j, i, text, ha="center", va="center", fontsize=8,
                        color="white" if dark else "black")
        im = ax.imshow(np.ma.masked_invalid(tau), cmap=cmap, vmin=-1.0, vmax=1.0,
                       aspect="auto")
        ax.set_yticks(range(len(pars)), [LABELS.get(p, p) for p in pars])
        n = sub["n"].dropna() if "n" in sub.columns else pd.Series(dtype=int)
        n_txt = ""
        if len(n):
            lo, hi = int(n.min()), int(n.max())
            n_txt = f", n = {hi}" if lo == hi else f", n = {lo}-{hi}"
        ax.set_title(f"fit: {fit} ({level} level{n_txt})", fontsize=10)
    axes[-1, 0].set_xticks(range(len(comps)), comps, rotation=45, ha="right")
    fig.colorbar(im, ax=axes[:, 0].tolist(), label=r"Kendall $\tau_b$", shrink=0.9)
    axes[-1, 0].set_xlabel(f"* p < {threshold:g}   {BH_MARK} BH-adjusted p < {threshold:g}",
                           fontsize=8, loc="left")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    log.info("wrote %s", path)
    return path


def regression_plots(parameters: pd.DataFrame, composition: pd.DataFrame,
                     components: Sequence[str], path: str, fit: str = "all") -> str:
    """The paper's Figure 8: for each selected component (columns) the region-averaged
    relative concentration c [-] (x) against mu [kPa] (top row) and alpha [-] (bottom row)
    (y), one point per region labelled with its name, the least-squares line
    y = a + b c, and Kendall tau-b with its p-value in the panel title.

    Per-specimen parameters are averaged per region first (as in
    :func:`analysis.correlation.kendall_table` at the region level).  Returns ``path``.
    """
    components = list(components)
    if not components:
        raise ValueError("no components to plot")
    require_columns(composition, components, "composition")
    path = _check_dir(path)
    data = joined(parameters, composition, "region")
    data = data[data["fit"] == fit]
    if data.empty:
        raise ValueError(f"no region-level parameters for fit {fit!r}")
    fig, axes = plt.subplots(len(PARAMETERS), len(components), squeeze=False,
                             figsize=(3.2 * len(components), 5.6))
    for j, comp in enumerate(components):
        for i, par in enumerate(PARAMETERS):
            ax = axes[i, j]
            keep = data[[comp, par]].notna().all(axis=1)
            d = data[keep]
            x, y = d[comp].to_numpy(dtype=float), d[par].to_numpy(dtype=float)
            ax.scatter(x, y, s=22, color="C0", zorder=3)
            for xi, yi, name in zip(x, y, d["region"], strict=True):
                ax.annotate(name, (xi, yi), xytext=(3, 3), textcoords="offset points",
                            fontsize=7)
            if x.size >= 2 and np.ptp(x) > 0:
                b, a = np.polyfit(x, y, 1)
                xs = np.linspace(x.min(), x.max(), 2)
                ax.plot(xs, a + b * xs, color="C3", lw=1.2)
            n, tau, p = kendall_pair(x, y, f"plot, fit {fit}, {par} vs {comp}")
            ax.set_title(f"$\\tau$ = {tau:.2f}, p = {p:.3g} (n = {n})", fontsize=9)
            ax.set_xlabel(f"{comp} [-]" if i == len(PARAMETERS) - 1 else "")
            if j == 0:
                ax.set_ylabel(LABELS.get(par, par))
            ax.grid(alpha=0.3)
    fig.suptitle(f"fit: {fit}, region averages", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    log.info("wrote %s", path)
    return path
