"""Forward simulators with the interface the diagnosis fits: ``predict(values, names)``.

``values`` maps parameter names (base ``mu_0, alpha_0``; effect parameters of
:mod:`diagnosis.effects`) to numbers; ``predict`` returns the prediction at every row of
the observation table and its derivatives with respect to ``names`` (n_obs x len(names)).
The FE simulator follows the recorded path (history-dependent physics) and differentiates
by the forward model's sensitivities, with the chain rule for transformed parameters:
d/dmu_p at fixed nu0 includes dkappa/dmu = kappa/mu, d/dnu0 = 2 mu/(1 - 2 nu0)^2 d/dkappa,
d/dlog10(q) = ln(10) q d/dq.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
from mpi4py import MPI

from brain_fe.artefacts import Artefacts
from brain_fe.material import kappa_from_nu0
from brain_fe.model import ForwardModel, MaterialParameters

from .observations import CHANNEL_COLUMN, RecordedPath

log = logging.getLogger(__name__)
LN10 = math.log(10.0)
ARTEFACT_KEYS = {"stretch_offset": "stretch_offset", "force_offset": "force_offset_mN",
                 "torque_offset": "torque_offset_mNmm", "height_rel": "height_rel",
                 "radius_rel": "radius_rel"}


def material_from_values(values: dict, nu0: float) -> tuple[MaterialParameters, Artefacts]:
    n = 1 + max([int(k.split("_")[1]) for k in values if k.startswith("mu_")] + [0])
    mu = tuple(values.get(f"mu_{p}", 0.0) for p in range(n))
    alpha = tuple(values.get(f"alpha_{p}", 1.0) for p in range(n))
    kw = {}
    if "beta_0" in values:
        kw.update(beta=(max(values["beta_0"], 0.0),), tau_s=(10 ** values["log10_tau_0"],))
    if "softening" in values:
        kw.update(softening=max(values["softening"], 0.0),
                  softening_m_kPa=10 ** values["log10_softening_m"])
    if "log10_k" in values:
        k = 10 ** values["log10_k"]
        kw.update(k_r_kPa_mm=k, k_theta_kPa_mm=k)
    nu = values.get("nu0", nu0)
    params = MaterialParameters(mu=mu, alpha=alpha, nu0=None,
                                kappa=kappa_from_nu0(sum(mu), nu), **kw)
    art = Artefacts(**{ARTEFACT_KEYS[k]: v for k, v in values.items() if k in ARTEFACT_KEYS})
    return params, art


class FESimulator:
    """Axisymmetric FE model of one specimen following its recorded paths.

    ``correction`` (an array over the observations, default 0) is added to every
    prediction: the diagnosis stores there the discretisation error of this mesh,
    estimated against the next finer one at the base fit (deferred correction).
    """

    kind = "fe"

    def __init__(self, obs: pd.DataFrame, radius_mm: float, height_mm: float, *,
                 refinement: int = 1, nu0: float = 0.49, comm=MPI.COMM_SELF):
        from brain_fe.api import make_geometry

        self.obs = obs.reset_index(drop=True)
        self.nu0 = nu0
        self.refinement = refinement
        self.geometry = make_geometry("axisymmetric", radius_mm, height_mm, refinement,
                                      comm=comm)
        self._models: dict = {}
        self.curves = []
        for curve, g in self.obs.groupby("curve", sort=False):
            first = g[g.channel == g.channel.iloc[0]]
            path, index = RecordedPath.from_curve(first)
            rows = {ch: (gc.index.to_numpy(), index) for ch, gc in g.groupby("channel")}
            self.curves.append((curve, path, rows))
        self.correction = np.zeros(len(self.obs))
        self.solves = 0

    def model(self, key: tuple) -> ForwardModel:
        """Compiled model for (Ogden terms, Maxwell branches, softening, springs)."""
        if key not in self._models:
            self._models[key] = ForwardModel(
                self.geometry, n_terms=key[0], maxwell=key[1], mullins=key[2],
                ends="springs" if key[3] else "glued")
        return self._models[key]

    def predict(self, values: dict, names=()) -> tuple[np.ndarray, np.ndarray]:
        params, art = material_from_values(values, self.nu0)
        fm = self.model((len(params.mu), params.maxwell, "softening" in values,
                         "log10_k" in values))
        wanted = sorted({m for n in names for m in self._model_names(n)})
        y = np.zeros(len(self.obs))
        J = np.zeros((len(self.obs), len(names)))
        mu_tot = params.mu_total
        nu = values.get("nu0", self.nu0)
        kappa = params.kappa_kPa
        for _curve, path, rows in self.curves:
            df = fm.run(path, params, artefacts=art, sensitivities=wanted or False)
            self.solves += 1
            for ch, (obs_rows, idx) in rows.items():
                col = CHANNEL_COLUMN[ch]
                y[obs_rows] = df[col].to_numpy()[idx]

                def d(m, col=col, idx=idx, df=df):
                    return df[f"d_{col}/d_{m}"].to_numpy()[idx]

                for j, n in enumerate(names):
                    if n.startswith("mu_"):
                        J[obs_rows, j] = d(n) + kappa / mu_tot * d("kappa")
                    elif n == "nu0":
                        J[obs_rows, j] = 2 * mu_tot / (1 - 2 * nu) ** 2 * d("kappa")
                    elif n == "log10_tau_0":
                        J[obs_rows, j] = LN10 * params.tau_s[0] * d("tau_0")
                    elif n == "log10_softening_m":
                        J[obs_rows, j] = LN10 * params.softening_m_kPa * d("softening_m")
                    elif n == "log10_k":
                        J[obs_rows, j] = LN10 * params.k_r_kPa_mm * (d("k_r") + d("k_theta"))
                    else:
                        J[obs_rows, j] = d(n)
        return y + self.correction, J

    @staticmethod
    def _model_names(name: str) -> list[str]:
        if name.startswith("mu_"):
            return [name, "kappa"]
        return {"nu0": ["kappa"], "log10_tau_0": ["tau_0"],
                "log10_softening_m": ["softening_m"],
                "log10_k": ["k_r", "k_theta"]}.get(name, [name])
