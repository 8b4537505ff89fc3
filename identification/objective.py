r"""The identification objective (after Gavrus et al., as in the paper).

Per test t with recorded stresses e_i and simulated stresses s_i at the recorded control
values:

.. math::  \varepsilon_t = \sqrt{\sum_i (s_i - e_i)^2 / \sum_i e_i^2}

The residual vector concatenates (s_i - e_i) / sqrt(sum_i e_i^2) over the tests used, so
that ``||r||^2 = sum_t eps_t^2``: the quantity minimised by both stages (a least-squares
form, which the trust-region FE stage needs). Reports also give ``sum_t eps_t``.
Stresses: nominal stress [kPa] for compression/tension, torque-derived shear stress
2 T / (pi R^3) [kPa] for torsion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

STRESS = {"compression_tension": "nominal_stress_kPa", "torsion": "shear_stress_kPa"}
CONTROL = {"compression_tension": "stretch", "torsion": "shear"}


@dataclass(frozen=True)
class Curve:
    """One recorded test of one specimen (or region average) in the objective."""

    key: str  # compression_tension | torsion_0.15 | torsion_0.30
    test: str  # compression_tension | torsion
    amplitude: float
    control: np.ndarray  # stretch or amount of shear at each recorded point
    stress: np.ndarray  # recorded stress [kPa]
    branch: np.ndarray  # loading | unloading

    @property
    def norm(self) -> float:
        return float(np.sqrt(np.sum(self.stress**2)))


def curves_from_recordings(rec: pd.DataFrame, radius_mm: float) -> list[Curve]:
    """Curves of one specimen from its validated recordings (identification.recordings)."""
    from brain_fe.model import shear_stress_kPa

    from .recordings import key_for_test

    out = []
    for (test, amp), g in rec.groupby(["test", "amplitude"], sort=True):
        key = key_for_test(test, amp)
        if test == "compression_tension":
            stress = g["nominal_stress_kPa"].to_numpy(float)
        else:
            stress = shear_stress_kPa(g["torque_mNmm"].to_numpy(float), radius_mm)
        out.append(Curve(key, test, float(amp), g[CONTROL[test]].to_numpy(float), stress,
                         g["branch"].to_numpy()))
    return out


def gavrus_errors(curves: list[Curve], simulated: list[np.ndarray]) -> np.ndarray:
    """eps_t for every curve."""
    return np.array([np.sqrt(np.sum((s - c.stress) ** 2)) / c.norm
                     for c, s in zip(curves, simulated, strict=True)])


def residuals(curves: list[Curve], simulated: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([(s - c.stress) / c.norm
                           for c, s in zip(curves, simulated, strict=True)])
