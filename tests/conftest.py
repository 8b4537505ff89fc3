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
