"""Logging set-up for the command line: rank 0 only by default, messages on stderr.

The other ranks' warnings and errors are said too where a rank works on its own
(:func:`rank_local`: a specimen of a batch, a case of a benchmark, an item of shared work),
marked with the rank; where all ranks do the same, rank 0 speaks for them.
"""

from __future__ import annotations

import contextlib
import logging
import sys

_LOCAL = [0]  # depth of rank_local blocks on this rank


@contextlib.contextmanager
def rank_local():
    """Within this block this rank works on its own: its warnings and errors reach the
    log from any rank (marked with the rank), not only from rank 0."""
    _LOCAL[0] += 1
    try:
        yield
    finally:
        _LOCAL[0] -= 1


class RankFilter(logging.Filter):
    """Everything from MPI rank 0; from the other ranks the warnings and errors made in a
    :func:`rank_local` block, marked with the rank (a candidate that failed on rank 1, or
    a specimen of a batch diagnosed there, is said, not dropped)."""

    def __init__(self, rank: int):
        super().__init__()
        self.rank = rank

    def filter(self, record: logging.LogRecord) -> bool:
        if self.rank == 0:
            return True
        if record.levelno < logging.WARNING or not _LOCAL[0]:
            return False
        record.msg = f"[rank {self.rank}] {record.msg}"
        return True


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
