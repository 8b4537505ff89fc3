"""Plates that cannot pull: lift-off and re-contact of the top plate (``lift_off=True``,
``ends="unglued"``).

A specimen resting between rough (sandblasted) plates without glue is held tangentially
while the plate presses on it, but the plate cannot pull.  Where the state with the top
plate on the specimen would pull on the plate (a tensile axial force), the plate leaves the
specimen: the axial force is zero and the specimen's top face sits at the axial position
``w`` where the force vanishes, below the plate, while its history (viscoelastic recovery)
goes on.  When the plate comes back down to ``w`` it touches the specimen again
(re-contact) and pushes it as before.

Simplifications, stated: off the plate the top face stays flat, radially held where it was
held and twisted with the plate (a free face would bulge slightly; a test with no twist has
none to keep); contact is all or nothing over the face (no partial lift-off from the rim);
no adhesion (a real specimen may pull the plate a little before it lets go).

:class:`LiftOff` wraps Newton's method with the same ``solve()`` interface, so that the
protocol stepper (:mod:`brain_fe.stepper`) and its cut-back need nothing else: each solve
finds the contact state and, off the plate, ``w`` by a safeguarded secant iteration on the
axial force (each evaluation a Newton solve, starting from the last one).  Its state is
committed only at converged (sub)steps (:meth:`LiftOff.commit`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from .solver import NewtonReport

log = logging.getLogger(__name__)

FORCE_RTOL = 1e-7  # |axial force| off the plate, relative to the run's peak force so far
MAX_SECANT = 20


@dataclass
class ContactEvent:
    """A change of the contact state at a converged output point."""

    kind: str  # "lift-off" or "re-contact"
    time_s: float
    control: float  # the plate's control value (stretch) at the point
    gap_mm: float  # plate position above the specimen's top face at the point (0: touching)
    cycle: int = 1


class LiftOff:
    """Contact state of the top plate over one protocol, and the solve that keeps it.

    ``newton``: the model's :class:`~brain_fe.solver.NewtonSolver`; ``ends``: its
    :class:`~brain_fe.ends.EndConditions` (the top face's axial displacement is
    ``ends.c_axial``, ``ends.tension(fz)`` > 0 where the plate pulls); ``reactions()``: the
    model's (axial force, torque) at the current state; ``stiffness()``: a first guess of
    the axial stiffness [mN/mm] before one is measured in contact.
    """

    def __init__(self, newton, ends, reactions, stiffness):
        self.newton, self.ends = newton, ends
        self._reactions, self._stiffness = reactions, stiffness
        self.reset()

    def reset(self) -> None:
        self.off = False  # committed state: the plate is off the specimen
        self.w = 0.0  # committed axial displacement of the specimen's top face [mm]
        self.peak = 0.0  # largest |axial force| at a converged state of the run [mN]
        self.slope = None  # last d(tension)/d(top displacement) in contact [mN/mm]
        self.events: list[ContactEvent] = []
        self._trial = (False, 0.0, 0.0)  # (off, w, plate) of the last solve
        self._force_committed = None  # axial force of the last committed state [mN]
        self._drift = 0.0  # change of w over the last committed step off the plate

    # ------------------------------------------------------------------ state
    @property
    def trial_off(self) -> bool:
        """Whether the state just solved has the plate off the specimen."""
        return self._trial[0]

    def commit(self, time_s: float | None = None, control: float | None = None,
               cycle: int = 1) -> None:
        """The last solve converged and is kept: take its contact state (an event at an
        output point when the state changed)."""
        off, w, plate = self._trial
        force = self._force()
        before = self._force_committed is not None  # (self.off, self.w): the last state
        if before and not off and not self.off and w != self.w:
            slope = self.ends.tension(force - self._force_committed) / (w - self.w)
            self.slope = slope if slope > 0 else self.slope
        self._drift = w - self.w if before and off and self.off else 0.0
        self._force_committed = force
        self.peak = max(self.peak, abs(force))
        if off != self.off and time_s is not None:
            kind = "lift-off" if off else "re-contact"
            self.events.append(ContactEvent(kind, float(time_s), float(control),
                                            float(plate - w), int(cycle)))
            log.debug("%s at t = %.4g s, control %.5g", kind, time_s, control)
        self.off, self.w = off, w

    def _force(self) -> float:
        return self._reactions()[0]

    # ------------------------------------------------------------------ solve
    def solve(self) -> NewtonReport:
        """Newton at the plate position set by the stepper, with the plate lifted off
        where it would pull.  Returns the last Newton report, its iterations summed."""
        plate = float(self.ends.c_axial.value)
        total = NewtonReport(False, 0)
        if self.off and plate > self.w:  # still above the specimen's last top: off?
            rep, w = self._free(self.w + self._drift, total)
            if rep.converged and w < plate:
                self._trial = (True, w, plate)
                return rep
            if not rep.converged:
                return rep
        rep = self._at(plate, total)  # the plate on the specimen
        if not rep.converged:
            return rep
        if self._tension() <= self._tolerance():
            self._trial = (False, plate, plate)
            return rep
        rep, w = self._free(plate, total, rep)
        if rep.converged:
            self._trial = (True, min(w, plate), plate)
        return rep

    def _tension(self) -> float:
        return self.ends.tension(self._force())

    def _tolerance(self) -> float:
        return max(FORCE_RTOL * self.peak, 10 * self.newton.atol)

    def _at(self, w: float, total: NewtonReport) -> NewtonReport:
        self.ends.set_axial(w)
        rep = self.newton.solve()
        total.iterations += rep.iterations
        total.residuals += rep.residuals
        rep.iterations, rep.residuals = total.iterations, total.residuals
        return rep

    def _free(self, w0: float, total: NewtonReport, rep: NewtonReport | None = None):
        """The top displacement where the axial force vanishes, by secant steps kept
        inside the bracket found so far (bisection when a step leaves it), from ``w0``
        (solved here unless ``rep`` is the report of its current solve)."""
        rep = rep or self._at(w0, total)
        if not rep.converged:
            return rep, w0
        lo = hi = None  # top displacements with compressive / tensile force
        w, f = w0, self._tension()
        k = self.slope or self._stiffness()
        for _ in range(MAX_SECANT):
            if abs(f) <= self._tolerance():
                return rep, w
            if f > 0:
                hi = w if hi is None else min(hi, w)
            else:
                lo = w if lo is None else max(lo, w)
            w_new = w - f / k
            if lo is not None and hi is not None and not lo < w_new < hi:
                w_new = 0.5 * (lo + hi)
            rep = self._at(w_new, total)
            if not rep.converged:
                return rep, w
            f_new = self._tension()
            if w_new != w and (f_new - f) / (w_new - w) > 0:
                k = (f_new - f) / (w_new - w)
            w, f = w_new, f_new
        rep.converged = False
        rep.reason = (f"no force-free top position in {MAX_SECANT} secant steps "
                      f"(|force| {abs(f):.3e} mN)")
        return rep, w
