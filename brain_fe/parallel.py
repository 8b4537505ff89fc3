"""The one progress-and-MPI helper: progress bars on rank 0 and work shared among ranks.

* :class:`Progress`: a tqdm bar on rank 0 of ``comm`` (silent on the other ranks, when
  disabled, and when stderr is not a terminal), used as a context manager.
* :class:`SharedCounter`: int64 counters in rank 0's MPI window, updated with atomic
  ``Fetch_and_op``; :func:`dynamic_items` hands out the items of a list one at a time to
  whichever rank asks next (dynamic load balancing without a master rank), so one command
  scales from a laptop to a cluster under ``mpirun``/``srun``.
* :func:`balanced`: a static share of items of known costs (longest first, each to the
  least loaded rank), the same on every rank that holds the same costs.
* :func:`rank0_first`: build something on rank 0 first (it fills the on-disk JIT cache),
  then on the other ranks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np


class Progress:
    """A progress bar on rank 0; ``update(n, note)`` advances it and shows ``note``."""

    def __init__(self, total: int | None = None, desc: str = "", unit: str = "it", *,
                 enabled: bool = True, comm=None, initial: int = 0):
        rank = 0 if comm is None else comm.rank
        self.bar = None
        if enabled and rank == 0:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=None,
                            dynamic_ncols=True, leave=True)

    def update(self, n: int = 1, note: str | None = None) -> None:
        if self.bar is None:
            return
        if note is not None:
            self.bar.set_postfix_str(note)
        if n:
            self.bar.update(n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def as_progress(progress, total: int | None, desc: str, unit: str, comm=None):
    """``progress`` True -> a :class:`Progress` bar; a callable ``f(note)`` -> an adapter
    calling it per update; False/None -> a silent bar."""
    if callable(progress) and progress is not True:
        bar = Progress(enabled=False)
        bar.update = lambda n=1, note=None: progress(note or "")  # type: ignore[method-assign]
        return bar
    return Progress(total, desc, unit, enabled=bool(progress), comm=comm)


class SharedCounter:
    """``slots`` int64 counters in rank 0's MPI window (all ranks of ``comm`` take part)."""

    def __init__(self, comm, slots: int = 1):
        from mpi4py import MPI

        self.MPI = MPI
        self.comm = comm
        self.win = MPI.Win.Allocate(slots * 8 if comm.rank == 0 else 0, 8, comm=comm)
        if comm.rank == 0:
            np.frombuffer(self.win.tomemory(), dtype=np.int64)[:] = 0
        comm.Barrier()

    def add(self, slot: int = 0, value: int = 1) -> int:
        """Atomically add ``value``; returns the value before."""
        MPI = self.MPI
        one = np.array([value], dtype=np.int64)
        res = np.zeros(1, dtype=np.int64)
        self.win.Lock(0, MPI.LOCK_SHARED)
        self.win.Fetch_and_op([one, MPI.INT64_T], [res, MPI.INT64_T], 0, slot, MPI.SUM)
        self.win.Unlock(0)
        return int(res[0])

    def read(self, slot: int = 0) -> int:
        return self.add(slot, 0)

    def free(self) -> None:
        if self.win is not None:
            self.win.Free()
            self.win = None


def dynamic_items(items: Sequence, counter: SharedCounter, slot: int = 0) -> Iterator:
    """The items this rank takes from the shared ``counter``, one at a time."""
    while True:
        pos = counter.add(slot)
        if pos >= len(items):
            return
        yield items[pos]


def balanced(costs: Sequence[float], size: int) -> list[list[int]]:
    """The indices of the items each of ``size`` ranks takes: longest first, each to the
    rank with the least cost so far (ties: the lower rank), in index order per rank."""
    load = [0.0] * size
    share: list[list[int]] = [[] for _ in range(size)]
    for i in sorted(range(len(costs)), key=lambda i: (-costs[i], i)):
        r = min(range(size), key=lambda r: (load[r], r))
        load[r] += costs[i]
        share[r].append(i)
    return [sorted(s) for s in share]


def rank0_first(comm, build: Callable):
    """``build()`` on rank 0, then (after a barrier) on the other ranks."""
    out = build() if comm.rank == 0 else None
    comm.Barrier()
    return out if comm.rank == 0 else build()


def gather_all(comm, mine: list) -> list:
    """Every rank's list, concatenated in rank order, on every rank."""
    return [x for part in comm.allgather(mine) for x in part]
