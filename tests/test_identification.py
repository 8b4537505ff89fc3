"""Two-stage identification on synthetic FE recordings with known parameters."""

import math
import warnings

import numpy as np
import pandas as pd
import pytest
from mpi4py import MPI

TRUTH = [(0.8, -18.0), (2.0, -8.0), (0.4, -30.0)]


@pytest.fixture(scope="module")
def fe_k1():
    from brain_fe import geometry
    from brain_fe.model import ForwardModel

    return ForwardModel(geometry.axisymmetric(refinement=1, comm=MPI.COMM_SELF))


def _specimens(n):
    return pd.DataFrame({"specimen": [f"S{i}" for i in range(n)], "region": "R",
                         "brain": "B1", "radius_mm": 4.0, "height_mm": 5.0})


@pytest.fixture(scope="module")
def synthetic(fe_k1):
    from recordings.synthetic import make_recordings

    spec = _specimens(len(TRUTH))
    truth = pd.DataFrame({"specimen": spec.specimen, "mu_kPa": [t[0] for t in TRUTH],
                          "alpha": [t[1] for t in TRUTH]})
    rec = make_recordings(spec, truth, noise=0.01, seed=11,
                          model_cache={(4.0, 5.0): fe_k1})
    return spec, truth, rec


@pytest.mark.parametrize("test", ["compression_tension", "torsion"])
def test_sensitivities_match_finite_differences(fe_k1, test):
    """d(stress, axial force)/d(mu, alpha, kappa) by direct differentiation vs central
    differences (h = 1e-6 relative) to 1e-4 relative."""
    from brain_fe.materials import MaterialParameters
    from brain_fe.protocols import Protocol

    prot = (Protocol(test, (1.0, 0.85, 1.15), max_increment=0.075) if test != "torsion"
            else Protocol(test, (0.0, 0.3), max_increment=0.1))
    base = {"mu": 1.3, "alpha": -12.0, "kappa": 60.0}

    def run(sens=False, **d):
        q = {k: base[k] + d.get(k, 0.0) for k in base}
        return fe_k1.run(prot, MaterialParameters(mu=(q["mu"],), alpha=(q["alpha"],),
                                                  kappa=q["kappa"], nu0=None),
                         sensitivities=sens)

    df = run(sens=True)
    cols = (["nominal_stress_kPa"] if test != "torsion" else ["torque_mNmm"]) + \
        ["axial_force_mN"]
    for name, key in (("mu_0", "mu"), ("alpha_0", "alpha"), ("kappa", "kappa")):
        h = 1e-6 * abs(base[key])
        plus, minus = run(**{key: h}), run(**{key: -h})
        for col in cols:
            fd = (plus[col] - minus[col]).to_numpy() / (2 * h)
            an = df[f"d_{col}/d_{name}"].to_numpy()
            big = np.abs(fd) > 1e-6 * np.abs(fd).max()
            np.testing.assert_allclose(an[big], fd[big], rtol=1e-4)


def test_spline_of_loading_branches_matches_direct_solve(fe_k1):
    """The FE simulator's spline through the loading branches equals a direct solve at
    off-grid stretches to 1e-5 of the peak stress."""
    from brain_fe.materials import MaterialParameters
    from brain_fe.protocols import Protocol
    from simulators.fe import FESimulator

    at = np.array([0.8733, 0.9517, 1.0021, 1.1234])
    obs = pd.DataFrame({"specimen": "S", "curve": "compression_tension",
                        "test": "compression_tension", "amplitude": 0.15, "channel": "stress",
                        "branch": "loading", "cycle": 1, "control": at, "time_s": np.nan,
                        "value": 1.0})
    sim = FESimulator(obs, 4.0, 5.0, nu0=0.49, path="branches",
                      geometry=fe_k1.geometry).predict({"mu_0": 0.9, "alpha_0": -15.0}).y
    p = MaterialParameters(mu=(0.9,), alpha=(-15.0,), nu0=0.49)
    direct = [fe_k1.run(Protocol("compression_tension", (1.0, x), max_increment=0.015), p)
              .nominal_stress_kPa.iloc[-1] for x in at]
    peak = abs(direct[0])
    np.testing.assert_allclose(sim, direct, atol=1e-5 * peak)


def _simulators(rec, sid, tiny_models, fe_k1, fit="all"):
    """Stage-1 (surrogates) and stage-2 (FE, branch shortcut) simulators of one specimen."""
    from identification.fit import select
    from identification.objective import identification_obs
    from simulators.fe import FESimulator
    from simulators.surrogate import SurrogateSimulator
    from surrogate.persist import load_surrogates

    obs = select(identification_obs(rec[rec.specimen == sid]), fit)
    bundles = load_surrogates(str(tiny_models[0]))
    sur = SurrogateSimulator(obs, bundles, radius_mm=4.0, height_mm=5.0, nu0=0.49)
    fe = FESimulator(obs, 4.0, 5.0, nu0=0.49, path="branches", geometry=fe_k1.geometry,
                     models=_MODELS)
    return sur, fe


_MODELS: dict = {}  # compiled models shared by the simulators of this module


def test_recovers_known_parameters_with_one_percent_noise(synthetic, tiny_models, fe_k1):
    """All tests, 1 % noise: mu within 2 %, alpha within 3 %; the FE stage lowers the FE
    objective from the surrogate optimum, in <= 15 FE protocol solves; estimates within
    4 standard errors of the truth."""
    from identification.fit import identify

    spec, truth, rec = synthetic
    for (mu, alpha), sid in zip(TRUTH, spec.specimen, strict=True):
        sur, fe = _simulators(rec, sid, tiny_models, fe_k1)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # all tests: identifiable, no warning
            res = identify(sur, fe, fit="all")
        assert res.mu_kPa == pytest.approx(mu, rel=0.02)
        assert res.alpha == pytest.approx(alpha, rel=0.03)
        assert res.stage2.objective < res.stage2.history[0][3]
        assert res.stage2.protocol_solves <= 15
        assert abs(res.mu_kPa - mu) < 4 * res.mu_se_kPa
        assert abs(res.alpha - alpha) < 4 * res.alpha_se


def test_compression_only_warns_when_not_identifiable(synthetic, tiny_models, fe_k1):
    """With alpha = -30 the compression/tension curve alone cannot separate mu from alpha
    (|correlation| > 0.99): the fit says so."""
    from identification.fit import IdentifiabilityWarning, identify

    spec, truth, rec = synthetic
    sur, fe = _simulators(rec, "S2", tiny_models, fe_k1, fit="compression_tension")
    with pytest.warns(IdentifiabilityWarning, match="not separately identifiable"):
        res = identify(sur, fe, fit="compression_tension")
    assert abs(res.correlation) > 0.99
    assert res.tests == ["compression_tension"]


def test_identify_cli_end_to_end(synthetic, tiny_models, tmp_path):
    from brainmech.main import main
    from recordings.tables import write_table as write_table_atomic

    spec, truth, rec = synthetic
    write_table_atomic(spec.iloc[:1], str(tmp_path / "specimens.csv"))
    write_table_atomic(rec[rec.specimen == "S0"], str(tmp_path / "rec.csv"))
    out = tmp_path / "out"
    rc = main(["identify", "--recordings", str(tmp_path / "rec.csv"), "--specimens",
               str(tmp_path / "specimens.csv"), "--surrogates", str(tiny_models[0]),
               "--fit", "both", "--refinement", "1", "--out", str(out)])
    assert rc == 0
    p = pd.read_csv(out / "parameters.csv")
    assert list(p.columns[:11]) == ["specimen", "region", "fit", "mu_kPa", "alpha",
                                    "mu_se_kPa", "alpha_se", "objective", "fe_solves",
                                    "surrogate_mu_kPa", "surrogate_alpha"]
    assert list(p.fit) == ["compression_tension", "all"]
    allrow = p[p.fit == "all"].iloc[0]
    assert allrow.mu_kPa == pytest.approx(TRUTH[0][0], rel=0.02)
    assert allrow.alpha == pytest.approx(TRUTH[0][1], rel=0.03)
    assert (out / "history.csv").exists() and (out / "figures" / "history.png").exists()
    assert math.isfinite(allrow.mu_se_kPa)


def test_identify_cli_bad_recordings_one_line(synthetic, tiny_models, tmp_path, capsys):
    from brainmech.main import main
    from recordings.tables import write_table as write_table_atomic

    spec, truth, rec = synthetic
    write_table_atomic(spec, str(tmp_path / "specimens.csv"))
    bad = rec.copy()
    bad["stretch"] = bad["stretch"].astype(object)
    bad.loc[3, "stretch"] = "abc"
    bad.to_csv(tmp_path / "rec.csv", index=False)
    out = tmp_path / "out"
    rc = main(["identify", "--recordings", str(tmp_path / "rec.csv"), "--specimens",
               str(tmp_path / "specimens.csv"), "--surrogates", str(tiny_models[0]),
               "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1
    assert "rec.csv line 5, column stretch" in err
    assert not out.exists()


def test_identify_region_averaged_curves(synthetic, tiny_models, tmp_path):
    """Region-averaged input (specimen ids are region names): parameters.csv is keyed by
    region, and the values match the per-specimen fit of the same curves (1e-9)."""
    from identification.batch import identify_all
    from recordings.tables import write_table as write_table_atomic

    spec, truth, rec = synthetic
    one = rec[rec.specimen == "S1"].assign(specimen="Hippocampus")
    regions = spec.iloc[[1]].assign(specimen="Hippocampus", region="Hippocampus")
    write_table_atomic(regions, str(tmp_path / "regions.csv"))
    write_table_atomic(one, str(tmp_path / "rec.csv"))
    t = identify_all(str(tmp_path / "rec.csv"), str(tmp_path / "regions.csv"),
                     str(tiny_models[0]), str(tmp_path / "out"), refinement=1)
    assert list(t.columns[:2]) == ["region", "fit"] and "specimen" not in t
    assert t.region.tolist() == ["Hippocampus"]
    assert t.mu_kPa.iloc[0] == pytest.approx(TRUTH[1][0], rel=0.02)
    assert t.alpha.iloc[0] == pytest.approx(TRUTH[1][1], rel=0.03)


def test_identify_failing_late_leaves_no_output(synthetic, tiny_models, tmp_path,
                                                monkeypatch):
    """A failure after every fit and table (here the last figure) leaves nothing behind:
    the outputs are staged and moved into place only when all succeeded (issue 18)."""
    import identification.batch as batch
    from recordings.tables import write_table as write_table_atomic

    def broken(*args, **kw):
        raise OSError("No space left on device")

    spec, truth, rec = synthetic
    write_table_atomic(spec.iloc[:1], str(tmp_path / "specimens.csv"))
    write_table_atomic(rec[rec.specimen == "S0"], str(tmp_path / "rec.csv"))
    monkeypatch.setattr(batch, "plot_history", broken)
    out = tmp_path / "out"
    with pytest.raises(OSError, match="No space left"):
        batch.identify_all(str(tmp_path / "rec.csv"), str(tmp_path / "specimens.csv"),
                           str(tiny_models[0]), str(out), refinement=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.csv", "specimens.csv"]

