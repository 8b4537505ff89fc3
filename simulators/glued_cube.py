"""Cube tests reduced as if homogeneous, with the end constraint as a candidate effect.

Budday et al. (2017) glued cubes of about 5 mm to the plates and computed the stress as
if the deformation were homogeneous. The glue stops the ends from expanding or
contracting laterally, so in tension and compression the real specimen is inhomogeneous
and the apparent stress differs from the homogeneous one. :class:`GluedCubeSimulator`
predicts every row with the homogeneous analytical model (:mod:`diagnosis.homogeneous`)
and, when the effect parameter ``log10_k`` is present, replaces the tension/compression
rows by the axisymmetric FE model of a cylinder of the same height and cross-section
(R = a / sqrt(pi)) whose ends are held by tangential interface springs of stiffness
k [kPa/mm] (``ends="springs"``). The effect nests the base model: k -> 0 is a frictionless
end, where the FE solution is the homogeneous one; k -> infinity is a perfect glue.
Simple shear stays homogeneous (the plates impose the shear; the free faces are a smaller
perturbation that this model does not represent). The cylinder stands in for the cube:
it has its height, area and end constraint, not its corners.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
from mpi4py import MPI

from brain_fe.parameters import Param
from brain_fe.vocabulary import COMPRESSION_TENSION

from .base import Prediction
from .coordinates import LOG10_K, NU0
from .fe import FESimulator
from .homogeneous import STRESS_OFFSET, STRETCH_OFFSET, UNIAXIAL_CURVES, HomogeneousSimulator

log = logging.getLogger(__name__)
# what the FE model of the glued specimen depends on (the offsets act on the records)
FE_PARAMETERS = (Param("mu", 0), Param("alpha", 0), NU0, LOG10_K)


class GluedCubeSimulator:
    """Homogeneous base model plus the glued-end candidate (see the module docstring)."""

    kind = "cube"

    def __init__(self, obs: pd.DataFrame, *, edge_mm: float = 5.0, refinement: int = 2,
                 nu0: float = 0.49, comm=MPI.COMM_SELF):
        self.obs = obs.reset_index(drop=True)
        self.nu0 = nu0
        self.refinement = refinement
        self.homogeneous = HomogeneousSimulator(self.obs, nu0=nu0)
        curve = self.obs["curve"].astype(str).to_numpy()
        self._uni = np.flatnonzero(np.isin(curve, UNIAXIAL_CURVES))
        fe_obs = self.obs.iloc[self._uni].assign(test=COMPRESSION_TENSION, amplitude=np.nan)
        fe_obs = fe_obs.reset_index(drop=True)
        self._fe = None
        if len(fe_obs):
            self._fe = FESimulator(fe_obs, edge_mm / math.sqrt(math.pi), edge_mm,
                                   refinement=refinement, nu0=nu0, comm=comm)

    def predict(self, values, wrt=()) -> Prediction:
        values = {Param.parse(k): float(v) for k, v in values.items()}
        names = tuple(Param.parse(q) for q in wrt)
        values.setdefault(NU0, self.nu0)
        if LOG10_K not in values or self._fe is None:
            return self.homogeneous.predict(values, names)
        if values.get(STRETCH_OFFSET, 0.0) != 0.0:
            raise ValueError("a stretch offset and the glued-end model cannot be combined")
        hom_vals = {k: v for k, v in values.items() if k != LOG10_K}
        hom_names = [n for n in names if n != LOG10_K]
        y, jh = self.homogeneous.predict(hom_vals, hom_names)
        J = np.zeros((len(y), len(names)))
        for j, n in enumerate(names):
            if n in hom_names:
                J[:, j] = jh[:, hom_names.index(n)]
        fe_names = [n for n in names if n in FE_PARAMETERS]
        fe_vals = {k: v for k, v in values.items() if k in FE_PARAMETERS}
        yf, jf = self._fe.predict(fe_vals, fe_names)
        # offsets of the measurement layer act on the recorded values, not on the physics
        y[self._uni] = yf + values.get(STRESS_OFFSET, 0.0)
        for j, n in enumerate(names):
            J[self._uni, j] = jf[:, fe_names.index(n)] if n in fe_names else (
                1.0 if n == STRESS_OFFSET else 0.0)
        return Prediction(y, J, names)
