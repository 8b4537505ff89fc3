"""Locating systematic misfit (diagnosis.locate) on hand-made residuals.

Observation tables follow the project's protocols: compression/tension
1 -> 1 - A -> 1 -> 1 + A -> 1 (A = 0.15) and torsion 0 -> gamma_max -> 0, ``k`` points per
branch leg, ``loading`` away from the neutral value, ``unloading`` back.  Every random
number comes from a seeded generator; tolerances are stated next to each assertion.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from diagnosis import figures as F
from diagnosis import locate as L
from diagnosis import noise as N

SIGMA = 0.3
CT = "compression_tension"
FULL = ((CT, ("stress",)), ("torsion_0.15", ("torque", "axial_force")),
        ("torsion_0.30", ("torque", "axial_force")))


def _protocol(curve: str, k: int, cycles: int) -> list[tuple[int, str, float]]:
    if curve.startswith("torsion"):
        neutral, way = 0.0, [0.0, float(curve.split("_")[1]), 0.0]
    else:
        neutral, way = 1.0, [1.0, 0.85, 1.0, 1.15, 1.0]
    rows = []
    for cy in range(1, cycles + 1):
        for a, b in zip(way[:-1], way[1:], strict=True):
            br = "loading" if abs(b - neutral) > abs(a - neutral) else "unloading"
            rows += [(cy, br, a + (b - a) * i / k) for i in range(1, k + 1)]
    return rows


def make_obs(curves=FULL, k_ct: int = 15, k_tor: int = 15, cycles: int = 2,
             specimen: str = "S1") -> pd.DataFrame:
    rows = []
    for curve, channels in curves:
        steps = _protocol(curve, k_ct if curve == CT else k_tor, cycles)
        for ch in channels:
            for j, (cy, br, c) in enumerate(steps):
                value = 10.0 * c if curve.startswith("torsion") else 5.0 * (c - 1.0)
                rows.append({"specimen": specimen, "curve": curve, "channel": ch, "branch": br,
                             "cycle": cy, "control": c, "time_s": float(j), "value": value})
    return pd.DataFrame(rows)


def three_curves() -> pd.DataFrame:
    """3 curves x 60 points, one channel each."""
    return make_obs(((CT, ("stress",)), ("torsion_0.15", ("torque",)),
                     ("torsion_0.30", ("torque",))), k_ct=15, k_tor=30, cycles=1)


def series_sigma(obs: pd.DataFrame, sigma: np.ndarray) -> np.ndarray:
    return pd.Series(sigma).groupby([obs["curve"], obs["channel"]], sort=False).first().to_numpy()


def row(table: pd.DataFrame, axis: str, segment: str) -> pd.Series:
    hit = table[(table["axis"] == axis) & (table["segment"] == segment)]
    assert len(hit) == 1, (axis, segment)
    return hit.iloc[0]


def flagged(table: pd.DataFrame, axis: str, segment: str) -> bool:
    return bool(row(table, axis, segment)["systematic"])


def run(obs: pd.DataFrame, r: np.ndarray) -> pd.DataFrame:
    return L.locate(obs, r, N.estimate_noise(obs, r))


# ------------------------------------------------------------------------ noise estimate

def quadratic_misfit(obs: pd.DataFrame, rms: float) -> np.ndarray:
    """Per series a * u^2 + b * u with u = (control - neutral) / amplitude, scaled to the
    given RMS: smooth within every (branch, cycle) run."""
    neutral = np.where(obs["curve"].str.startswith("torsion"), 0.0, 1.0)
    u = obs["control"].to_numpy() - neutral
    u = u / np.abs(u).max()
    m = u**2 + 0.5 * u
    out = np.empty(len(obs))
    for _, idx in obs.groupby(["curve", "channel"]).indices.items():
        out[idx] = m[idx] * rms / np.sqrt(np.mean(m[idx] ** 2))
    return out


def test_noise_white_and_with_smooth_misfit():
    obs = three_curves()
    assert obs.groupby("curve").size().tolist() == [60, 60, 60]
    e = SIGMA * np.random.default_rng(11).standard_normal(len(obs))
    s = series_sigma(obs, N.estimate_noise(obs, e))
    # pooled over the 3 series: within 15 % (expected relative SE ~ 8 %); each within 40 %
    # (single-series SE ~ 14 %, see noise_dof)
    assert abs(np.sqrt(np.mean(s**2)) / SIGMA - 1) < 0.15
    assert np.all(np.abs(s / SIGMA - 1) < 0.40)
    # smooth quadratic misfit of RMS 3 sigma: still within 20 %, and within 5 % of the
    # noise-only estimate (the misfit hardly enters the second differences)
    m = quadratic_misfit(obs, 3 * SIGMA)
    assert np.allclose(np.sqrt(pd.Series(m).groupby(obs["curve"]).apply(
        lambda x: np.mean(x**2))), 3 * SIGMA)
    s_m = series_sigma(obs, N.estimate_noise(obs, e + m))
    assert abs(np.sqrt(np.mean(s_m**2)) / SIGMA - 1) < 0.20
    assert np.all(np.abs(s_m / s - 1) < 0.05)
    # for contrast: the RMS of the residual is inflated more than threefold
    assert np.sqrt(np.mean((e + m) ** 2)) > 3 * SIGMA


def test_noise_bias_and_dof_over_replicates():
    """Over 60 replicates: mean sigma within 5 % of the truth, and its relative SD agrees
    with noise_dof (1 / sqrt(2 nu)) within 35 %, which the F test of locate relies on."""
    obs = three_curves()
    rng = np.random.default_rng(5)
    est = np.array([series_sigma(obs, N.estimate_noise(obs, SIGMA * rng.standard_normal(
        len(obs)))) for _ in range(60)])
    assert abs(est.mean() / SIGMA - 1) < 0.05
    nu = series_sigma(obs, N.noise_dof(obs, np.zeros(len(obs))))
    predicted = 1 / np.sqrt(2 * nu.mean())
    assert abs((est / SIGMA).std() / predicted - 1) < 0.35


def test_noise_ignores_turning_points():
    """A jump of the misfit at every branch change (offsets +-3 sigma by branch) does not
    enter: differences are formed within runs of equal (branch, cycle) only."""
    obs = three_curves()
    e = SIGMA * np.random.default_rng(2).standard_normal(len(obs))
    jump = np.where(obs["branch"] == "loading", 3 * SIGMA, -3 * SIGMA)
    np.testing.assert_allclose(N.estimate_noise(obs, e + jump), N.estimate_noise(obs, e),
                               rtol=1e-9)


def test_noise_guards():
    obs = three_curves()
    e = SIGMA * np.random.default_rng(3).standard_normal(len(obs))
    # a 4-point series borrows the pooled estimate of its channel (torque here)
    short = obs[(obs["curve"] == "torsion_0.30")].head(4)
    both = pd.concat([obs[obs["curve"] == "torsion_0.15"], short], ignore_index=True)
    r = np.concatenate([e[(obs["curve"] == "torsion_0.15").to_numpy()], [5.0, -5.0, 5.0, -5.0]])
    s = N.estimate_noise(both, r)
    assert np.all(s[-4:] == s[0])
    # alone (no pooled differences worth the name): the RMS of its residual
    s = N.estimate_noise(short, np.array([1.0, -1.0, 1.0, -1.0]))
    np.testing.assert_allclose(s, 1.0)
    # exact zero residual: never 0, floored at 1e-12 x the channel's peak |value|
    s = N.estimate_noise(obs, np.zeros(len(obs)))
    assert np.all(s > 0)
    peak = obs.groupby("channel")["value"].transform(lambda v: v.abs().max()).to_numpy()
    np.testing.assert_allclose(s, 1e-12 * peak)
    with pytest.raises(ValueError, match="residual"):
        N.estimate_noise(obs, np.zeros(3))


# -------------------------------------------------------------------------- segments

def test_segments_axes_and_cells():
    obs = make_obs()
    segs = L.segments(obs)
    labels = {(a, s) for a, s, _ in segs}
    for want in [("test", CT), ("test", "torsion_0.30"), ("channel", "torsion_0.15/torque"),
                 ("channel", "axial_force"), ("branch", "unloading"),
                 ("branch", "torsion_0.30/loading"), ("cycle", "cycle 2"),
                 ("range", f"{CT}/compression"), ("range", f"{CT}/tension"),
                 ("range", "torsion_0.15/large"), ("cell", f"{CT}/stress/loading/tension"),
                 ("cell", "torsion_0.30/axial_force/unloading/small")]:
        assert want in labels
    # a single-channel curve has no per-curve channel segment
    assert ("channel", f"{CT}/stress") not in labels
    assert all(m.dtype == bool and m.shape == (len(obs),) for _, _, m in segs)
    cells = np.array([m for a, _, m in segs if a == "cell"])
    assert np.all(cells.sum(axis=0) == 1)  # a partition
    tension = next(m for a, s, m in segs if s == f"{CT}/tension")
    assert np.all(obs["control"].to_numpy()[tension] > 1)
    small = next(m for a, s, m in segs if s == "torsion_0.30/small")
    assert obs["control"].to_numpy()[small].max() <= 0.15 + 1e-12
    # one cycle: no cycle axis; one curve: per-curve branch duplicates are dropped
    one = make_obs(((CT, ("stress",)),), cycles=1)
    axes = [(a, s) for a, s, _ in L.segments(one)]
    assert not any(a == "cycle" for a, _ in axes)
    assert ("branch", f"{CT}/loading") not in axes and ("branch", "loading") in axes


def test_runs_test_formula():
    # n1 = n2 = 10, R = 2: E R = 11, var R = 2*100*180/(400*19) = 90/19
    z, p, runs = L.runs_test(np.r_[np.ones(10), -np.ones(10)])
    assert runs == 2
    assert z == pytest.approx((2 - 11 + 0.5) / np.sqrt(90 / 19))
    assert p < 1e-4
    z, p, runs = L.runs_test(np.tile([1.0, -1.0], 10))
    assert runs == 20 and p > 0.99
    z, p, runs = L.runs_test(np.ones(12))  # a single run: p = 2^(1 - N)
    assert p == pytest.approx(2.0**-11)


# ------------------------------------------------------------- false alarms / detection

def test_false_alarm_rate_pure_noise():
    """200 replicates of white noise with the estimated sigma: replicates with any
    systematic segment <= 3 % (alpha = 1 %, Bonferroni over ~48 segments)."""
    obs = make_obs()
    rng = np.random.default_rng(2024)
    alarms = 0
    for _ in range(200):
        r = SIGMA * rng.standard_normal(len(obs))
        alarms += bool(run(obs, r)["systematic"].any())
    assert alarms / 200 <= 0.03


def _tension_loading_misfit(obs: pd.DataFrame, rms: float) -> tuple[np.ndarray, np.ndarray]:
    lam = obs["control"].to_numpy()
    cell = ((obs["curve"] == CT) & (obs["branch"] == "loading")).to_numpy() & (lam > 1 + 1e-9)
    m = np.where(cell, ((lam - 1) / 0.15) ** 2, 0.0)
    return m * rms / np.sqrt(np.mean(m[cell] ** 2)), cell


def _unloading_misfit(obs: pd.DataFrame, rms: float) -> tuple[np.ndarray, np.ndarray]:
    neutral = np.where(obs["curve"].str.startswith("torsion"), 0.0, 1.0)
    dev = np.abs(obs["control"].to_numpy() - neutral)
    top = pd.Series(dev).groupby(obs["curve"]).transform("max").to_numpy()
    unl = (obs["branch"] == "unloading").to_numpy()
    m = np.where(unl, np.sin(np.pi * dev / top), 0.0)
    return m * rms / np.sqrt(np.mean(m[unl] ** 2)), unl


def test_detects_misfit_on_tension_side_of_loading():
    obs = make_obs()
    m, cell = _tension_loading_misfit(obs, 2 * SIGMA)
    assert np.sqrt(np.mean(m[cell] ** 2)) == pytest.approx(2 * SIGMA)
    e = SIGMA * np.random.default_rng(7).standard_normal(len(obs))
    table = run(obs, e + m)
    assert flagged(table, "cell", f"{CT}/stress/loading/tension")
    # on the range axis the tension side beats the compression side and large strain
    # beats small strain (the misfit grows with stretch); one of them is the best range
    p = row(table, "range", f"{CT}/tension")["p_value"]
    assert p < row(table, "range", f"{CT}/compression")["p_value"]
    assert row(table, "range", f"{CT}/large")["p_value"] < row(table, "range", f"{CT}/small")[
        "p_value"]
    ranges = table[table["axis"] == "range"]
    assert ranges.loc[ranges["p_value"].idxmin(), "segment"] in {f"{CT}/tension", f"{CT}/large"}
    assert not table[table["segment"].str.startswith("torsion")]["systematic"].any()
    info = L.summary(table)
    assert info["systematic"]
    assert info["worst"] in {f"{CT}/stress/loading/tension", f"{CT}/tension",
                             f"{CT}/loading", CT, "stress", "loading"}
    assert any(d["segment"] == f"{CT}/stress/loading/tension" for d in info["located"])
    # rate over 40 further replicates: cell located in >= 90 % (measured ~97 %), a torsion
    # segment flagged in <= 1 of them
    rng = np.random.default_rng(8)
    hits = torsion = 0
    for _ in range(40):
        t = run(obs, SIGMA * rng.standard_normal(len(obs)) + m)
        hits += flagged(t, "cell", f"{CT}/stress/loading/tension")
        torsion += bool(t[t["segment"].str.startswith("torsion")]["systematic"].any())
    assert hits >= 36 and torsion <= 1


def test_detects_misfit_on_unloading_branch():
    obs = make_obs()
    m, unl = _unloading_misfit(obs, 2 * SIGMA)
    assert np.sqrt(np.mean(m[unl] ** 2)) == pytest.approx(2 * SIGMA)
    rng = np.random.default_rng(9)
    for _ in range(10):
        table = run(obs, SIGMA * rng.standard_normal(len(obs)) + m)
        assert flagged(table, "branch", "unloading")
        assert not flagged(table, "branch", "loading")
        assert row(table, "branch", "unloading")["p_value"] < 1e-6


def test_detects_constant_offset_on_torque_only():
    obs = make_obs()
    torque = (obs["channel"] == "torque").to_numpy()
    rng = np.random.default_rng(10)
    for _ in range(10):
        r = SIGMA * rng.standard_normal(len(obs)) + 2 * SIGMA * torque
        sigma = N.estimate_noise(obs, r)
        table = L.locate(obs, r, sigma)
        assert flagged(table, "channel", "torque")
        assert not flagged(table, "channel", "axial_force")
        assert not table[table["segment"].str.contains("axial_force")]["systematic"].any()
        # mean z = offset / sigma_hat up to noise (SE ~ 0.1 for 120 points; 4 SE allowed)
        expected = np.mean(2 * SIGMA / sigma[torque])
        assert row(table, "channel", "torque")["mean_z"] == pytest.approx(expected, abs=0.4)


def test_runs_test_catches_sign_changing_misfit():
    """An S-shaped misfit (one period of a sine over the stretch range) of RMS 1 sigma on the
    compression/tension curve adds little variance but long runs: over 30 replicates the
    runs p is the smaller one in >= 80 % (measured 97 %), and the curve is located in
    >= 50 % (measured 75 %; the chi-square test alone: 8 %)."""
    obs = make_obs()
    ct = (obs["curve"] == CT).to_numpy()
    m = np.where(ct, np.sin(2 * np.pi * (obs["control"].to_numpy() - 0.85) / 0.3), 0.0)
    m *= SIGMA / np.sqrt(np.mean(m[ct] ** 2))
    rng = np.random.default_rng(14)
    runs_smaller = hits = 0
    for _ in range(30):
        x = row(run(obs, SIGMA * rng.standard_normal(len(obs)) + m), "test", CT)
        runs_smaller += x["p_runs"] < x["p_chi2"]
        hits += x["systematic"]
    assert runs_smaller >= 24 and hits >= 15


# ------------------------------------------------------------------- outputs and guards

def test_table_columns_and_summary_json():
    obs = make_obs()
    m, _ = _tension_loading_misfit(obs, 3 * SIGMA)
    r = SIGMA * np.random.default_rng(12).standard_normal(len(obs)) + m
    table = run(obs, r)
    assert list(table.columns[:11]) == ["axis", "segment", "n", "mean_z", "rms_z", "chi2",
                                        "p_chi2", "runs_z", "p_runs", "p_value", "systematic"]
    tested = table["p_value"].notna()
    assert table.attrs["m"] == int(tested.sum())
    np.testing.assert_allclose(table.loc[tested, "p_value"], np.minimum(
        1, 2 * np.minimum(table.loc[tested, "p_chi2"], table.loc[tested, "p_runs"])))
    assert (table["systematic"] == (table["p_value"] < 0.01 / table.attrs["m"])).all()
    info = L.summary(table)
    assert json.loads(json.dumps(info)) == info
    ps = [d["p_value"] for d in info["located"]]
    assert ps == sorted(ps) and len(ps) == int(table["systematic"].sum())
    assert all(type(d["n"]) is int and type(d["rms_z"]) is float for d in info["located"])
    # pure noise: nothing located, still a worst segment
    quiet = L.summary(run(obs, SIGMA * np.random.default_rng(13).standard_normal(len(obs))))
    assert quiet["systematic"] is False and quiet["located"] == []
    assert isinstance(quiet["worst"], str)
    with pytest.raises(ValueError):
        L.locate(obs, r, np.ones(3))


def test_mismatch_map_writes_png(tmp_path):
    obs = make_obs()
    m, _ = _tension_loading_misfit(obs, 2 * SIGMA)
    r = SIGMA * np.random.default_rng(7).standard_normal(len(obs)) + m
    sigma = N.estimate_noise(obs, r)
    table = L.locate(obs, r, sigma)
    path = tmp_path / "map.png"
    assert F.mismatch_map(obs, r, sigma, table, path) == str(path)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    with pytest.raises(ValueError, match="does not exist"):
        F.mismatch_map(obs, r, sigma, table, tmp_path / "missing" / "map.png")
