"""``brainmech train``: one MLP surrogate per test on a sample store."""

from __future__ import annotations

import json

from .. import args as a
from ..errors import CLIError, say


def add(sub) -> None:
    p = sub.add_parser(
        "train", help="train one MLP surrogate per test on a sample store",
        description="Per test (compression_tension, torsion_0.15, torsion_0.30): split the "
        "curves by parameter set (train / validation / test), choose the architecture by "
        "Gaussian-process Bayesian optimisation (scikit-optimize gp_minimize), retrain with "
        "the best hyper-parameters, evaluate the R^2 of every test curve. Writes "
        "MODEL_DIR/<test>.joblib, metrics.json and figures.")
    p.add_argument("--samples", required=True, metavar="DIR", help="sample store (brainmech "
                   "sample --out DIR)")
    p.add_argument("--out", required=True, metavar="MODEL_DIR")
    p.add_argument("--profile", choices=["default", "paper", "tiny"], default="default",
                   help="default: early stopping (fast); paper: 6000 epochs compression/"
                   "tension, 1000 torsion; tiny: for smoke tests")
    p.add_argument("--trials", type=a.count(1), default=10,
                   help="GP search trials (default 10)")
    p.add_argument("--executions", type=a.count(1), default=2,
                   help="trainings per trial, different seeds (default 2)")
    p.add_argument("--seed", type=a.count(0), default=0)
    p.add_argument("--allow-incomplete", action="store_true",
                   help="train on a store whose sampling has not finished")
    p.set_defaults(run=run)


def run(args) -> int:
    from brain_fe.io import check_output_dir
    from brain_fe.store import load_samples, read_manifest, summarize
    from surrogate.data import TEST_KEYS
    from surrogate.train import train_all

    manifest = read_manifest(args.samples)
    check_output_dir(args.out)
    stored = [t["name"] for t in manifest["spec"]["tests"]]
    tests = tuple(k for k in TEST_KEYS if k in stored)
    if not tests:
        raise CLIError(f"{args.samples}: the store has none of the tests {', '.join(TEST_KEYS)}")
    s = summarize(args.samples)
    if s.missing and not args.allow_incomplete:
        raise CLIError(f"{args.samples}: the sampling is not finished ({s.line()}); run the "
                       "same `brainmech sample` again to complete it, or pass "
                       "--allow-incomplete")
    metrics = train_all(load_samples(args.samples), manifest, args.out, profile=args.profile,
                        trials=args.trials, executions=args.executions, seed=args.seed,
                        tests=tests, progress=True)
    lines = [f"{args.out}: surrogates trained ({args.profile} profile)"]
    for k in tests:
        m = metrics[k]
        lines.append(f"  {k}: test R^2 = {m['r2_mean']:.4f} +- {m['r2_std']:.4f} over "
                     f"{m['n_test_curves']} curves; {json.dumps(m['hyperparameters'])}")
    say(lines)
    return 0
