"""``brainmech``: the command line. It only parses arguments and calls library code."""

from __future__ import annotations

import argparse
import logging
import sys
from importlib.metadata import PackageNotFoundError, version

log = logging.getLogger("brainmech")


class CLIError(Exception):
    """An error reported to the user as one line, without a traceback."""


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


def _add_simulate(sub):
    p = sub.add_parser(
        "simulate", help="run one test protocol on the FE model and write a CSV",
        description="Displacement-controlled compression/tension (1 -> 1-A -> 1 -> 1+A -> 1) "
        "or torsion (0 -> A -> 0, height fixed) of a glued cylinder with a compressible "
        "N-term Ogden material. Units: mm, kPa, mN, mN mm, s.")
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
    p.add_argument("--ends", choices=["glued", "slip"], default="glued")
    p.add_argument("--refinement", type=int, default=None,
                   help="mesh refinement level k (default: the level with <= 1 %% force "
                   "error, see BENCHMARKS.md)")
    p.add_argument("--rate", type=_positive, default=0.01,
                   help="rate of the controlled quantity, 1/s (default 0.01)")
    p.add_argument("--cycles", type=int, default=1)
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
                      rate_per_s=args.rate, cycles=args.cycles, field_output=args.fields,
                      progress=True)
    if args.out:
        api.write_csv_atomic(df, args.out)
        log.info("wrote %s (%d rows)", args.out, len(df))
    else:
        from mpi4py import MPI

        if MPI.COMM_WORLD.rank == 0:
            sys.stdout.write(df.to_csv(index=False, float_format="%.10g"))
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
