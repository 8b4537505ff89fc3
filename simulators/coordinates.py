"""Fit coordinates: the parameters optimisers move, mapped to the forward model's.

Most coordinates *are* model parameters (``mu_p``, ``alpha_p``, ``beta_i``, ``softening``,
and the artefacts ``stretch_offset``, ``force_offset``, ``torque_offset``, ``height_rel``,
``radius_rel``).  The others, with their map and derivative:

=====================  ==========================================================
``nu0``                kappa = 2 mu (1 + nu0) / (3 (1 - 2 nu0)), mu = sum mu_p; with
                       nu0 held, kappa moves with every mu_p: dkappa/dmu_p = kappa/mu
``log10_tau_i``        tau_i = 10^q  (d/dq = ln 10 tau_i)
``log10_softening_m``  softening_m = 10^q
``log10_k``            k_r = k_theta = 10^q  (one glue stiffness)
=====================  ==========================================================

:func:`model_point` turns coordinate values into what the forward model takes (material
values, glue interface, artefacts, and the physics the model must be compiled with);
:func:`directions` gives, per coordinate, the direction in the model's parameter space the
model differentiates along (the columns of d theta / d q).  A new effect whose parameters
are model parameters needs nothing here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from brain_fe.artefacts import NAMES as ARTEFACT_NAMES
from brain_fe.artefacts import Artefacts
from brain_fe.ends import Interface
from brain_fe.materials import kappa_from_nu0, law_for
from brain_fe.parameters import (
    K_R,
    K_THETA,
    KAPPA,
    SOFTENING,
    SOFTENING_M,
    Direction,
    Param,
    Parameters,
    mu,
)

LN10 = math.log(10.0)
NU0 = Param("nu0")
LOG10_K = Param("log10_k")
LOG10_SOFTENING_M = Param("log10_softening_m")
ARTEFACTS = tuple(Param(n) for n in ARTEFACT_NAMES)
_ARTEFACT_FIELD = {"force_offset": "force_offset_mN", "torque_offset": "torque_offset_mNmm"}
# log10 coordinates: family -> model family
_LOG10 = {"log10_tau": "tau", "log10_softening_m": "softening_m"}


@dataclass(frozen=True)
class Physics:
    """What a forward model must be compiled with."""

    n_terms: int = 1
    maxwell: int = 0
    softening: bool = False
    springs: bool = False
    laws: tuple[str, ...] = ()  # further isochoric laws of the registry, by name


@dataclass
class ModelPoint:
    material: Parameters
    interface: Interface | None
    artefacts: Artefacts
    physics: Physics


def _log10_target(q: Param) -> Param | None:
    fam = _LOG10.get(q.family)
    return None if fam is None else Param(fam, q.index)


def model_point(values: Mapping[Param, float], nu0: float) -> ModelPoint:
    """The forward model's inputs at coordinate ``values`` (``nu0`` when not among them)."""
    v = {Param.parse(k): float(x) for k, x in values.items()}
    n_terms = 1 + max([p.index for p in v if p.family == "mu"] + [0])
    mat: dict[Param, float] = {}
    laws: list[str] = []
    for p, x in v.items():
        target = _log10_target(p)
        if target is not None:
            mat[target] = 10.0 ** x
        elif p.family in ("mu", "alpha", "beta", "softening"):
            mat[p] = max(x, 0.0) if p.family in ("beta", "softening") else x
        elif law_for(p.family) is not None:  # a parameter of a further registered law
            mat[p] = x
            laws.append(law_for(p.family))
    for p in range(n_terms):  # terms without values stay neutral
        mat.setdefault(mu(p), 0.0)
        mat.setdefault(Param("alpha", p), 1.0)
    mu_total = sum(mat[mu(p)] for p in range(n_terms))
    mat[KAPPA] = v[KAPPA] if KAPPA in v else kappa_from_nu0(mu_total, v.get(NU0, nu0))
    softening = SOFTENING in mat
    if softening:
        mat.setdefault(SOFTENING_M, 0.05)
    interface = None
    if LOG10_K in v:
        k = 10.0 ** v[LOG10_K]
        interface = Interface(k, k)
    art = Artefacts(**{_ARTEFACT_FIELD.get(p.family, p.family): x for p, x in v.items()
                       if p in ARTEFACTS})
    maxwell = sum(1 for p in mat if p.family == "beta")
    return ModelPoint(Parameters(mat), interface, art,
                      Physics(n_terms, maxwell, softening, interface is not None,
                              tuple(sorted(set(laws)))))


def directions(values: Mapping[Param, float], point: ModelPoint,
               wrt: Sequence[Param]) -> list:
    """What the forward model differentiates for each coordinate of ``wrt``: the direction
    d theta / d q in its parameter space (a :class:`~brain_fe.parameters.Direction`), or the
    artefact name.  So every coordinate costs one sensitivity, and the model returns the
    Jacobian in coordinates directly."""
    mat = point.material
    mu_total = sum(mat.family("mu"))
    out = []
    for q in wrt:
        if q in ARTEFACTS:
            out.append(str(q))
        elif q.family == "mu" and KAPPA not in values:  # kappa follows mu at fixed nu0
            out.append(Direction(str(q), ((q, 1.0), (KAPPA, mat[KAPPA] / mu_total))))
        elif q == NU0:
            nu = values[NU0]
            out.append(Direction(str(q), ((KAPPA, 2 * mu_total / (1 - 2 * nu) ** 2),)))
        elif q == LOG10_K:
            k = point.interface.k_r_kPa_mm
            out.append(Direction(str(q), ((K_R, LN10 * k), (K_THETA, LN10 * k))))
        elif _log10_target(q) is not None:
            t = _log10_target(q)
            out.append(Direction(str(q), ((t, LN10 * mat[t]),)))
        else:
            out.append(Direction.of(q))
    return out
