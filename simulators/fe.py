"""The FE model of one specimen as a simulator of its observation table.

Two ways to follow the recordings:

* ``path="recorded"`` (default): the model follows each curve's recorded (time, control)
  path through every recorded point, so history-dependent physics (viscoelasticity,
  softening) and the measurement artefacts are represented exactly;
* ``path="branches"``: for elastic models only, whose response depends on the control value
  and not on the path: the loading branches (1 -> 1-A, 1 -> 1+A; 0 -> gamma_max) are solved
  at fine increments (0.015; A/10 in torsion) and a cubic spline through them is evaluated
  at the recorded points, loading and unloading alike (spline error below 1e-5 of the
  stress, tested).  About half the cost; used by the identification.

``correction`` (an array over the observations, default 0) is added to every prediction:
the diagnosis keeps there the discretisation error of this mesh, estimated against a finer
one (deferred correction).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from mpi4py import MPI
from scipy.interpolate import CubicSpline

from brain_fe import geometry as geo
from brain_fe.materials import MaterialModel
from brain_fe.model import ForwardModel
from brain_fe.parameters import Param
from brain_fe.protocols import Protocol
from brain_fe.vocabulary import CHANNELS, COMPRESSION_TENSION
from recordings.observations import recorded_paths

from . import coordinates as co
from .base import Prediction

log = logging.getLogger(__name__)


class FESimulator:
    """Axisymmetric FE model of one specimen (radius, height [mm]) predicting ``obs``.

    ``geometry`` and ``models`` (a dict of compiled models by physics) may be shared by
    several simulators of the same specimen, which then compile their forms once."""

    kind = "fe"

    def __init__(self, obs: pd.DataFrame, radius_mm: float, height_mm: float, *,
                 refinement: int = 1, nu0: float = 0.49, path: str = "recorded",
                 ends: str = "glued", comm=MPI.COMM_SELF,
                 geometry: geo.Geometry | None = None, models: dict | None = None):
        if path not in ("recorded", "branches"):
            raise ValueError(f"path must be 'recorded' or 'branches', got {path!r}")
        self.obs = obs.reset_index(drop=True)
        self.nu0, self.refinement, self.path, self.ends = nu0, refinement, path, ends
        self.geometry = geometry or geo.make("axisymmetric", radius_mm, height_mm,
                                             refinement, comm=comm)
        self.refinement = self.geometry.refinement
        self._models = {} if models is None else models  # shared by simulators of one mesh
        self.curves = recorded_paths(self.obs)
        self.correction = np.zeros(len(self.obs))
        self.solves = 0  # protocol solves (one per curve and prediction)

    def model(self, physics: co.Physics) -> ForwardModel:
        """The compiled model with ``physics`` (compiled once per kind, then reused)."""
        ends = "springs" if physics.springs else self.ends
        key = (physics, ends)
        if key not in self._models:
            material = MaterialModel.build(physics.n_terms, maxwell=physics.maxwell,
                                           softening=physics.softening, laws=physics.laws)
            self._models[key] = ForwardModel(self.geometry, material, ends=ends)
        return self._models[key]

    def predict(self, values: Mapping[Param, float],
                wrt: Sequence[Param] = ()) -> Prediction:
        values = {Param.parse(k): v for k, v in values.items()}
        wrt = tuple(Param.parse(q) for q in wrt)
        point = co.model_point(values, self.nu0)
        fm = self.model(point.physics)
        needed = co.model_sensitivities(wrt)
        y = np.zeros(len(self.obs))
        J = np.zeros((len(self.obs), len(wrt)))
        for _curve, path, rows in self.curves:
            if self.path == "branches":
                vals, ders = self._branches(fm, point, path, rows, needed)
            else:
                resp = fm.solve(path, point.material, interface=point.interface,
                                artefacts=point.artefacts, sensitivities=needed or False)
                vals = {ch: resp.values[CHANNELS[ch].column][idx]
                        for ch, (_, idx) in rows.items()}
                ders = {ch: {p: resp.jacobian[p][CHANNELS[ch].column][idx] for p in needed}
                        for ch, (_, idx) in rows.items()}
            self.solves += 1
            for ch, (obs_rows, _) in rows.items():
                y[obs_rows] = vals[ch]
                if wrt:
                    J[obs_rows] = co.chain(values, point, wrt, ders[ch], len(obs_rows))
        return Prediction(y + self.correction, J, wrt)

    def _branches(self, fm, point, path, rows, needed):
        """Channels (and sensitivities) at the recorded controls by splines through the
        loading branches of an elastic model."""
        if fm.path_sensitivities or not point.artefacts.neutral:
            raise ValueError("the branch shortcut is for elastic models without artefacts")
        A = path.amplitude
        prots = ([Protocol(COMPRESSION_TENSION, (1.0, 1.0 - A), max_increment=0.015),
                  Protocol(COMPRESSION_TENSION, (1.0, 1.0 + A), max_increment=0.015)]
                 if path.test == COMPRESSION_TENSION
                 else [Protocol(path.test, (0.0, A), max_increment=A / 10)])
        resps = [fm.solve(p, point.material, sensitivities=needed or False) for p in prots]
        x = np.concatenate([r.control for r in resps])
        order = np.argsort(x)
        x, keep = np.unique(x[order], return_index=True)
        at = np.array([s.value for s in path.points])

        def spline(parts):
            return CubicSpline(x, np.concatenate(parts)[order][keep])

        vals, ders = {}, {}
        for ch, (_, idx) in rows.items():
            col = CHANNELS[ch].column
            vals[ch] = spline([r.values[col] for r in resps])(at)[idx]
            ders[ch] = {p: spline([r.jacobian[p][col] for r in resps])(at)[idx]
                        for p in needed}
        return vals, ders
