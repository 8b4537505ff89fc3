"""`brainmech reproduce` on a tiny configuration: every stage, the report, summary.json,
and stage reuse on a re-run."""

import json
import os

import pytest


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from analysis.reproduce import ReproduceProfile, reproduce
    from recordings.brain_bank import BankSpec, make_brain_bank

    bank = tmp_path_factory.mktemp("bank")
    make_brain_bank(str(bank), BankSpec(seed=9, n_brains=2, elisa_brains=2,
                                        regions=("Am", "Hi", "Th"), refinement=1,
                                        p_missing_mechanics=0.0, p_missing_elisa=0.0))
    prof = ReproduceProfile("tiny", n_samples=10, sample_refinement=1, train_profile="tiny",
                            trials=1, executions=1, specimens=True, fit_refinement=1)
    out = tmp_path_factory.mktemp("reproduce")
    s = reproduce(str(out), custom=prof, bank=str(bank), progress=False)
    return out, bank, prof, s


def test_report_and_summary(tiny_run):
    out, bank, prof, s = tiny_run
    report = (out / "report.md").read_text()
    assert "Synthetic data" in report and "## 3. Correlation" in report
    on_disk = json.loads((out / "summary.json").read_text())
    assert set(on_disk["metrics"]) >= {"compression_tension", "torsion_0.15", "torsion_0.30"}
    truth = {r["region"]: r for r in json.loads((bank / "truth.json").read_text())
             ["region_truth"]}
    assert {r["region"] for r in on_disk["regions"]} == set(truth)
    for r in on_disk["regions"]:  # errors recomputed from the truth file (1e-12)
        assert r["true_mu_kPa"] == pytest.approx(truth[r["region"]]["mu_kPa"], rel=1e-12)
        assert r["mu_rel_err"] == pytest.approx(r["mu_kPa"] / r["true_mu_kPa"] - 1, abs=1e-12)
    assert len(on_disk["specimens"]) == 2 * 6  # 6 specimens x 2 fit sets
    assert {"sample", "train", "identify_regions", "identify_specimens", "correlate",
            "report"} <= set(on_disk["wall_time_s"])
    kend = on_disk["kendall"]
    assert all(-1 <= k["tau"] <= 1 for k in kend if k["tau"] == k["tau"])
    for f in ("figure7_fit_sets.png", "analysis/regions/heatmap_region.png",
              "fits_regions/figures/history.png", "models/compression_tension_test_curves.png"):
        assert os.path.getsize(out / f) > 5_000


def test_rerun_reuses_finished_stages(tiny_run):
    from analysis.reproduce import reproduce

    out, bank, prof, _ = tiny_run
    marks = {d: os.path.getmtime(out / d / "stage.json")
             for d in ("samples", "models", "fits_regions", "fits_specimens", "analysis")}
    s = reproduce(str(out), custom=prof, bank=str(bank), progress=False)
    assert {d: os.path.getmtime(out / d / "stage.json") for d in marks} == marks
    assert s["wall_time_s"]["sample"] > 0  # the first run's time is reported again


def test_unknown_profile_is_refused(tmp_path):
    from analysis.reproduce import reproduce

    with pytest.raises(ValueError, match="profile must be one of quick, default, paper"):
        reproduce(str(tmp_path), "fast")
