"""Homogeneous analytical Ogden model (diagnosis/homogeneous.py) and the Budday et al. reader
(diagnosis/budday.py) against independent references computed here: DESIGN.md section 3
values, a root solve on an energy written in this file and differentiated numerically,
closed forms (neo-Hooke, incompressible limit, simple shear W(g)), finite differences.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import brentq, least_squares

from recordings import budday
from simulators.homogeneous import (
    HomogeneousSimulator,
    bulk_modulus,
    simple_shear_stress,
    uniaxial_lateral_stretch,
    uniaxial_nominal_stress,
)

# --- independent reference: the energy in principal stretches, differentiated numerically ---


def energy(l1, l2, l3, mu, alpha, kappa, volumetric="quadratic"):
    """W = sum_p 2 mu_p/alpha_p^2 (sum_i (J^-1/3 l_i)^alpha_p - 3) + U(J) [kPa]
    (complex-step safe)."""
    J = l1 * l2 * l3
    W = 0.0
    for m, a in zip(mu, alpha, strict=True):
        W = W + 2 * m / a**2 * (sum((J ** (-1 / 3) * li) ** a for li in (l1, l2, l3)) - 3)
    if volumetric == "quadratic":
        return W + kappa / 2 * (J - 1) ** 2
    return W + kappa / 4 * (J**2 - 1 - 2 * np.log(J))


def nominal(i, lams, *args):
    """P_i = dW/dlambda_i [kPa] by complex step (h = 1e-30: exact to rounding)."""
    z = [complex(x) for x in lams]
    z[i] += 1e-30j
    return energy(*z, *args).imag / 1e-30


def reference_uniaxial(lam, *args):
    """(P11, s) with s from brentq on P22(lam, s, s) = 0."""
    s = brentq(lambda s: nominal(1, (lam, s, s), *args), 0.5, 2.0, xtol=1e-15, rtol=1e-15)
    return nominal(0, (lam, s, s), *args), s


def make_obs(stretches, shears, shuffle_seed=None) -> pd.DataFrame:
    """Observation table with tension/compression rows (by stretch) and simple shear rows."""
    rows = [("S", "tension" if x >= 1 else "compression", x) for x in stretches]
    rows += [("S", "simple_shear", g) for g in shears]
    obs = pd.DataFrame(rows, columns=["specimen", "curve", "control"])
    obs = obs.assign(channel="stress", branch="loading", cycle=1, time_s=np.nan, value=0.0)
    if shuffle_seed is not None:
        obs = obs.sample(frac=1.0, random_state=shuffle_seed).reset_index(drop=True)
    return obs


# --- uniaxial ---


def test_uniaxial_design_reference_and_lateral_equilibrium():
    """DESIGN.md: mu = 1 kPa, alpha = -20, kappa = 100 kPa, quadratic U:
    P(0.85) = -2.85049 kPa (rel. 1e-5); P22 = 0 at the returned s (1e-9 kPa) and P11 equal
    to dW/dlambda_1 there (rel. 1e-10)."""
    args = ([1.0], [-20.0], 100.0)
    P = uniaxial_nominal_stress(0.85, *args)
    assert P == pytest.approx(-2.85049, rel=1e-5)
    s = uniaxial_lateral_stretch(0.85, *args)
    assert abs(nominal(1, (0.85, s, s), *args)) < 1e-9
    assert P == pytest.approx(nominal(0, (0.85, s, s), *args), rel=1e-10)


@pytest.mark.parametrize("volumetric", ["quadratic", "log"])
def test_uniaxial_two_terms_against_root_solve(volumetric):
    """Two Ogden terms, both volumetric forms, stretch 0.8..1.25: P11 and s against brentq on
    the numerically differentiated energy (rel. 1e-9; 1e-12 kPa absolute near lambda = 1)."""
    mu, alpha, kappa = [0.6, 0.4], [-25.0, 5.0], 7.0
    lams = np.array([0.8, 0.9, 0.97, 1.0, 1.03, 1.1, 1.25])
    P = uniaxial_nominal_stress(lams, mu, alpha, kappa, volumetric)
    s = uniaxial_lateral_stretch(lams, mu, alpha, kappa, volumetric)
    for k, lam in enumerate(lams):
        P_ref, s_ref = reference_uniaxial(lam, mu, alpha, kappa, volumetric)
        assert P[k] == pytest.approx(P_ref, rel=1e-9, abs=1e-12)
        assert s[k] == pytest.approx(s_ref, rel=1e-12)


def test_uniaxial_alpha2_neo_hooke_and_incompressible_limit():
    """alpha = 2 is neo-Hooke W = mu/2 (Ibar1 - 3) + U: P11 = [mu (lbar1^2 - Ibar1/3) + J U']/lam
    with s from tau_2 = mu (lbar2^2 - Ibar1/3) + J U' = 0 (rel. 1e-10); and for kappa/mu = 1e7
    the incompressible closed form P = mu (lam - lam^-2) (rel. 1e-5)."""
    mu, kappa = 1.3, 40.0

    def tau(lam, s):
        J = lam * s * s
        lb1, lb2 = J ** (-1 / 3) * lam, J ** (-1 / 3) * s
        I1 = lb1**2 + 2 * lb2**2
        p = kappa * J * (J - 1)
        return mu * (lb1**2 - I1 / 3) + p, mu * (lb2**2 - I1 / 3) + p

    for lam in (0.85, 0.95, 1.1, 1.2):
        s = brentq(lambda s, lam=lam: tau(lam, s)[1], 0.5, 2.0, xtol=1e-15)
        P = uniaxial_nominal_stress(lam, [mu], [2.0], kappa)
        assert P == pytest.approx(tau(lam, s)[0] / lam, rel=1e-10)
        P_inc = uniaxial_nominal_stress(lam, [mu], [2.0], 1e7 * mu)
        assert P_inc == pytest.approx(mu * (lam - lam**-2), rel=1e-5)


# --- simple shear ---


@pytest.mark.parametrize("kappa", [1.0, 100.0, 1e6])
def test_simple_shear_alpha2_is_mu_g(kappa):
    """alpha = 2 (neo-Hooke), J = 1 exactly: P12 = mu g for any kappa (abs. 1e-10 kPa)."""
    g = np.linspace(-0.5, 0.5, 11)
    P = simple_shear_stress(g, [0.7], [2.0], kappa)
    np.testing.assert_allclose(P, 0.7 * g, rtol=0, atol=1e-10)


@pytest.mark.parametrize(("mu", "alpha"), [([1.0], [-20.0]), ([0.5], [-5.0]), ([2.0], [3.5]),
                                           ([0.6, 0.4], [-25.0, 10.0])])
def test_simple_shear_against_closed_form_energy(mu, alpha):
    """P12 = dW/dg, W(g) = sum_p 2 mu_p/alpha_p^2 (l^alpha_p + l^-alpha_p - 2),
    l = g/2 + sqrt(1 + g^2/4); central difference h = 1e-5 in the test (rel. 1e-7)."""

    def W(g):
        l1 = g / 2 + np.sqrt(1 + g * g / 4)
        return sum(2 * m / a**2 * (l1**a + l1**-a - 2) for m, a in zip(mu, alpha, strict=True))

    h = 1e-5
    for g in (0.02, 0.1, 0.2, 0.35):
        ref = (W(g + h) - W(g - h)) / (2 * h)
        assert simple_shear_stress(g, mu, alpha) == pytest.approx(ref, rel=1e-7)


# --- N terms, offsets ---


def test_two_terms_with_zero_second_modulus_equal_one_term():
    """mu_1 = 0 (any alpha_1): functions and simulator equal the one-term model (rel. 1e-12)."""
    lams, g = np.linspace(0.9, 1.1, 9), np.linspace(0, 0.2, 5)
    one = ([1.2], [-18.0])
    two = ([1.2, 0.0], [-18.0, 7.0])
    np.testing.assert_allclose(uniaxial_nominal_stress(lams, *two, 50.0),
                               uniaxial_nominal_stress(lams, *one, 50.0), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(simple_shear_stress(g, *two), simple_shear_stress(g, *one),
                               rtol=1e-12, atol=1e-15)
    sim = HomogeneousSimulator(make_obs(lams, g))
    y1, _ = sim.predict({"mu_0": 1.2, "alpha_0": -18.0, "nu0": 0.49}, [])
    y2, _ = sim.predict({"mu_0": 1.2, "alpha_0": -18.0, "mu_1": 0.0, "alpha_1": 7.0,
                         "nu0": 0.49}, [])
    np.testing.assert_allclose(y2, y1, rtol=1e-12, atol=1e-15)


def test_offsets_shift_the_curves_exactly():
    """stretch_offset d: P(lam; d) = P(lam + d; 0) (rel. 1e-14); in the simulator
    stretch_offset/stress_offset act on tension/compression rows, shear_offset on shear rows
    (abs. 1e-14 kPa)."""
    args = ([1.0], [-20.0], 100.0)
    lams, d = np.linspace(0.9, 1.1, 9), 0.013
    np.testing.assert_allclose(uniaxial_nominal_stress(lams, *args, stretch_offset=d),
                               uniaxial_nominal_stress(lams + d, *args), rtol=1e-14)
    g = np.array([0.05, 0.1])
    obs = make_obs(lams, g)
    sim = HomogeneousSimulator(obs)
    base = {"mu_0": 1.0, "alpha_0": -20.0, "kappa": 100.0}
    y, _ = sim.predict(base | {"stretch_offset": d, "stress_offset": 0.1, "shear_offset": -0.2},
                       [])
    uni = obs["curve"].ne("simple_shear").to_numpy()
    np.testing.assert_allclose(y[uni], uniaxial_nominal_stress(lams + d, *args) + 0.1,
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(y[~uni], simple_shear_stress(g, [1.0], [-20.0]) - 0.2,
                               rtol=0, atol=1e-14)


# --- simulator: row order and Jacobian ---

ALL_NAMES_NU = ["mu_0", "alpha_0", "mu_1", "alpha_1", "nu0", "stretch_offset", "stress_offset",
                "shear_offset"]


@pytest.mark.parametrize(("values", "names"), [
    ({"mu_0": 1.1, "alpha_0": -19.0, "nu0": 0.49, "stretch_offset": 0.004,
      "stress_offset": 0.02, "shear_offset": -0.01},
     ["mu_0", "alpha_0", "nu0", "stretch_offset", "stress_offset", "shear_offset"]),
    ({"mu_0": 0.6, "alpha_0": -25.0, "mu_1": 0.4, "alpha_1": 6.0, "nu0": 0.45,
      "stretch_offset": -0.003}, ALL_NAMES_NU),
    ({"mu_0": 0.8, "alpha_0": -12.0, "kappa": 30.0}, ["kappa", "alpha_0", "mu_0"]),
])
def test_predict_jacobian_against_finite_differences(values, names):
    """J = dy/d(names) against central differences of predict (step 1e-6 max(|v|, 1); error
    <= 1e-5 of the column's largest entry); kappa moves with mu_p when nu0 is given."""
    sim = HomogeneousSimulator(make_obs(np.linspace(0.9, 1.1, 17), np.linspace(0, 0.2, 9),
                                        shuffle_seed=4))
    y, J = sim.predict(values, names)
    assert J.shape == (len(y), len(names))
    for j, name in enumerate(names):
        v0 = values.get(name, 0.0)
        h = 1e-6 * max(abs(v0), 1.0)
        up, dn = dict(values), dict(values)
        up[name], dn[name] = v0 + h, v0 - h
        fd = (sim.predict(up, [])[0] - sim.predict(dn, [])[0]) / (2 * h)
        scale = max(np.max(np.abs(fd)), 1e-12)
        assert np.max(np.abs(J[:, j] - fd)) <= 1e-5 * scale, name


def test_predict_follows_row_order_and_bulk_modulus():
    """Rows in any order: y equals the module functions at each row's control, with kappa =
    2 mu (1 + nu0)/(3 (1 - 2 nu0)) (rel. 1e-13)."""
    obs = make_obs(np.linspace(0.9, 1.1, 5), np.linspace(0.0, 0.2, 4), shuffle_seed=1)
    mu, alpha = [0.6, 0.4], [-25.0, 6.0]
    kappa = 2 * 1.0 * (1 + 0.45) / (3 * (1 - 2 * 0.45))
    assert bulk_modulus(1.0, 0.45) == pytest.approx(kappa, rel=1e-15)
    y, _ = HomogeneousSimulator(obs).predict(
        {"mu_0": 0.6, "alpha_0": -25.0, "mu_1": 0.4, "alpha_1": 6.0, "nu0": 0.45}, [])
    for k, row in obs.iterrows():
        if row["curve"] == "simple_shear":
            ref = simple_shear_stress(row["control"], mu, alpha)
        else:
            ref = uniaxial_nominal_stress(row["control"], mu, alpha, kappa)
        assert y[k] == pytest.approx(ref, rel=1e-13, abs=1e-16)


@pytest.mark.parametrize(("values", "names"), [
    ({"mu_0": 1.0, "nu0": 0.49}, []),                                # alpha_0 missing
    ({"mu_0": 1.0, "alpha_0": -20.0}, []),                           # neither nu0 nor kappa
    ({"mu_0": 1.0, "alpha_0": -20.0, "nu0": 0.49, "mu_2": 1.0, "alpha_2": 3.0}, []),
    ({"mu_0": 1.0, "alpha_0": -20.0, "nu0": 0.49}, ["mu_1"]),        # term not in values
    ({"mu_0": 1.0, "alpha_0": -20.0, "nu0": 0.49}, ["kappa"]),       # kappa follows nu0
    ({"mu_0": 1.0, "alpha_0": -20.0, "nu0": 0.49, "radius": 4.0}, []),
])
def test_predict_rejects_bad_parameter_sets(values, names):
    sim = HomogeneousSimulator(make_obs([0.9, 1.1], [0.1]))
    with pytest.raises(ValueError):
        sim.predict(values, names)


def test_names_available():
    names = HomogeneousSimulator.names_available
    for name in ("mu_0", "alpha_0", "mu_1", "alpha_1", "nu0", "kappa", "stretch_offset",
                 "stress_offset", "shear_offset"):
        assert name in names


# --- Budday et al. reader ---

HEADER = "region,test,strain_measure,value,nominal_stress_kPa\n"


def _write(tmp_path, text):
    path = tmp_path / "curves.csv"
    path.write_text(text)
    return path


def test_read_budday_small_file(tmp_path):
    path = _write(tmp_path, HEADER + "CX,tension,stretch,1.05,0.25\n"
                  "CX,simple_shear,shear,0.1,0.1\n")
    obs = budday.read_budday(path)
    assert list(obs.columns) == ["specimen", "curve", "channel", "branch", "cycle", "control",
                                 "time_s", "value"]
    assert obs["curve"].tolist() == ["tension", "simple_shear"]
    assert obs["control"].tolist() == [1.05, 0.1]
    assert obs["value"].tolist() == [0.25, 0.1]
    assert obs["time_s"].isna().all() and (obs["channel"] == "stress").all()


@pytest.mark.parametrize(("body", "row", "column"), [
    ("CX,tension,stretch,1.05,0.2\nCX,tension,stretch,1.06,0.2\nCX,tension,stretch,1.07,x1\n",
     4, "nominal_stress_kPa"),
    ("CX,tension,stretch,abc,0.2\n", 2, "value"),
    ("CX,tension,stretch,1.05,0.2\nCX,torsion,stretch,1.05,0.2\n", 3, "test"),
    ("CX,compression,shear,0.95,-0.2\n", 2, "strain_measure"),
    ("XX,compression,stretch,0.95,-0.2\n", 2, "region"),
])
def test_read_budday_bad_cell_names_file_row_column(tmp_path, body, row, column):
    """One-line ValueError naming the file, the spreadsheet row (header = row 1), the column."""
    path = _write(tmp_path, HEADER + body)
    with pytest.raises(ValueError) as err:
        budday.read_budday(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert str(path) in msg and f"row {row}," in msg and f"column {column}" in msg


def test_read_budday_missing_file_and_column(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        budday.read_budday(tmp_path / "absent.csv")
    path = _write(tmp_path, "region,test,strain_measure,value\nCX,tension,stretch,1.05\n")
    with pytest.raises(ValueError, match=r"row 1, column nominal_stress_kPa") as err:
        budday.read_budday(path)
    assert "\n" not in str(err.value)


needs_data = pytest.mark.skipif(not budday.available(),
                                reason="../shared/data/budday2017 is absent")


@needs_data
def test_real_data_shape():
    """4 regions x 3 tests x 16 points; stretches in [0.9, 1.1], shear in [0, 0.2]."""
    obs = budday.read_budday()
    counts = obs.groupby(["specimen", "curve"]).size()
    assert len(obs) == 192 and len(counts) == 12 and (counts == 16).all()
    assert set(obs["specimen"]) == {"CX", "CR", "BG", "CC"}
    uni = obs["curve"] != "simple_shear"
    assert obs.loc[uni, "control"].between(0.9 - 1e-9, 1.1 + 1e-9).all()
    assert obs.loc[~uni, "control"].between(0.0, 0.2 + 1e-9).all()


@needs_data
def test_real_data_one_term_fit_cortex():
    """One-term Ogden fit of CX (tension, compression, simple shear; nu0 = 0.49) with
    least_squares from alpha = +10 and -10: both reach the same optimum (rel. 1e-4), with
    0.1 < mu < 5 kPa and alpha < 0 (tension-compression asymmetry, Budday et al.), and an
    rms residual below 10% of the largest measured stress."""
    obs = budday.read_budday()
    cx = obs[obs["specimen"] == "CX"].reset_index(drop=True)
    sim, data = HomogeneousSimulator(cx), cx["value"].to_numpy()
    names = ["mu_0", "alpha_0"]

    def values(p):
        return {"mu_0": p[0], "alpha_0": p[1], "nu0": 0.49}

    fits = [least_squares(lambda p: sim.predict(values(p), names)[0] - data, [1.0, a0],
                          jac=lambda p: sim.predict(values(p), names)[1],
                          bounds=([1e-3, -60.0], [50.0, 60.0]), xtol=1e-12, ftol=1e-12)
            for a0 in (-10.0, 10.0)]
    mu, alpha = fits[0].x
    rms = np.sqrt(np.mean(fits[0].fun ** 2))
    info = f"CX fit: mu = {mu:.4f} kPa, alpha = {alpha:.3f}, rms = {rms:.4f} kPa"
    assert all(f.success for f in fits), info
    np.testing.assert_allclose(fits[1].x, fits[0].x, rtol=1e-4, err_msg=info)
    assert 0.1 < mu < 5.0 and alpha < 0.0, info
    assert rms < 0.1 * np.max(np.abs(data)), info
