"""Displacement-controlled test protocols as piecewise-linear paths in time.

The controlled quantity is the stretch ``lambda = h / H`` (compression/tension) or the
amount of shear at the outer radius ``gamma = theta R / H`` (torsion, height held fixed).
A protocol is a list of waypoints traversed at a constant rate, repeated ``cycles`` times;
each straight segment is a *branch*: ``loading`` when it moves away from the neutral
value (1 or 0), ``unloading`` when it moves back.  An optional dwell of ``hold_s`` seconds
after every segment (branch ``hold``) gives relaxation tests for rate-dependent materials.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .vocabulary import (
    COMPRESSION_TENSION,
    CONTROL,
    DEFAULT_AMPLITUDE,
    HOLD,
    LOADING,
    NEUTRAL,
    TORSION,
    UNLOADING,
    check_test,
)


@dataclass(frozen=True)
class Step:
    """One output point of a protocol."""

    time_s: float
    cycle: int
    branch: str
    value: float


@dataclass(frozen=True)
class Protocol:
    """Piecewise-linear path of the controlled quantity.

    Parameters
    ----------
    test: ``compression_tension`` or ``torsion``.
    waypoints: values at the branch ends of one cycle, starting at the neutral value.
    rate_per_s: |d value / dt| (1/s), sets the time stamps (history-dependent physics).
    max_increment: largest change of the controlled quantity between output points.
    cycles: repetitions of the waypoint cycle.
    hold_s: dwell at the end of every segment [s] (0: none), output at ``hold_points``
        equally spaced times.
    """

    test: str
    waypoints: tuple[float, ...]
    rate_per_s: float = 0.01
    max_increment: float = 0.015
    cycles: int = 1
    hold_s: float = 0.0
    hold_points: int = 10

    def __post_init__(self):
        check_test(self.test)
        if len(self.waypoints) < 2:
            raise ValueError("a protocol needs at least two waypoints")
        if not all(math.isfinite(w) for w in self.waypoints):
            raise ValueError("protocol waypoints must be finite numbers")
        if not np.isclose(self.waypoints[0], NEUTRAL[self.test]):
            raise ValueError(f"{self.test} protocols start at {NEUTRAL[self.test]}")
        for name in ("rate_per_s", "max_increment", "hold_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be a finite number")
        if self.rate_per_s <= 0 or self.max_increment <= 0 or self.cycles < 1:
            raise ValueError("rate, increment and cycles must be positive")
        if self.hold_s < 0 or self.hold_points < 1:
            raise ValueError("hold_s must be >= 0 and hold_points >= 1")
        if self.test == COMPRESSION_TENSION and min(self.waypoints) <= 0.0:
            raise ValueError("stretch must stay positive")

    @property
    def control(self) -> str:
        return CONTROL[self.test]

    @property
    def amplitude(self) -> float:
        return float(max(abs(w - NEUTRAL[self.test]) for w in self.waypoints))

    def steps(self) -> list[Step]:
        """Output points, the initial state first."""
        neutral = NEUTRAL[self.test]
        out = [Step(0.0, 1, LOADING, float(self.waypoints[0]))]
        t = 0.0
        for cycle in range(1, self.cycles + 1):
            for a, b in zip(self.waypoints[:-1], self.waypoints[1:], strict=True):
                if np.isclose(a, b):
                    continue
                branch = LOADING if abs(b - neutral) > abs(a - neutral) else UNLOADING
                n = max(1, int(np.ceil(abs(b - a) / self.max_increment - 1e-9)))
                for i in range(1, n + 1):
                    v = a + (b - a) * i / n
                    out.append(Step(t + abs(v - a) / self.rate_per_s, cycle, branch, float(v)))
                t += abs(b - a) / self.rate_per_s
                if self.hold_s > 0:
                    for i in range(1, self.hold_points + 1):
                        out.append(Step(t + self.hold_s * i / self.hold_points, cycle, HOLD,
                                        float(b)))
                    t += self.hold_s
        return out


def plate_position(test: str, value: float, preload: float, height_mm: float,
                   radius_mm: float) -> tuple[float, float]:
    """(axial displacement [mm], rotation [rad]) of the top plate at ``value`` of the
    controlled quantity, on top of an axial ``preload`` stretch offset: the kinematics that
    define each test (torsion runs at the height (1 + preload) H)."""
    if test == COMPRESSION_TENSION:
        return (value + preload - 1.0) * height_mm, 0.0
    if test == TORSION:
        return preload * height_mm, value * height_mm / radius_mm
    raise ValueError(f"no plate motion defined for test {test!r}")


def plate_at_rest(test: str, preload: float) -> float:
    """The value of the controlled quantity at which the top plate stands at the unloaded
    specimen's height (:func:`plate_position`'s axial displacement zero): where a plate
    that can lift off meets the specimen in compression/tension."""
    if test != COMPRESSION_TENSION:
        raise ValueError(f"the plate of test {test!r} does not move axially with its control")
    return 1.0 - preload


def compression_tension(amplitude: float = 0.15, **kw) -> Protocol:
    """1 -> 1 - A -> 1 -> 1 + A -> 1."""
    if not (math.isfinite(amplitude) and 0 < amplitude < 1):
        raise ValueError(f"compression/tension amplitude must lie in (0, 1), got {amplitude}")
    return Protocol(COMPRESSION_TENSION, (1.0, 1.0 - amplitude, 1.0, 1.0 + amplitude, 1.0),
                    **kw)


def torsion(gamma_max: float = 0.30, **kw) -> Protocol:
    """0 -> gamma_max -> 0 at fixed height."""
    if not (math.isfinite(gamma_max) and 0 < gamma_max):
        raise ValueError(f"torsion amplitude must be positive, got {gamma_max}")
    kw.setdefault("max_increment", gamma_max / 10)
    return Protocol(TORSION, (0.0, gamma_max, 0.0), **kw)


def make(test: str, amplitude: float | None = None, **kw) -> Protocol:
    """The standard protocol of ``test`` (default amplitudes 0.15 and 0.30); ``kw`` as
    :class:`Protocol` (``rate_per_s``, ``cycles``, ``hold_s``, ``max_increment``)."""
    check_test(test)
    a = DEFAULT_AMPLITUDE[test] if amplitude is None else amplitude
    return (compression_tension if test == COMPRESSION_TENSION else torsion)(a, **kw)


def _turning_points(test: str, amplitude: float, t, x, rate: float
                    ) -> list[tuple[int, tuple[float, float]]]:
    """The protocol's turning points that the recorded samples straddle, as (position in
    the list of recorded points, (time, control value)): an instrument samples at its own
    clock, so the extreme of a ramp (where history-dependent models decide their damage
    and their relaxation turns) lies between two samples.  A turning point is inserted only
    where the path reverses within one sampling interval of the protocol's extreme
    (``1 +- A`` in compression/tension, ``A`` and ``0`` in torsion); its time follows from
    the rate."""
    if test == COMPRESSION_TENSION:
        high, low = 1.0 + amplitude, 1.0 - amplitude
    else:
        high, low = amplitude, 0.0
    out = []
    dx = np.diff(x)
    for i in range(1, len(x) - 1):
        before, after = dx[i - 1], dx[i]
        if before * after >= 0:
            continue
        ext = high if before > 0 else low
        gap = (ext - x[i]) * np.sign(before)  # how far the extreme lies beyond sample i
        reach = max(abs(before), abs(after))
        if not (1e-12 < gap <= reach * (1 + 1e-9)) or rate <= 0:
            continue
        t_turn = t[i - 1] + abs(ext - x[i - 1]) / rate
        if t_turn < t[i]:  # sample i was taken on the way back: the turn came before it
            out.append((i, (float(t_turn), float(ext))))
        else:
            t_turn = min(t[i] + gap / rate, t[i + 1])
            out.append((i + 1, (float(t_turn), float(ext))))
    return out


@dataclass
class RecordedPath:
    """The recorded (time, control) points of one test as a protocol for the forward model:
    the model follows the piecewise-linear path through them and reports at every one."""

    test: str
    amplitude: float
    points: list[Step]
    rate_per_s: float

    @property
    def control(self) -> str:
        return CONTROL[self.test]

    def steps(self) -> list[Step]:
        return self.points

    @classmethod
    def through(cls, test: str, amplitude: float, time_s, control, cycle, branch,
                default_rate: float = 0.01) -> tuple[RecordedPath, np.ndarray]:
        """Path through recorded points and, for each point, its step index.  A path that
        does not start at the neutral value starts from the undeformed state at the median
        recorded rate; without a clock (NaN times) the rate is ``default_rate``."""
        t = np.asarray(time_s, float)
        x = np.asarray(control, float)
        if np.isnan(t).any():  # no clock: assume the default rate
            t = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(x)))]) / default_rate
        steps = [Step(float(ti), int(c), str(b), float(xi))
                 for ti, c, b, xi in zip(t, cycle, branch, x, strict=True)]
        index = np.arange(len(steps))
        dt = np.diff(t)
        moving = (dt > 0) & (np.abs(np.diff(x)) > 0)
        rate = float(np.median(np.abs(np.diff(x))[moving] / dt[moving])) if moving.any() \
            else default_rate
        for pos, (t_turn, ext) in reversed(_turning_points(test, amplitude, t, x, rate)):
            prev = steps[pos - 1]  # the turning point ends the ramp it closes
            steps.insert(pos, Step(t_turn, prev.cycle, prev.branch, ext))
            index[index >= pos] += 1
        neutral = NEUTRAL[test]
        if not np.isclose(x[0], neutral):  # start from the undeformed state
            steps.insert(0, Step(float(t[0] - abs(x[0] - neutral) / rate), 1, LOADING,
                                 neutral))
            index = index + 1
        return cls(test, float(amplitude), steps, rate), index
