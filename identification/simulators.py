"""Stress at the recorded control values from the surrogate or from the FE model.

Both simulators map (mu [kPa], alpha) to one array of stresses per :class:`Curve`. The FE
simulator also returns d(stress)/d(mu, alpha) by direct differentiation (nu0 fixed, so
kappa = kappa(nu0) mu moves with mu and enters d/dmu through the chain rule).

The one-term Ogden model is elastic, so its response depends on the control value only,
not on the path: the FE simulator solves the loading branches (1 -> 1-A, 1 -> 1+A;
0 -> gamma_max) at increments of 0.015 (A/10 in torsion) and evaluates a cubic spline
through them at the recorded points, loading and unloading alike. The spline error is
below 1e-5 of the stress (checked in the tests against a direct solve).
"""

from __future__ import annotations

import logging

import numpy as np
from mpi4py import MPI
from scipy.interpolate import CubicSpline

from brain_fe.model import ForwardModel, MaterialParameters
from brain_fe.protocols import Protocol

from .objective import Curve

log = logging.getLogger(__name__)

_STRESS = {"compression_tension": "nominal_stress_kPa", "torsion": "shear_stress_kPa"}


class SurrogateSimulator:
    """Stage 1: the trained MLP bundles (surrogate.persist) for the curves' tests."""

    def __init__(self, bundles: dict, *, radius_mm: float, height_mm: float, nu0: float,
                 on_mismatch: str = "error"):
        self.bundles = bundles
        self.on_mismatch = on_mismatch
        for b in bundles.values():
            b.check_conditions(on_error=on_mismatch, radius_mm=radius_mm, height_mm=height_mm,
                               nu0=nu0)
        self.calls = 0

    def bounds(self, keys) -> tuple[np.ndarray, np.ndarray]:
        lo = np.array([max(self.bundles[k].mu_range[0] for k in keys),
                       max(self.bundles[k].alpha_range[0] for k in keys)])
        hi = np.array([min(self.bundles[k].mu_range[1] for k in keys),
                       min(self.bundles[k].alpha_range[1] for k in keys)])
        return lo, hi

    def check_keys(self, curves: list[Curve]) -> None:
        missing = [c.key for c in curves if c.key not in self.bundles]
        if missing:
            raise ValueError(f"no surrogate for test(s) {', '.join(missing)} "
                             f"(have {', '.join(self.bundles)})")

    def __call__(self, curves: list[Curve], mu: float, alpha: float) -> list[np.ndarray]:
        self.calls += 1
        return [self.bundles[c.key].predict(mu, alpha, c.control) for c in curves]


class FESimulator:
    """Stage 2: the FE model of the specimen's geometry with sensitivities."""

    def __init__(self, radius_mm: float, height_mm: float, nu0: float, *,
                 model: str = "axisymmetric", refinement: int | None = None,
                 forward_model: ForwardModel | None = None):
        from brain_fe.api import make_geometry

        self.nu0 = nu0
        self.fm = forward_model or ForwardModel(
            make_geometry(model, radius_mm, height_mm, refinement, comm=MPI.COMM_SELF))
        self.protocol_solves = 0
        self.evaluations = 0
        self._cache: dict = {}

    def _branches(self, curve: Curve) -> list[Protocol]:
        if curve.test == "compression_tension":
            A = curve.amplitude
            return [Protocol(curve.test, (1.0, 1.0 - A), max_increment=0.015),
                    Protocol(curve.test, (1.0, 1.0 + A), max_increment=0.015)]
        return [Protocol(curve.test, (0.0, curve.amplitude), max_increment=curve.amplitude / 10)]

    def evaluate(self, curves: list[Curve], mu: float, alpha: float, *,
                 sensitivities: bool = True):
        """Simulated stresses per curve and, with ``sensitivities``, d/d(mu, alpha)."""
        key = (float(mu), float(alpha), sensitivities, tuple(c.key for c in curves))
        if key in self._cache:
            return self._cache[key]
        params = MaterialParameters(mu=(mu,), alpha=(alpha,), nu0=self.nu0)
        dkappa_dmu = params.kappa_kPa / mu  # kappa proportional to mu at fixed nu0
        sims, jacs = [], []
        for c in curves:
            col = _STRESS[c.test]
            xs, ys, dmu, dal = [], [], [], []
            for prot in self._branches(c):
                df = self.fm.run(prot, params, sensitivities=sensitivities)
                xs.append(df[prot.control].to_numpy())
                ys.append(df[col].to_numpy())
                if sensitivities:
                    dmu.append(df[f"d_{col}/d_mu_0"].to_numpy()
                               + dkappa_dmu * df[f"d_{col}/d_kappa"].to_numpy())
                    dal.append(df[f"d_{col}/d_alpha_0"].to_numpy())
            self.protocol_solves += 1
            x = np.concatenate(xs)
            order = np.argsort(x)
            x, keep = np.unique(x[order], return_index=True)

            def spline(parts, order=order, keep=keep, x=x, at=c.control):
                return CubicSpline(x, np.concatenate(parts)[order][keep])(at)

            sims.append(spline(ys))
            if sensitivities:
                jacs.append(np.column_stack([spline(dmu), spline(dal)]))
        self.evaluations += 1
        out = (sims, jacs if sensitivities else None)
        self._cache = {key: out}  # the least-squares solver asks fun and jac at one point
        return out

    def __call__(self, curves: list[Curve], mu: float, alpha: float) -> list[np.ndarray]:
        return self.evaluate(curves, mu, alpha, sensitivities=False)[0]
