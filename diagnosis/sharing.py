"""How the ranks of an MPI communicator share the work of one diagnosis.

Two ways: independent items (candidates' fits, design points, groups of detection limits)
handed out one at a time to whichever rank is free (:func:`share_with`), and the curves of
one simulator's predictions split among the ranks (:func:`sharing`).  Every rank ends with
every result, so the diagnosis is the same on any number of ranks.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass

from brain_fe.logs import rank_local
from brain_fe.parallel import SharedCounter, dynamic_items

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Internal:
    """An item of shared work that failed for a reason other than the model (picklable)."""

    why: str


def share_with(comm, sim=None, errors: list | None = None):
    """The function ``share(items, work, cost)`` that works on items among the ranks of
    ``comm`` (None: this process alone); ``sim``: the simulator whose curves all ranks
    share when a single item is left; ``errors``: where internal errors are recorded."""
    def attempt(work, item):
        try:
            return work(item)
        except Exception as exc:  # noqa: BLE001 - the work catches the model's failures
            log.error("internal error, an item of the diagnosis left out: %s: %s",
                      type(exc).__name__, exc)
            return Internal(f"{type(exc).__name__}: {exc}")

    def share(items, work, cost):
        """``work`` on the ``items``, most expensive first (by the estimated ``cost``),
        each taken by whichever rank of ``comm`` is free; every rank gets every result,
        in the order of ``items``.  A lone item (a round with one candidate left) is
        worked on by all ranks together, each solving its share of ``sim``'s curves
        (every solve starts afresh, so the result is the same as on one rank).  An item
        whose work raises (an internal error: ``work`` catches the model's own failures)
        gives None, and ``errors`` gets why, on every rank alike."""
        order = sorted(range(len(items)), key=lambda i: -cost(items[i]))
        if comm is None or comm.size == 1:
            done = [(i, attempt(work, items[i])) for i in order]
        elif len(items) == 1:
            with sharing(sim, comm):
                done = [(0, attempt(work, items[0]))]
        else:
            counter = SharedCounter(comm)
            with rank_local():  # this rank's own items: its warnings are said
                done = [(i, attempt(work, items[i])) for i in dynamic_items(order, counter)]
            counter.free()
            done = [x for part in comm.allgather(done) for x in part]
        out = [r for _, r in sorted(done, key=lambda x: x[0])]
        if errors is not None:
            errors.extend(dict.fromkeys(r.why for r in out if isinstance(r, Internal)
                                        and r.why not in errors))
        return [None if isinstance(r, Internal) else r for r in out]
    return share


@contextlib.contextmanager
def sharing(sim, comm):
    """Let the ranks of ``comm`` share the curves of ``sim``'s predictions, where the
    simulator can (the FE model); otherwise every rank computes everything."""
    if sim is None or not hasattr(sim, "sharing"):
        yield sim
        return
    with sim.sharing(comm):
        yield sim
