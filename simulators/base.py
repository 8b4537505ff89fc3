"""The one simulator interface: predict the recorded channels of an observation table
(:mod:`recordings.observations`) and their Jacobian with respect to named parameters.

Parameters are :class:`~brain_fe.parameters.Param` keys in *fit coordinates*
(:mod:`simulators.coordinates`): ``mu_0``, ``alpha_0``, ``nu0``, ``log10_tau_0``, the
artefact offsets, ...  A simulator predicts every row of the observation table it was
built for, in row order, in the channel's unit.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import pandas as pd

from brain_fe.parameters import Param


@dataclass
class Prediction:
    """``y[i]``: the prediction of observation row i; ``jacobian[i, j]``: dy_i / d wrt[j]."""

    y: np.ndarray
    jacobian: np.ndarray
    wrt: tuple[Param, ...]

    def __iter__(self):
        """A pair: ``y, jacobian = prediction`` (``prediction[0]`` is ``y``)."""
        return iter((self.y, self.jacobian))

    def __getitem__(self, i: int) -> np.ndarray:
        return (self.y, self.jacobian)[i]

    def __len__(self) -> int:
        return 2


@runtime_checkable
class Simulator(Protocol):
    """What identification and diagnosis ask of a model."""

    obs: pd.DataFrame  # the observation rows it predicts
    kind: str  # which candidate effects it can express (diagnosis.effects.library)
    nu0: float  # the assumed initial Poisson ratio where the values do not give one

    def predict(self, values: Mapping[Param, float],
                wrt: Sequence[Param] = ()) -> Prediction:
        """Predictions at ``values`` and their derivatives with respect to ``wrt``."""
        ...


class PredictionMemo:
    """Memo of a simulator's predictions within one fit: optimisers ask for the residual
    and the Jacobian at one point in two calls, and a trust-region fit returns a point it
    evaluated before its last (rejected) trials, which the caller predicts again.  Every
    prediction starts afresh (:meth:`brain_fe.solver.NewtonSolver.forget`), so one made
    again equals the one kept.  Keeps the last ``size`` points (a fit's evaluations)."""

    def __init__(self, sim: Simulator, size: int = 64):
        self.sim = sim
        self.size = size
        self._memo: OrderedDict = OrderedDict()

    def __call__(self, values: Mapping[Param, float], wrt: Sequence[Param]) -> Prediction:
        key = (tuple(sorted((str(k), round(float(v), 14)) for k, v in values.items())),
               tuple(map(str, wrt)))
        if key in self._memo:
            self._memo.move_to_end(key)
        else:
            self._memo[key] = self.sim.predict(values, wrt)
            if len(self._memo) > self.size:
                self._memo.popitem(last=False)
        return self._memo[key]
