"""Parameter sensitivities of the top-plate reactions, d(axial force, torque)/d(param).

* :class:`DirectSensitivities` (hyperelastic models): at each converged state,
  K z = -dR/dtheta on the free dofs (the Dirichlet values do not depend on the parameters),
  with the Jacobian factorised at that state; the reaction w . R(u(theta), theta) changes by
  w . (dR/dtheta + K z).  dR/dtheta comes from ``ufl.diff`` of the energy.
* :class:`PathSensitivities` (history-dependent models, glue springs, lift-off): z =
  du/dtheta and the history sensitivities ds are carried along the path.  With D the
  derivative along the direction (theta + e, state + ds, u + z): K z = -(dR/dtheta +
  dR/dstate ds), the reaction changes by D reaction, and ds <- D G.  The partial
  derivatives are central differences of the compiled residual and history update; the
  tangent solve is exact.  With the plate lifted off (:mod:`brain_fe.contact`) the top
  face's position w(theta) keeps the axial force zero: z gains dw/dtheta times the
  response to a unit shift of the face.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import dolfinx.fem.petsc as fem_petsc
import numpy as np
import ufl
from dolfinx import fem

from . import _compat
from .solver import ghost_forward, ghost_reverse

log = logging.getLogger(__name__)

# Floor of the central-difference step per parameter family (relative step 1e-6)
FD_FLOOR = {"mu": 1e-2, "alpha": 1.0, "kappa": 1.0, "beta": 0.1, "tau": 1.0,
            "softening": 0.1, "softening_m": 1e-2, "k_r": 0.1, "k_theta": 0.1}


@dataclass
class Converged:
    """What the model computes once at a converged (sub)step, before any sensitivity
    perturbs it: the residual without its Dirichlet rows set (None where nothing needs
    it), the plate's reactions (None off the output points) and the history update G
    (None without history)."""

    residual: object = None
    reactions: tuple[float, float] | None = None
    update: np.ndarray | None = None


class DirectSensitivities:
    """Exact direct differentiation of an elastic model at converged states."""

    def __init__(self, model):
        self.model = model
        self._forms = None

    def _compile(self) -> None:
        if self._forms is not None:
            return
        m = self.model
        t0 = time.perf_counter()
        v = ufl.TestFunction(m.V)
        dx = m.geometry.dx
        self._forms = {p: _compat.form(ufl.derivative(
            ufl.diff(m.energy_density, var) * m.geometry.volume_weight() * dx, m.u, v))
            for p, var in m.param_vars.items()}
        self._z = fem.Function(m.V)
        # only its rows of the top plate are read (the reactions' change K z)
        self._action_form = m.at_top(ufl.derivative(m.residual_ufl, m.u, self._z))
        self._vecs = {p: fem_petsc.create_vector(f) for p, f in self._forms.items()}
        self._action = fem_petsc.create_vector(self._action_form)
        self._rhs = self._action.duplicate()
        self._dir = self._action.duplicate()
        log.debug("compiled sensitivity forms in %.1f s", time.perf_counter() - t0)

    def start(self, requests: list) -> None:
        """``requests``: [(key, Direction)] of elastic constants."""
        self._compile()
        for _, d in requests:
            bad = [str(p) for p, _ in d.weights if p not in self._forms]
            if bad:
                raise ValueError(f"no direct sensitivity for {', '.join(bad)}")
        self.requests = requests

    def at_state(self, record: bool, base: Converged) -> dict:
        """Reaction derivatives at a converged state if ``record`` (``base`` unused)."""
        if not record:
            return {}
        m = self.model
        m.newton.ensure_factorised()
        x = _compat.petsc_vec(m.u)
        zvec = _compat.petsc_vec(self._z)
        assembled = {}
        for _, d in self.requests:
            for p, _ in d.weights:
                if p not in assembled:
                    v = self._vecs[p]
                    with v.localForm() as vl:
                        vl.set(0.0)
                    fem_petsc.assemble_vector(v, self._forms[p])
                    ghost_reverse(v)
                    assembled[p] = v
        out = {}
        for key, d in self.requests:
            r = self._dir
            r.set(0.0)
            for p, w in d.weights:  # dR/ds along the direction
                r.axpy(w, assembled[p])
            r.copy(self._rhs)
            self._rhs.scale(-1.0)
            _compat.set_bc(self._rhs, m.bcs, x, 0.0)
            m.newton.solve_tangent(self._rhs, zvec)
            ghost_forward(zvec)
            a = self._action
            with a.localForm() as al:
                al.set(0.0)
            fem_petsc.assemble_vector(a, self._action_form)
            ghost_reverse(a)
            a.axpy(1.0, r)
            out[key] = m.ends.directional(a)
        return out


class PathSensitivities:
    """Sensitivities carried along the path (history variables, glue springs)."""

    def __init__(self, model):
        self.model = model

    def start(self, requests: list) -> None:
        """``requests``: [(key, Direction)]."""
        m = self.model
        self.requests = requests
        x = _compat.petsc_vec(m.u)
        self._z = {k: x.duplicate() for k, _ in requests}
        for z in self._z.values():
            z.set(0.0)
        self._ds = ({k: np.zeros_like(m.state.array) for k, _ in requests}
                    if m.state is not None else {})

    def _step(self, d) -> float:
        """Step of the central differences along ``d``: a relative change of 1e-6 of its
        most sensitive constant (floored per family)."""
        c = self.model.constants
        return 1e-6 * min(max(abs(float(c[p].value)), FD_FLOOR.get(p.family, 1e-3)) / abs(w)
                          for p, w in d.weights if w != 0.0)

    def at_state(self, record: bool, base: Converged) -> dict:
        """Carry z and ds over a converged (sub)step; reaction derivatives if ``record``.
        ``base``: the converged state's residual, reactions (if ``record``) and history
        update."""
        m = self.model
        m.newton.ensure_factorised()
        x = _compat.petsc_vec(m.u)
        u0 = x.copy()
        state = m.state
        s0 = state.array.copy() if state is not None else None
        out, new_ds = {}, {}
        theta0 = {p: float(c.value) for p, c in m.constants.items()}
        directions = dict(self.requests)

        def perturb(key, h, with_u):
            for p, w in directions[key].weights:
                m.constants[p].value = theta0[p] + h * w
            if state is not None:
                state.array[:] = s0 + h * self._ds[key]
            if with_u:
                u0.copy(x)
                x.axpy(h, self._z[key])
                ghost_forward(x)

        # one-sided differences from the converged state (its residual, reactions and
        # state update are shared by every direction): 2 assemblies and 1 state update per
        # direction instead of 4 and 2; truncation error ~ the relative step, 1e-6
        r0 = base.residual
        off = m.lift_off is not None and m.lift_off.trial_off
        f0 = (np.array(base.reactions) if base.reactions is not None
              else np.array(m.ends.reactions(r0, m.comm)) if record or off else None)
        g0 = base.update
        if off:  # the top face moves with the parameters so that the force stays zero
            zw, dfz_dw = self._unit_top_shift(x, u0, r0, f0)
        for p, d in self.requests:
            eps = self._step(d)
            # right-hand side: -(explicit + history) derivative of the residual at fixed u
            perturb(p, eps, False)
            rhs = m.newton.assemble_residual(with_bcs=False).copy()
            rhs.axpy(-1.0, r0)
            rhs.scale(-1.0 / eps)
            perturb(p, 0.0, False)  # u is still the converged one (a failed tangent solve
            # factorises again, at the converged constants and state)
            _compat.set_bc(rhs, m.bcs, x, 0.0)
            z = self._z[p]
            m.newton.solve_tangent(rhs, z)
            ghost_forward(z)
            if off:  # add the shift of the top face that keeps the axial force zero
                perturb(p, eps, True)
                dfz = (m.reactions()[0] - f0[0]) / eps
                z.axpy(-dfz / dfz_dw, zw)
                ghost_forward(z)
            if record or state is not None:
                perturb(p, eps, True)
                if record:
                    out[p] = tuple((np.array(m.reactions()) - f0) / eps)
                if state is not None:
                    new_ds[p] = state.scatter((state.evaluate() - g0) / eps,
                                              np.empty_like(s0))
            perturb(p, 0.0, True)
        self._ds.update(new_ds)
        return out

    def _unit_top_shift(self, x, u0, r0, f0) -> tuple:
        """Off the plate: the response zw of u to a unit axial shift of the top face at
        fixed parameters and history (K zw = 0 on the free dofs, zw = 1 on the top face's
        axial dofs), and d(axial force)/d(shift).  K zw's free rows come from a one-sided
        difference of the residual along the shift."""
        m = self.model
        e = m.ends.w_axial  # 1 on the top face's axial dofs
        h = 1e-7 * m.geometry.height_mm
        x.axpy(h, e)
        ghost_forward(x)
        rhs = m.newton.assemble_residual(with_bcs=False).copy()
        u0.copy(x)
        ghost_forward(x)
        rhs.axpy(-1.0, r0)
        rhs.scale(-1.0 / h)
        _compat.set_bc(rhs, m.bcs, x, 0.0)
        rhs.axpy(1.0, e)
        zw = x.duplicate()
        m.newton.solve_tangent(rhs, zw)
        ghost_forward(zw)
        x.axpy(h, zw)
        ghost_forward(x)
        dfz_dw = (m.reactions()[0] - f0[0]) / h
        u0.copy(x)
        ghost_forward(x)
        return zw, dfz_dw
