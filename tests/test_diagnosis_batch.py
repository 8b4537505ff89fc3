"""The batch of ``brainmech diagnose`` over many specimens: a specimen the model cannot
solve is recorded as not diagnosed (with why) and does not stop the others; the summary
groups the specimens (material/protocol of imported exports) and is resumable.  The FE
diagnosis itself is replaced by a stand-in here (it is tested in test_diagnosis.py and
test_open_world.py); what is tested is the batch's bookkeeping."""

from __future__ import annotations

import json

import pytest

import diagnosis.batch as batch
from diagnosis.fitting import UnsolvableStart, solvable_start

HEADER = ("specimen,test,amplitude,cycle,branch,time_s,stretch,shear,"
          "nominal_stress_kPa,torque_mNmm,axial_force_mN\n")


def _tables(tmp_path):
    spec = tmp_path / "specimens.csv"
    spec.write_text("specimen,region,brain,radius_mm,height_mm\n"
                    "a/1,fungi,2s,4,9\na/2,fungi,2s,4,9\nb/1,fungi,8s,4,9\n")
    rows = "".join(f"{s},compression_tension,0.2,1,loading,{i},{1 - 0.05 * i},,"
                   f"{-0.5 * i},,\n" for s in ("a/1", "a/2", "b/1") for i in range(5))
    rec = tmp_path / "recordings.csv"
    rec.write_text(HEADER + rows)
    return str(rec), str(spec)


def _stand_in(calls):
    def one(name, rec, specs, target, *, refinement, effects, nu0, noise, comm, progress,
            check_digits):
        calls.append((name, noise))
        if name == "a/2":
            raise UnsolvableStart("the base model cannot be solved along this protocol")
        res = {"verdict": "viscoelastic", "effects": ["viscoelastic"], "status": "explained",
               "rms_before": 4.0, "rms_after": 1.0, "located": [], "remaining": {},
               "refit_parameters": {"mu_0": 2.0 if name == "a/1" else 3.0}}
        target.mkdir(parents=True, exist_ok=True)
        (target / "diagnosis.json").write_text(json.dumps(res))
        return res
    return one


def test_a_specimen_that_cannot_be_modelled_does_not_stop_the_batch(tmp_path, monkeypatch):
    rec, spec = _tables(tmp_path)
    noise = tmp_path / "noise.json"
    noise.write_text(json.dumps({"a/1": {"stress": 0.2}, "b/1": {"stress": 0.1}}))
    from brainmech.args import noise_option

    calls = []
    monkeypatch.setattr(batch, "_diagnose_one", _stand_in(calls))
    out = tmp_path / "out"
    res = batch.diagnose_recordings(rec, spec, str(out), noise=noise_option(str(noise)))
    assert dict(calls) == {"a/1": {"stress": 0.2}, "a/2": None, "b/1": {"stress": 0.1}}
    assert res["a/2"]["verdict"] == "not diagnosed" and "cannot be solved" in res["a/2"]["error"]
    assert (out / "a" / "2" / batch.FAILED).exists()
    summary = (out / "summary.md").read_text()
    assert "| a/2 | not diagnosed |" in summary
    # grouped by material/protocol: fungi/2s holds a/1 (diagnosed) and a/2 (not)
    assert "| fungi/2s | 1 | viscoelastic 1, not diagnosed 1 | viscoelastic 1 |" in summary
    assert "| fungi/2s | mu_0 | 1 | 2 | 2 | 2 |" in summary
    assert "1/1" in summary  # RMS after <= half of before where an effect is named
    assert (out / "summary.png").stat().st_size > 10_000
    # resumed: nothing diagnosed again, the failure included
    monkeypatch.setattr(batch, "_diagnose_one", lambda *a, **k: pytest.fail("re-diagnosed"))
    again = batch.diagnose_recordings(rec, spec, str(out), noise=noise_option(str(noise)))
    assert all(r["reused"] for r in again.values()) and set(again) == {"a/1", "a/2", "b/1"}
    # diagnoses of another engine are not mixed in: the same folder is refused
    monkeypatch.setattr(batch, "ENGINE_VERSION", "another")
    with pytest.raises(ValueError, match="another engine"):
        batch.diagnose_recordings(rec, spec, str(out), noise=noise_option(str(noise)))


class _Stiff:
    """A stand-in simulator that cannot be solved for alpha < 0 (like a brain-like start at
    50 % compression)."""

    def predict(self, values, wrt):
        import numpy as np

        from brain_fe.solver import ConvergenceError

        if {str(k): v for k, v in values.items()}["alpha_0"] < 0:
            raise ConvergenceError("Newton failed at stretch = 0.58")
        return np.ones(3), None


def test_the_base_start_moves_on_when_the_model_cannot_be_solved():
    start = solvable_start(_Stiff(), {"mu_0": 1.0, "alpha_0": -10.0, "nu0": 0.49})
    assert {str(k): v for k, v in start.items()}["alpha_0"] == 2.0  # the first solvable one

    class Never(_Stiff):
        def predict(self, values, wrt):
            from brain_fe.solver import ConvergenceError

            raise ConvergenceError("Newton failed at stretch = 0.58")

    with pytest.raises(UnsolvableStart, match="stretch = 0.58"):
        solvable_start(Never(), {"mu_0": 1.0, "alpha_0": -10.0, "nu0": 0.49})


def test_a_finer_mesh_that_cannot_follow_leaves_the_model_uncorrected_and_says_so():
    """The k + 1 mesh of the discretisation correction can fail where the working mesh
    solves (its glued corner at 40 % compression, measured on the rheometer's double
    compressions): the diagnosis goes on uncorrected and the report says why.  The base fit
    is then exactly the working model's (the analytical homogeneous model here: mu = 1.3
    kPa, alpha = -15 recovered to 1e-6 from noise-free data)."""
    import numpy as np
    import pandas as pd

    from brain_fe.solver import ConvergenceError
    from diagnosis.engine import _base
    from simulators.homogeneous import HomogeneousSimulator

    lam = np.r_[np.linspace(0.99, 0.85, 8), np.linspace(1.01, 1.15, 8)]
    obs = pd.DataFrame({"specimen": "S", "curve": ["compression"] * 8 + ["tension"] * 8,
                        "channel": "stress", "branch": "loading", "cycle": 1,
                        "control": lam, "time_s": np.nan, "value": 0.0})
    sim = HomogeneousSimulator(obs)
    truth = {"mu_0": 1.3, "alpha_0": -15.0, "nu0": 0.49}
    obs["value"] = sim.predict(truth, [])[0]

    class Fails:
        refinement = 2

        def predict(self, values, wrt):
            raise ConvergenceError("Newton failed at stretch = 0.6")

    base, _, disc, _ = _base(sim, Fails(), obs, {"stress": 1e-3})
    assert disc["corrected"] is False
    assert "k = 2 cannot be solved" in disc["not_corrected_because"]
    assert "stretch = 0.6" in disc["not_corrected_because"]
    got = {str(k): v for k, v in base.values.items()}
    assert got["mu_0"] == pytest.approx(1.3, rel=1e-6)
    assert got["alpha_0"] == pytest.approx(-15.0, rel=1e-6)


def test_points_off_the_specimen_are_reported_apart():
    """The misfit on the points recorded after a lift-off is stated apart from the rest
    (unit noise: the RMS is the plain RMS of the residual)."""
    import numpy as np
    import pandas as pd

    from diagnosis.fitting import Fit
    from diagnosis.notes import contact_notes

    def fit(prediction):
        return Fit(effect="", names=[], values={}, chi2=0.0, n=6, prediction=prediction,
                   z=np.zeros(6), nfev=0)

    obs = pd.DataFrame({"value": np.zeros(6), "in_contact": [1, 1, 1, 1, 0, 0]})
    base = fit(np.array([1.0, -1, 1, -1, 4, 4]))
    final = fit(np.array([0.5, -0.5, 0.5, -0.5, 3, 3]))
    (note,) = contact_notes(obs, base, final, np.ones(6))
    assert note.startswith("2 of 6 points") and "on them 4.00 (base) -> 3.00" in note
    assert "in contact 1.00 -> 0.50" in note
    assert contact_notes(obs.assign(in_contact=1), base, final, np.ones(6)) == []


def test_the_model_s_lift_off_is_set_beside_the_recorded_one():
    """Unglued ends: the final model's contact events (here of a stand-in simulator) are
    reported beside the changes of in_contact in the recordings, per curve and cycle."""
    from types import SimpleNamespace

    import pandas as pd

    from brain_fe.contact import ContactEvent
    from diagnosis.notes import contact_event_notes, recorded_events

    obs = pd.DataFrame({"curve": "ct", "channel": "stress", "cycle": [1, 1, 1, 2, 2, 2],
                        "control": [0.6, 0.7, 0.8, 0.9, 0.75, 0.6],
                        "in_contact": [1, 0, 0, 0, 1, 1]})
    assert recorded_events(obs) == {"ct": [("lift-off", 1, 0.7), ("re-contact", 2, 0.75)]}
    events = [ContactEvent("lift-off", 1.0, 0.68, 0.01, 1),
              ContactEvent("re-contact", 2.0, 0.78, 0.0, 2)]
    sim = SimpleNamespace(contact_events=lambda values: {"ct": events})
    (note,) = contact_event_notes(obs, sim, SimpleNamespace(values={}))
    assert note == ("ct: the final model lift-off in cycle 1 at 0.680, re-contact in cycle 2 "
                    "at 0.780; recorded lift-off in cycle 1 at 0.700, re-contact in cycle 2 "
                    "at 0.750 (stretch)")


def test_the_summary_says_what_the_diagnoses_make_of_rate_and_cycles():
    """Two groups of one material, the same two-cycle test at loading rates 0.1 and 0.025
    per second (stretch 1 -> 0.9 in 1 s and in 4 s): the fast one named viscoelastic (tau
    10^-1 s) and Mullins, the slow one with both candidates unsolvable along its path.
    The rates are read from the recordings; the summary names what each speed shows."""
    import pandas as pd

    from diagnosis.batch import protocol_facts, signatures_markdown

    rows = []
    for name, ramp_s in (("A", 1.0), ("B", 4.0)):
        for cycle in (1, 2):
            t0 = (cycle - 1) * 2 * ramp_s
            for k in range(5):
                rows.append({"specimen": name, "test": "compression_tension",
                             "amplitude": 0.1, "cycle": cycle, "branch": "loading",
                             "time_s": t0 + k * ramp_s / 4, "stretch": 1.0 - 0.1 * k / 4})
    for branch, x0, x1, t0 in (("loading", 1.0, 0.9, 0.0), ("unloading", 0.9, 1.0, 1.0),
                               ("loading", 1.0, 1.1, 2.0), ("unloading", 1.1, 1.0, 3.0)):
        for k in range(5):  # C: one compression-tension cycle, each ramp 0.1 in 1 s
            rows.append({"specimen": "C", "test": "compression_tension", "amplitude": 0.1,
                         "cycle": 1, "branch": branch, "time_s": t0 + k / 4,
                         "stretch": x0 + (x1 - x0) * k / 4})
    facts = protocol_facts(pd.DataFrame(rows))
    assert facts["C"]["rate_per_s"] == pytest.approx(0.1)  # ramp by ramp, not per cycle
    assert facts["A"]["rate_per_s"] == pytest.approx(0.1)
    assert facts["B"]["rate_per_s"] == pytest.approx(0.025)
    assert facts["A"]["cycles"] == 2
    blind = {"rounds": [{"table": [{"effect": "viscoelastic", "score_failed": True},
                                   {"effect": "mullins", "score_failed": True}]}]}
    results = {"A": {"effects": ["viscoelastic", "mullins"], "rounds": [{"table": []}],
                     "refit_parameters": {"log10_tau_0": -1.0, "beta_0": 2.0,
                                          "softening": 0.3}},
               "B": {"effects": [], "refit_parameters": {}, **blind}}
    text = signatures_markdown(results, {"A": "m/fast", "B": "m/slow"},
                               {"A": "m", "B": "m"}, facts)
    assert "m/fast: viscoelastic in 1 of 1, tau 0.1 s" in text
    assert "m/slow: cannot tell (the viscoelastic model could not be solved along the " \
           "recorded path in 1 of 1)" in text
    assert "| m/fast | 1 | 1 | 1 | 0.30 | 0 | 1 |" in text
    assert "| m/slow | 1 | 0 | 0 | - | 1 | 0 |" in text
    results["B"] = {"effects": [], "refit_parameters": {}, "rounds": [{"table": []}]}
    assert "m/slow: not tested (viscoelastic not a candidate in 1 of 1)" in \
        signatures_markdown(results, {"A": "m/fast", "B": "m/slow"}, {"A": "m", "B": "m"},
                            facts)
    # fitted beside a misfit the library does not explain (a stiffness trend): tried
    results["A"] = {"effects": [], "tried": ["viscoelastic", "mullins"],
                    "refit_parameters": {}, "rounds": [{"table": []}]}
    text = signatures_markdown(results, {"A": "m/fast", "B": "m/slow"},
                               {"A": "m", "B": "m"}, facts)
    assert "m/fast: viscoelastic named in 0 of 1, fitted but not named in 1 more" in text
    assert "| m/fast | 0.1 | 1 | 0 | - | - | 1 | 0 |" in text
    same_rate = {n: dict(f, rate_per_s=0.1) for n, f in facts.items()}
    assert "Rate dependence" not in signatures_markdown(
        results, {"A": "m/fast", "B": "m/slow"}, {"A": "m", "B": "m"}, same_rate)
