"""Test artefacts: a measurement layer around any forward model.

The machine believes the specimen has its nominal height H and radius R and that the top
plate touches it at the recorded zero; reality may differ.  The layer makes the model see
the real specimen while the outputs are computed the way the machine computes them:

- ``height_rel``, ``radius_rel``: true size (1 + e) times nominal; the machine still
  imposes u_z = (lambda - 1) H_nominal and theta = gamma H_nominal / R_nominal and divides
  by the nominal area (pi R^2) or polar factor (pi R^3 / 2).
- ``stretch_offset``: zero offset of the contact point; the true stretch is the recorded
  one plus the offset (torsion then runs at height (1 + offset) H).
- ``force_offset_mN``, ``torque_offset_mNmm``: additive offsets of the load cells.

Every value's neutral value is 0, which reproduces the bare model exactly.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import asdict, dataclass

from .vocabulary import channel_values

NAMES = ("height_rel", "radius_rel", "stretch_offset", "force_offset", "torque_offset")
GEOMETRIC = ("height_rel", "radius_rel", "stretch_offset")  # need another solve to differentiate


@dataclass(frozen=True)
class Artefacts:
    """Measurement artefacts (all neutral at 0); see the module docstring for meanings."""

    height_rel: float = 0.0
    radius_rel: float = 0.0
    stretch_offset: float = 0.0
    force_offset_mN: float = 0.0
    torque_offset_mNmm: float = 0.0

    def __post_init__(self):
        for name, v in self.values().items():
            if not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number")
        for name in ("height_rel", "radius_rel"):
            if not -0.5 < getattr(self, name) < 0.5:
                raise ValueError(f"{name} must lie in (-0.5, 0.5)")
        if not -0.2 < self.stretch_offset < 0.2:
            raise ValueError("stretch_offset must lie in (-0.2, 0.2)")

    def values(self) -> dict[str, float]:
        return {"height_rel": self.height_rel, "radius_rel": self.radius_rel,
                "stretch_offset": self.stretch_offset, "force_offset": self.force_offset_mN,
                "torque_offset": self.torque_offset_mNmm}

    def replace(self, name: str, value: float) -> Artefacts:
        d = asdict(self)
        key = {"force_offset": "force_offset_mN", "torque_offset": "torque_offset_mNmm"}.get(
            name, name)
        d[key] = value
        return Artefacts(**d)

    @property
    def neutral(self) -> bool:
        return all(v == 0.0 for v in self.values().values())


@contextlib.contextmanager
def scaled_mesh(geometry, art: Artefacts):
    """Temporarily stretch the mesh to the true specimen size (axisymmetric: x = (R, Z))."""
    if art.height_rel == 0.0 and art.radius_rel == 0.0:
        yield
        return
    if geometry.kind != "axisymmetric":
        raise ValueError("height/radius artefacts are implemented for the axisymmetric model")
    x = geometry.mesh.geometry.x
    saved = x.copy()
    x[:, 0] *= 1.0 + art.radius_rel
    x[:, 1] *= 1.0 + art.height_rel
    try:
        yield
    finally:
        x[:] = saved


def offset_channels(test: str, radius_mm: float, art: Artefacts) -> dict[str, float]:
    """Additive offsets of every reported channel (the load-cell offsets)."""
    return channel_values(test, art.force_offset_mN, art.torque_offset_mNmm, radius_mm)
