"""Surrogates: split without leakage, GP search end to end on a tiny FE sample store,
persistence with its validity range, refusal outside it, and the mu-scaling it relies on."""

import json
import math
import warnings

import numpy as np
import pytest
from sklearn.metrics import r2_score


def test_split_never_shares_a_parameter_set():
    from surrogate.data import split_by_parameter_set

    ids = np.repeat(np.arange(50), 21)  # 50 curves of 21 points
    sp = split_by_parameter_set(ids, seed=4)
    assert not (set(sp.train) & set(sp.val) or set(sp.train) & set(sp.test)
                or set(sp.val) & set(sp.test))
    assert sorted([*sp.train, *sp.val, *sp.test]) == list(range(50))
    assert (len(sp.test), len(sp.val), len(sp.train)) == (5, 9, 36)  # 10 %, 20 % of the rest


def test_fe_stress_scales_with_mu_at_fixed_nu0(axi_slip):
    """The exact scaling behind scale_by_mu: with nu0 fixed (kappa ~ mu) every stress of the
    one-term model is proportional to mu (here to 1e-9 of the peak: back at stretch 1 the
    stress is zero up to Newton's tolerance, ~1e-11 kPa, so no relative test holds there)."""
    from brain_fe.materials import MaterialParameters
    from brain_fe.protocols import Protocol

    prot = Protocol("compression_tension", (1.0, 0.85, 1.1), max_increment=0.05)
    a = axi_slip.run(prot, MaterialParameters(mu=(0.7,), alpha=(-12.0,), nu0=0.49))
    b = axi_slip.run(prot, MaterialParameters(mu=(2.1,), alpha=(-12.0,), nu0=0.49))
    peak = float(np.max(np.abs(b.nominal_stress_kPa)))
    np.testing.assert_allclose(b.nominal_stress_kPa, 3 * a.nominal_stress_kPa, rtol=1e-9,
                               atol=1e-9 * peak)


def test_search_end_to_end_and_metrics(tiny_models, tiny_store):
    """metrics.json per test; its R^2 statistics recomputed independently from the saved
    models through the scikit-learn pipeline and sklearn's r2_score (1e-9)."""
    from brain_fe.store import load_samples
    from surrogate.data import TEST_KEYS, arrays, split_by_parameter_set, table_for_test
    from surrogate.persist import load_surrogates

    out, metrics = tiny_models
    on_disk = json.loads((out / "metrics.json").read_text())
    samples = load_samples(tiny_store)
    models = load_surrogates(str(out))
    for key in TEST_KEYS:
        m = on_disk[key]
        hp = m["hyperparameters"]
        assert 64 <= hp["hidden1"] <= 512 and hp["hidden1"] % 32 == 0
        assert 64 <= hp["hidden2"] <= 512 and hp["hidden2"] % 32 == 0
        assert hp["activation"] in ("relu", "tanh", "logistic")
        assert hp["learning_rate_init"] in (1e-4, 1e-3, 1e-2)
        assert len(m["trials"]) == 2
        table = table_for_test(samples, key)
        sp = split_by_parameter_set(table["sample"], seed=1)
        r2 = []
        for sid in sp.test:
            X, y, _ = arrays(table, key, [sid])
            r2.append(r2_score(y, models[key].estimator.predict_pipeline(X)))
        assert m["n_test_curves"] == len(sp.test)
        assert m["r2_mean"] == pytest.approx(np.mean(r2), abs=1e-9)
        assert m["r2_std"] == pytest.approx(np.std(r2), abs=1e-9)
        assert (out / f"{key}_test_curves.png").stat().st_size > 10_000


def test_fast_forward_pass_equals_pipeline(tiny_models):
    from surrogate.persist import load_surrogates

    out, _ = tiny_models
    for b in load_surrogates(str(out)).values():
        lo, hi = b.control_range
        X = np.column_stack([np.full(30, np.mean(b.mu_range)), np.full(30, np.mean(b.alpha_range)),
                             np.linspace(lo, hi, 30)])
        np.testing.assert_allclose(b.estimator.predict(X), b.estimator.predict_pipeline(X),
                                   rtol=1e-12, atol=1e-14)


def test_refuses_outside_training_range_and_other_conditions(tiny_models):
    from surrogate.persist import OutOfRangeError, OutOfRangeWarning, load_surrogates

    out, _ = tiny_models
    b = load_surrogates(str(out))["compression_tension"]
    mu_ok, al_ok = math.sqrt(b.mu_range[0] * b.mu_range[1]), np.mean(b.alpha_range)
    assert np.all(np.isfinite(b.predict(mu_ok, al_ok, [0.9, 1.1])))
    with pytest.raises(OutOfRangeError, match="mu_kPa = .* outside the training range"):
        b.predict(10 * b.mu_range[1], al_ok, [0.9])
    with pytest.raises(OutOfRangeError, match="stretch"):
        b.predict(mu_ok, al_ok, [0.5])
    with pytest.warns(OutOfRangeWarning):
        b.predict(mu_ok, b.alpha_range[0] - 5, [0.9], on_out_of_range="warn")
    with pytest.raises(OutOfRangeError, match="nu0 = 0.49"):
        b.check_conditions(nu0=0.45)
    with pytest.raises(OutOfRangeError, match="radius_mm"):
        b.check_conditions(radius_mm=5.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b.check_conditions(nu0=0.49, radius_mm=4.0, height_mm=5.0)


def test_gradient_matches_central_differences(tiny_models):
    """predict_with_gradient: the values of predict (bit for bit) and d stress/d(mu, alpha)
    against central differences of predict (relative step 1e-6: agreement to 1e-6 of the
    largest derivative)."""
    from surrogate.persist import load_surrogates

    out, _ = tiny_models
    for b in load_surrogates(str(out)).values():
        lo, hi = b.control_range
        mu, alpha = np.mean(b.mu_range), np.mean(b.alpha_range)
        X = np.column_stack([np.full(25, mu), np.full(25, alpha), np.linspace(lo, hi, 25)])
        f, df = b.estimator.predict_with_gradient(X)
        np.testing.assert_array_equal(f, b.estimator.predict(X))
        for j, h in enumerate((1e-6 * mu, 1e-6 * abs(alpha))):
            e = np.zeros(3)
            e[j] = h
            fd = (b.estimator.predict(X + e) - b.estimator.predict(X - e)) / (2 * h)
            np.testing.assert_allclose(df[:, j], fd, rtol=0, atol=1e-6 * np.abs(fd).max())
