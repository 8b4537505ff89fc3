"""Material laws as small composable objects, and the registry of the ones the tool knows.

A material (:class:`MaterialModel`) is

* one or more *isochoric* elastic laws, summed (``strain_energy(Cbar, p)``; the one-term
  Ogden law is the paper's model),
* one *volumetric* law ``U(J)`` (``strain_energy(J, p)``),
* optional *history wrappers* around the isochoric stress (Maxwell branches,
  Ogden-Roxburgh softening: ``apply(S, S_iso, W_iso, state, p, dt)``), applied in order.

Every law lists the :class:`~brain_fe.parameters.Param` it reads (``parameters()``) and
receives them as a mapping ``p`` of UFL expressions, so one compiled form serves every
parameter value.  To add a law (say a fibre family along the specimen axis), write one file
beside these with a frozen dataclass that has ``name``, ``parameters()`` and
``strain_energy(Cbar, p)``, and add it to :data:`ISOCHORIC` below.

:class:`MaterialParameters` holds the values of the built-in laws (mu_p, alpha_p, kappa or
nu0, Maxwell and softening parameters) and turns them into the typed mapping the forward
model takes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import ufl

from ..parameters import KAPPA, SOFTENING, SOFTENING_M, Parameters, alpha, beta, mu, tau
from .fibres import AxialFibres
from .ogden import Ogden
from .softening import OgdenRoxburgh
from .viscoelastic import Maxwell
from .volumetric import LogVolumetric, QuadraticVolumetric, kappa_from_nu0

# The registry: every law the forward model can be built with, by name.
ISOCHORIC = {"ogden": Ogden, "axial_fibres": AxialFibres}
VOLUMETRIC = {"quadratic": QuadraticVolumetric, "log": LogVolumetric}
WRAPPERS = {"softening": OgdenRoxburgh, "maxwell": Maxwell}

__all__ = ["ISOCHORIC", "VOLUMETRIC", "WRAPPERS", "AxialFibres", "MaterialModel",
           "MaterialParameters", "Maxwell", "Ogden", "OgdenRoxburgh", "kappa_from_nu0",
           "law_for"]


def law_for(family: str) -> str | None:
    """The registered isochoric law (other than Ogden) that owns a parameter family."""
    for name, law in ISOCHORIC.items():
        if name != "ogden" and any(p.family == family for p in law().parameters()):
            return name
    return None


class _Slice:
    """Components ``offset ..`` of a vector-valued UFL state."""

    def __init__(self, state, offset: int):
        self.state, self.offset = state, offset

    def __getitem__(self, k: int):
        return self.state[self.offset + k]


@dataclass(frozen=True)
class MaterialModel:
    """W(C) = sum of isochoric laws of Cbar = J^(-2/3) C, plus U(J); history wrappers act
    on the isochoric second Piola-Kirchhoff stress S_iso = 2 dW_iso/dC."""

    isochoric: tuple = (Ogden(1),)
    volumetric: object = field(default_factory=QuadraticVolumetric)
    wrappers: tuple = ()

    @classmethod
    def build(cls, n_terms: int = 1, volumetric: str = "quadratic", maxwell: int = 0,
              softening: bool = False, laws: tuple[str, ...] = ()) -> MaterialModel:
        """The built-in composition: N-term Ogden plus further isochoric ``laws`` of the
        registry (by name), a volumetric law by name, optional softening and Maxwell
        branches (in that order, as the history stress is built)."""
        if volumetric not in VOLUMETRIC:
            raise ValueError(f"volumetric must be one of {', '.join(VOLUMETRIC)}")
        if maxwell < 0:
            raise ValueError("maxwell must be >= 0")
        unknown = [n for n in laws if n not in ISOCHORIC]
        if unknown:
            raise ValueError(f"unknown material law(s) {', '.join(unknown)}; known: "
                             f"{', '.join(ISOCHORIC)}")
        wrappers = ((OgdenRoxburgh(),) if softening else ()) + \
            ((Maxwell(int(maxwell)),) if maxwell else ())
        isochoric = (Ogden(int(n_terms)),) + tuple(ISOCHORIC[n]() for n in laws)
        return cls(isochoric, VOLUMETRIC[volumetric](), wrappers)

    def _laws(self):
        return (*self.isochoric, self.volumetric, *self.wrappers)

    def parameters(self) -> tuple:
        return tuple(p for law in self._laws() for p in law.parameters())

    @property
    def n_terms(self) -> int:
        return sum(getattr(law, "terms", 0) for law in self.isochoric)

    @property
    def maxwell(self) -> int:
        return sum(w.branches for w in self.wrappers if isinstance(w, Maxwell))

    @property
    def softening(self) -> bool:
        return any(isinstance(w, OgdenRoxburgh) for w in self.wrappers)

    @property
    def history(self) -> bool:
        return any(w.state_size for w in self.wrappers)

    @property
    def state_size(self) -> int:
        return sum(w.state_size for w in self.wrappers)

    def isochoric_energy(self, Cbar, p):
        return sum(law.strain_energy(Cbar, p) for law in self.isochoric)

    def strain_energy(self, C, J, p):
        """Energy density [kPa]; ``J = det F`` so that inverted elements give NaN (and a
        load-step cut-back) instead of the always-positive sqrt(det C)."""
        return self.isochoric_energy(J ** (-2.0 / 3.0) * C, p) + \
            self.volumetric.strain_energy(J, p)

    def history_stress(self, F, state, p, dt):
        """(isochoric stress with the wrappers applied, new state vector) at F.

        S_iso = 2 dW_iso/dC by ``ufl.diff``; every wrapper gets its slice of ``state``."""
        C = ufl.variable(F.T * F)
        Jc = ufl.sqrt(ufl.det(C))
        W_iso = self.isochoric_energy(Jc ** (-2.0 / 3.0) * C, p)
        S_iso = 2 * ufl.diff(W_iso, C)
        S, comps, offset = S_iso, [], 0
        for w in self.wrappers:
            S, new = w.apply(S, S_iso, W_iso, _Slice(state, offset), p, dt)
            comps += new
            offset += w.state_size
        return S, ufl.as_vector(comps)


def _floats(v, name: str) -> tuple[float, ...]:
    out = tuple(float(x) for x in np.atleast_1d(v))
    if not all(math.isfinite(x) for x in out):
        raise ValueError(f"{name} must be finite numbers, got {v}")
    return out


@dataclass(frozen=True)
class MaterialParameters:
    """Values of the built-in laws: N-term Ogden (mu_p [kPa], alpha_p [-]), compressibility
    and the optional history physics; every extension's default is its neutral value.

    ``kappa`` [kPa] wins over ``nu0``; otherwise kappa = 2 mu (1 + nu0) / (3 (1 - 2 nu0))
    with mu = sum(mu_p).  ``beta``/``tau_s``: Maxwell branches (beta_i >= 0, tau_i > 0 [s];
    beta = 0 is elastic).  ``softening``/``softening_m_kPa``: Ogden-Roxburgh d = 1/r in
    [0, 1) and m > 0 [kPa] (d = 0 is elastic).
    """

    mu: tuple[float, ...]
    alpha: tuple[float, ...]
    nu0: float | None = 0.49
    kappa: float | None = None
    beta: tuple[float, ...] = ()
    tau_s: tuple[float, ...] = ()
    softening: float = 0.0
    softening_m_kPa: float = 0.05

    def __post_init__(self):
        mu_, alpha_ = _floats(self.mu, "mu"), _floats(self.alpha, "alpha")
        object.__setattr__(self, "mu", mu_)
        object.__setattr__(self, "alpha", alpha_)
        if len(mu_) != len(alpha_) or not mu_:
            raise ValueError("give as many mu values as alpha values")
        if any(a == 0.0 for a in alpha_):
            raise ValueError("alpha must be non-zero")
        if sum(mu_) <= 0.0:
            # In the 2 mu_p / alpha_p^2 form the small-strain shear modulus is sum(mu_p)
            raise ValueError("the shear modulus sum(mu_p) must be positive")
        if self.kappa is None and self.nu0 is None:
            raise ValueError("give kappa or nu0")
        if self.kappa is not None and not (math.isfinite(self.kappa) and self.kappa > 0):
            raise ValueError("kappa must be a positive number")
        if self.kappa is None:
            kappa_from_nu0(self.mu_total, float(self.nu0))  # validates nu0 before any work
        beta_, tau_ = _floats(self.beta, "beta"), _floats(self.tau_s, "tau_s")
        object.__setattr__(self, "beta", beta_)
        object.__setattr__(self, "tau_s", tau_)
        if len(beta_) != len(tau_):
            raise ValueError("give as many Maxwell beta values as relaxation times tau_s")
        if any(b < 0 for b in beta_) or any(t <= 0 for t in tau_):
            raise ValueError("Maxwell branches need beta >= 0 and tau_s > 0")
        if not (math.isfinite(self.softening) and 0.0 <= self.softening < 1.0):
            raise ValueError(f"softening d = 1/r must lie in [0, 1), got {self.softening}")
        if not (math.isfinite(self.softening_m_kPa) and self.softening_m_kPa > 0):
            raise ValueError("softening_m_kPa must be positive")

    @property
    def mu_total(self) -> float:
        return float(sum(self.mu))

    @property
    def kappa_kPa(self) -> float:
        if self.kappa is not None:
            return float(self.kappa)
        return kappa_from_nu0(self.mu_total, float(self.nu0))

    @property
    def maxwell(self) -> int:
        return len(self.beta)

    def values(self) -> Parameters:
        """The typed mapping of every parameter of the built-in laws."""
        out = {mu(p): m for p, m in enumerate(self.mu)}
        out.update({alpha(p): a for p, a in enumerate(self.alpha)})
        out[KAPPA] = self.kappa_kPa
        out.update({beta(i): b for i, b in enumerate(self.beta)})
        out.update({tau(i): t for i, t in enumerate(self.tau_s)})
        out[SOFTENING] = self.softening
        out[SOFTENING_M] = self.softening_m_kPa
        return Parameters(out)

    def describe(self) -> str:
        return f"mu={self.mu}, alpha={self.alpha}, kappa={self.kappa_kPa:.4g} kPa"
