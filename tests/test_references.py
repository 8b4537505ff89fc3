"""The independent references reproduce the numbers quoted in DESIGN.md section 3."""

import pytest
from references import homogeneous_uniaxial, rivlin_torque


def test_homogeneous_uniaxial_design_value():
    assert homogeneous_uniaxial(0.85) == pytest.approx(-2.85049, abs=5e-6)


def test_rivlin_design_value():
    assert rivlin_torque(0.30) == pytest.approx(71.339, abs=5e-4)
