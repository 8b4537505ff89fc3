"""The error the command line reports as one line, without a traceback."""

import sys


class CLIError(Exception):
    """A usage error found by the command line itself (not by the library)."""


def one_line(exc: BaseException) -> str:
    """An error's message on one line (its type's name where it has none)."""
    return " ".join(str(exc).splitlines()) or type(exc).__name__


def abort_other_ranks(code: int) -> None:
    """Under ``mpirun``, a failure of one rank's own work (a solve, a file) ends the whole
    run: the other ranks would otherwise wait for it forever.  Errors in the inputs are
    found by every rank alike and end each of them cleanly, without this."""
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is not None and mpi.Is_initialized() and not mpi.Is_finalized() \
            and mpi.COMM_WORLD.size > 1:
        sys.stderr.flush()
        mpi.COMM_WORLD.Abort(code)


def say(lines: list[str]) -> None:
    """A command's result summary on stdout (the only place the tool writes to stdout)."""
    sys.stdout.write("\n".join(lines) + "\n")
