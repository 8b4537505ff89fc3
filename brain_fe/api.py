"""High-level entry points used by the CLI and by scripts."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import pandas as pd
from mpi4py import MPI

from . import geometry as geo
from .io import write_table_atomic
from .model import ForwardModel, MaterialParameters
from .protocols import Protocol, compression_tension, torsion

log = logging.getLogger(__name__)

DEFAULT_REFINEMENT = {"axisymmetric": geo.DEFAULT_REFINEMENT, "3d": 2}


def make_geometry(model: str = "axisymmetric", radius_mm: float = 4.0, height_mm: float = 5.0,
                  refinement: int | None = None, comm=MPI.COMM_WORLD) -> geo.Geometry:
    if model not in DEFAULT_REFINEMENT:
        raise ValueError(f"model must be 'axisymmetric' or '3d', got {model!r}")
    k = DEFAULT_REFINEMENT[model] if refinement is None else refinement
    if model == "axisymmetric":
        return geo.axisymmetric(radius_mm, height_mm, k, comm=comm)
    return geo.cylinder3d(radius_mm, height_mm, k, comm=comm)


def make_protocol(test: str, amplitude: float | None = None, rate_per_s: float = 0.01,
                  cycles: int = 1, hold_s: float = 0.0) -> Protocol:
    if test == "compression_tension":
        return compression_tension(0.15 if amplitude is None else amplitude,
                                   rate_per_s=rate_per_s, cycles=cycles, hold_s=hold_s)
    if test == "torsion":
        return torsion(0.30 if amplitude is None else amplitude, rate_per_s=rate_per_s,
                       cycles=cycles, hold_s=hold_s)
    raise ValueError(f"test must be 'compression_tension' or 'torsion', got {test!r}")


def simulate(*, model: str = "axisymmetric", test: str = "compression_tension",
             amplitude: float | None = None, mu: Sequence[float] = (1.0,),
             alpha: Sequence[float] = (-20.0,), kappa: float | None = None,
             nu0: float | None = 0.49, volumetric: str = "quadratic", radius_mm: float = 4.0,
             height_mm: float = 5.0, ends: str = "glued", refinement: int | None = None,
             rate_per_s: float = 0.01, cycles: int = 1, hold_s: float = 0.0,
             field_output: str | None = None, progress: bool = False,
             physics: dict | None = None, artefacts: dict | None = None,
             sensitivities: bool = False, comm=MPI.COMM_WORLD) -> pd.DataFrame:
    """One protocol on one freshly built model; returns the per-step table.

    ``physics``: extension parameters of :class:`MaterialParameters` (``beta``, ``tau_s``,
    ``softening``, ``softening_m_kPa``, ``k_r_kPa_mm``, ``k_theta_kPa_mm``); ``artefacts``:
    fields of :class:`brain_fe.artefacts.Artefacts`.
    """
    from .artefacts import Artefacts

    physics = dict(physics or {})
    if ends == "springs" and physics.get("k_r_kPa_mm") is None:
        raise ValueError("--ends springs needs --k-r and --k-theta (kPa/mm)")
    if ends != "springs" and (physics.get("k_r_kPa_mm") is not None
                              or physics.get("k_theta_kPa_mm") is not None):
        raise ValueError("--k-r/--k-theta need --ends springs")
    params = MaterialParameters(mu=tuple(mu), alpha=tuple(alpha), nu0=nu0, kappa=kappa,
                                **physics)
    art = Artefacts(**(artefacts or {}))
    protocol = make_protocol(test, amplitude, rate_per_s, cycles, hold_s)
    if protocol.test == "torsion" and ends == "slip":
        raise ValueError("torsion needs glued ends (frictionless plates cannot twist)")
    g = make_geometry(model, radius_mm, height_mm, refinement, comm)
    fm = ForwardModel(g, n_terms=len(params.mu), volumetric=volumetric, ends=ends,
                      maxwell=params.maxwell, mullins=params.softening > 0)
    bar = None
    if progress and comm.rank == 0:
        from tqdm import tqdm

        bar = tqdm(total=len(protocol.steps()), desc=f"{test}", unit="step", leave=False,
                   disable=None)

    def cb(i, n):
        if bar is not None:
            bar.update(1)

    try:
        return fm.run(protocol, params, field_output=field_output, callback=cb,
                      artefacts=art, sensitivities=sensitivities)
    finally:
        if bar is not None:
            bar.close()


def write_csv_atomic(df: pd.DataFrame, path: str, comm=MPI.COMM_WORLD) -> None:
    """Write on rank 0 through a temporary file and a rename: never a partial file."""
    if comm.rank == 0:
        write_table_atomic(df, path, float_format="%.10g")
    comm.Barrier()
