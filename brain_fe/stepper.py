"""Follow a protocol's path step by step: Newton per step, linear extrapolation along the
path as predictor, and automatic load-step cut-back (halving) on failure.

The path is the sequence of (time, control value, preload) targets of the protocol's output
points; a preload (contact-point stretch offset) is applied first as its own segment, ending
when the protocol starts.  ``on_converged(step)`` is called after every converged (sub)step,
with the protocol's :class:`~brain_fe.protocols.Step` at output points and None at the
intermediate points of a cut-back.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .solver import ConvergenceError, ghost_forward

log = logging.getLogger(__name__)


@dataclass
class StepperLog:
    """Counters of one protocol: Newton iterations, cut-backs and per (sub)step the control
    value and the residual history."""

    iterations: int = 0
    cutbacks: int = 0
    newton: list[tuple[float, list[float]]] = field(default_factory=list)


def follow(protocol, steps, *, x, newton, set_control: Callable, set_dt: Callable,
           on_converged: Callable, describe: Callable[[], str], preload: float = 0.0,
           max_cutbacks: int = 6, callback: Callable[[int, int], None] | None = None
           ) -> StepperLog:
    """Solve along ``steps`` from the state in ``x`` (the undeformed state on entry).

    ``set_control(q, p)`` moves the plates to control value q on top of the preload p;
    ``set_dt(dt)`` sets the time increment of the (sub)step; ``describe()`` names the
    parameters in the error raised when Newton still fails after ``max_cutbacks`` halvings.
    """
    rec = StepperLog()
    prev, saved = x.duplicate(), x.duplicate()
    x.copy(prev)
    t_cur, q_cur, p_cur = steps[0].time_s, steps[0].value, 0.0
    q_prev = q_cur
    targets = [(t_cur, q_cur, preload, 0)]
    if preload:
        t_cur -= abs(preload) / protocol.rate_per_s  # the preload ends when the protocol starts
    else:
        set_control(q_cur, 0.0)
        # the initial state's tangent (its sensitivities, and the first step's Newton
        # reuses its factorisation) holds the time increment of a history model: the first
        # step's, not the last one of whatever run came before on this model (a prediction
        # then depended on the curves solved before it, by 4e-10 relative in viscoelastic
        # sensitivities, and the ranks sharing a diagnosis disagreed from run to run)
        set_dt(max(steps[1].time_s - steps[0].time_s, 1e-12) if len(steps) > 1 else 1.0)
        on_converged(steps[0])
        targets = []
    targets += [(s.time_s, s.value, preload, k) for k, s in enumerate(steps) if k > 0]
    for t_tg, q_tg, p_tg, k in targets:
        if not all(np.isfinite((t_tg, q_tg, p_tg))):
            raise ValueError(f"{protocol.test}: step {k} of the protocol is not a finite "
                             f"(time, {protocol.control}) point: ({t_tg}, {q_tg})")
        step = steps[k]
        while not (abs(q_cur - q_tg) <= 1e-14 and abs(p_cur - p_tg) <= 1e-14
                   and abs(t_cur - t_tg) <= 1e-9):
            frac = 1.0
            for _ in range(max_cutbacks + 1):
                t_new = t_cur + frac * (t_tg - t_cur)
                q_new = q_cur + frac * (q_tg - q_cur)
                p_new = p_cur + frac * (p_tg - p_cur)
                x.copy(saved)
                dq = q_new - q_cur
                if dq and q_cur != q_prev:  # linear extrapolation along the path
                    x.axpy(dq / (q_cur - q_prev), saved)
                    x.axpy(-dq / (q_cur - q_prev), prev)
                    ghost_forward(x)
                set_dt(max(t_new - t_cur, 1e-12))
                set_control(q_new, p_new)
                rep = newton.solve()
                rec.iterations += rep.iterations
                rec.newton.append((q_new, rep.residuals))
                if rep.converged:
                    break
                log.info("Newton failed at %s = %.5g (%s); cutting the step back",
                         protocol.control, q_new, rep.reason)
                saved.copy(x)
                ghost_forward(x)
                frac /= 2
                rec.cutbacks += 1
            else:
                raise ConvergenceError(
                    f"{protocol.test}: Newton failed at {protocol.control} = {q_new:.5g} "
                    f"after {max_cutbacks} step cut-backs ({rep.reason}); parameters "
                    f"{describe()}")
            if dq:
                saved.copy(prev)
                q_prev = q_cur
            t_cur, q_cur, p_cur = t_new, q_new, p_new
            on_converged(step if frac == 1.0 else None)
        if callback:
            callback(k + 1, len(steps))
    return rec
