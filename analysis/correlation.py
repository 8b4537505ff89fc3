"""Kendall rank correlation between identified parameters and tissue composition.

Re-implements the statistics of the paper's sections 2.6 and 3.3: the Kendall rank
correlation coefficient tau-b between each identified Ogden parameter (shear modulus
``mu_kPa`` [kPa], exponent ``alpha`` [-]) and the relative concentration [-] of each ELISA
tissue component, for each fit set (``compression_tension``, ``all``) and on two levels:

* ``"region"``: region averages of the composition against region-level parameters
  (one point per brain region, the paper's main analysis and Figure 8);
* ``"specimen"``: only specimens present in both tables (the paper's "both" specimens,
  comparable to Linka et al.).

Input tables
------------
**parameters** (``brainmech identify`` -> ``DIR/parameters.csv``)::

    region     str    brain region (always present)
    specimen   str    specimen id (only for per-specimen fits)
    fit        str    ``compression_tension`` or ``all``
    mu_kPa     float  shear modulus mu [kPa]
    alpha      float  Ogden exponent alpha [-]
    ...               further columns are ignored

**composition** (one row per ELISA specimen)::

    specimen   str    specimen id
    region     str    brain region
    brain      str    donor brain id
    <component> float relative concentration [-], one column per component
                      (every numeric, non-boolean column other than the id columns)

Output table (:func:`kendall_table`), one row per (fit, parameter, component)::

    fit, parameter, component, level, n, tau, p_value[, p_bh], significant[, significant_bh]

Ids are compared as text (``"3"`` and ``3`` are the same specimen).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats

log = logging.getLogger(__name__)

ID_COLUMNS = ("specimen", "region", "brain")
PARAMETERS = ("mu_kPa", "alpha")
LEVELS = ("region", "specimen")
ALPHA_LEVEL = 0.05
MIN_N = 3

TABLE_COLUMNS = ["fit", "parameter", "component", "level", "n", "tau", "p_value"]


# --------------------------------------------------------------------------- validation
def require_columns(df: pd.DataFrame, columns: Sequence[str], what: str) -> None:
    """Raise ``ValueError`` naming the missing columns of the ``what`` table."""
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what} table: missing column(s) {', '.join(map(repr, missing))} "
                         f"(has {', '.join(map(str, df.columns))})")


def components_of(composition: pd.DataFrame) -> list[str]:
    """Component columns of a composition table: every numeric, non-boolean column that is
    not an id column (``specimen``, ``region``, ``brain``), in table order."""
    out = [c for c in composition.columns
           if c not in ID_COLUMNS
           and pd.api.types.is_numeric_dtype(composition[c])
           and not pd.api.types.is_bool_dtype(composition[c])]
    return out


def _check_composition(composition: pd.DataFrame, need_specimen: bool = False) -> list[str]:
    require_columns(composition, ["specimen", "region"] if need_specimen else ["region"],
             "composition")
    comps = components_of(composition)
    if not comps:
        raise ValueError("composition table: no numeric component columns (every numeric "
                         f"column other than {', '.join(ID_COLUMNS)} is a component)")
    return comps


def _check_parameters(parameters: pd.DataFrame) -> None:
    require_columns(parameters, ["region", "fit", *PARAMETERS], "parameters")
    for p in PARAMETERS:
        if not pd.api.types.is_numeric_dtype(parameters[p]):
            raise ValueError(f"parameters table: column {p!r} is not numeric")


def _as_text(s: pd.Series) -> pd.Series:
    return s.astype(str).str.strip()


# --------------------------------------------------------------------------- statistics
def benjamini_hochberg(p_values) -> np.ndarray:
    """Benjamini-Hochberg adjusted p-values (false discovery rate, independent or
    positively dependent tests).

    With the m finite p-values sorted ascending, p_(1) <= ... <= p_(m),

        q_(i) = min_{j >= i} min(1, m p_(j) / j),

    returned in the input order.  NaN entries (tests that were not performed) stay NaN and
    do not count in m.  Uses ``scipy.stats.false_discovery_control`` where scipy has it
    (>= 1.11), otherwise the formula above.

    Raises ``ValueError`` for p-values outside [0, 1].
    """
    p = np.asarray(p_values, dtype=float)
    out = np.full(p.shape, np.nan)
    ok = ~np.isnan(p)
    if not ok.any():
        return out
    q = p[ok]
    if np.any((q < 0) | (q > 1)):
        raise ValueError("p-values must lie in [0, 1]")
    fdc = getattr(stats, "false_discovery_control", None)
    if fdc is not None:
        out[ok] = fdc(q, method="bh")
        return out
    m = q.size
    order = np.argsort(q, kind="mergesort")
    scaled = q[order] * m / np.arange(1, m + 1)
    # step-up: running minimum from the largest p-value down keeps q monotone in p
    adj = np.minimum.accumulate(scaled[::-1])[::-1]
    res = np.empty(m)
    res[order] = np.minimum(adj, 1.0)
    out[ok] = res
    return out


def kendall_pair(x: np.ndarray, y: np.ndarray, label: str = "") -> tuple[int, float, float]:
    """(n, tau_b, p) of ``scipy.stats.kendalltau`` over the pairs where both values are
    finite; NaN below ``MIN_N`` pairs or when one variable is constant (tau-b undefined)."""
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    n = int(x.size)
    if n < MIN_N:
        log.warning("%s: only %d paired value(s) (< %d), Kendall tau not computed",
                    label, n, MIN_N)
        return n, math.nan, math.nan
    if np.all(x == x[0]) or np.all(y == y[0]):
        log.warning("%s: one variable is constant over the %d pairs, tau-b undefined",
                    label, n)
        return n, math.nan, math.nan
    res = stats.kendalltau(x, y)  # tau-b; exact p for small n without ties
    return n, float(res[0]), float(res[1])


# --------------------------------------------------------------------------- joins
def region_averages(composition: pd.DataFrame) -> pd.DataFrame:
    """Mean relative concentration [-] of every component per region.

    c_bar(region, k) = (1 / N_region) sum_{specimens s in region} c(s, k), NaN values
    skipped.  Returns one row per region (column ``region`` plus one column per component,
    ``n_specimens`` last: the number of composition rows of that region), sorted by region.
    """
    comps = _check_composition(composition)
    comp = composition.copy()
    comp["region"] = _as_text(comp["region"])
    g = comp.groupby("region", sort=True)
    out = g[comps].mean()
    out["n_specimens"] = g.size()
    return out.reset_index()


def region_parameters(parameters: pd.DataFrame) -> pd.DataFrame:
    """Region-level parameters: ``fit, region, mu_kPa, alpha``.

    Region-level tables (no ``specimen`` column, one row per (fit, region)) pass through.
    Per-specimen tables are averaged per (fit, region): mu_bar = mean(mu_kPa) [kPa],
    alpha_bar = mean(alpha) [-].  Note that this is not the same as the paper's fit to
    region-averaged curves (the averages of nonlinear fits differ from the fit of averaged
    data); identify region-averaged recordings to reproduce the paper exactly.
    """
    _check_parameters(parameters)
    par = parameters[["fit", "region", *PARAMETERS]].copy()
    par["region"] = _as_text(par["region"])
    par["fit"] = _as_text(par["fit"])
    if "specimen" in parameters.columns:
        log.info("parameters are per specimen: averaging mu_kPa and alpha per (fit, region)")
    elif par.duplicated(["fit", "region"]).any():
        log.warning("parameters: several rows per (fit, region) without a specimen column; "
                    "averaging them")
    return par.groupby(["fit", "region"], sort=True)[list(PARAMETERS)].mean().reset_index()


def joined(parameters: pd.DataFrame, composition: pd.DataFrame,
           level: str = "region") -> pd.DataFrame:
    """The paired data behind :func:`kendall_table`: one row per (fit, region) for
    ``level="region"`` or per (fit, specimen) for ``level="specimen"``, with the columns
    ``fit``, the id column(s), ``mu_kPa``, ``alpha`` and the component columns.

    * region: :func:`region_parameters` inner-joined on ``region`` with
      :func:`region_averages`;
    * specimen: per-specimen parameters inner-joined on ``specimen`` with the composition
      rows (several composition rows of one specimen are averaged).  The region is taken
      from the parameters table.

    Raises ``ValueError`` for missing columns, an unknown level, region-level parameters at
    the specimen level, or when the two tables have nothing in common.
    """
    if level not in LEVELS:
        raise ValueError(f"level must be one of {', '.join(LEVELS)}, got {level!r}")
    _check_parameters(parameters)
    comps = _check_composition(composition, need_specimen=(level == "specimen"))
    if level == "region":
        left = region_parameters(parameters)
        right = region_averages(composition).drop(columns="n_specimens")
        out = left.merge(right, on="region", how="inner")
        if out.empty:
            raise ValueError("no region in common between the parameters "
                             f"({', '.join(sorted(left['region'].unique()))}) and the "
                             f"composition table ({', '.join(right['region'])})")
        dropped = sorted(set(left["region"]) ^ set(right["region"]))
        if dropped:
            log.info("region level: regions only in one table are left out: %s",
                     ", ".join(dropped))
        return out
    if "specimen" not in parameters.columns:
        raise ValueError("specimen-level correlation needs per-specimen parameters "
                         "(column 'specimen' in the parameters table); these are "
                         "region-level fits")
    par = parameters[["specimen", "region", "fit", *PARAMETERS]].copy()
    for c in ("specimen", "region", "fit"):
        par[c] = _as_text(par[c])
    comp = composition[["specimen", *comps]].copy()
    comp["specimen"] = _as_text(comp["specimen"])
    if comp["specimen"].duplicated().any():
        log.warning("composition: several rows for some specimens; averaging them")
        comp = comp.groupby("specimen", sort=False)[comps].mean().reset_index()
    out = par.merge(comp, on="specimen", how="inner")
    if out.empty:
        raise ValueError("no specimen in common between the parameters and the composition "
                         "table (specimen-level correlation uses only specimens in both)")
    n_par, n_comp = par["specimen"].nunique(), comp["specimen"].nunique()
    n_both = out["specimen"].nunique()
    log.info("specimen level: %d specimen(s) in both tables (%d with parameters, %d with "
             "composition)", n_both, n_par, n_comp)
    return out.sort_values(["fit", "specimen"], kind="mergesort").reset_index(drop=True)


# --------------------------------------------------------------------------- tables
def kendall_table(parameters: pd.DataFrame, composition: pd.DataFrame, level: str = "region",
                  bh: bool = True, threshold: float = ALPHA_LEVEL) -> pd.DataFrame:
    """Kendall tau-b of each parameter (``mu_kPa``, ``alpha``) with each component.

    For n pairs (x_i, y_i) with C concordant and D discordant pairs, n0 = n (n - 1) / 2,
    n1 = sum_ties_x t (t - 1) / 2 and n2 = sum_ties_y u (u - 1) / 2,

        tau_b = (C - D) / sqrt((n0 - n1) (n0 - n2)),

    computed with ``scipy.stats.kendalltau`` (two-sided p-value; exact for small n
    without ties, normal approximation otherwise).  Pairs with a missing value are left
    out of that test, and ``n`` reports the pairs used; below 3 pairs (or with a constant
    variable) tau and p are NaN and a warning is logged.

    Levels (see :func:`joined`): ``"region"`` correlates region means of the composition
    with region-level parameters (per-specimen parameters are first averaged per region);
    ``"specimen"`` uses only specimens present in both tables.

    With ``bh`` the Benjamini-Hochberg adjusted p-value ``p_bh`` is computed within each
    (fit, level) family over all parameter x component tests that have a p-value, and
    ``significant_bh = p_bh < threshold``; ``significant = p_value < threshold`` (raw,
    threshold 0.05 by default).

    Returns one row per (fit, parameter, component), ordered by fit, parameter (mu_kPa,
    alpha) and component (table order).
    """
    data = joined(parameters, composition, level)
    comps = components_of(composition)
    rows = []
    for fit, g in data.groupby("fit", sort=True):
        for par in PARAMETERS:
            y = g[par].to_numpy(dtype=float)
            for comp in comps:
                x = g[comp].to_numpy(dtype=float)
                n, tau, p = kendall_pair(x, y, f"{level} level, fit {fit}, {par} vs {comp}")
                rows.append({"fit": fit, "parameter": par, "component": comp,
                             "level": level, "n": n, "tau": tau, "p_value": p})
    table = pd.DataFrame(rows, columns=TABLE_COLUMNS)
    table["n"] = table["n"].astype(int)
    if bh:
        table["p_bh"] = np.nan
        for _, idx in table.groupby(["fit", "level"]).groups.items():
            table.loc[idx, "p_bh"] = benjamini_hochberg(table.loc[idx, "p_value"].to_numpy())
    table["significant"] = (table["p_value"] < threshold).to_numpy(dtype=bool)
    if bh:
        table["significant_bh"] = (table["p_bh"] < threshold).to_numpy(dtype=bool)
    return table


def top_components(table: pd.DataFrame, fit: str, parameter: str, k: int = 4,
                   level: str | None = None) -> pd.DataFrame:
    """The ``k`` components with the largest |tau| for one fit and parameter.

    Ties in |tau| are broken by the smaller p-value; NaN tau comes last.  ``level`` selects
    the level when ``table`` holds both (required then).
    """
    require_columns(table, ["fit", "parameter", "component", "tau", "p_value"], "Kendall")
    sel = table[(table["fit"] == fit) & (table["parameter"] == parameter)]
    if level is not None:
        require_columns(table, ["level"], "Kendall")
        sel = sel[sel["level"] == level]
    elif "level" in sel.columns and sel["level"].nunique() > 1:
        raise ValueError("the Kendall table holds several levels "
                         f"({', '.join(sorted(sel['level'].unique()))}); pass level=")
    if sel.empty:
        raise ValueError(f"no rows for fit {fit!r} and parameter {parameter!r} "
                         f"(fits: {', '.join(map(str, table['fit'].unique()))}; parameters: "
                         f"{', '.join(map(str, table['parameter'].unique()))})")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    sel = sel.assign(abs_tau=sel["tau"].abs())
    sel = sel.sort_values(["abs_tau", "p_value"], ascending=[False, True],
                          na_position="last", kind="mergesort")
    return sel.drop(columns="abs_tau").head(k).reset_index(drop=True)
