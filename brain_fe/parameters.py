"""Model parameters as a typed mapping.

A :class:`Param` names one scalar of the model: a *family* (``mu``, ``alpha``, ``kappa``,
``beta``, ``tau``, ...) and, for families with several members, an index (Ogden term p,
Maxwell branch i).  :class:`Parameters` is an immutable mapping ``Param -> float``.  The
forward model's constants, its sensitivities and the simulators' Jacobians are all keyed
by ``Param``; ``str(param)`` (``mu_0``, ``kappa``) appears only at the edges (tables,
JSON, the command line), and :meth:`Param.parse` reads it back.

Families of the built-in physics (units in brackets):

=============  ==========================================================================
``mu_p``       Ogden shear modulus of term p [kPa]
``alpha_p``    Ogden exponent of term p [-]
``kappa``      bulk modulus [kPa]
``beta_i``     relative stiffness of Maxwell branch i [-]
``tau_i``      relaxation time of Maxwell branch i [s]
``softening``  Ogden-Roxburgh d = 1/r [-]
``softening_m``  Ogden-Roxburgh energy scale m [kPa]
``k_r``, ``k_theta``  tangential stiffness per area of a glue layer [kPa/mm]
``fibre_k1``   stiffness of the axial fibre family [kPa] (``materials/fibres.py``)
``fibre_k2``   exponential stiffening of the axial fibres [-]
=============  ==========================================================================
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9]*(?:_[A-Za-z][A-Za-z0-9]*)*)(?:_(\d+))?$")


@dataclass(frozen=True, order=True)
class Param:
    """One named scalar of a model: ``family`` and, for indexed families, ``index``."""

    family: str
    index: int | None = None

    def __str__(self) -> str:
        return self.family if self.index is None else f"{self.family}_{self.index}"

    def __repr__(self) -> str:
        return f"Param({str(self)!r})"

    @classmethod
    def parse(cls, text: str | Param) -> Param:
        """``"mu_0"`` -> ``Param("mu", 0)``, ``"kappa"`` -> ``Param("kappa")``."""
        if isinstance(text, Param):
            return text
        m = _NAME.match(str(text).strip())
        if not m:
            raise ValueError(f"not a parameter name: {text!r}")
        return cls(m.group(1), None if m.group(2) is None else int(m.group(2)))


def mu(p: int = 0) -> Param:
    return Param("mu", p)


def alpha(p: int = 0) -> Param:
    return Param("alpha", p)


def beta(i: int = 0) -> Param:
    return Param("beta", i)


def tau(i: int = 0) -> Param:
    return Param("tau", i)


KAPPA = Param("kappa")
SOFTENING = Param("softening")
SOFTENING_M = Param("softening_m")
K_R = Param("k_r")
K_THETA = Param("k_theta")


class Parameters(Mapping[Param, float]):
    """Immutable mapping ``Param -> float``; keys given as text are parsed."""

    __slots__ = ("_d",)

    def __init__(self, items: Mapping | Iterable[tuple] = ()):
        pairs = items.items() if isinstance(items, Mapping) else items
        self._d = {Param.parse(k): float(v) for k, v in pairs}

    def __getitem__(self, key: Param | str) -> float:
        return self._d[Param.parse(key)]

    def __contains__(self, key) -> bool:
        try:
            return Param.parse(key) in self._d
        except ValueError:
            return False

    def __iter__(self) -> Iterator[Param]:
        return iter(self._d)

    def __len__(self) -> int:
        return len(self._d)

    def __or__(self, other: Mapping) -> Parameters:
        return Parameters({**self._d, **Parameters(other)._d})

    def __repr__(self) -> str:
        return "Parameters({" + ", ".join(f"{k}: {v:g}" for k, v in self._d.items()) + "})"

    def replace(self, key: Param | str, value: float) -> Parameters:
        return self | {Param.parse(key): value}

    def named(self) -> dict[str, float]:
        """Plain ``{"mu_0": ...}`` for JSON and tables."""
        return {str(k): v for k, v in self._d.items()}

    def family(self, name: str) -> list[float]:
        """Values of an indexed family in index order (``family("mu")`` -> [mu_0, mu_1])."""
        idx = sorted(k.index for k in self._d if k.family == name and k.index is not None)
        return [self._d[Param(name, i)] for i in idx]


@dataclass(frozen=True)
class Direction:
    """A direction in parameter space: ``sum_p weight_p e_p``.  The derivative of the
    outputs along it, d/ds y(theta + s w), is one sensitivity of the forward model, e.g.
    d/d mu_0 with kappa following mu at fixed nu0 is
    ``Direction("mu_0", ((mu(0), 1.0), (KAPPA, kappa / mu)))``."""

    name: str
    weights: tuple[tuple[Param, float], ...]

    def __str__(self) -> str:
        return self.name

    @classmethod
    def of(cls, p: Param) -> Direction:
        return cls(str(p), ((p, 1.0),))
