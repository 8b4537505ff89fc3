"""The virtual brain bank: valid tables, overlap, region averages, ground truth apart."""

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def bank(tmp_path_factory):
    from recordings.brain_bank import BankSpec, make_brain_bank

    out = tmp_path_factory.mktemp("bank")
    spec = BankSpec(seed=5, n_brains=2, elisa_brains=1, regions=("Am", "Hi"), refinement=1,
                    p_missing_mechanics=0.0, p_missing_elisa=0.0)
    return out, make_brain_bank(str(out), spec)


def test_tables_pass_the_recordings_validator(bank):
    from recordings.tables import read_recordings, read_specimens

    out, summary = bank
    spec = read_specimens(str(out / "specimens.csv"))
    rec = read_recordings(str(out / "recordings.csv"), spec)
    assert summary["synthetic"] is True
    assert len(spec) == 4 and set(rec.specimen) == set(spec.specimen)
    assert set(zip(rec.test, rec.amplitude, strict=True)) == {
        ("compression_tension", 0.15), ("torsion", 0.15), ("torsion", 0.30)}
    assert set(rec.branch) == {"loading", "unloading"}
    regions = read_specimens(str(out / "regions.csv"))
    read_recordings(str(out / "recordings_regions.csv"), regions)


def test_composition_and_overlap(bank):
    import pandas as pd

    from recordings.brain_bank import COMPONENTS

    out, summary = bank
    comp = pd.read_csv(out / "composition.csv")
    assert [c for c in comp.columns if c in COMPONENTS] == list(COMPONENTS)
    assert len(COMPONENTS) == 11 and (comp[list(COMPONENTS)] > 0).all().all()
    # ELISA only for brain 1: its two specimens are in both tables
    assert sorted(comp.specimen) == ["B1-Am", "B1-Hi"]
    assert summary["counts"] == {"mechanics": 4, "composition": 2, "both": 2, "regions": 2}


def test_region_average_is_the_mean_of_normalised_curves(bank):
    """Nominal stress: plain mean; torque: mean of 2T/(pi R^3) returned for R = 4 mm
    (1e-12 relative)."""
    import pandas as pd

    out, _ = bank
    spec = pd.read_csv(out / "specimens.csv").set_index("specimen")
    rec = pd.read_csv(out / "recordings.csv")
    avg = pd.read_csv(out / "recordings_regions.csv")
    for region in ("Am", "Hi"):
        ids = spec.index[spec.region == region]
        ct = [rec[(rec.specimen == s) & (rec.test == "compression_tension")]
              .nominal_stress_kPa.to_numpy() for s in ids]
        got = avg[(avg.specimen == region) & (avg.test == "compression_tension")]
        np.testing.assert_allclose(got.nominal_stress_kPa, np.mean(ct, axis=0), rtol=1e-12)
        tau = [2 * rec[(rec.specimen == s) & (rec.test == "torsion") & (rec.amplitude == 0.3)]
               .torque_mNmm.to_numpy() / (np.pi * spec.radius_mm[s] ** 3) for s in ids]
        got = avg[(avg.specimen == region) & (avg.test == "torsion") & (avg.amplitude == 0.3)]
        np.testing.assert_allclose(got.torque_mNmm, np.mean(tau, axis=0) * np.pi * 64 / 2,
                                   rtol=1e-12, atol=1e-12)


def test_truth_is_kept_apart_and_consistent(bank):
    """truth.json holds the planted parameters; the recorded peak compression stress of a
    specimen is within the noise of a direct FE solve with its true parameters."""
    import pandas as pd

    from brain_fe import geometry
    from brain_fe.materials import MaterialParameters
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import Protocol

    out, _ = bank
    truth = json.loads((out / "truth.json").read_text())
    assert {r["region"] for r in truth["region_truth"]} == {"Am", "Hi"}
    t = truth["specimen_truth"][0]
    spec = pd.read_csv(out / "specimens.csv").set_index("specimen").loc[t["specimen"]]
    rec = pd.read_csv(out / "recordings.csv")
    ct = rec[(rec.specimen == t["specimen"]) & (rec.test == "compression_tension")]
    fm = ForwardModel(geometry.axisymmetric(spec.radius_mm, spec.height_mm, refinement=1))
    p = fm.run(Protocol("compression_tension", (1.0, 0.85), max_increment=0.015),
               MaterialParameters(mu=(t["mu_kPa"],), alpha=(t["alpha"],), nu0=0.49))
    peak = p.nominal_stress_kPa.iloc[-1]
    rec_peak = ct[np.isclose(ct.stretch, 0.85)].nominal_stress_kPa.iloc[0]
    assert rec_peak == pytest.approx(peak, abs=5 * 0.015 * abs(peak))  # 5 sigma of noise
