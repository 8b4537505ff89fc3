"""``brainmech``: the command line. It only parses arguments and calls library code."""

from __future__ import annotations

import argparse
import logging
import re
import sys
from importlib.metadata import PackageNotFoundError, version

log = logging.getLogger("brainmech")


class CLIError(Exception):
    """An error reported to the user as one line, without a traceback."""


def _say(lines: list[str]) -> None:
    """A command's result summary on stdout (the only place the CLI writes to stdout)."""
    sys.stdout.write("\n".join(lines) + "\n")


def _version() -> str:
    try:
        return version("brainmech")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "unknown"


def _floats(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}") from None
    if not vals:
        raise argparse.ArgumentTypeError("expected at least one number")
    return vals


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def _accept_negative_lists(p: argparse.ArgumentParser) -> None:
    """Let negative comma lists through as option values (``--alpha -25,5``,
    ``--alpha-range -40,-2``); argparse otherwise only recognises single negative numbers
    and takes ``-25,5`` for an option."""
    p._negative_number_matcher = re.compile(r"^-\.?\d[\d.,eE+-]*$")


def _add_simulate(sub):
    p = sub.add_parser(
        "simulate", help="run one test protocol on the FE model and write a CSV",
        description="Displacement-controlled compression/tension (1 -> 1-A -> 1 -> 1+A -> 1) "
        "or torsion (0 -> A -> 0, height fixed) of a glued cylinder with a compressible "
        "N-term Ogden material. Units: mm, kPa, mN, mN mm, s.")
    _accept_negative_lists(p)
    p.add_argument("--model", choices=["axisymmetric", "3d"], default="axisymmetric")
    p.add_argument("--test", choices=["compression_tension", "torsion"],
                   default="compression_tension")
    p.add_argument("--amplitude", type=_positive, default=None,
                   help="stretch amplitude A (default 0.15) or maximum amount of shear "
                   "(default 0.30)")
    p.add_argument("--mu", type=_floats, default=(1.0,),
                   help="shear modulus per Ogden term, kPa, comma list (default 1.0)")
    p.add_argument("--alpha", type=_floats, default=(-20.0,),
                   help="Ogden exponent per term, comma list (default -20)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--kappa", type=_positive, default=None, help="bulk modulus, kPa")
    g.add_argument("--nu0", type=float, default=None,
                   help="initial Poisson ratio (default 0.49); kappa = 2 mu (1+nu0)/(3(1-2 nu0))")
    p.add_argument("--volumetric", choices=["quadratic", "log"], default="quadratic",
                   help="U(J): quadratic kappa/2 (J-1)^2 (default) or log "
                   "kappa/4 (J^2-1-2 ln J)")
    p.add_argument("--radius-mm", type=_positive, default=4.0)
    p.add_argument("--height-mm", type=_positive, default=5.0)
    p.add_argument("--ends", choices=["glued", "slip", "springs"], default="glued",
                   help="glued plates (default), frictionless (slip) or a compliant glue "
                   "layer (springs: give --k-r and --k-theta)")
    p.add_argument("--refinement", type=int, default=None,
                   help="mesh refinement level k (default: the level with <= 1 %% force "
                   "error, see BENCHMARKS.md)")
    p.add_argument("--rate", type=_positive, default=0.01,
                   help="rate of the controlled quantity, 1/s (default 0.01)")
    p.add_argument("--cycles", type=int, default=1)
    p.add_argument("--hold", type=float, default=0.0, metavar="S",
                   help="dwell after every branch, s (relaxation; default 0)")
    x = p.add_argument_group("physics extensions (docs/physics.md); defaults are neutral")
    x.add_argument("--maxwell-beta", type=_floats, default=(), metavar="LIST",
                   help="relative stiffness beta_i >= 0 of each Maxwell branch")
    x.add_argument("--maxwell-tau", type=_floats, default=(), metavar="LIST",
                   help="relaxation time tau_i > 0 of each Maxwell branch, s")
    x.add_argument("--softening", type=float, default=0.0, metavar="D",
                   help="Ogden-Roxburgh softening d = 1/r in [0, 1) (Mullins effect)")
    x.add_argument("--softening-m", type=_positive, default=0.05, metavar="KPA",
                   help="Ogden-Roxburgh energy scale m, kPa (default 0.05)")
    x.add_argument("--k-r", type=float, default=None, metavar="KPA_MM",
                   help="radial stiffness per area of the glue layer (--ends springs)")
    x.add_argument("--k-theta", type=float, default=None, metavar="KPA_MM",
                   help="circumferential stiffness per area of the glue layer")
    a = p.add_argument_group("measurement artefacts (true = nominal x (1 + e)); default 0")
    a.add_argument("--height-rel", type=float, default=0.0, metavar="E")
    a.add_argument("--radius-rel", type=float, default=0.0, metavar="E")
    a.add_argument("--stretch-offset", type=float, default=0.0, metavar="S",
                   help="contact-point zero offset: true stretch = recorded + S")
    a.add_argument("--force-offset", type=float, default=0.0, metavar="MN")
    a.add_argument("--torque-offset", type=float, default=0.0, metavar="MNMM")
    p.add_argument("--sensitivities", action="store_true",
                   help="add d_<column>/d_<parameter> columns for every model parameter")
    p.add_argument("--out", default=None, help="CSV file (default: print to stdout)")
    p.add_argument("--fields", default=None,
                   help="XDMF file for the displacement field per step (ParaView)")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args) -> int:
    import os

    from brain_fe import api

    if args.out and not os.path.isdir(os.path.dirname(os.path.abspath(args.out))):
        raise CLIError(f"--out: directory does not exist: {os.path.dirname(args.out)}")
    nu0 = args.nu0 if args.nu0 is not None else (None if args.kappa else 0.49)
    df = api.simulate(model=args.model, test=args.test, amplitude=args.amplitude, mu=args.mu,
                      alpha=args.alpha, kappa=args.kappa, nu0=nu0,
                      volumetric=args.volumetric, radius_mm=args.radius_mm,
                      height_mm=args.height_mm, ends=args.ends, refinement=args.refinement,
                      rate_per_s=args.rate, cycles=args.cycles, hold_s=args.hold,
                      field_output=args.fields, progress=True,
                      sensitivities=args.sensitivities,
                      physics=dict(beta=args.maxwell_beta, tau_s=args.maxwell_tau,
                                   softening=args.softening,
                                   softening_m_kPa=args.softening_m, k_r_kPa_mm=args.k_r,
                                   k_theta_kPa_mm=args.k_theta),
                      artefacts=dict(height_rel=args.height_rel, radius_rel=args.radius_rel,
                                     stretch_offset=args.stretch_offset,
                                     force_offset_mN=args.force_offset,
                                     torque_offset_mNmm=args.torque_offset))
    if args.out:
        api.write_csv_atomic(df, args.out)
        log.info("wrote %s (%d rows)", args.out, len(df))
    else:
        from mpi4py import MPI

        if MPI.COMM_WORLD.rank == 0:
            sys.stdout.write(df.to_csv(index=False, float_format="%.10g"))
    return 0


def _range(text: str) -> tuple[float, float]:
    vals = _floats(text)
    if len(vals) != 2 or not vals[0] < vals[1]:
        raise argparse.ArgumentTypeError(f"expected two numbers lo,hi with lo < hi, got {text!r}")
    return vals


def _add_sample(sub):
    p = sub.add_parser(
        "sample", help="generate FE samples over a parameter design (parallel, resumable)",
        description="Solve the forward model for n parameter sets (mu log-uniform, alpha "
        "uniform) and store the results in DIR (manifest.json + Parquet chunks). Run as "
        "`mpirun -n K brainmech sample ...`: every rank solves its own share on "
        "MPI.COMM_SELF. Re-running the same command resumes: it computes only the missing "
        "samples.")
    _accept_negative_lists(p)
    p.add_argument("--n", type=int, required=True, help="number of parameter sets")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--design", choices=["sobol", "lhs"], default="sobol")
    p.add_argument("--mu-range", type=_range, default=(0.1, 5.0),
                   help="mu range in kPa, log-uniform (default 0.1,5)")
    p.add_argument("--alpha-range", type=_range, default=(-40.0, -2.0),
                   help="alpha range, uniform (default -40,-2)")
    p.add_argument("--nu0", type=float, default=0.49, help="initial Poisson ratio (0.49)")
    p.add_argument("--tests", default="compression_tension,torsion:0.15,torsion:0.30",
                   help="comma list of test[:amplitude] (default "
                   "compression_tension,torsion:0.15,torsion:0.30)")
    p.add_argument("--model", choices=["axisymmetric", "3d"], default="axisymmetric")
    p.add_argument("--refinement", type=int, default=None,
                   help="mesh refinement level k (default: the model's default)")
    p.add_argument("--radius-mm", type=_positive, default=4.0)
    p.add_argument("--height-mm", type=_positive, default=5.0)
    p.add_argument("--ends", choices=["glued", "slip", "springs"], default="glued",
                   help="glued plates (default), frictionless (slip) or a compliant glue "
                   "layer (springs: give --k-r and --k-theta)")
    p.add_argument("--volumetric", choices=["quadratic", "log"], default="quadratic")
    p.add_argument("--chunk-size", type=int, default=16,
                   help="samples per Parquet chunk and rank (default 16)")
    p.add_argument("--out", required=True, metavar="DIR", help="store directory")
    p.set_defaults(func=_cmd_sample)


def _cmd_sample(args) -> int:
    from mpi4py import MPI

    from brain_fe import sampling

    comm = MPI.COMM_WORLD
    try:
        spec = sampling.SampleSpec(
            n=args.n, seed=args.seed, design=args.design, mu_range=args.mu_range,
            alpha_range=args.alpha_range, nu0=args.nu0, tests=args.tests, model=args.model,
            radius_mm=args.radius_mm, height_mm=args.height_mm, refinement=args.refinement,
            ends=args.ends, volumetric=args.volumetric)
        summary = sampling.run_sampling(spec, args.out, comm=comm, chunk_size=args.chunk_size)
    except (ValueError, OSError):
        if comm.rank != 0:  # every rank raises the same error; rank 0 reports it once
            return 1
        raise
    if comm.rank == 0:
        lines = [f"{args.out}: {summary.line()}; computed {summary.computed} in this run"]
        lines += [f"  failed: sample {s} {t}: {r}" for s, t, r in summary.failures[:10]]
        if len(summary.failures) > 10:
            lines.append(f"  ... {len(summary.failures) - 10} more failed tests")
        _say(lines)
    return 0


def _add_train(sub):
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
    p.add_argument("--trials", type=int, default=10, help="GP search trials (default 10)")
    p.add_argument("--executions", type=int, default=2,
                   help="trainings per trial, different seeds (default 2)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_cmd_train)


def _cmd_train(args) -> int:
    import json

    from brain_fe.sampling import load_samples, read_manifest
    from surrogate.data import TEST_KEYS
    from surrogate.train import train_all

    if args.trials < 1 or args.executions < 1:
        raise CLIError("--trials and --executions must be at least 1")
    manifest = read_manifest(args.samples)
    stored = [t["name"] for t in manifest["spec"]["tests"]]
    tests = tuple(k for k in TEST_KEYS if k in stored)
    if not tests:
        raise CLIError(f"{args.samples}: the store has none of the tests {', '.join(TEST_KEYS)}")
    metrics = train_all(load_samples(args.samples), manifest, args.out, profile=args.profile,
                        trials=args.trials, executions=args.executions, seed=args.seed,
                        tests=tests, progress=True)
    lines = [f"{args.out}: surrogates trained ({args.profile} profile)"]
    for k in tests:
        m = metrics[k]
        lines.append(f"  {k}: test R^2 = {m['r2_mean']:.4f} +- {m['r2_std']:.4f} over "
                     f"{m['n_test_curves']} curves; {json.dumps(m['hyperparameters'])}")
    _say(lines)
    return 0


def _add_identify(sub):
    p = sub.add_parser(
        "identify", help="two-stage identification of (mu, alpha): surrogate, then FE",
        description="For every specimen (or region-averaged curve) of the recordings: "
        "stage 1 minimises the normalised stress error (Gavrus) on the surrogates, stage 2 "
        "restarts from that optimum with the FE model and its exact sensitivities "
        "(trust-region least squares). Writes DIR/parameters.csv, DIR/history.csv and "
        "DIR/figures/.")
    p.add_argument("--recordings", required=True, metavar="FILE", help="CSV or Parquet")
    p.add_argument("--specimens", required=True, metavar="FILE", help="CSV or Parquet")
    p.add_argument("--surrogates", required=True, metavar="MODEL_DIR")
    p.add_argument("--fit", choices=["compression_tension", "all", "both"], default="all",
                   help="tests used: compression/tension only, all tests, or both fits")
    p.add_argument("--refinement", type=int, default=None, help="FE mesh level (default: "
                   "the <= 1 %% error level)")
    p.add_argument("--strict-surrogates", action="store_true",
                   help="refuse surrogates trained for another specimen geometry (default: "
                   "use them for the stage-1 start with a warning)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.set_defaults(func=_cmd_identify)


def _cmd_identify(args) -> int:
    from identification.batch import identify_all

    fits = ("compression_tension", "all") if args.fit == "both" else (args.fit,)
    table = identify_all(args.recordings, args.specimens, args.surrogates, args.out,
                         fits=fits, refinement=args.refinement,
                         surrogate_mismatch="error" if args.strict_surrogates else "warn",
                         progress=True)
    first = "region" if "region" in table and "specimen" not in table else "specimen"
    lines = [f"{args.out}/parameters.csv: {len(table)} fits"]
    for r in table.itertuples(index=False):
        d = r._asdict()
        lines.append(f"  {d[first]} [{d['fit']}]: mu = {d['mu_kPa']:.4g} +- "
                     f"{d['mu_se_kPa']:.2g} kPa, alpha = {d['alpha']:.4g} +- "
                     f"{d['alpha_se']:.2g}, objective {d['objective']:.3g}, "
                     f"{d['fe_solves']} FE solves")
    _say(lines)
    return 0


def _add_brain_bank(sub):
    p = sub.add_parser(
        "make-brain-bank", help="generate the synthetic virtual brain bank (FE recordings)",
        description="Synthetic data made by the project's own FE model: 8 regions, several "
        "brains, specimen geometry around R = 4 mm, H = 5 mm, compression/tension and "
        "torsion (0.15, 0.30) recordings with noise, a composition table of 11 components "
        "with partial overlap, region-averaged curves, and truth.json (never read by the "
        "pipeline).")
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--brains", type=int, default=6)
    p.add_argument("--elisa-brains", type=int, default=4)
    p.add_argument("--refinement", type=int, default=None)
    p.add_argument("--out", required=True, metavar="DIR")
    p.set_defaults(func=_cmd_brain_bank)


def _cmd_brain_bank(args) -> int:
    from analysis.brain_bank import BankSpec, make_brain_bank

    if args.brains < 1 or not 0 <= args.elisa_brains <= args.brains:
        raise CLIError("need --brains >= 1 and 0 <= --elisa-brains <= --brains")
    s = make_brain_bank(args.out, BankSpec(seed=args.seed, n_brains=args.brains,
                                           elisa_brains=args.elisa_brains,
                                           refinement=args.refinement), progress=True)
    _say([f"{args.out}: synthetic brain bank {s['counts']}"])
    return 0


def _add_reproduce(sub):
    p = sub.add_parser(
        "reproduce", help="the whole study on the embedded synthetic brain bank",
        description="sample -> train -> identify (both fit sets) -> correlate -> report, on "
        "data/brain_bank. A re-run reuses finished stages. Writes OUT/report.md and "
        "OUT/summary.json.")
    p.add_argument("--profile", choices=["quick", "default", "paper"], default="quick")
    p.add_argument("--out", default="results/reproduce", metavar="DIR")
    p.set_defaults(func=_cmd_reproduce)


def _cmd_reproduce(args) -> int:
    from analysis.reproduce import reproduce, summary_lines

    _say(summary_lines(reproduce(args.out, args.profile), args.out))
    return 0


def _add_diagnose(sub):
    p = sub.add_parser(
        "diagnose", help="locate the mismatch, name the missing physics, model it",
        description="Fit the base model, locate where the misfit is systematic, fit every "
        "candidate physics extension (FE in the loop), rank them by BIC and likelihood-ratio "
        "tests and refit with the winner. Writes DIR/diagnosis.json, DIR/report.md and "
        "figures. Run under `mpirun -n K` to share the candidate fits among K ranks. "
        "With --budday the homogeneous analytical model is the base and the averaged "
        "human-brain curves of Budday et al. (2017) are diagnosed region by region.")
    p.add_argument("--recordings", default=None, help="recordings table (CSV or Parquet)")
    p.add_argument("--specimens", default=None, help="specimens table (CSV or Parquet)")
    p.add_argument("--specimen", default=None, help="diagnose only this specimen")
    p.add_argument("--base", choices=["one-term-ogden", "homogeneous-ogden"],
                   default="one-term-ogden")
    p.add_argument("--budday", nargs="?", const="", default=None, metavar="CSV",
                   help="diagnose the Budday 2017 averaged curves (default path: "
                   "../shared/data/budday2017/budday2017_averaged.csv)")
    p.add_argument("--effects", default=None,
                   help="comma list of candidate effects (default: all the base can express)")
    p.add_argument("--refinement", type=int, default=1,
                   help="working mesh level; k+1 corrects its discretisation error")
    p.add_argument("--nu0", type=float, default=0.49, help="assumed initial Poisson ratio")
    p.add_argument("--out", required=True, help="output directory")
    p.set_defaults(func=_cmd_diagnose)


def _cmd_diagnose(args) -> int:
    from diagnosis import api

    effects = [e.strip() for e in args.effects.split(",")] if args.effects else None
    if args.budday is not None or args.base == "homogeneous-ogden":
        if args.recordings:
            raise CLIError("the homogeneous base model reads --budday data, not --recordings")
        res = api.diagnose_budday(args.budday or None, args.out, nu0=args.nu0)
        _say([f"{r}: verdict {v['verdict']}, RMS/noise {v['rms_before']:.2f} -> "
              f"{v['rms_after']:.2f}" for r, v in res.items()] + [f"wrote {args.out}"])
        return 0
    if not args.recordings or not args.specimens:
        raise CLIError("give --recordings and --specimens (or --budday)")
    res = api.diagnose_recordings(args.recordings, args.specimens, args.out,
                                  specimen=args.specimen, refinement=args.refinement,
                                  effects=effects, nu0=args.nu0, progress=True)
    from mpi4py import MPI

    if MPI.COMM_WORLD.rank == 0:
        _say([f"{n}: verdict {r['verdict']}, RMS/noise {r['rms_before']:.2f} -> "
              f"{r['rms_after']:.2f}" for n, r in res.items()] + [f"wrote {args.out}"])
    return 0


def _add_benchmark_diagnosis(sub):
    p = sub.add_parser(
        "benchmark-diagnosis", help="blind benchmark of the diagnosis on synthetic specimens",
        description="Generate N synthetic specimens (full protocol, 2 cycles, 1 %% noise, a "
        "finer mesh than the diagnosis), each with one concealed effect or none (controls, "
        ">= 20 %%), store the labels apart, diagnose blind and score: confusion matrix, "
        "accuracy, false alarms, RMS after modelling, parameter recovery. Cases are shared "
        "among MPI ranks (mpirun -n K).")
    p.add_argument("--cases", type=int, default=None, help="number of cases (required "
                   "unless --rescore)")
    p.add_argument("--rescore", action="store_true",
                   help="score the finished benchmark in --out again (no new runs)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--refinement", type=int, default=1)
    p.add_argument("--truth-refinement", type=int, default=3)
    p.add_argument("--effects", default=None, help="comma list (default: all)")
    p.add_argument("--cycles", type=int, default=2)
    p.add_argument("--increment", type=float, default=0.03,
                   help="stretch increment between recorded points (default 0.03)")
    p.add_argument("--out", required=True)
    p.set_defaults(func=_cmd_benchmark_diagnosis)


def _cmd_benchmark_diagnosis(args) -> int:
    from mpi4py import MPI

    from diagnosis.benchmark import rescore, run_benchmark

    if args.rescore:
        s = rescore(args.out)
        _say([f"cases {s['cases']}, accuracy {s['accuracy']:.3f}, false alarms "
              f"{s['false_alarms_on_controls']}/{s['controls']}", f"wrote {args.out}"])
        return 0
    if args.cases is None or args.cases < 1:
        raise CLIError("--cases must be >= 1")
    effects = [e.strip() for e in args.effects.split(",")] if args.effects else None
    s = run_benchmark(args.cases, args.seed, args.out, refinement=args.refinement,
                      truth_refinement=args.truth_refinement,
                      correction_refinement=args.refinement + 1, effects=effects,
                      cycles=args.cycles, increment=args.increment, progress=True)
    if MPI.COMM_WORLD.rank == 0:
        _say([f"cases {s['cases']}, accuracy {s['accuracy']:.3f}, false alarms "
              f"{s['false_alarms_on_controls']}/{s['controls']}, median RMS after/noise "
              f"{s['rms_after_over_noise_median']:.2f}", f"wrote {args.out}"])
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="brainmech",
        description="Brain-tissue mechanics: FE model of glued cylinders, surrogates, "
        "identification and composition analysis.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_simulate(sub)
    _add_sample(sub)
    _add_train(sub)
    _add_identify(sub)
    _add_brain_bank(sub)
    _add_reproduce(sub)
    _add_diagnose(sub)
    _add_benchmark_diagnosis(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    from brain_fe.logs import configure_logging

    configure_logging(logging.DEBUG if args.verbose else logging.INFO)
    from brain_fe.solver import ConvergenceError

    try:
        return args.func(args)
    except (CLIError, ValueError, ConvergenceError, FileNotFoundError, OSError) as exc:
        print(f"brainmech {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("brainmech: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
