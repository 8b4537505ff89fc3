"""Logging set-up for the command line: rank 0 only by default, messages on stderr."""

from __future__ import annotations

import logging
import sys


class RankFilter(logging.Filter):
    """Let records through on MPI rank 0 only (records of other ranks are dropped)."""

    def __init__(self, rank: int):
        super().__init__()
        self.rank = rank

    def filter(self, record: logging.LogRecord) -> bool:
        return self.rank == 0


class QuietJIT(logging.Filter):
    """Drop the INFO chatter that cffi/setuptools send to the root logger (one line per
    compiler call during FFCx JIT compilation); everything else passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.name == "root" and record.levelno < logging.WARNING)


def configure_logging(level: int = logging.INFO, all_ranks: bool = False) -> None:
    from mpi4py import MPI

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    handler.addFilter(QuietJIT())
    if not all_ranks:
        handler.addFilter(RankFilter(MPI.COMM_WORLD.rank))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    # The JIT compilers log every compiler call at INFO; keep them quiet.
    for noisy in ("ffcx", "UFL", "ufl", "FFCx", "dolfinx"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
