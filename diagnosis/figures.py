"""Figures of a diagnosis: where the misfit is (the mismatch map) and the fits before and
after modelling the named physics."""

from __future__ import annotations

import io
import logging
import math
import os

import numpy as np
import pandas as pd

from brain_fe.io import write_figure_atomic

from .locate import cells
from .series import as_float, check, neutral_of, run_ids

log = logging.getLogger(__name__)



def _margins(fig, *, left, right, top, bottom, wgap, hgap) -> None:
    """Place a figure's grid of panels by fixed margins and gaps (inches): a layout engine
    (constrained or tight) measures every tick label of every panel and costs more than
    drawing the figure (0.4 s of a 1-s mismatch map).  For the same reason the titles sit
    at a fixed height (``y=1.0``: matplotlib otherwise measures each panel's decorations
    to place its title above them)."""
    w, h = fig.get_size_inches()
    gs = fig.axes[0].get_subplotspec().get_gridspec()
    nrows, ncols = gs.get_geometry()
    aw = (w - left - right - (ncols - 1) * wgap) / ncols  # one panel's width
    ah = (h - top - bottom - (nrows - 1) * hgap) / nrows
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wgap / aw, hspace=hgap / ah)


def mismatch_map(obs: pd.DataFrame, residual, sigma, table: pd.DataFrame, path) -> str:
    """Figure of where the misfit is, written to ``path`` (PNG; parent directory must exist).

    One panel per (curve, channel): ``z = residual / sigma`` against the control value,
    loading and unloading in different colours (recording order joined by thin lines
    within each (branch, cycle) run), the band ``|z| <= 2`` shaded grey, and the control
    range of each systematic ``cell`` shaded red and named by its branch.  A last panel
    is a heat map of ``-log10 p_value`` over the cells (rows curve/channel, columns
    branch/part), systematic cells marked ``*`` and the Bonferroni level on the colour bar;
    untested cells are grey.  Returns ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    check(obs)
    path = os.fspath(path)
    n_rows = len(obs)
    r = as_float(residual, "residual", n_rows)
    s = as_float(np.broadcast_to(np.asarray(sigma, dtype=float), (n_rows,)), "sigma", n_rows)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = r / s
    curve = obs["curve"].astype(str).to_numpy()
    channel = obs["channel"].astype(str).to_numpy()
    branch = obs["branch"].astype(str).to_numpy()
    control = obs["control"].to_numpy(dtype=float)
    run_id = run_ids(obs)

    cell_list = cells(obs)
    ctab = table[table["axis"] == "cell"].set_index("segment")
    pairs = list(dict.fromkeys((c.curve, c.channel) for c in cell_list))
    colors = {"loading": "tab:blue", "unloading": "tab:orange"}

    n_panels = len(pairs) + 1
    ncols = min(3, n_panels)
    nrows = math.ceil(n_panels / ncols)
    fig, axes = plt.subplots(nrows, ncols, squeeze=False, figsize=(4.6 * ncols, 3.4 * nrows))
    # the heat map's row labels (curve over channel, 6 pt) need their width left of it,
    # whichever column it lands in: ~0.055 in per character and the ticks
    label_in = 0.055 * max(len(w) for cv, ch in pairs for w in (cv, ch)) + 0.2 \
        if pairs else 0.0
    _margins(fig, left=max(0.85, label_in + 0.05), right=0.4, top=0.4, bottom=0.85,
             wgap=max(1.0, label_in + 0.15), hgap=0.95)
    flat = list(axes.ravel())
    for ax, (cv, ch) in zip(flat, pairs, strict=False):
        m_cc = (curve == cv) & (channel == ch) & np.isfinite(z) & np.isfinite(control)
        ax.axhspan(-2.0, 2.0, color="0.88", zorder=0, label=r"$|z| \leq 2$")
        ax.axhline(0.0, color="0.5", lw=0.6, zorder=1)
        for c in cell_list:
            if c.curve != cv or c.channel != ch or c.label not in ctab.index:
                continue
            if not bool(ctab.loc[c.label, "systematic"]):
                continue
            x = control[c.mask & np.isfinite(control)]
            if x.size:
                lo, hi = float(x.min()), float(x.max())
                if hi == lo:
                    pad = 0.01 * max(abs(lo), 1e-3)
                    lo, hi = lo - pad, hi + pad
                ax.axvspan(lo, hi, color="tab:red", alpha=0.13, zorder=0)
                ax.text(0.5 * (lo + hi), 1.0, f"{c.branch}\np={ctab.loc[c.label, 'p_value']:.1g}",
                        transform=ax.get_xaxis_transform(), ha="center", va="top", fontsize=7,
                        color="tab:red")
        shown = set()
        for rid in np.unique(run_id[m_cc]):
            m = m_cc & (run_id == rid)
            br = branch[m][0]
            col = colors.get(br, "0.4")
            ax.plot(control[m], z[m], "-", color=col, lw=0.5, alpha=0.6, zorder=2)
            ax.plot(control[m], z[m], "o", ms=2.8, color=col, zorder=3,
                    label=None if br in shown else br)
            shown.add(br)
        ax.axvline(neutral_of(cv), color="0.6", lw=0.6, ls=":")
        ax.set_title(f"{cv} - {ch}", fontsize=9, y=1.0)
        ax.set_xlabel("amount of shear [-]" if neutral_of(cv) == 0.0 else "stretch [-]")
        ax.set_ylabel(r"$z = r / \sigma$")
        ax.legend(fontsize=7, loc="lower left")

    hm = flat[len(pairs)]
    cols = list(dict.fromkeys((c.branch, c.part) for c in cell_list))
    # drop columns with nothing tested (e.g. the few points at stretch exactly 1)
    tested_cols = {(c.branch, c.part) for c in cell_list if c.label in ctab.index
                   and math.isfinite(float(ctab.loc[c.label, "p_value"]))}
    cols = [c for c in cols if c in tested_cols] or cols
    mat = np.full((len(pairs), len(cols)), np.nan)
    mark = np.zeros_like(mat, dtype=bool)
    for c in cell_list:
        if c.label in ctab.index and (c.branch, c.part) in cols:
            i, j = pairs.index((c.curve, c.channel)), cols.index((c.branch, c.part))
            p = float(ctab.loc[c.label, "p_value"])
            if math.isfinite(p):
                mat[i, j] = -math.log10(max(p, 1e-300))
            mark[i, j] = bool(ctab.loc[c.label, "systematic"])
    cmap = plt.get_cmap("magma_r").copy()
    cmap.set_bad("0.85")
    thr = table.attrs.get("threshold")
    finite_vals = mat[np.isfinite(mat)]
    vmax = max(float(finite_vals.max()) if finite_vals.size else 1.0,
               -math.log10(thr) if thr and math.isfinite(thr) else 1.0, 1.0)
    im = hm.imshow(np.ma.masked_invalid(mat), cmap=cmap, vmin=0.0, vmax=vmax, aspect="auto")
    for i, j in zip(*np.nonzero(mark), strict=True):
        hm.text(j, i, "*", ha="center", va="center", color="white", fontsize=12,
                fontweight="bold")
    hm.set_xticks(range(len(cols)), [f"{b}\n{p}" for b, p in cols], fontsize=6, rotation=90)
    hm.set_yticks(range(len(pairs)), [f"{cv}\n{ch}" for cv, ch in pairs], fontsize=6)
    hm.set_title(r"$-\log_{10} p$ per cell (* systematic)", fontsize=9, y=1.0)
    cb = fig.colorbar(im, ax=hm, shrink=0.9, fraction=0.08, pad=0.03)
    if thr and math.isfinite(thr):
        cb.ax.axhline(-math.log10(thr), color="tab:cyan", lw=1.5)
        cb.set_label(r"$-\log_{10} p$ (line: $\alpha / m$)", fontsize=7)
    for ax in flat[len(pairs) + 1:]:
        ax.set_visible(False)
    write_figure_atomic(fig, path, dpi=110)
    plt.close(fig)
    log.info("mismatch map written to %s", path)
    return path


def before_after_png(d) -> bytes:
    """Recording, base fit and refit for every curve/channel, loading and unloading, as
    PNG bytes (another MPI rank may draw it)."""
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
        if d.effects:
            ax.plot(x, d.final.prediction[i], "-", color="tab:red", lw=1,
                    label=f"with {d.verdict}")
        rb, ra = d.base.rms(d.obs, d.sigma, i), d.final.rms(d.obs, d.sigma, i)
        ax.set_title(f"{curve} / {ch}\nRMS/noise {rb:.2f} -> {ra:.2f}", fontsize=9, y=1.0)
        ax.set_xlabel("stretch" if "compression" in curve or "tension" in curve
                      else "amount of shear")
    axes[0][0].legend(fontsize=7)
    _margins(fig, left=0.7, right=0.15, top=0.5, bottom=0.5, wgap=0.7, hgap=0.0)  # "-1500"
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def across_specimens(results: dict, groups: dict, path) -> None:
    """Every specimen of a batch: RMS against the noise before and after (log-log, one
    marker per group; below the dashed line the effects fitted halve it: named, unless
    they leave a stiffness trend) and the verdicts per group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(groups.values()))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 4.2))
    markers = "osD^v<>phX*"
    for k, g in enumerate(names):
        rs = [r for n, r in results.items() if groups.get(n) == g and "error" not in r]
        if rs:
            ax.loglog([r["rms_before"] for r in rs], [r["rms_after"] for r in rs],
                      markers[k % len(markers)], label=g, alpha=0.8)
    lim = ax.get_xlim()
    ax.plot(lim, lim, "k-", lw=0.7)
    ax.plot(lim, [0.5 * v for v in lim], "k--", lw=0.7)
    ax.set_xlabel("RMS / noise, base model")
    ax.set_ylabel("RMS / noise, final model")
    ax.legend(fontsize=7)
    verdicts = sorted({r["verdict"] for r in results.values()})
    bottom = np.zeros(len(names))
    for v in verdicts:
        h = np.array([sum(1 for n, r in results.items() if groups.get(n) == g
                          and r["verdict"] == v) for g in names], float)
        bx.barh(names, h, left=bottom, label=v)
        bottom += h
    bx.set_xlabel("specimens")
    bx.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # off the bars
    fig.tight_layout()
    write_figure_atomic(fig, path, dpi=110)
    plt.close(fig)
