"""The MLP surrogates (:mod:`surrogate`) as a simulator of an observation table: stage 1 of
the identification.

Each curve is predicted by the surrogate of its test key: the nominal stress
(compression/tension) or the torque-derived shear stress (torsion), returned as the torque
channel (T = tau pi R^3 / 2).  Parameters ``mu_0`` [kPa] and ``alpha_0``; nu0 is the one
the surrogates were trained at.  The Jacobian is the network's exact derivative.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from brain_fe.parameters import Param, alpha, mu
from brain_fe.vocabulary import torque_mNmm

from .base import Prediction

MU0, ALPHA0 = mu(0), alpha(0)


class SurrogateSimulator:
    """The surrogate bundles (``{test key: SurrogateBundle}``) for the curves of ``obs``."""

    kind = "surrogate"

    def __init__(self, obs: pd.DataFrame, bundles: dict, *, radius_mm: float,
                 height_mm: float, nu0: float, on_mismatch: str = "error"):
        self.obs = obs.reset_index(drop=True)
        self.bundles, self.nu0, self.radius_mm = bundles, nu0, radius_mm
        missing = sorted(set(self.obs["curve"]) - set(bundles))
        if missing:
            raise ValueError(f"no surrogate for test(s) {', '.join(missing)} "
                             f"(have {', '.join(bundles)})")
        channels = set(self.obs["channel"]) - {"stress", "torque"}
        if channels:
            raise ValueError(f"the surrogates predict stress and torque, not "
                             f"{', '.join(sorted(channels))}")
        for b in bundles.values():
            b.check_conditions(on_error=on_mismatch, radius_mm=radius_mm, height_mm=height_mm,
                               nu0=nu0)
        self._groups = [(key, g.index.to_numpy(), g["control"].to_numpy(float),
                         g["channel"].to_numpy()) for key, g in self.obs.groupby("curve")]
        self.calls = 0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The (mu, alpha) box every surrogate of the table was trained on."""
        keys = [k for k, *_ in self._groups]
        lo = np.array([max(self.bundles[k].mu_range[0] for k in keys),
                       max(self.bundles[k].alpha_range[0] for k in keys)])
        hi = np.array([min(self.bundles[k].mu_range[1] for k in keys),
                       min(self.bundles[k].alpha_range[1] for k in keys)])
        return lo, hi

    def predict(self, values: Mapping, wrt: Sequence = ()) -> Prediction:
        values = {Param.parse(k): float(v) for k, v in values.items()}
        wrt = tuple(Param.parse(q) for q in wrt)
        bad = [str(q) for q in wrt if q not in (MU0, ALPHA0)]
        if bad:
            raise ValueError(f"the surrogates have no derivative with respect to "
                             f"{', '.join(bad)}")
        self.calls += 1
        m, a = values[MU0], values[ALPHA0]
        y = np.zeros(len(self.obs))
        J = np.zeros((len(self.obs), len(wrt)))
        polar = torque_mNmm(1.0, self.radius_mm)  # torque per kPa of shear stress
        for key, rows, control, channel in self._groups:
            b = self.bundles[key]
            X = np.column_stack([np.full(len(control), m), np.full(len(control), a), control])
            b.check_range(X)
            if wrt:
                s, ds = b.estimator.predict_with_gradient(X)
            else:  # the same values without the derivatives' cost
                s = b.estimator.predict(X)
            scale = np.where(channel == "torque", polar, 1.0)
            y[rows] = s * scale
            for j, q in enumerate(wrt):
                J[rows, j] = ds[:, 0 if q == MU0 else 1] * scale
        return Prediction(y, J, wrt)

