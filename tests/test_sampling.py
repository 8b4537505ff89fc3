"""Parallel, resumable sample generation (brain_fe.sampling, `brainmech sample`).

Tiny stores (n <= 6, refinement 1) keep this file well under a minute and a half. None of
these tests is marked `mpi`: the parallel one launches `mpirun -n 2` itself.
"""

import json
import math
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import pytest
from launch import child_env
from mpi4py import MPI

from brain_fe import sampling, store

TESTS2 = "compression_tension,torsion:0.30"  # two protocols: enough, and fast
# Columns whose values must be reproducible (wall_time_s is a measurement).
COMPARE = [c for c in store.COLUMNS if c != "wall_time_s"]


def _cli(out, *extra, n=5, tests=TESTS2):
    return [sys.executable, "-m", "brainmech", "sample", "--n", str(n), "--seed", "7",
            "--refinement", "1", "--mu-range", "0.1,5", "--alpha-range", "-40,-2",
            "--tests", tests, "--chunk-size", "1", "--out", str(out), *extra]


def _run(cmd, **kw):
    return subprocess.run(cmd, env=child_env(), capture_output=True, text=True, timeout=300, **kw)


@pytest.fixture(scope="module")
def reference_model():
    """A model built directly (not through sampling) for the independent reference."""
    from brain_fe.geometry import make as make_geometry
    from brain_fe.model import ForwardModel

    return ForwardModel(make_geometry("axisymmetric", 4.0, 5.0, 1, comm=MPI.COMM_SELF))


def _direct(model, mu, alpha, test):
    from brain_fe.materials import MaterialParameters

    spec = sampling.parse_tests(test)[0]
    return model.run(spec.protocol(), MaterialParameters(mu=(mu,), alpha=(alpha,), nu0=0.49))


def _assert_matches_direct(df, model, sample, test, kind_amp):
    rows = df[(df["sample"] == sample) & (df.test == test)]
    ref = _direct(model, rows.mu_kPa.iloc[0], rows.alpha.iloc[0], kind_amp)
    assert len(rows) == len(ref)
    for c in ref.columns:
        if ref[c].dtype.kind == "f":
            np.testing.assert_allclose(rows[c].to_numpy(), ref[c].to_numpy(), rtol=1e-12,
                                       atol=1e-12)
        else:
            assert list(rows[c]) == list(ref[c])


@pytest.fixture(scope="module")
def serial_store(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "store"
    r = _run(_cli(out))
    assert r.returncode == 0, r.stderr
    assert "5/5 samples stored (5 ok, 0 failed), 0 missing; computed 5" in r.stdout
    return out


# ------------------------------------------------------------------------------ design
@pytest.mark.parametrize("design", ["sobol", "lhs"])
def test_design_reproducible_and_within_ranges(design):
    """Pure function of (n, seed, ranges): equal under a disturbed global RNG; mu
    log-uniform (one point per 1/n stratum of log mu, which both a scrambled Sobol
    sequence with n = 2^m and a Latin hypercube guarantee), alpha likewise uniform."""
    n, mu_r, al_r = 64, (0.1, 5.0), (-40.0, -2.0)
    np.random.seed(1)  # noqa: NPY002 - a disturbed global RNG must not matter
    a = sampling.make_design(n, 3, design, mu_r, al_r)
    np.random.seed(2)  # noqa: NPY002
    np.random.default_rng().random(10)
    b = sampling.make_design(n, 3, design, mu_r, al_r)
    pd.testing.assert_frame_equal(a, b, check_exact=True)
    assert not np.array_equal(a.mu_kPa, sampling.make_design(n, 4, design, mu_r, al_r).mu_kPa)
    u_mu = (np.log(a.mu_kPa) - math.log(0.1)) / (math.log(5.0) - math.log(0.1))
    u_al = (a.alpha + 40.0) / 38.0
    for u in (u_mu, u_al):
        assert np.all((u >= 0) & (u <= 1))
        assert sorted(np.floor(u * n).astype(int)) == list(range(n))
    # other ranges: the same unit-cube points, mapped
    c = sampling.make_design(n, 3, design, (1.0, 2.0), (-3.0, -1.0))
    np.testing.assert_allclose(np.log2(c.mu_kPa), u_mu, rtol=0, atol=1e-12)
    np.testing.assert_allclose(c.alpha, -3.0 + 2.0 * u_al, rtol=0, atol=1e-12)
    assert store.design_hash(a) == store.design_hash(b)


def test_tests_option_names():
    t = sampling.parse_tests(sampling.DEFAULT_TESTS)
    assert [s.name for s in t] == ["compression_tension", "torsion_0.15", "torsion_0.30"]
    assert [s.amplitude for s in t] == [0.15, 0.15, 0.30]
    for bad in ("shear", "torsion:x", "torsion:0.3,torsion:0.30", "compression_tension:1.5"):
        with pytest.raises(ValueError):
            sampling.parse_tests(bad)


# ------------------------------------------------------------------------------ parallel
def test_mpirun_2_gives_the_serial_store(serial_store, reference_model, tmp_path):
    """`mpirun -n 2` and serial stores hold the same rows and values (to 1e-12; in practice
    bit for bit), both ranks took work, and the values equal a direct model.run."""
    out = tmp_path / "par"
    r = _run(["mpirun", "-n", "2", *_cli(out)])
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("samples stored") == 1  # rank 0 reports once
    ranks = {p.name.split("-r")[1][:5] for p in store.chunk_files(out)}
    assert ranks == {"00000", "00001"}
    a, b = store.load_samples(serial_store), store.load_samples(out)
    assert len(a) == 5 * (41 + 21)
    pd.testing.assert_frame_equal(a[COMPARE], b[COMPARE], check_exact=False, rtol=1e-12,
                                  atol=1e-12)
    man = json.loads((out / "manifest.json").read_text())
    assert man["spec"]["refinement"] == 1 and man["spec"]["n"] == 5
    assert set(man["software"]) >= {"brainmech", "dolfinx", "numpy"}
    d = sampling.make_design(5, 7)
    np.testing.assert_array_equal(a.groupby("sample").mu_kPa.first(), d.mu_kPa)
    _assert_matches_direct(b, reference_model, 3, "torsion_0.30", "torsion:0.30")
    _assert_matches_direct(b, reference_model, 4, "compression_tension", "compression_tension")


# ------------------------------------------------------------------------------ resume
def test_sigkill_then_resume_stores_every_sample_once(serial_store, tmp_path):
    """Kill -9 after the first chunk appears; the re-run computes exactly the missing
    samples; every (sample, test) is stored exactly once; stale temp files are removed."""
    out = tmp_path / "killed"
    proc = subprocess.Popen(_cli(out, n=6, tests=sampling.DEFAULT_TESTS), env=child_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    try:
        while not store.chunk_files(out):
            assert proc.poll() is None, "the run ended before writing a chunk"
            assert time.monotonic() < deadline
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    before = store.read_chunks(out, with_file=True)
    first = set(before["sample"])
    assert 1 <= len(first) < 6, "the kill came too late to test resuming"
    old_files = set(before.chunk)
    (out / "chunks" / ".tmp-interrupted.parquet").write_bytes(b"PAR1 half a file")

    r = _run(_cli(out, n=6, tests=sampling.DEFAULT_TESTS))
    assert r.returncode == 0, r.stderr
    assert f"computed {6 - len(first)} in this run" in r.stdout
    assert not list((out / "chunks").glob(".tmp-*"))
    raw = store.read_chunks(out, with_file=True)
    per_pair = raw.groupby(["sample", "test"]).chunk.nunique()
    assert len(per_pair) == 6 * 3 and (per_pair == 1).all()
    new = raw[~raw.chunk.isin(old_files)]
    assert set(new["sample"]) == set(range(6)) - first  # only the missing ones
    assert set(raw[raw.chunk.isin(old_files)].chunk) == old_files  # old chunks untouched
    s = store.summarize(out)
    assert (s.total, s.done, s.failed, s.missing) == (6, 6, 0, 0)
    # the first 5 Sobol points of n = 6 and n = 5 coincide: compare with the serial store
    df = store.load_samples(out)
    ref = store.load_samples(serial_store)
    for test in ("compression_tension", "torsion_0.30"):
        a = df[(df.test == test) & (df["sample"] < 5)].reset_index(drop=True)
        b = ref[ref.test == test].reset_index(drop=True)
        pd.testing.assert_frame_equal(a[COMPARE], b[COMPARE], rtol=1e-12, atol=1e-12)
    # a duplicated chunk (e.g. copied by hand) is de-duplicated on load
    src = store.chunk_files(out)[0]
    shutil.copy(src, src.with_name("zz-copy.parquet"))
    pd.testing.assert_frame_equal(store.load_samples(out), df)
    assert store.summarize(out).done == 6


# ------------------------------------------------------------------------------ manifests
@pytest.mark.parametrize("case", ["bad_json", "wrong_schema", "other_seed", "other_tests",
                                  "checksum"])
def test_corrupted_or_foreign_manifest_is_refused(serial_store, tmp_path, case):
    out = tmp_path / "store"
    shutil.copytree(serial_store, out)
    mpath = out / "manifest.json"
    man = json.loads(mpath.read_text())
    args, expect = [], ""
    if case == "bad_json":
        mpath.write_text(mpath.read_text()[:-40])
        expect = "is corrupted (not valid JSON"
    elif case == "wrong_schema":
        man["schema"] = "someone.else"
        mpath.write_text(json.dumps(man))
        expect = "is not a brainmech sample manifest"
    elif case == "checksum":
        man["parameters"]["mu_kPa"][2] *= 1.001
        mpath.write_text(json.dumps(man))
        expect = "checksum"
    elif case == "other_seed":
        args, expect = ["--seed", "8"], "different seed (stored 7, requested 8)"
    else:
        args = ["--tests", "compression_tension"]
        expect = ("different tests (stored compression_tension,torsion_0.30, requested "
                  "compression_tension)")
    before = {p.name: p.read_bytes() for p in store.chunk_files(out)}
    cmd = _cli(out)
    if args:  # a later option wins in argparse
        cmd += args
    r = _run(cmd)
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("brainmech sample: error: "), r.stderr
    assert expect in lines[0] and "Traceback" not in r.stderr
    assert {p.name: p.read_bytes() for p in store.chunk_files(out)} == before
    if case in ("bad_json", "wrong_schema", "checksum"):
        with pytest.raises(store.StoreError):
            store.load_samples(out)


# ------------------------------------------------------------------------------ failures
def test_failed_solves_are_recorded_and_counted(tmp_path, reference_model):
    """A model that raises ConvergenceError for one parameter set in torsion: the sample is
    stored with status 'failed' and the reason, counted in the summary, not recomputed on a
    re-run; its compression/tension and the other samples equal direct model.run."""
    from brain_fe.solver import ConvergenceError

    spec = sampling.SampleSpec(n=4, seed=7, tests=TESTS2, refinement=1)
    bad_mu = float(sampling.make_design(4, 7).mu_kPa[2])
    calls = []

    class Flaky:
        def __init__(self, model):
            self.model = model

        def run(self, protocol, params):
            calls.append(params.mu[0])
            if protocol.test == "torsion" and params.mu[0] == bad_mu:
                raise ConvergenceError("torsion: Newton failed at shear = 0.27 (provoked)")
            return self.model.run(protocol, params)

    def factory(s):
        assert s == spec
        return Flaky(reference_model)

    out = tmp_path / "store"
    summ = sampling.run_sampling(spec, out, comm=MPI.COMM_SELF, progress=False,
                                 model_factory=factory)
    assert (summ.total, summ.done, summ.failed, summ.missing, summ.computed) == (4, 4, 1, 0, 4)
    assert summ.failures == [(2, "torsion_0.30",
                              "ConvergenceError: torsion: Newton failed at shear = 0.27 "
                              "(provoked)")]
    full = store.load_samples(out, include_failed=True)
    f = full[full.status == "failed"]
    assert len(f) == 1 and f["sample"].iloc[0] == 2 and f.torque_mNmm.isna().all()
    ok = store.load_samples(out)
    assert len(ok) == 4 * (41 + 21) - 21
    _assert_matches_direct(ok, reference_model, 2, "compression_tension", "compression_tension")
    _assert_matches_direct(ok, reference_model, 1, "torsion_0.30", "torsion:0.30")
    n_calls = len(calls)
    again = sampling.run_sampling(spec, out, comm=MPI.COMM_SELF, progress=False,
                                  model_factory=factory)
    assert again.computed == 0 and len(calls) == n_calls and again.failed == 1
