"""The FE model of one specimen as a simulator of its observation table.

Two ways to follow the recordings:

* ``path="recorded"``: the model follows each curve's recorded (time, control) path
  through every recorded point, so history-dependent physics (viscoelasticity, softening)
  is represented exactly;
* ``path="branches"``: for elastic models (glue springs and the measurement artefacts
  included), whose response depends on the control value and not on the path: the
  branches from the neutral value to the extremes the curve reaches (1 -> min, 1 -> max;
  0 -> max) are solved at fine increments (0.015; A/10 in torsion) and a cubic spline
  through them is evaluated at the recorded points, loading, unloading and every cycle
  alike (spline error below 1e-5 of the stress, tested).  Each ramp is solved once instead
  of at every passage: 2x cheaper for one cycle, 4x for two;
  With plates that lift off (``ends="unglued"``) the response has a kink where the plate
  meets the specimen (zero force above it), inside the recorded range when the contact
  point is shifted (``stretch_offset`` > 0) or the curve reaches tension: the kink is
  then solved as a point of the branch and the spline is split there, and the spline of
  d/d stretch_offset leaves the kink out (the central differences straddle it there);
  one spline across it was 0.8 % of the peak stress off at the first point of a real
  20 % compression and stalled fits of the contact offset;
* ``path="auto"`` (default): branches for elastic models, the recorded path for history.

``correction`` (an array over the observations, default 0) is added to every prediction:
the diagnosis keeps there the discretisation error of this mesh, estimated against a finer
one (deferred correction).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from mpi4py import MPI
from scipy.interpolate import CubicSpline

from brain_fe import geometry as geo
from brain_fe.ends import resolve
from brain_fe.materials import MaterialModel
from brain_fe.model import ForwardModel
from brain_fe.parallel import balanced
from brain_fe.parameters import Param
from brain_fe.protocols import Protocol, plate_at_rest
from brain_fe.vocabulary import CHANNELS, COMPRESSION_TENSION, NEUTRAL
from recordings.observations import recorded_paths

from . import coordinates as co
from .base import Prediction

log = logging.getLogger(__name__)


class FESimulator:
    """Axisymmetric FE model of one specimen (radius, height [mm]) predicting ``obs``.

    ``ends``: ``glued``, ``slip`` or ``unglued`` (the top plate lifts off instead of
    pulling); the imperfect-gluing effect replaces the tangential condition by springs.

    ``geometry`` and ``models`` (a dict of compiled models by physics) may be shared by
    several simulators of the same specimen, which then compile their forms once."""

    kind = "fe"

    def __init__(self, obs: pd.DataFrame, radius_mm: float, height_mm: float, *,
                 refinement: int = 1, nu0: float = 0.49, path: str = "auto",
                 ends: str = "glued", comm=MPI.COMM_SELF,
                 geometry: geo.Geometry | None = None, models: dict | None = None):
        if path not in ("recorded", "branches", "auto"):
            raise ValueError(f"path must be 'recorded', 'branches' or 'auto', got {path!r}")
        self.obs = obs.reset_index(drop=True)
        self.nu0, self.refinement, self.path, self.ends = nu0, refinement, path, ends
        self.geometry = geometry or geo.make("axisymmetric", radius_mm, height_mm,
                                             refinement, comm=comm)
        self.refinement = self.geometry.refinement
        self._models = {} if models is None else models  # shared by simulators of one mesh
        self.curves = recorded_paths(self.obs)
        self.correction = np.zeros(len(self.obs))
        self.solves = 0  # protocol solves (one per curve and prediction)
        self.shared = None  # an MPI communicator whose ranks share the curves of a prediction
        # seconds of each curve's last shared solve, per way of following it (branches or
        # the recorded path); before the first, its number of recorded points
        self._cost = {}

    @contextlib.contextmanager
    def sharing(self, comm):
        """Within this block every prediction is computed by all ranks of ``comm`` together,
        each solving its share of the curves (every rank gets the whole result)."""
        self.shared = comm if comm is not None and comm.size > 1 else None
        try:
            yield self
        finally:
            self.shared = None

    def model(self, physics: co.Physics) -> ForwardModel:
        """The compiled model with ``physics`` (compiled once per kind, then reused)."""
        kind, lift_off = resolve(self.ends)
        ends = "springs" if physics.springs else kind
        key = (physics, ends, lift_off)
        if key not in self._models:
            material = MaterialModel.build(physics.n_terms, maxwell=physics.maxwell,
                                           softening=physics.softening, laws=physics.laws)
            self._models[key] = ForwardModel(self.geometry, material, ends=ends,
                                             lift_off=lift_off)
        return self._models[key]

    def predict(self, values: Mapping[Param, float],
                wrt: Sequence[Param] = ()) -> Prediction:
        values = {Param.parse(k): v for k, v in values.items()}
        wrt = tuple(Param.parse(q) for q in wrt)
        point = co.model_point(values, self.nu0)
        fm = self.model(point.physics)
        needed = co.directions(values, point, wrt)
        y = np.zeros(len(self.obs))
        J = np.zeros((len(self.obs), len(wrt)))
        branches = self.path == "branches" or (self.path == "auto" and fm.state is None)
        c = self.shared
        seconds = np.zeros(len(self.curves))
        try:
            self._solve_curves(fm, point, needed, branches, c, y, J, seconds)
        except Exception as exc:  # noqa: BLE001 - every rank must learn of it
            if c is None:
                raise
            failure = exc
        else:
            failure = None
        if c is not None:  # each row was computed by one rank: the sum is exact
            # a curve that failed on one rank fails the prediction on every rank (the
            # others would otherwise wait for it in the sum below, for ever)
            failures = [f for f in c.allgather(failure) if f is not None]
            if failures:
                raise failures[0]
            y, J = c.allreduce(y), c.allreduce(J)
            # each curve timed on the rank that solved it, 0 on the others: the sum is
            # exact, so every rank holds the same costs and shares the next one alike
            self._cost[branches] = c.allreduce(seconds)
        return Prediction(y + self.correction, J, wrt)

    def contact_events(self, values: Mapping[Param, float]) -> dict[str, list]:
        """Per curve, the lift-off and re-contact events (:class:`~brain_fe.contact.
        ContactEvent`) of the model at ``values`` along the recorded path; {} when the
        plates can pull."""
        point = co.model_point({Param.parse(k): v for k, v in values.items()}, self.nu0)
        fm = self.model(point.physics)
        if fm.lift_off is None:
            return {}
        return {curve: fm.solve(path, point.material, interface=point.interface,
                                artefacts=point.artefacts).contact_events
                for curve, path, _ in self.curves}

    def share_of(self, branches: bool, comm) -> list[int]:
        """The curves this rank of ``comm`` solves: the costliest first, each to the rank
        with the least work so far (by the seconds of the last shared solve; the default
        protocol's compression/tension costs about as much as its two torsions together,
        so it goes alone to one rank and the torsions to the other)."""
        if comm is None:
            return list(range(len(self.curves)))
        cost = self._cost.get(branches)
        if cost is None or len(cost) != len(self.curves) or not (cost > 0).all():
            cost = [float(len(path.points)) for _, path, _ in self.curves]
        return balanced(list(cost), comm.size)[comm.rank]

    def _solve_curves(self, fm, point, needed, branches, c, y, J, seconds) -> None:
        """Fill ``y`` and ``J`` with the rows of this rank's share of the curves, and
        ``seconds`` with the time each of them took."""
        for i in self.share_of(branches, c):
            _curve, path, rows = self.curves[i]
            t0 = time.perf_counter()
            if branches:
                vals, ders = self._branches(fm, point, path, rows, needed)
            else:
                resp = fm.solve(path, point.material, interface=point.interface,
                                artefacts=point.artefacts, sensitivities=needed or False)
                vals = {ch: resp.values[CHANNELS[ch].column][idx]
                        for ch, (_, idx) in rows.items()}
                ders = {ch: [resp.jacobian[_key(d)][CHANNELS[ch].column][idx] for d in needed]
                        for ch, (_, idx) in rows.items()}
            self.solves += 1
            for ch, (obs_rows, _) in rows.items():
                y[obs_rows] = vals[ch]
                for j, d in enumerate(ders[ch]):
                    J[obs_rows, j] = d
            seconds[i] = time.perf_counter() - t0

    def _branches(self, fm, point, path, rows, needed):
        """Channels (and sensitivities) at the recorded controls by splines through the
        branches of an elastic model from the neutral value to the extremes reached."""
        if fm.state is not None:
            raise ValueError("the branch shortcut is for elastic models (no history)")
        at = np.array([s.value for s in path.points])
        neutral = NEUTRAL[path.test]
        ends = [e for e in (float(at.min()), float(at.max())) if not np.isclose(e, neutral)]
        step = 0.015 if path.test == COMPRESSION_TENSION else \
            max(abs(e - neutral) for e in ends) / 10
        kink = _contact_kink(fm, point, path.test)
        inside = kink is not None and float(at.min()) < kink < float(at.max())
        prots = [Protocol(path.test, (neutral, kink, e) if inside
                          and min(neutral, e) < kink < max(neutral, e) else (neutral, e),
                          max_increment=step) for e in ends]
        resps = [fm.solve(p, point.material, interface=point.interface,
                          artefacts=point.artefacts, sensitivities=needed or False)
                 for p in prots]
        x = np.concatenate([r.control for r in resps])
        order = np.argsort(x)
        x, keep = np.unique(x[order], return_index=True)
        # one spline on each side of the kink (both hold the kink itself)
        pieces = [(x <= kink, at <= kink), (x >= kink, at > kink)] if inside \
            else [(np.ones(x.size, bool), np.ones(at.size, bool))]
        # at the kink, d/d stretch_offset jumps (central differences give the mean of the
        # two sides): its splines leave that point out
        at_kink = np.isclose(x, kink, rtol=0.0, atol=1e-12) if kink is not None \
            else np.zeros(x.size, bool)

        def spline(parts, one_sided=False):
            v = np.concatenate(parts)[order][keep]
            out = np.empty(at.size)
            for on_x, on_at in pieces:
                if not on_at.any():
                    continue
                use = on_x & ~at_kink if one_sided else on_x
                use = use if use.sum() >= 2 else on_x
                out[on_at] = CubicSpline(x[use], v[use])(at[on_at])
            return out

        vals, ders = {}, {}
        for ch, (_, idx) in rows.items():
            col = CHANNELS[ch].column
            vals[ch] = spline([r.values[col] for r in resps])[idx]
            ders[ch] = [spline([r.jacobian[_key(d)][col] for r in resps],
                               one_sided=str(_key(d)) == "stretch_offset")[idx]
                        for d in needed]
        return vals, ders


KINK_SNAP = 2e-5  # a kink this close to the neutral value is put on it (a solved point)


def _contact_kink(fm, point, test: str) -> float | None:
    """The control value at which the top plate of a lift-off model meets the elastic
    specimen (true stretch 1, i.e. recorded 1 - stretch_offset); None without lift-off or
    in torsion."""
    if fm.lift_off is None or test != COMPRESSION_TENSION:
        return None
    kink = plate_at_rest(test, point.artefacts.stretch_offset)
    return NEUTRAL[test] if abs(kink - NEUTRAL[test]) < KINK_SNAP else kink


def _key(d):
    """The response's key of a requested sensitivity (artefacts by name, as Params)."""
    return Param.parse(d) if isinstance(d, str) else d
