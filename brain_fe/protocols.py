"""Displacement-controlled test protocols as piecewise-linear paths in time.

The controlled quantity is the stretch ``lambda = h / H`` (compression/tension) or the
amount of shear at the outer radius ``gamma = theta R / H`` (torsion, height held fixed).
A protocol is a list of waypoints traversed at a constant rate, repeated ``cycles`` times;
each straight segment is a *branch*: ``loading`` when it moves away from the neutral
value (1 or 0), ``unloading`` when it moves back.  An optional dwell of ``hold_s`` seconds
after every segment (branch ``hold``) gives relaxation tests for rate-dependent materials.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TESTS = ("compression_tension", "torsion")
NEUTRAL = {"compression_tension": 1.0, "torsion": 0.0}
CONTROL = {"compression_tension": "stretch", "torsion": "shear"}


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
        if self.test not in TESTS:
            raise ValueError(f"unknown test {self.test!r}; expected one of {', '.join(TESTS)}")
        if len(self.waypoints) < 2:
            raise ValueError("a protocol needs at least two waypoints")
        if not np.isclose(self.waypoints[0], NEUTRAL[self.test]):
            raise ValueError(f"{self.test} protocols start at {NEUTRAL[self.test]}")
        if self.rate_per_s <= 0 or self.max_increment <= 0 or self.cycles < 1:
            raise ValueError("rate, increment and cycles must be positive")
        if self.hold_s < 0 or self.hold_points < 1:
            raise ValueError("hold_s must be >= 0 and hold_points >= 1")
        if self.test == "compression_tension" and min(self.waypoints) <= 0.0:
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
        out = [Step(0.0, 1, "loading", float(self.waypoints[0]))]
        t = 0.0
        for cycle in range(1, self.cycles + 1):
            for a, b in zip(self.waypoints[:-1], self.waypoints[1:], strict=True):
                if np.isclose(a, b):
                    continue
                branch = "loading" if abs(b - neutral) > abs(a - neutral) else "unloading"
                n = max(1, int(np.ceil(abs(b - a) / self.max_increment - 1e-9)))
                for i in range(1, n + 1):
                    v = a + (b - a) * i / n
                    out.append(Step(t + abs(v - a) / self.rate_per_s, cycle, branch, float(v)))
                t += abs(b - a) / self.rate_per_s
                if self.hold_s > 0:
                    for i in range(1, self.hold_points + 1):
                        out.append(Step(t + self.hold_s * i / self.hold_points, cycle, "hold",
                                        float(b)))
                    t += self.hold_s
        return out


def compression_tension(amplitude: float = 0.15, **kw) -> Protocol:
    """1 -> 1 - A -> 1 -> 1 + A -> 1."""
    if not 0 < amplitude < 1:
        raise ValueError(f"compression/tension amplitude must lie in (0, 1), got {amplitude}")
    return Protocol("compression_tension", (1.0, 1.0 - amplitude, 1.0, 1.0 + amplitude, 1.0), **kw)


def torsion(gamma_max: float = 0.30, **kw) -> Protocol:
    """0 -> gamma_max -> 0 at fixed height."""
    if not 0 < gamma_max:
        raise ValueError(f"torsion amplitude must be positive, got {gamma_max}")
    kw.setdefault("max_increment", gamma_max / 10)
    return Protocol("torsion", (0.0, gamma_max, 0.0), **kw)


def default_protocol(test: str, amplitude: float | None = None) -> Protocol:
    if test == "compression_tension":
        return compression_tension(0.15 if amplitude is None else amplitude)
    if test == "torsion":
        return torsion(0.30 if amplitude is None else amplitude)
    raise ValueError(f"unknown test {test!r}; expected one of {', '.join(TESTS)}")
