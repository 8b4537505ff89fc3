"""Correlation of identified parameters with tissue composition (DESIGN.md section 2).

* :mod:`analysis.correlation`: Kendall tau-b tables (region and specimen level) with
  Benjamini-Hochberg adjusted p-values, region averages, top components;
* :mod:`analysis.plots`: tau heat map and the paper's Figure 8 regression plots.

:func:`correlate` runs both levels and writes the tables and figures of one analysis.
"""

from __future__ import annotations

import logging
import os

import pandas as pd

from .correlation import (
    benjamini_hochberg,
    components_of,
    joined,
    kendall_pair,
    kendall_table,
    region_averages,
    region_parameters,
    top_components,
)

__all__ = [
    "benjamini_hochberg",
    "components_of",
    "correlate",
    "joined",
    "kendall_pair",
    "kendall_table",
    "region_averages",
    "region_parameters",
    "top_components",
]

log = logging.getLogger(__name__)


def correlate(parameters: pd.DataFrame, composition: pd.DataFrame, out_dir: str, *,
              k: int = 4, fits: tuple[str, ...] | None = None) -> pd.DataFrame:
    """Kendall tables at the region level and, for per-specimen parameters, at the specimen
    level; writes ``out_dir/kendall.csv`` (both levels stacked), ``out_dir/heatmap_<level>.png``
    and ``out_dir/regression_<fit>.png`` (the ``k`` components with the largest |tau| with
    mu at the region level).  Every table is computed before anything is written, so bad
    input leaves no output.  Returns the stacked table.
    """
    from . import plots

    levels = ["region"] + (["specimen"] if "specimen" in parameters.columns else [])
    tables = [kendall_table(parameters, composition, level=lv) for lv in levels]
    table = pd.concat(tables, ignore_index=True)
    fits = tuple(fits) if fits is not None else tuple(dict.fromkeys(tables[0]["fit"]))
    picks = {f: list(top_components(tables[0], f, "mu_kPa", k=k)["component"]) for f in fits}
    os.makedirs(out_dir, exist_ok=True)
    from brain_fe.io import write_table_atomic

    write_table_atomic(table, os.path.join(out_dir, "kendall.csv"))
    for lv in levels:
        plots.heatmap(table, os.path.join(out_dir, f"heatmap_{lv}.png"), level=lv)
    for f, comps in picks.items():
        plots.regression_plots(parameters, composition, comps,
                               os.path.join(out_dir, f"regression_{f}.png"), fit=f)
    log.info("wrote Kendall tables and figures to %s", out_dir)
    return table
