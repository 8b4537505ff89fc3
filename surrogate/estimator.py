"""MLP surrogate of one FE test: (mu [kPa], alpha, stretch or shear) -> stress [kPa].

A scikit-learn estimator (hyper-parameters in ``__init__``, fitted attributes end in ``_``,
``fit`` returns self) wrapping a ``Pipeline`` with input scaling and an ``MLPRegressor``
(Adam, two hidden layers), inside a ``TransformedTargetRegressor`` for output scaling.

Physics-informed target (``scale_by_mu=True``, default): with nu0 fixed, kappa is
proportional to mu, so the whole energy and every stress of the one-term Ogden model are
exactly proportional to mu. The network then learns stress / mu as a function of
(log mu, alpha, control) - the log mu input is kept so the estimator stays general (e.g.
for samples with other physics), but the dominant scale is handled exactly.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.special import expit
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.compose import ColumnTransformer, TransformedTargetRegressor
from sklearn.exceptions import ConvergenceWarning
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import FunctionTransformer, StandardScaler
from sklearn.utils.validation import check_is_fitted, check_X_y, validate_data

ACTIVATIONS = ("relu", "tanh", "logistic")  # scikit-learn has no ELU (the paper's third)
LEARNING_RATES = (1e-4, 1e-3, 1e-2)


_ACT = {"relu": lambda h: np.maximum(h, 0.0), "tanh": np.tanh, "logistic": expit}
# derivative of each activation from its value a = act(z)
_DACT = {"relu": lambda a: (a > 0.0).astype(float), "tanh": lambda a: 1.0 - a * a,
         "logistic": lambda a: a * (1.0 - a)}


def _log_first_column(X):
    X = np.array(X, dtype=float, copy=True)
    X[:, 0] = np.log(X[:, 0])
    return X


class StressSurrogate(RegressorMixin, BaseEstimator):
    """MLP regression of the stress of one test on (mu, alpha, control).

    Parameters
    ----------
    hidden1, hidden2: neurons of the two hidden layers (the search uses 64..512 step 32).
    activation: ``relu``, ``tanh`` or ``logistic`` for both hidden layers.
    learning_rate_init: Adam's step size (1e-4, 1e-3 or 1e-2 in the search).
    max_iter: epochs.
    early_stopping: hold out ``validation_fraction`` of the *training* rows and stop when
        the validation score stalls for ``n_iter_no_change`` epochs.
    scale_by_mu: learn stress / mu (exact scaling of the one-term model at fixed nu0).
    batch_size, alpha_l2, random_state: passed to ``MLPRegressor``.
    """

    def __init__(self, hidden1: int = 128, hidden2: int = 128, activation: str = "tanh",
                 learning_rate_init: float = 1e-3, max_iter: int = 500,
                 early_stopping: bool = True, n_iter_no_change: int = 30,
                 validation_fraction: float = 0.1, scale_by_mu: bool = True,
                 batch_size: int = 256, alpha_l2: float = 1e-6, random_state=None):
        self.hidden1 = hidden1
        self.hidden2 = hidden2
        self.activation = activation
        self.learning_rate_init = learning_rate_init
        self.max_iter = max_iter
        self.early_stopping = early_stopping
        self.n_iter_no_change = n_iter_no_change
        self.validation_fraction = validation_fraction
        self.scale_by_mu = scale_by_mu
        self.batch_size = batch_size
        self.alpha_l2 = alpha_l2
        self.random_state = random_state

    def _network(self):
        mlp = MLPRegressor(hidden_layer_sizes=(int(self.hidden1), int(self.hidden2)),
                           activation=self.activation, solver="adam",
                           learning_rate_init=self.learning_rate_init, max_iter=self.max_iter,
                           early_stopping=self.early_stopping,
                           n_iter_no_change=self.n_iter_no_change,
                           validation_fraction=self.validation_fraction,
                           batch_size=self.batch_size, alpha=self.alpha_l2, tol=1e-7,
                           random_state=self.random_state)
        inputs = ColumnTransformer([("all", FunctionTransformer(_log_first_column), [0, 1, 2])])
        pipe = Pipeline([("log_mu", inputs), ("scale", StandardScaler()), ("mlp", mlp)])
        return TransformedTargetRegressor(regressor=pipe, transformer=StandardScaler())

    def fit(self, X, y):
        """X: (n, 3) array of mu [kPa] > 0, alpha, stretch|shear; y: stress [kPa]."""
        X, y = check_X_y(X, y, y_numeric=True)
        if X.shape[1] != 3:
            raise ValueError(f"expected 3 input columns (mu, alpha, control), got {X.shape[1]}")
        if np.any(X[:, 0] <= 0):
            raise ValueError("mu must be positive")
        validate_data(self, X, reset=True, skip_check_array=True)
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}")
        target = y / X[:, 0] if self.scale_by_mu else y
        with warnings.catch_warnings():
            # a fixed epoch budget (search trials, 'paper' profile) is a choice, not a fault
            warnings.simplefilter("ignore", ConvergenceWarning)
            self.model_ = self._network().fit(X, target)
        mlp = self.model_.regressor_.named_steps["mlp"]
        self.n_iter_ = mlp.n_iter_
        self.loss_curve_ = list(mlp.loss_curve_)
        return self

    def predict(self, X):
        """Stress [kPa]. A direct numpy forward pass through the fitted scalers and network
        (identical to the sklearn pipeline's ``predict``, which the tests check) because the
        identification calls it thousands of times on 20-point curves, where the pipeline's
        per-call validation dominates."""
        check_is_fitted(self, "model_")
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ValueError("X must have 3 columns (mu, alpha, control)")
        out = self._forward(X)
        return out * X[:, 0] if self.scale_by_mu else out

    def predict_with_gradient(self, X) -> tuple[np.ndarray, np.ndarray]:
        """Stress [kPa] and its exact derivatives with respect to (mu, alpha), shape (n, 2):
        the network differentiated layer by layer (forward mode) through the input scaling
        (log mu) and the mu scaling of the target."""
        check_is_fitted(self, "model_")
        X = np.asarray(X, dtype=float)
        reg = self.model_.regressor_
        sc, mlp = reg.named_steps["scale"], reg.named_steps["mlp"]
        h = (_log_first_column(X) - sc.mean_) / sc.scale_
        # dh/d(mu, alpha), one (points x width) slice per parameter: d log(mu)/d mu = 1 / mu,
        # then the scaler.  Each layer is then a matrix product per slice (BLAS): an einsum
        # over (point, input, parameter) took 40-55 times as long and made the surrogate
        # stage of an identification cost more than its FE stage
        dh = np.zeros((2, *X.shape))
        dh[0, :, 0] = 1.0 / (X[:, 0] * sc.scale_[0])
        dh[1, :, 1] = 1.0 / sc.scale_[1]
        last = len(mlp.coefs_) - 1
        for i, (W, b) in enumerate(zip(mlp.coefs_, mlp.intercepts_, strict=True)):
            h = h @ W + b
            dh = dh @ W
            if i < last:
                h = _ACT[mlp.activation](h)
                dh = dh * _DACT[mlp.activation](h)
        t = self.model_.transformer_
        f = h[:, 0] * t.scale_[0] + t.mean_[0]
        df = dh[:, :, 0].T * t.scale_[0]
        if not self.scale_by_mu:
            return f, df
        mu = X[:, 0]
        return f * mu, np.column_stack([f + mu * df[:, 0], mu * df[:, 1]])

    def predict_pipeline(self, X):
        """The same prediction through the scikit-learn pipeline (reference path)."""
        check_is_fitted(self, "model_")
        X = np.asarray(X, dtype=float)
        out = self.model_.predict(X)
        return out * X[:, 0] if self.scale_by_mu else out

    def _forward(self, X):
        reg = self.model_.regressor_
        sc = reg.named_steps["scale"]
        mlp = reg.named_steps["mlp"]
        h = (_log_first_column(X) - sc.mean_) / sc.scale_
        act = _ACT[mlp.activation]
        last = len(mlp.coefs_) - 1
        for i, (W, b) in enumerate(zip(mlp.coefs_, mlp.intercepts_, strict=True)):
            h = h @ W + b
            if i < last:
                h = act(h)
        t = self.model_.transformer_
        return h[:, 0] * t.scale_[0] + t.mean_[0]
