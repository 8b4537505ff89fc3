"""From the tidy sample table to per-test arrays, and the split by parameter set.

The split never separates the points of one curve: whole parameter sets go to train,
validation or test (paper: 10 % test set aside, untouched until the final evaluation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from brain_fe import vocabulary as v

# One surrogate per protocol of the paper: compression/tension 0.15, torsion 0.15 and 0.30
TEST_KEYS = (v.test_key(v.COMPRESSION_TENSION, 0.15), v.test_key(v.TORSION, 0.15),
             v.test_key(v.TORSION, 0.30))
CONTROL = {k: v.CONTROL[v.test_of_key(k)] for k in TEST_KEYS}
TARGET = {k: v.STRESS_COLUMN[v.test_of_key(k)] for k in TEST_KEYS}
SECOND_TARGET = {k: v.AXIAL_FORCE for k in TEST_KEYS if v.test_of_key(k) == v.TORSION}


@dataclass
class Split:
    train: np.ndarray  # sample ids
    val: np.ndarray
    test: np.ndarray

    def check_disjoint(self) -> None:
        a, b, c = set(self.train), set(self.val), set(self.test)
        if a & b or a & c or b & c:
            raise AssertionError("a parameter set appears in two subsets")


def split_by_parameter_set(sample_ids, *, test_fraction: float = 0.10,
                           val_fraction: float = 0.20, seed: int = 0) -> Split:
    """Shuffle the unique parameter sets and cut them into train / validation / test.

    ``val_fraction`` is taken from what remains after the test set (paper-style
    train_test_split twice). At least one set goes to each subset when possible.
    """
    ids = np.unique(np.asarray(sample_ids))
    if len(ids) < 3:
        raise ValueError(f"need at least 3 parameter sets to split, got {len(ids)}")
    rng = np.random.default_rng(seed)
    ids = rng.permutation(ids)
    n_test = max(1, int(round(test_fraction * len(ids))))
    n_val = max(1, int(round(val_fraction * (len(ids) - n_test))))
    if n_test + n_val >= len(ids):
        n_val = max(1, len(ids) - n_test - 1)
    sp = Split(train=np.sort(ids[n_test + n_val:]), val=np.sort(ids[n_test:n_test + n_val]),
               test=np.sort(ids[:n_test]))
    sp.check_disjoint()
    return sp


def table_for_test(samples: pd.DataFrame, key: str) -> pd.DataFrame:
    """Rows of one test (successful solves only), with the columns the surrogate uses."""
    if key not in TEST_KEYS:
        raise ValueError(f"unknown test {key!r}; expected one of {', '.join(TEST_KEYS)}")
    df = samples[samples["test"] == key]
    if "status" in df:
        df = df[df["status"] == "ok"]
    cols = ["sample", "mu_kPa", "alpha", CONTROL[key], TARGET[key]]
    if key in SECOND_TARGET:
        cols.append(SECOND_TARGET[key])
    df = df[cols + [c for c in ("branch", "time_s") if c in df]].dropna(subset=cols[:5])
    return df.reset_index(drop=True)


def arrays(df: pd.DataFrame, key: str, ids=None, target: str | None = None):
    """X = (mu, alpha, control), y = target column, groups = sample id."""
    if ids is not None:
        df = df[df["sample"].isin(ids)]
    X = df[["mu_kPa", "alpha", CONTROL[key]]].to_numpy(float)
    y = df[target or TARGET[key]].to_numpy(float)
    return X, y, df["sample"].to_numpy()


def unique_rows(X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge repeated inputs (mean target). The elastic model's unloading branch repeats its
    loading branch point for point; training on both doubles the cost for no information."""
    key = np.round(X, 12)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    ym = np.bincount(inv, weights=y) / np.bincount(inv)
    Xu = np.zeros_like(uniq)
    Xu[inv] = X
    return Xu, ym
