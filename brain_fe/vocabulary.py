"""The one vocabulary of the tool: tests, controlled quantities, channels, units, branches.

Every package names tests and table columns through this module (DESIGN.md sections 5-6);
nothing else spells ``"compression_tension"`` or ``"nominal_stress_kPa"`` as a literal.

Units: lengths mm, stresses kPa, forces mN (= kPa mm^2), torques mN mm, time s.

* A *test* is ``compression_tension`` (the plate moves axially; controlled quantity the
  stretch lambda = h / H, neutral value 1) or ``torsion`` (the top plate turns at fixed
  height; controlled quantity the amount of shear at the outer radius gamma = theta R / H,
  neutral value 0).
* A *channel* is one recorded quantity: ``stress`` (nominal stress F / (pi R^2), kPa),
  ``torque`` (mN mm), ``axial_force`` (mN); the table column of each carries its unit.
* A *test key* names one protocol of a specimen: ``compression_tension`` (amplitude 0.15),
  ``compression_tension_0.10``, ``torsion_0.15``, ``torsion_0.30``.
* A *branch* is ``loading`` (moving away from the neutral value), ``unloading`` (moving
  back) or ``hold`` (dwell at constant control).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

COMPRESSION_TENSION = "compression_tension"
TORSION = "torsion"
TESTS = (COMPRESSION_TENSION, TORSION)

STRETCH = "stretch"
SHEAR = "shear"
CONTROL = {COMPRESSION_TENSION: STRETCH, TORSION: SHEAR}
NEUTRAL = {COMPRESSION_TENSION: 1.0, TORSION: 0.0}
DEFAULT_AMPLITUDE = {COMPRESSION_TENSION: 0.15, TORSION: 0.30}

LOADING, UNLOADING, HOLD = "loading", "unloading", "hold"
BRANCHES = (LOADING, UNLOADING, HOLD)

# Table columns of the reported quantities (DESIGN.md section 3, "Outputs")
NOMINAL_STRESS = "nominal_stress_kPa"
TORQUE = "torque_mNmm"
SHEAR_STRESS = "shear_stress_kPa"
AXIAL_FORCE = "axial_force_mN"
TIME = "time_s"


@dataclass(frozen=True)
class Channel:
    """A recorded quantity: its short name, table column and unit."""

    name: str
    column: str
    unit: str


CHANNELS = {c.name: c for c in (Channel("stress", NOMINAL_STRESS, "kPa"),
                                Channel("torque", TORQUE, "mN mm"),
                                Channel("axial_force", AXIAL_FORCE, "mN"))}
# The channels each test records (compression/tension reports the nominal stress; torsion the
# torque and the axial force of the Poynting effect)
TEST_CHANNELS = {COMPRESSION_TENSION: ("stress",), TORSION: ("torque", "axial_force")}
# Columns the forward model reports per test, in table order
OUTPUT_COLUMNS = {COMPRESSION_TENSION: (NOMINAL_STRESS, AXIAL_FORCE),
                  TORSION: (TORQUE, SHEAR_STRESS, AXIAL_FORCE)}
# The stress each test is identified on (Gavrus objective, surrogates)
STRESS_COLUMN = {COMPRESSION_TENSION: NOMINAL_STRESS, TORSION: SHEAR_STRESS}


def check_test(test: str) -> str:
    if test not in TESTS:
        raise ValueError(f"unknown test {test!r}; expected one of {', '.join(TESTS)}")
    return test


def test_key(test: str, amplitude: float) -> str:
    """Name of one protocol: ``compression_tension`` (amplitude 0.15), otherwise
    ``<test>_<amplitude:.2f>`` (``torsion_0.15``, ``compression_tension_0.10``)."""
    check_test(test)
    if test == COMPRESSION_TENSION and math.isclose(float(amplitude), 0.15):
        return COMPRESSION_TENSION
    return f"{test}_{float(amplitude):.2f}"


def test_of_key(key: str) -> str:
    """The test of a test key (``torsion_0.15`` -> ``torsion``)."""
    for t in TESTS:
        if key == t or key.startswith(t + "_"):
            return t
    raise ValueError(f"unknown test key {key!r}")


def is_shear_curve(curve: str) -> bool:
    """Curves whose control is an amount of shear (neutral 0): torsion, simple shear."""
    return str(curve).startswith((TORSION, "simple_shear"))


def shear_stress_kPa(torque_mNmm, radius_mm):
    """Torque-derived shear stress tau = 2 T / (pi R^3) [kPa] (T in mN mm, R in mm)."""
    return 2.0 * torque_mNmm / (math.pi * radius_mm**3)


def torque_mNmm(shear_stress_kPa, radius_mm):
    """Inverse of :func:`shear_stress_kPa`: T = tau pi R^3 / 2 [mN mm]."""
    return shear_stress_kPa * math.pi * radius_mm**3 / 2.0


def channel_values(test: str, axial_force_mN: float, torque: float,
                   radius_mm: float) -> dict[str, float]:
    """The reported columns of ``test`` from the top-plate axial force and torque."""
    if test == COMPRESSION_TENSION:
        return {NOMINAL_STRESS: axial_force_mN / (math.pi * radius_mm**2),
                AXIAL_FORCE: axial_force_mN}
    return {TORQUE: torque, SHEAR_STRESS: shear_stress_kPa(torque, radius_mm),
            AXIAL_FORCE: axial_force_mN}
