"""One protocol on a freshly built model: the library call behind ``brainmech simulate``."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import pandas as pd
from mpi4py import MPI

from . import geometry as geo
from .artefacts import Artefacts
from .ends import Interface, check_ends
from .io import write_table_atomic
from .materials import MaterialParameters
from .model import ForwardModel
from .parallel import Progress
from .protocols import make

log = logging.getLogger(__name__)


def simulate(*, model: str = "axisymmetric", test: str = "compression_tension",
             amplitude: float | None = None, mu: Sequence[float] = (1.0,),
             alpha: Sequence[float] = (-20.0,), kappa: float | None = None,
             nu0: float | None = 0.49, volumetric: str = "quadratic", radius_mm: float = 4.0,
             height_mm: float = 5.0, ends: str = "glued", refinement: int | None = None,
             rate_per_s: float = 0.01, cycles: int = 1, hold_s: float = 0.0,
             field_output: str | None = None, progress: bool = False,
             physics: dict | None = None, interface: tuple[float, float] | None = None,
             artefacts: dict | None = None, sensitivities: bool = False,
             comm=MPI.COMM_WORLD) -> pd.DataFrame:
    """One protocol on one freshly built model; returns the per-step table.

    ``physics``: history parameters of :class:`~brain_fe.materials.MaterialParameters`
    (``beta``, ``tau_s``, ``softening``, ``softening_m_kPa``); ``interface``: (k_r, k_theta)
    of the glue layer [kPa/mm], required with ``ends="springs"`` and only there;
    ``artefacts``: fields of :class:`~brain_fe.artefacts.Artefacts`.
    """
    if (ends == "springs") != (interface is not None):
        raise ValueError("the glue-layer stiffnesses k_r, k_theta go with springs ends, "
                         "and springs ends need them")
    params = MaterialParameters(mu=tuple(mu), alpha=tuple(alpha), nu0=nu0, kappa=kappa,
                                **(physics or {}))
    glue = Interface(*interface) if interface is not None else None
    art = Artefacts(**(artefacts or {}))
    protocol = make(test, amplitude, rate_per_s=rate_per_s, cycles=cycles, hold_s=hold_s)
    check_ends(ends, model, protocol.test)
    g = geo.make(model, radius_mm, height_mm, refinement, comm)
    fm = ForwardModel(g, n_terms=len(params.mu), volumetric=volumetric, ends=ends,
                      maxwell=params.maxwell, mullins=params.softening > 0)
    with Progress(len(protocol.steps()), test, "step", enabled=progress, comm=comm) as bar:
        return fm.run(protocol, params, interface=glue, field_output=field_output,
                      callback=lambda i, n: bar.update(1), artefacts=art,
                      sensitivities=sensitivities)


def write_csv(df: pd.DataFrame, path: str, comm=MPI.COMM_WORLD) -> None:
    """Write on rank 0 through a temporary file and a rename: never a partial file."""
    if comm.rank == 0:
        write_table_atomic(df, path, float_format="%.10g")
    comm.Barrier()
