"""Train, evaluate and persist one surrogate per test (``brainmech train``).

For each test: split by parameter set, GP hyper-parameter search on train/validation,
final model retrained with the best hyper-parameters on the same train/validation data,
evaluation on the untouched test curves (R^2 of every test curve, the paper's Table 3),
figures of the best, median and worst test curves (the paper's Figure 4), and
``MODEL_DIR/<test>.joblib`` with the training range, geometry, nu0 and library versions.
``MODEL_DIR/metrics.json`` gathers the numbers.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
from sklearn.metrics import r2_score

from brain_fe.io import staged_directory, write_json_atomic
from brain_fe.parallel import Progress
from brain_fe.vocabulary import COMPRESSION_TENSION as CT
from brain_fe.vocabulary import TORSION, test_of_key

from .data import (
    CONTROL,
    TARGET,
    TEST_KEYS,
    arrays,
    split_by_parameter_set,
    table_for_test,
    unique_rows,
)
from .estimator import StressSurrogate
from .persist import SurrogateBundle, library_versions, save_bundle
from .search import gp_search

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Profile:
    """Training budget. ``paper``: fixed epochs as in the paper (6000 compression/tension,
    1000 torsion), no early stopping; ``default``: early stopping, far cheaper."""

    name: str
    search_epochs: dict
    final_epochs: dict
    early_stopping: bool

    def fixed(self, key: str, final: bool) -> dict:
        epochs = (self.final_epochs if final else self.search_epochs)[test_of_key(key)]
        return {"max_iter": epochs, "early_stopping": self.early_stopping}


PROFILES = {
    "paper": Profile("paper", {CT: 6000, TORSION: 1000}, {CT: 6000, TORSION: 1000}, False),
    "default": Profile("default", {CT: 60, TORSION: 60}, {CT: 1000, TORSION: 1000}, True),
    # for tests and the quick reproduce profile
    "tiny": Profile("tiny", {CT: 40, TORSION: 40}, {CT: 200, TORSION: 200}, True),
}


def curve_r2(df_test: pd.DataFrame, key: str, model) -> pd.DataFrame:
    """Coefficient of determination of every test curve (one per parameter set)."""
    rows = []
    for sid, g in df_test.groupby("sample"):
        X, y, _ = arrays(g, key)
        pred = model.predict(X)
        rows.append({"sample": sid, "mu_kPa": g.mu_kPa.iloc[0], "alpha": g.alpha.iloc[0],
                     "r2": float(r2_score(y, pred)) if np.ptp(y) > 0 else np.nan,
                     "mae_kPa": float(np.mean(np.abs(y - pred)))})
    return pd.DataFrame(rows).sort_values("r2").reset_index(drop=True)


def plot_curves(df_test: pd.DataFrame, key: str, model, r2: pd.DataFrame, path: str) -> None:
    """Best, median and worst test curves: FE points vs surrogate line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    picks = {"worst": r2.iloc[0], "median": r2.iloc[len(r2) // 2], "best": r2.iloc[-1]}
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), sharey=False)
    for ax, (label, row) in zip(axes, picks.items(), strict=True):
        g = df_test[df_test["sample"] == row["sample"]]
        X, y, _ = arrays(g, key)
        order = np.argsort(X[:, 2])
        xs = np.linspace(X[:, 2].min(), X[:, 2].max(), 200)
        Xs = np.column_stack([np.full_like(xs, X[0, 0]), np.full_like(xs, X[0, 1]), xs])
        ax.plot(X[order, 2], y[order], "o", ms=4, label="FE")
        ax.plot(xs, model.predict(Xs), "-", label="surrogate")
        ax.set_title(f"{label}: R$^2$ = {row['r2']:.4f}\nmu = {row['mu_kPa']:.3g} kPa, "
                     f"alpha = {row['alpha']:.3g}", fontsize=9)
        ax.set_xlabel(CONTROL[key])
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"{TARGET[key]}")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{key}: test curves (FE discretisation error <= 1 %, see BENCHMARKS.md)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def train_all(samples: pd.DataFrame, manifest: dict, out_dir: str, *, profile: str = "default",
              trials: int = 10, executions: int = 2, seed: int = 0,
              tests: tuple[str, ...] = TEST_KEYS, progress: bool = False) -> dict:
    """Train and evaluate one surrogate per test; returns the metrics dictionary."""
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; expected one of {', '.join(PROFILES)}")
    prof = PROFILES[profile]
    with staged_directory(out_dir) as stage, \
            Progress(trials * len(tests), "hyper-parameter trials", "trial",
                     enabled=progress) as bar:
        return _train(samples, manifest, str(stage), prof, trials, executions, seed, tests,
                      bar)


def _train(samples, manifest, out_dir, prof, trials, executions, seed, tests, bar) -> dict:
    metrics: dict = {"profile": prof.name, "trials": trials, "executions": executions,
                     "seed": seed, "versions": library_versions()}
    for key in tests:
        table = table_for_test(samples, key)
        if table.empty:
            raise ValueError(f"the sample store has no successful {key} curves")
        split = split_by_parameter_set(table["sample"], seed=seed)
        Xtr, ytr = unique_rows(*arrays(table, key, split.train)[:2])
        Xva, yva = unique_rows(*arrays(table, key, split.val)[:2])
        t0 = time.perf_counter()

        def on_trial(i, params, score, key=key):
            bar.update(1, f"{key} trial {i}: MAE {score:.3g} kPa")

        search = gp_search(Xtr, ytr, Xva, yva, trials=trials, executions=executions,
                           seed=seed, fixed=prof.fixed(key, final=False), on_trial=on_trial)
        final = StressSurrogate(**search.best_params, **prof.fixed(key, final=True),
                                random_state=seed).fit(Xtr, ytr)
        train_time = time.perf_counter() - t0
        df_test = table[table["sample"].isin(split.test)]
        r2 = curve_r2(df_test, key, final)
        bundle = SurrogateBundle(
            key=key, estimator=final, control=CONTROL[key], target=TARGET[key],
            mu_range=(float(table.mu_kPa.min()), float(table.mu_kPa.max())),
            alpha_range=(float(table.alpha.min()), float(table.alpha.max())),
            control_range=(float(table[CONTROL[key]].min()),
                           float(table[CONTROL[key]].max())),
            manifest=manifest, hyperparameters=search.best_params,
            versions=library_versions())
        save_bundle(bundle, os.path.join(out_dir, f"{key}.joblib"))
        plot_curves(df_test, key, final, r2, os.path.join(out_dir, f"{key}_test_curves.png"))
        r2.to_csv(os.path.join(out_dir, f"{key}_test_r2.csv"), index=False)
        metrics[key] = {
            "r2_mean": float(r2.r2.mean()), "r2_std": float(r2.r2.std(ddof=0)),
            "r2_min": float(r2.r2.min()), "n_test_curves": int(len(r2)),
            "n_train_curves": int(len(split.train)), "n_val_curves": int(len(split.val)),
            "test_mae_kPa": float(r2.mae_kPa.mean()),
            "hyperparameters": search.best_params, "val_mae_kPa": search.best_score,
            "trials": search.trials, "epochs_final": int(final.n_iter_),
            "train_time_s": train_time,
        }
        log.info("%s: R2 = %.4f +- %.4f over %d test curves", key, metrics[key]["r2_mean"],
                 metrics[key]["r2_std"], len(r2))
    write_json_atomic(os.path.join(out_dir, "metrics.json"), metrics, indent=2)
    return metrics
