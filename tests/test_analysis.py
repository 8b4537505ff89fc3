"""Kendall correlation analysis (analysis package): every number is checked against an
independent reference (hand-counted pairs, scipy, hand-computed BH values, hand means)."""

import itertools
import logging
import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from analysis import correlate
from analysis.correlation import (
    benjamini_hochberg,
    components_of,
    joined,
    kendall_table,
    region_averages,
    region_parameters,
    top_components,
)

TOL = 1e-12

# Hand-made data with one tie in x (regions B, C) and one in y (regions C, D):
#   x = mu  = [1, 2, 2, 3, 4],  y = Iba1 = [1, 3, 2, 2, 5]
# pairs (i<j): (A,B) C, (A,C) C, (A,D) C, (A,E) C, (B,C) x-tie, (B,D) D, (B,E) C,
#              (C,D) y-tie, (C,E) C, (D,E) C  ->  C = 7, D = 1
# n0 = 10, n1 = 1 (x ties), n2 = 1 (y ties): tau_b = (7 - 1) / sqrt(9 * 9) = 2 / 3
X_TIES = [1.0, 2.0, 2.0, 3.0, 4.0]
Y_TIES = [1.0, 3.0, 2.0, 2.0, 5.0]
REGIONS = ["A", "B", "C", "D", "E"]


def tau_b_by_pairs(x, y) -> float:
    """Independent tau-b: count concordant/discordant pairs and ties directly."""
    n = len(x)
    c = d = 0
    for i, j in itertools.combinations(range(n), 2):
        s = np.sign(x[j] - x[i]) * np.sign(y[j] - y[i])
        c += s > 0
        d += s < 0
    n0 = n * (n - 1) / 2
    n1 = sum(t * (t - 1) / 2 for t in pd.Series(x).value_counts())
    n2 = sum(t * (t - 1) / 2 for t in pd.Series(y).value_counts())
    return (c - d) / math.sqrt((n0 - n1) * (n0 - n2))


def region_tables(mu, comps: dict[str, list[float]], alpha=None, fit="all", regions=None):
    """Region-level parameters and a composition table with one specimen per region."""
    k = len(mu)
    regions = regions if regions is not None else REGIONS[:k]
    par = pd.DataFrame({"region": regions, "fit": fit, "mu_kPa": mu,
                        "alpha": alpha if alpha is not None else np.linspace(-30, -10, k),
                        "objective": 0.1})
    comp = pd.DataFrame({"specimen": [f"s{i}" for i in range(k)], "region": regions,
                         "brain": 1, **comps})
    return par, comp


# --------------------------------------------------------------------------- Kendall
def test_tau_b_with_ties_hand_counted_and_scipy():
    assert tau_b_by_pairs(X_TIES, Y_TIES) == pytest.approx(2 / 3, abs=TOL)
    par, comp = region_tables(X_TIES, {"Iba1": Y_TIES})
    tab = kendall_table(par, comp, level="region")
    row = tab[(tab.parameter == "mu_kPa") & (tab.component == "Iba1")].iloc[0]
    ref = stats.kendalltau(Y_TIES, X_TIES)
    assert row.n == 5
    assert row.tau == pytest.approx(2 / 3, abs=TOL)          # hand count above
    assert row.tau == pytest.approx(ref[0], abs=TOL)          # scipy tau-b
    assert row.p_value == pytest.approx(ref[1], abs=TOL)


def test_tau_random_tables_against_pair_count_and_scipy():
    rng = np.random.default_rng(4)
    mu = rng.integers(0, 4, 8).astype(float)  # integer values: many ties
    alpha = rng.normal(-20, 5, 8)
    comps = {"GFAP": rng.integers(0, 3, 8).astype(float), "HA": rng.random(8)}
    par, comp = region_tables(mu, comps, alpha=alpha, regions=[f"R{i}" for i in range(8)])
    tab = kendall_table(par, comp).set_index(["parameter", "component"])
    for p, y in (("mu_kPa", mu), ("alpha", alpha)):
        for c, x in comps.items():
            ref = stats.kendalltau(x, y)
            assert tab.loc[(p, c), "tau"] == pytest.approx(tau_b_by_pairs(x, y), abs=TOL)
            assert tab.loc[(p, c), "tau"] == pytest.approx(ref[0], abs=TOL)
            assert tab.loc[(p, c), "p_value"] == pytest.approx(ref[1], abs=TOL)


def test_monotone_component_gives_plus_and_minus_one():
    mu = [0.3, 0.5, 0.9, 1.4, 2.0]
    par, comp = region_tables(mu, {"up": [0.1, 0.2, 0.25, 0.7, 0.8],
                                   "down": [5.0, 4.0, 1.0, 0.5, -1.0]},
                              alpha=[-30.0, -25.0, -20.0, -15.0, -10.0])
    tab = kendall_table(par, comp).set_index(["parameter", "component"])
    assert tab.loc[("mu_kPa", "up"), "tau"] == pytest.approx(1.0, abs=TOL)
    assert tab.loc[("mu_kPa", "down"), "tau"] == pytest.approx(-1.0, abs=TOL)
    assert tab.loc[("alpha", "down"), "tau"] == pytest.approx(-1.0, abs=TOL)
    # exact two-sided p for n = 5, no ties: P(|T| = 1) = 2 / 5! = 1 / 60
    assert tab.loc[("mu_kPa", "up"), "p_value"] == pytest.approx(2 / 120, abs=TOL)


def test_table_format_and_families():
    par, comp = region_tables(X_TIES, {"Iba1": Y_TIES, "GFAP": [3.0, 1, 4, 1, 5],
                                       "Col_IV": [2.0, 7, 1, 8, 2]})
    par2 = par.assign(fit="compression_tension", mu_kPa=par.mu_kPa[::-1].to_numpy())
    tab = kendall_table(pd.concat([par, par2]), comp)
    assert list(tab.columns) == ["fit", "parameter", "component", "level", "n", "tau",
                                 "p_value", "p_bh", "significant", "significant_bh"]
    assert len(tab) == 2 * 2 * 3  # fits x parameters x components
    assert set(tab.level) == {"region"}
    # BH within each fit family over its 2 x 3 tests
    for _, fam in tab.groupby("fit"):
        ref = stats_bh_reference(fam.p_value.to_numpy())
        np.testing.assert_allclose(fam.p_bh.to_numpy(), ref, rtol=0, atol=TOL)
    np.testing.assert_array_equal(tab.significant, tab.p_value < 0.05)
    np.testing.assert_array_equal(tab.significant_bh, tab.p_bh < 0.05)
    assert "p_bh" not in kendall_table(par, comp, bh=False).columns


def test_top_components_ranked_by_abs_tau():
    tab = pd.DataFrame({"fit": "all", "parameter": "mu_kPa", "level": "region",
                        "component": ["a", "b", "c", "d", "e"],
                        "tau": [0.2, -0.9, np.nan, 0.5, -0.5],
                        "p_value": [0.5, 0.01, np.nan, 0.2, 0.1]})
    top = top_components(tab, "all", "mu_kPa", k=4)
    assert list(top.component) == ["b", "e", "d", "a"]  # |tau| tie broken by p
    with pytest.raises(ValueError, match="no rows for fit"):
        top_components(tab, "compression_tension", "mu_kPa")


def test_too_few_pairs_gives_nan_and_warning(caplog):
    par, comp = region_tables([1.0, 2.0, 3.0, 4.0], {"FN": [1.0, np.nan, np.nan, 2.0],
                                                    "HA": [4.0, 3.0, 2.0, 1.0]})
    with caplog.at_level(logging.WARNING, logger="analysis.correlation"):
        tab = kendall_table(par, comp).set_index(["parameter", "component"])
    assert tab.loc[("mu_kPa", "FN"), "n"] == 2
    assert np.isnan(tab.loc[("mu_kPa", "FN"), "tau"])
    assert np.isnan(tab.loc[("mu_kPa", "FN"), "p_bh"])
    assert not tab.loc[("mu_kPa", "FN"), "significant"]
    assert tab.loc[("mu_kPa", "HA"), "tau"] == pytest.approx(-1.0, abs=TOL)
    assert "only 2 paired" in caplog.text


# --------------------------------------------------------------------------- BH
def stats_bh_reference(p):
    """Independent BH: q_i = min_{j: p_j >= p_i} min(1, m p_j / rank_j), by brute force."""
    p = np.asarray(p, float)
    m = len(p)
    rank = stats.rankdata(p, method="ordinal")
    return np.array([min(1.0, min(m * p[j] / rank[j] for j in range(m) if p[j] >= p[i]))
                     for i in range(m)])


def test_bh_hand_computed():
    # sorted 0.005, 0.01, 0.03, 0.04 -> m p / i = 0.02, 0.02, 0.04, 0.04
    q = benjamini_hochberg([0.01, 0.04, 0.03, 0.005])
    np.testing.assert_allclose(q, [0.02, 0.04, 0.04, 0.02], rtol=0, atol=TOL)
    # step-up: m p / i = 0.04, 0.04, 0.1/3, 0.5 -> running min from the top gives 0.1/3
    q = benjamini_hochberg([0.01, 0.02, 0.025, 0.5])
    np.testing.assert_allclose(q, [0.1 / 3, 0.1 / 3, 0.1 / 3, 0.5], rtol=0, atol=TOL)


def test_bh_monotone_capped_nan_and_brute_force():
    rng = np.random.default_rng(7)
    p = rng.random(40) ** 3
    q = benjamini_hochberg(p)
    np.testing.assert_allclose(q, stats_bh_reference(p), rtol=0, atol=TOL)
    o = np.argsort(p)
    assert np.all(np.diff(q[o]) >= 0)              # monotone in p
    assert np.all(q >= p) and np.all(q <= 1.0)
    np.testing.assert_allclose(benjamini_hochberg([1.0, 0.9, 1.0]), [1.0, 1.0, 1.0],
                               rtol=0, atol=TOL)
    q = benjamini_hochberg([0.01, np.nan, 0.04])   # NaN is no test: m = 2
    np.testing.assert_allclose(q, [0.02, np.nan, 0.04], rtol=0, atol=TOL)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        benjamini_hochberg([0.2, 1.5])


# --------------------------------------------------------------------------- joins
@pytest.fixture
def overlap_tables():
    """Composition for s1..s6 (regions A, A, B, B, C, C); per-specimen parameters for
    s3..s8 (s7 in C, s8 in region D without composition)."""
    comp = pd.DataFrame({"specimen": [f"s{i}" for i in range(1, 7)],
                         "region": ["A", "A", "B", "B", "C", "C"],
                         "brain": [1, 2, 1, 2, 1, 2],
                         "Iba1": [1.0, 3.0, 2.0, 6.0, 5.0, 9.0],
                         "GFAP": [0.5, 0.1, 0.4, 0.2, 0.3, 0.7],
                         "identifiable": True})
    par = pd.DataFrame({"specimen": [f"s{i}" for i in range(3, 9)],
                        "region": ["B", "B", "C", "C", "C", "D"],
                        "fit": "all",
                        "mu_kPa": [0.4, 0.8, 1.0, 1.6, 2.2, 9.0],
                        "alpha": [-20.0, -24.0, -18.0, -12.0, -15.0, -1.0]})
    return par, comp


def test_region_averages_hand_means(overlap_tables):
    _, comp = overlap_tables
    assert components_of(comp) == ["Iba1", "GFAP"]  # brain (id) and booleans excluded
    avg = region_averages(comp).set_index("region")
    np.testing.assert_allclose(avg.Iba1.loc[["A", "B", "C"]], [2.0, 4.0, 7.0], atol=TOL)
    np.testing.assert_allclose(avg.GFAP.loc[["A", "B", "C"]], [0.3, 0.3, 0.5], atol=TOL)
    assert list(avg.n_specimens) == [2, 2, 2]


def test_region_and_specimen_join_n(overlap_tables):
    par, comp = overlap_tables
    rp = region_parameters(par).set_index("region")
    np.testing.assert_allclose(rp.mu_kPa.loc[["B", "C", "D"]], [0.6, 1.6, 9.0], atol=TOL)
    # region level: regions in both tables are B, C (A has no parameters, D no composition)
    reg = kendall_table(par, comp, level="region")
    assert set(reg.n) == {2} and reg.tau.isna().all()
    assert sorted(joined(par, comp, "region").region) == ["B", "C"]
    # specimen level: only s3..s6 are in both tables
    sp = kendall_table(par, comp, level="specimen")
    assert set(sp.n) == {4} and set(sp.level) == {"specimen"}
    j = joined(par, comp, "specimen")
    assert list(j.specimen) == ["s3", "s4", "s5", "s6"]
    row = sp[(sp.parameter == "mu_kPa") & (sp.component == "Iba1")].iloc[0]
    ref = stats.kendalltau([2.0, 6.0, 5.0, 9.0], [0.4, 0.8, 1.0, 1.6])
    assert row.tau == pytest.approx(ref[0], abs=TOL)
    assert row.tau == pytest.approx(tau_b_by_pairs([2, 6, 5, 9], [0.4, 0.8, 1.0, 1.6]),
                                    abs=TOL)


def test_specimen_ids_compared_as_text(overlap_tables):
    par, comp = overlap_tables
    par = par.assign(specimen=[3, 4, 5, 6, 7, 8])
    comp = comp.assign(specimen=[str(i) for i in range(1, 7)])
    assert set(kendall_table(par, comp, level="specimen").n) == {4}


# --------------------------------------------------------------------------- errors
def test_errors(overlap_tables):
    par, comp = overlap_tables
    with pytest.raises(ValueError, match="parameters table: missing column.*'mu_kPa'"):
        kendall_table(par.drop(columns="mu_kPa"), comp)
    with pytest.raises(ValueError, match="parameters table: missing column.*'fit'"):
        kendall_table(par.drop(columns="fit"), comp)
    with pytest.raises(ValueError, match="composition table: missing column.*'region'"):
        kendall_table(par, comp.drop(columns="region"))
    with pytest.raises(ValueError, match="composition table: missing column.*'specimen'"):
        kendall_table(par, comp.drop(columns="specimen"), level="specimen")
    with pytest.raises(ValueError, match="no numeric component"):
        kendall_table(par, comp[["specimen", "region", "brain"]])
    with pytest.raises(ValueError, match="level must be one of"):
        kendall_table(par, comp, level="brain")
    with pytest.raises(ValueError, match="needs per-specimen parameters"):
        kendall_table(par.drop(columns="specimen"), comp, level="specimen")
    with pytest.raises(ValueError, match="no specimen in common"):
        kendall_table(par.assign(specimen=["x1", "x2", "x3", "x4", "x5", "x6"]), comp,
                      level="specimen")
    with pytest.raises(ValueError, match="no region in common"):
        kendall_table(par.assign(region="Z"), comp)


# --------------------------------------------------------------------------- plots
def test_plots_written(tmp_path):
    from analysis import plots

    par, comp = region_tables(X_TIES, {"Iba1": Y_TIES, "GFAP": [3.0, 1, 4, 1, 5],
                                       "HA": [0.1, 0.4, 0.2, 0.8, 0.9]})
    par = pd.concat([par, par.assign(fit="compression_tension", mu_kPa=par.mu_kPa * 0.5)])
    tab = kendall_table(par, comp)
    hm = plots.heatmap(tab, str(tmp_path / "heat.png"), level="region")
    rg = plots.regression_plots(par, comp, ["Iba1", "HA"], str(tmp_path / "reg.png"))
    for path in (hm, rg):
        with open(path, "rb") as fh:
            head = fh.read(8)
        assert head == b"\x89PNG\r\n\x1a\n"
        assert (tmp_path / path).stat().st_size > 10_000
    with pytest.raises(ValueError, match="missing column.*'FN'"):
        plots.regression_plots(par, comp, ["FN"], str(tmp_path / "x.png"))
    with pytest.raises(ValueError, match="output directory does not exist"):
        plots.heatmap(tab, str(tmp_path / "no" / "heat.png"))


def test_correlate_writes_both_levels(tmp_path, overlap_tables):
    par, comp = overlap_tables
    # add composition for region D so that the region level has 3 regions (B, C, D)
    comp = pd.concat([comp, pd.DataFrame({"specimen": ["s8"], "region": ["D"], "brain": [3],
                                          "Iba1": [11.0], "GFAP": [0.9],
                                          "identifiable": [True]})], ignore_index=True)
    tab = correlate(par, comp, str(tmp_path / "out"), k=2)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "heatmap_region.png", "heatmap_specimen.png", "kendall.csv", "regression_all.png"]
    back = pd.read_csv(tmp_path / "out" / "kendall.csv")
    assert len(back) == len(tab) == 2 * 2 * 2
    assert dict(back.groupby("level").n.max()) == {"region": 3, "specimen": 5}
    # region level, mu vs Iba1: region means B, C, D = 4, 7, 11; mu = 0.6, 1.6, 9 -> tau = 1
    r = back[(back.level == "region") & (back.parameter == "mu_kPa")
             & (back.component == "Iba1")].iloc[0]
    assert r.tau == pytest.approx(1.0, abs=TOL)
