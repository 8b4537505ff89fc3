"""Shared fixtures: compiled models are built once per session (JIT compilation is the
expensive part; forms are reused across parameter values)."""

import logging

import pytest
from mpi4py import MPI

logging.getLogger("ffcx").setLevel(logging.WARNING)
logging.getLogger("UFL").setLevel(logging.WARNING)


@pytest.fixture(scope="session")
def axi_glued():
    from brain_fe import geometry
    from brain_fe.model import ForwardModel

    return ForwardModel(geometry.axisymmetric(refinement=2, comm=MPI.COMM_WORLD))


@pytest.fixture(scope="session")
def axi_slip():
    from brain_fe import geometry
    from brain_fe.model import ForwardModel

    return ForwardModel(geometry.axisymmetric(refinement=1, comm=MPI.COMM_WORLD), ends="slip")


@pytest.fixture(scope="session")
def tiny_store(tmp_path_factory):
    """12 parameter sets, default tests, coarse mesh (k = 1)."""
    from brain_fe.sampling import SampleSpec, run_sampling

    store = tmp_path_factory.mktemp("store")
    run_sampling(SampleSpec(n=12, seed=3, refinement=1), store, comm=MPI.COMM_SELF,
                 progress=False)
    return store


@pytest.fixture(scope="session")
def tiny_models(tiny_store, tmp_path_factory):
    """Surrogates of the tiny store (tiny profile, 2 trials): (model dir, metrics)."""
    from brain_fe.store import load_samples, read_manifest
    from surrogate.train import train_all

    out = tmp_path_factory.mktemp("models")
    metrics = train_all(load_samples(tiny_store), read_manifest(tiny_store), str(out),
                        profile="tiny", trials=2, executions=1, seed=1)
    return out, metrics
