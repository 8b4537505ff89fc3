"""Bayesian (Gaussian-process) hyper-parameter search with scikit-optimize's ``gp_minimize``.

Search space (paper section 2.5): two hidden layers of 64..512 neurons in steps of 32
(searched as integers 2..16 times 32: ``BayesSearchCV`` cannot take tuples as categories),
activation in {relu, tanh, logistic} (scikit-learn has no ELU), Adam learning rate in
{1e-4, 1e-3, 1e-2}. Each trial trains ``executions`` networks with different seeds and
scores their mean validation mean-absolute error (kPa) on the validation curves.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from sklearn.metrics import mean_absolute_error

from .estimator import ACTIVATIONS, LEARNING_RATES, StressSurrogate

log = logging.getLogger(__name__)

WIDTH_STEP = 32
WIDTH_RANGE = (2, 16)  # x 32 -> 64 .. 512


@dataclass
class SearchResult:
    best_params: dict
    best_score: float
    trials: list[dict] = field(default_factory=list)


def _space():
    from skopt.space import Categorical, Integer

    return [Integer(*WIDTH_RANGE, name="width1"), Integer(*WIDTH_RANGE, name="width2"),
            Categorical(list(ACTIVATIONS), name="activation"),
            Categorical(list(LEARNING_RATES), name="learning_rate_init")]


def to_params(point) -> dict:
    w1, w2, act, lr = point
    return {"hidden1": int(w1) * WIDTH_STEP, "hidden2": int(w2) * WIDTH_STEP,
            "activation": str(act), "learning_rate_init": float(lr)}


def gp_search(X_train, y_train, X_val, y_val, *, trials: int = 10, executions: int = 2,
              seed: int = 0, fixed: dict | None = None,
              on_trial: Callable[[int, dict, float], None] | None = None) -> SearchResult:
    """Minimise the validation MAE over the search space with a GP surrogate (EI).

    ``fixed`` holds the non-searched estimator parameters (epochs, early stopping...).
    """
    from skopt import gp_minimize

    if trials < 1 or executions < 1:
        raise ValueError("trials and executions must be >= 1")
    fixed = dict(fixed or {})
    history: list[dict] = []

    def objective(point):
        params = to_params(point)
        scores = []
        for e in range(executions):
            est = StressSurrogate(**params, **fixed, random_state=seed * 1000 + e)
            est.fit(X_train, y_train)
            scores.append(mean_absolute_error(y_val, est.predict(X_val)))
        score = float(np.mean(scores))
        history.append({**params, "val_mae_kPa": score, "val_mae_runs": scores})
        log.info("trial %d: %s -> validation MAE %.4g kPa", len(history), params, score)
        if on_trial:
            on_trial(len(history), params, score)
        return score

    n_initial = min(trials, max(1, min(5, trials // 2)))
    res = gp_minimize(objective, _space(), n_calls=trials, n_initial_points=n_initial,
                      acq_func="EI", random_state=seed)
    best = to_params(res.x)
    return SearchResult(best_params=best, best_score=float(res.fun), trials=history)
