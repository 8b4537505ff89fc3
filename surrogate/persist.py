"""A trained surrogate with what it is valid for, persisted with joblib.

A bundle refuses (or, when asked, warns about) predictions outside its training range of
mu, alpha and the control variable, and use for a geometry, nu0 or FE model other than the
one its samples came from.
"""

from __future__ import annotations

import importlib.metadata as md
import logging
import os
import warnings
from dataclasses import dataclass, field

import joblib
import numpy as np

from brain_fe.io import write_atomic

log = logging.getLogger(__name__)

SCHEMA = "brainmech-surrogate/1"


class OutOfRangeError(ValueError):
    """A surrogate was asked for a prediction it was not trained for."""


class OutOfRangeWarning(UserWarning):
    pass


def library_versions() -> dict:
    out = {}
    for name in ("brainmech", "scikit-learn", "numpy", "scipy", "scikit-optimize",
                 "fenics-dolfinx"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    return out


def sample_conditions(manifest: dict) -> dict:
    """Geometry / material conditions of a sample store's manifest that a surrogate
    inherits: radius, height, nu0, FE model, ends, volumetric law."""
    keys = ("radius_mm", "height_mm", "nu0", "model", "ends", "volumetric")
    flat = {}

    def walk(d):
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v)
            elif k in keys and k not in flat:
                flat[k] = v

    walk(manifest or {})
    return flat


@dataclass
class SurrogateBundle:
    key: str
    estimator: object
    control: str
    target: str
    mu_range: tuple[float, float]
    alpha_range: tuple[float, float]
    control_range: tuple[float, float]
    manifest: dict = field(default_factory=dict)
    hyperparameters: dict = field(default_factory=dict)
    versions: dict = field(default_factory=dict)
    schema: str = SCHEMA

    @property
    def conditions(self) -> dict:
        return sample_conditions(self.manifest)

    def _complain(self, msg: str, on_error: str):
        if on_error == "warn":
            warnings.warn(msg, OutOfRangeWarning, stacklevel=3)
        elif on_error == "error":
            raise OutOfRangeError(msg)

    def check_range(self, X, on_error: str = "error", rtol: float = 1e-9) -> None:
        X = np.atleast_2d(np.asarray(X, dtype=float))
        for col, name, (lo, hi) in ((0, "mu_kPa", self.mu_range), (1, "alpha", self.alpha_range),
                                    (2, self.control, self.control_range)):
            tol = rtol * max(abs(lo), abs(hi), 1.0)
            bad = (X[:, col] < lo - tol) | (X[:, col] > hi + tol)
            if bad.any():
                v = X[bad, col][0]
                self._complain(f"surrogate {self.key}: {name} = {v:.6g} outside the training "
                               f"range [{lo:.6g}, {hi:.6g}]", on_error)

    def check_conditions(self, on_error: str = "error", rtol: float = 1e-9, **given) -> None:
        """Refuse use for another geometry, nu0 or model (keys of :func:`sample_conditions`)."""
        cond = self.conditions
        for k, v in given.items():
            if v is None or k not in cond or cond[k] is None:
                continue
            ref = cond[k]
            same = (np.isclose(float(v), float(ref), rtol=rtol, atol=0.0)
                    if isinstance(ref, (int, float)) and not isinstance(ref, bool) else v == ref)
            if not same:
                self._complain(f"surrogate {self.key} was trained for {k} = {ref}, "
                               f"asked for {k} = {v}", on_error)

    def predict(self, mu, alpha, control, on_out_of_range: str = "error") -> np.ndarray:
        """Stress [kPa] along ``control`` for scalar or array mu [kPa] and alpha."""
        control = np.atleast_1d(np.asarray(control, dtype=float))
        X = np.empty((len(control), 3))
        X[:, 0], X[:, 1], X[:, 2] = mu, alpha, control
        self.check_range(X, on_out_of_range)
        return self.estimator.predict(X)


def save_bundle(bundle: SurrogateBundle, path: str) -> None:
    write_atomic(path, lambda fh: joblib.dump(bundle, fh))


def load_bundle(path: str) -> SurrogateBundle:
    if not os.path.exists(path):
        raise FileNotFoundError(f"no surrogate at {path}")
    try:
        b = joblib.load(path)
    except Exception as exc:  # joblib raises many types for foreign/corrupted files
        raise ValueError(f"{path}: not a readable surrogate ({type(exc).__name__})") from None
    if not isinstance(b, SurrogateBundle) or getattr(b, "schema", None) != SCHEMA:
        raise ValueError(f"{path}: not a brainmech surrogate (schema {SCHEMA})")
    return b


def available_surrogates(model_dir: str) -> list[str]:
    """The test keys with a ``<key>.joblib`` in ``model_dir``."""
    from .data import TEST_KEYS

    keys = [k for k in TEST_KEYS if os.path.exists(os.path.join(model_dir, f"{k}.joblib"))]
    if not keys:
        raise FileNotFoundError(f"no surrogates (<test>.joblib) in {model_dir}")
    return keys


def load_surrogates(model_dir: str, keys=None) -> dict[str, SurrogateBundle]:
    from .data import TEST_KEYS

    keys = keys or TEST_KEYS
    out = {}
    for k in keys:
        out[k] = load_bundle(os.path.join(model_dir, f"{k}.joblib"))
    return out
