"""``brainmech``: parse the command line, run one subcommand, report errors in one line."""

from __future__ import annotations

import argparse
import logging
import sys
import traceback
from importlib.metadata import PackageNotFoundError, version

from .commands import COMMANDS
from .errors import CLIError, abort_other_ranks, one_line

log = logging.getLogger("brainmech")


def _version() -> str:
    try:
        return version("brainmech")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "unknown"


class Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors (exit code 2): ``brainmech simulate: error:
    argument --mu: expected a finite number, got 'nan'``; ``--help`` prints the usage."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="brainmech",
        description="Brain-tissue mechanics: FE model of glued cylinders, surrogates, "
        "identification, composition analysis and missing-physics diagnosis.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for cmd in COMMANDS:
        cmd.add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    from brain_fe.logs import configure_logging
    from brain_fe.solver import ConvergenceError

    configure_logging(logging.DEBUG if args.verbose else logging.INFO)
    try:
        return args.run(args)
    except (CLIError, ValueError, ConvergenceError, OSError) as exc:
        print(f"brainmech {args.command}: error: {one_line(exc)}", file=sys.stderr)
        if isinstance(exc, (ConvergenceError, OSError)):
            abort_other_ranks(1)
        return 1
    except KeyboardInterrupt:
        print("brainmech: interrupted", file=sys.stderr)
        return 130
    except Exception:  # an internal error: its traceback, and under mpirun the whole run
        # ends (the other ranks would wait for this one at their next collective call; an
        # MPI rank of the open benchmark did, spinning, for the rest of a 2-hour run)
        traceback.print_exc()
        abort_other_ranks(1)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
