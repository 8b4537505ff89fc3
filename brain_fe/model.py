"""Forward model: glued (or slip) cylinder under a displacement-controlled protocol.

One ``ForwardModel`` compiles its forms once; material parameters and boundary values are
``fem.Constant``s, so running another parameter set or protocol costs no compilation.
Reactions (axial force, torque) are the action of the assembled residual on a field equal
to the virtual rigid motion of the top plate (reaction by virtual work), reduced over MPI
ranks.  Units: mm, kPa, mN, mN mm, s.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import dolfinx.fem as fem
import dolfinx.fem.petsc as fem_petsc
import numpy as np
import pandas as pd
import ufl
from petsc4py import PETSc

from . import _compat
from . import artefacts as _art
from .artefacts import Artefacts
from .geometry import Geometry
from .material import VOLUMETRIC, CompressibleMaterial, Ogden, kappa_from_nu0
from .protocols import CONTROL, Protocol, Step
from .solver import ConvergenceError, NewtonSolver

log = logging.getLogger(__name__)

ENDS = ("glued", "slip", "springs")
TENSOR_SIZE = 9  # a 3x3 stress per quadrature point (full, for simple indexing)


@dataclass(frozen=True)
class MaterialParameters:
    """N-term Ogden parameters (mu_p in kPa, alpha_p dimensionless), compressibility and
    the optional physics extensions; every extension's default is its neutral value.

    ``kappa`` [kPa] wins over ``nu0``; otherwise kappa = 2 mu (1 + nu0) / (3 (1 - 2 nu0))
    with mu = sum(mu_p).

    Extensions (see :class:`ForwardModel`):
    ``beta``/``tau_s``: Maxwell branches on the isochoric stress, relative stiffness
    beta_i >= 0 (dimensionless) and relaxation time tau_i > 0 [s]; beta = 0 is elastic.
    ``softening``/``softening_m_kPa``: Ogden-Roxburgh damage eta = 1 - d erf((W_max - W)/m)
    with d = 1/r in [0, 1) and m > 0 [kPa]; d = 0 is elastic.
    ``k_r_kPa_mm``/``k_theta_kPa_mm``: tangential interface stiffness per area [kPa/mm] of
    the glue layer (``ends="springs"``): infinite is glued, 0 (radial) is slip.
    """

    mu: tuple[float, ...]
    alpha: tuple[float, ...]
    nu0: float | None = 0.49
    kappa: float | None = None
    beta: tuple[float, ...] = ()
    tau_s: tuple[float, ...] = ()
    softening: float = 0.0
    softening_m_kPa: float = 0.05
    k_r_kPa_mm: float | None = None
    k_theta_kPa_mm: float | None = None

    def __post_init__(self):
        mu = tuple(float(m) for m in np.atleast_1d(self.mu))
        alpha = tuple(float(a) for a in np.atleast_1d(self.alpha))
        object.__setattr__(self, "mu", mu)
        object.__setattr__(self, "alpha", alpha)
        if len(mu) != len(alpha) or not mu:
            raise ValueError("give as many mu values as alpha values")
        if any(a == 0.0 for a in alpha):
            raise ValueError("alpha must be non-zero")
        if sum(mu) <= 0.0:
            # In the 2 mu_p / alpha_p^2 form the small-strain shear modulus is sum(mu_p)
            raise ValueError("the shear modulus sum(mu_p) must be positive")
        if self.kappa is None and self.nu0 is None:
            raise ValueError("give kappa or nu0")
        if self.kappa is not None and self.kappa <= 0:
            raise ValueError("kappa must be positive")
        if self.kappa is None:
            kappa_from_nu0(self.mu_total, float(self.nu0))  # validates nu0 before any work
        beta = tuple(float(b) for b in np.atleast_1d(self.beta))
        tau = tuple(float(t) for t in np.atleast_1d(self.tau_s))
        object.__setattr__(self, "beta", beta)
        object.__setattr__(self, "tau_s", tau)
        if len(beta) != len(tau):
            raise ValueError("give as many Maxwell beta values as relaxation times tau_s")
        if any(b < 0 for b in beta) or any(t <= 0 for t in tau):
            raise ValueError("Maxwell branches need beta >= 0 and tau_s > 0")
        if not 0.0 <= self.softening < 1.0:
            raise ValueError(f"softening d = 1/r must lie in [0, 1), got {self.softening}")
        if self.softening_m_kPa <= 0:
            raise ValueError("softening_m_kPa must be positive")
        for k in (self.k_r_kPa_mm, self.k_theta_kPa_mm):
            if k is not None and k < 0:
                raise ValueError("interface stiffnesses must be >= 0")

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

    def values(self) -> dict[str, float]:
        """Flat ``name -> value`` of every parameter constant of a matching model."""
        out = {f"mu_{p}": m for p, m in enumerate(self.mu)}
        out.update({f"alpha_{p}": a for p, a in enumerate(self.alpha)})
        out["kappa"] = self.kappa_kPa
        out.update({f"beta_{i}": b for i, b in enumerate(self.beta)})
        out.update({f"tau_{i}": t for i, t in enumerate(self.tau_s)})
        out["softening"] = self.softening
        out["softening_m"] = self.softening_m_kPa
        out["k_r"] = np.inf if self.k_r_kPa_mm is None else self.k_r_kPa_mm
        out["k_theta"] = np.inf if self.k_theta_kPa_mm is None else self.k_theta_kPa_mm
        return out


def _axisymmetric_F(w, R):
    """Deformation gradient of the axisymmetric-with-twist kinematics (DESIGN.md section 3).

    Rows (e_r, e_theta, e_z), columns (E_R, E_Theta, E_Z); w = (u_r, u_z, phi).
    """
    g = ufl.grad(w)
    r = R + w[0]
    return ufl.as_matrix([[1 + g[0, 0], 0, g[0, 1]],
                          [r * g[2, 0], r / R, r * g[2, 1]],
                          [g[1, 0], 0, 1 + g[1, 1]]])


def shear_stress_kPa(torque_mNmm, radius_mm):
    """Torque-derived shear stress tau = 2 T / (pi R^3) [kPa] (T in mN mm, R in mm)."""
    return 2.0 * torque_mNmm / (math.pi * radius_mm**3)


def torque_mNmm(shear_stress_kPa, radius_mm):
    """Inverse of :func:`shear_stress_kPa`: T = tau pi R^3 / 2 [mN mm]."""
    return shear_stress_kPa * math.pi * radius_mm**3 / 2.0


class ForwardModel:
    """Compiled forward model of one geometry, material form and end condition.

    Parameters
    ----------
    geometry: from :func:`brain_fe.geometry.axisymmetric` or :func:`cylinder3d`.
    n_terms: number of Ogden terms.
    volumetric: ``quadratic`` (kappa/2 (J-1)^2) or ``log`` (kappa/4 (J^2-1-2 ln J)).
    ends: ``glued`` (no slip at the plates), ``slip`` (frictionless plates) or ``springs``
        (glue layer of finite tangential stiffness k_r, k_theta per area; axisymmetric).
    degree: polynomial degree of the displacement (and twist) field.
    maxwell: number of Maxwell branches (finite-strain viscoelasticity, Simo 1987 type):
        S = S_vol + S_iso + sum_i Q_i with dQ_i/dt + Q_i / tau_i = beta_i dS_iso/dt, S_iso
        the isochoric second Piola-Kirchhoff stress of the Ogden part; integrated by the
        recurrence Q_i(n+1) = exp(-x) Q_i(n) + beta_i (1 - exp(-x))/x (S_iso(n+1) - S_iso(n)),
        x = dt/tau_i, exact for piecewise-linear histories of S_iso.
    mullins: Ogden-Roxburgh pseudo-elastic softening of the isochoric part,
        S_iso -> eta S_iso, eta = 1 - d erf(max(W_max - W_iso, 0) / m), W_max the largest
        isochoric energy reached so far (internal variable).

    History variables (S_iso, Q_i, W_max) live at the quadrature points of ``geometry.dx``.
    """

    def __init__(self, geometry: Geometry, n_terms: int = 1, volumetric: str = "quadratic",
                 ends: str = "glued", degree: int = 2, maxwell: int = 0,
                 mullins: bool = False):
        if ends not in ENDS:
            raise ValueError(f"ends must be one of {', '.join(ENDS)}, got {ends!r}")
        if volumetric not in VOLUMETRIC:
            raise ValueError(f"volumetric must be one of {', '.join(VOLUMETRIC)}")
        if ends == "springs" and geometry.kind != "axisymmetric":
            raise ValueError("interface springs are implemented for the axisymmetric model")
        if maxwell < 0:
            raise ValueError("maxwell must be >= 0")
        self.geometry = geometry
        self.ends = ends
        self.n_terms = int(n_terms)
        self.maxwell = int(maxwell)
        self.mullins = bool(mullins)
        self.history = self.maxwell > 0 or self.mullins
        # Extended models get their sensitivities by path-following direct differentiation
        self.path_sensitivities = self.history or ends == "springs"
        msh = geometry.mesh
        self.comm = msh.comm
        self.V = _compat.vector_space(msh, degree, 3)
        self.u = fem.Function(self.V, name="displacement")
        v = ufl.TestFunction(self.V)
        du = ufl.TrialFunction(self.V)
        st = _compat.scalar_type()

        def const(value):
            return fem.Constant(msh, st(value))

        self.c_mu = [const(1.0) for _ in range(self.n_terms)]
        self.c_alpha = [const(-20.0) for _ in range(self.n_terms)]
        self.c_kappa = const(100.0)
        self.c_beta = [const(0.0) for _ in range(self.maxwell)]
        self.c_tau = [const(1.0) for _ in range(self.maxwell)]
        self.c_soft, self.c_soft_m = const(0.0), const(0.05)
        self.c_kr, self.c_kt = const(1.0), const(1.0)
        self.c_dt = const(1.0)  # time increment of the current (sub)step [s]
        self.c_top_axial = const(0.0)  # top axial displacement [mm]
        self.c_top_twist = const(0.0)  # top rotation angle [rad]
        self._twist_ufl = self.c_top_twist
        self.constants = {f"mu_{p}": c for p, c in enumerate(self.c_mu)}
        self.constants.update({f"alpha_{p}": c for p, c in enumerate(self.c_alpha)})
        self.constants["kappa"] = self.c_kappa
        self.constants.update({f"beta_{i}": c for i, c in enumerate(self.c_beta)})
        self.constants.update({f"tau_{i}": c for i, c in enumerate(self.c_tau)})
        if self.mullins:
            self.constants.update(softening=self.c_soft, softening_m=self.c_soft_m)
        if ends == "springs":
            self.constants.update(k_r=self.c_kr, k_theta=self.c_kt)
        # UFL variables around the constants: d(energy)/d(parameter) for the sensitivities
        self.param_vars = {f"mu_{p}": ufl.variable(c) for p, c in enumerate(self.c_mu)}
        self.param_vars.update({f"alpha_{p}": ufl.variable(c) for p, c in enumerate(self.c_alpha)})
        self.param_vars["kappa"] = ufl.variable(self.c_kappa)
        pv = self.param_vars
        self.material = CompressibleMaterial(
            Ogden(tuple(pv[f"mu_{p}"] for p in range(self.n_terms)),
                  tuple(pv[f"alpha_{p}"] for p in range(self.n_terms))),
            VOLUMETRIC[volumetric](pv["kappa"]))
        x = ufl.SpatialCoordinate(msh)
        if geometry.kind == "axisymmetric":
            F = _axisymmetric_F(self.u, x[0])
            weight = 2 * math.pi * x[0]
        else:
            F = ufl.Identity(3) + ufl.grad(self.u)
            weight = 1.0
        C = F.T * F
        self._weight = weight
        dx = geometry.dx
        if self.history:
            R = self._history_residual(F, v, weight)
        else:
            self.energy_density = self.material.strain_energy(C, J=ufl.det(F))
            R = ufl.derivative(self.energy_density * weight * dx, self.u, v)
        if ends == "springs":
            R = R + ufl.derivative(self._spring_energy(x), self.u, v)
        self._residual_ufl = R
        Jac = ufl.derivative(R, self.u, du)
        t0 = time.perf_counter()
        self.residual_form = _compat.form(R)
        self.jacobian_form = _compat.form(Jac)
        if self.history:
            self._state_expr = fem.Expression(self._state_update_ufl, self._q_points)
        self.compile_time_s = time.perf_counter() - t0
        log.debug("compiled %s forms in %.1f s", geometry.kind, self.compile_time_s)
        self._setup_bcs()
        self.newton = NewtonSolver(self.comm, self.residual_form, self.jacobian_form, self.u,
                                   self.bcs)
        self._sens_forms = None

    # ------------------------------------------------------------------ extensions
    def _history_residual(self, F, v, weight):
        """Residual with internal variables: int (1/2 S : dC + U'(J) dJ) w dx.

        S_iso = 2 dW_iso/dC is written through ``ufl.diff`` of the Ogden energy of C, the
        Maxwell and softening terms modify it, the volumetric part stays elastic.
        """
        msh = self.geometry.mesh
        n = TENSOR_SIZE * (1 + self.maxwell) if self.maxwell else 0
        n_state = n + (1 if self.mullins else 0)
        self.Vq, self._q_points = _compat.quadrature_space(msh, self.geometry.quadrature_degree,
                                                           n_state)
        self.state = fem.Function(self.Vq, name="history")
        dm = _compat.dofmap_array(self.Vq)
        bs = self.Vq.dofmap.bs
        self._state_index = (bs * dm[:, :, None] + np.arange(bs)).reshape(dm.shape[0], -1)
        self._cells = np.arange(_compat.num_local_cells(msh), dtype=np.int32)
        s = self.state

        def tensor(k0):
            return ufl.as_matrix([[s[k0 + 3 * i + j] for j in range(3)] for i in range(3)])

        C = ufl.variable(F.T * F)
        Jc = ufl.sqrt(ufl.det(C))
        W_iso = self.material.isochoric.strain_energy_isochoric(Jc ** (-2.0 / 3.0) * C)
        S_iso = 2 * ufl.diff(W_iso, C)
        S = S_iso
        new_state = []
        if self.mullins:
            W_max = s[n]
            eta = 1 - self.c_soft * ufl.erf(ufl.max_value(W_max - W_iso, 0.0) / self.c_soft_m)
            S = eta * S_iso
        if self.maxwell:
            S_prev = tensor(0)
            new_state.append(S_iso)
            for i in range(self.maxwell):
                xi = self.c_dt / self.c_tau[i]
                gamma = self.c_beta[i] * (1 - ufl.exp(-xi)) / xi
                Q_new = ufl.exp(-xi) * tensor(TENSOR_SIZE * (i + 1)) + gamma * (S_iso - S_prev)
                S = S + Q_new
                new_state.append(Q_new)
        comps = [t[i, j] for t in new_state for i in range(3) for j in range(3)]
        if self.mullins:
            comps.append(ufl.max_value(s[n], W_iso))
        self._state_update_ufl = ufl.as_vector(comps)
        J = ufl.det(F)
        dF = ufl.derivative(F, self.u, v)
        dC = dF.T * F + F.T * dF
        dx = self.geometry.dx
        U = self.material.volumetric.strain_energy(J)
        return (0.5 * ufl.inner(S, dC) * weight * dx
                + ufl.derivative(U * weight * dx, self.u, v))

    def _spring_energy(self, x):
        """Glue layer: 1/2 k_r u_r^2 + 1/2 k_theta (R (phi - phi_plate))^2 per area on both
        end faces (axisymmetric: dA = 2 pi R dR); the top plate turns by the twist angle."""
        ds = _compat.facet_measure(self.geometry, self.geometry.quadrature_degree)
        top, bottom = (self.geometry.markers[n].tag for n in ("top", "bottom"))
        u_r, phi, Rr = self.u[0], self.u[2], x[0]
        w = 2 * math.pi * Rr
        e_top = 0.5 * (self.c_kr * u_r**2 + self.c_kt * (Rr * (phi - self._twist_ufl)) ** 2)
        e_bot = 0.5 * (self.c_kr * u_r**2 + self.c_kt * (Rr * phi) ** 2)
        # Torque of the glue layer on the top plate, in the sense of the twist
        self._spring_torque_form = _compat.form(
            self.c_kt * Rr**2 * (self._twist_ufl - phi) * w * ds(top))
        return e_top * w * ds(top) + e_bot * w * ds(bottom)

    # ------------------------------------------------------------------ sensitivities
    def _compile_sensitivities(self):
        """dR/dtheta for every parameter constant and the Jacobian's action J(u)[z]."""
        if self._sens_forms is not None:
            return
        t0 = time.perf_counter()
        v = ufl.TestFunction(self.V)
        dx = self.geometry.dx
        forms = {}
        for name, var in self.param_vars.items():
            dW = ufl.diff(self.energy_density, var)
            forms[name] = _compat.form(ufl.derivative(dW * self._weight * dx, self.u, v))
        self._z = fem.Function(self.V)
        self._action_form = _compat.form(ufl.derivative(self._residual_ufl, self.u, self._z))
        self._sens_forms = forms
        self._sens_vecs = {k: fem_petsc.create_vector(f) for k, f in forms.items()}
        self._action_vec = fem_petsc.create_vector(self._action_form)
        self._sens_rhs = self._action_vec.duplicate()
        log.debug("compiled sensitivity forms in %.1f s", time.perf_counter() - t0)

    def _sensitivities(self) -> dict[str, tuple[float, float]]:
        """d(axial force, torque)/d(parameter) at the current converged state.

        Direct differentiation: K dz = -dR_f/dtheta on the free dofs (Dirichlet values do
        not depend on the parameters), with the Jacobian factorised at this state; the
        reaction w . R(u(theta), theta) then changes by w . (dR/dtheta + K z).
        """
        self.newton.ensure_factorised()
        x = _compat.petsc_vec(self.u)
        zvec = _compat.petsc_vec(self._z)
        out = {}
        for name, form in self._sens_forms.items():
            r = self._sens_vecs[name]
            with r.localForm() as rl:
                rl.set(0.0)
            fem_petsc.assemble_vector(r, form)
            r.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            rhs = self._sens_rhs
            r.copy(rhs)
            rhs.scale(-1.0)
            _compat.set_bc(rhs, self.bcs, x, 0.0)
            self.newton.ksp.solve(rhs, zvec)
            zvec.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            a = self._action_vec
            with a.localForm() as al:
                al.set(0.0)
            fem_petsc.assemble_vector(a, self._action_form)
            a.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            a.axpy(1.0, r)
            out[name] = (float(a.dot(self._w_axial)), float(a.dot(self._w_torque())))
        return out

    # ------------------------------------------------------------------ boundary conditions
    def _dofs(self, sub: int | None, facet_name: str) -> np.ndarray:
        return _compat.locate_dofs(self.V, sub, self.geometry.fdim,
                                   self.geometry.facets(facet_name))

    def _indicator(self, dofs: np.ndarray, values: np.ndarray | float = 1.0):
        """PETSc vector with ``values`` at the owned entries of ``dofs``, zero elsewhere."""
        w = fem_petsc.create_vector(self.residual_form)
        w.set(0.0)
        arr = w.getArray()
        owned = len(arr)
        vals = np.broadcast_to(np.asarray(values, dtype=float), dofs.shape)
        keep = dofs < owned
        arr[dofs[keep]] = vals[keep]
        w.setArray(arr)
        return w

    def _setup_bcs(self):
        st = _compat.scalar_type()
        msh = self.geometry.mesh
        zero = fem.Constant(msh, st(0.0))
        self.g_top = None  # 3D glued: top displacement field (rotation + axial shift)
        bcs = []
        if self.geometry.kind == "axisymmetric":
            UR, UZ, PHI = 0, 1, 2
            bcs.append(fem.dirichletbc(zero, self._dofs(UR, "axis"), self.V.sub(UR)))
            # springs: the glue layer, not a constraint, holds u_r and phi on both ends
            bottom = {"glued": [UZ, PHI, UR], "slip": [UZ, PHI], "springs": [UZ]}[self.ends]
            for c in bottom:
                bcs.append(fem.dirichletbc(zero, self._dofs(c, "bottom"), self.V.sub(c)))
            if self.ends == "glued":
                bcs.append(fem.dirichletbc(zero, self._dofs(UR, "top"), self.V.sub(UR)))
            top_uz, top_phi = self._dofs(UZ, "top"), self._dofs(PHI, "top")
            bcs.append(fem.dirichletbc(self.c_top_axial, top_uz, self.V.sub(UZ)))
            if self.ends != "springs":
                bcs.append(fem.dirichletbc(self.c_top_twist, top_phi, self.V.sub(PHI)))
            self._w_axial = self._indicator(top_uz)
            self._w_torque = lambda: self._w_torque_axi
            self._w_torque_axi = self._indicator(top_phi)
        else:
            bcs.extend(self._setup_bcs_3d(zero))
        self.bcs = bcs

    def _setup_bcs_3d(self, zero):
        st = _compat.scalar_type()
        msh = self.geometry.mesh
        bcs = []
        coords = self.V.tabulate_dof_coordinates()
        if self.ends == "glued":
            self.g_top = fem.Function(self.V)
            top = self._dofs(None, "top")
            zero_vec = fem.Constant(msh, np.zeros(3, dtype=st))
            bcs.append(fem.dirichletbc(zero_vec, self._dofs(None, "bottom"), self.V))
            bcs.append(fem.dirichletbc(self.g_top, top))
            self._top_nodes = top  # blocked space: these are node (block) indices
            self._top_xy = coords[self._top_nodes, :2]
        else:
            bcs.append(fem.dirichletbc(zero, self._dofs(2, "bottom"), self.V.sub(2)))
            # Rigid in-plane motion removed at points where the symmetric solution has
            # zero lateral displacement: the bottom centre (u_x = u_y = 0) and the bottom
            # rim point on the x axis (u_y = 0). Both are mesh nodes (see cylinder3d).
            Rr = self.geometry.radius_mm
            for sub, where in ((0, lambda p: np.isclose(p[0], 0) & np.isclose(p[1], 0)),
                              (1, lambda p: np.isclose(p[1], 0) & (np.isclose(p[0], 0)
                                                                   | np.isclose(p[0], Rr))),
                              ):
                pts = lambda p, w=where: w(p) & np.isclose(p[2], 0.0)  # noqa: E731
                Vs, _ = self.V.sub(sub).collapse()
                dofs = fem.locate_dofs_geometrical((self.V.sub(sub), Vs), pts)[0]
                bcs.append(fem.dirichletbc(zero, dofs, self.V.sub(sub)))
        top_z = self._dofs(2, "top")
        if self.ends == "slip":
            bcs.append(fem.dirichletbc(self.c_top_axial, top_z, self.V.sub(2)))
        self._w_axial = self._indicator(top_z)
        top_x, top_y = self._dofs(0, "top"), self._dofs(1, "top")
        self._top_x_dofs, self._top_y_dofs = top_x, top_y
        self._coords = coords
        self._w_torque = self._torque_field_3d
        return bcs

    def _torque_field_3d(self):
        """Virtual rotation of the top about z at the current twist: (-y', x', 0)."""
        th = float(self.c_top_twist.value)
        c, s = math.cos(th), math.sin(th)
        X = self._coords[self._top_x_dofs // 3]
        Y = self._coords[self._top_y_dofs // 3]
        wx = -(X[:, 0] * s + X[:, 1] * c)
        wy = Y[:, 0] * c - Y[:, 1] * s
        w = self._indicator(self._top_x_dofs, wx)
        w.axpy(1.0, self._indicator(self._top_y_dofs, wy))
        return w

    def _set_control(self, test: str, value: float, preload: float = 0.0):
        """Plate position for ``value`` of the controlled quantity, on top of an axial
        ``preload`` stretch offset (torsion then runs at the height (1 + preload) H)."""
        H, R = self.geometry.height_mm, self.geometry.radius_mm
        if test == "compression_tension":
            uz, twist = (value + preload - 1.0) * H, 0.0
        else:
            uz, twist = preload * H, value * H / R
        self.c_top_axial.value = uz
        self.c_top_twist.value = twist
        if self.g_top is not None:
            c, s = math.cos(twist), math.sin(twist)
            xy = self._top_xy
            vals = np.empty((len(xy), 3))
            vals[:, 0] = xy[:, 0] * c - xy[:, 1] * s - xy[:, 0]
            vals[:, 1] = xy[:, 0] * s + xy[:, 1] * c - xy[:, 1]
            vals[:, 2] = uz
            arr = self.g_top.x.array
            for k in range(3):
                arr[3 * self._top_nodes + k] = vals[:, k]

    # ------------------------------------------------------------------ parameters
    def check_parameters(self, params: MaterialParameters) -> None:
        """Raise ValueError when ``params`` needs physics this model was not compiled with."""
        if len(params.mu) != self.n_terms:
            raise ValueError(f"model compiled for {self.n_terms} Ogden term(s), "
                             f"got {len(params.mu)}")
        if params.maxwell != self.maxwell:
            raise ValueError(f"model compiled for {self.maxwell} Maxwell branch(es), "
                             f"got {params.maxwell}")
        if params.softening and not self.mullins:
            raise ValueError("softening needs a model compiled with mullins=True")
        springs = params.k_r_kPa_mm is not None or params.k_theta_kPa_mm is not None
        if springs != (self.ends == "springs"):
            raise ValueError("interface stiffnesses k_r, k_theta go with ends='springs' "
                             "(and are required there)")
        if springs and (params.k_r_kPa_mm is None or params.k_theta_kPa_mm is None):
            raise ValueError("ends='springs' needs both k_r_kPa_mm and k_theta_kPa_mm")

    def set_parameters(self, params: MaterialParameters):
        self.check_parameters(params)
        for name, value in params.values().items():
            if name in self.constants:
                self.constants[name].value = value
        scale = params.mu_total * math.pi * self.geometry.radius_mm ** 2  # mN
        self.newton.atol = 1e-10 * scale
        self.params = params

    @classmethod
    def for_parameters(cls, geometry: Geometry, params: MaterialParameters, **kw):
        """A model compiled with exactly the physics ``params`` switches on."""
        if params.k_r_kPa_mm is not None or params.k_theta_kPa_mm is not None:
            kw["ends"] = "springs"
        mullins = kw.pop("mullins", False) or params.softening > 0
        return cls(geometry, n_terms=len(params.mu), maxwell=params.maxwell,
                   mullins=mullins, **kw)

    # ------------------------------------------------------------------ outputs
    def reactions(self) -> tuple[float, float]:
        """(axial force [mN], torque [mN mm]) on the top plate at the current state."""
        b = self.newton.assemble_residual(with_bcs=False)
        if self.ends == "springs":
            return (float(b.dot(self._w_axial)),
                    _compat.assemble_scalar(self._spring_torque_form, self.comm))
        return float(b.dot(self._w_axial)), float(b.dot(self._w_torque()))

    # ------------------------------------------------------------------ protocol
    FD_FLOOR = {"mu": 1e-2, "alpha": 1.0, "kappa": 1.0, "beta": 0.1, "tau": 1.0,
                "softening": 0.1, "softening_m": 1e-2, "k_r": 0.1, "k_theta": 0.1}

    def _fd_step(self, name: str) -> float:
        """Step of the central differences along the sensitivity path (relative 1e-6)."""
        base = name.rsplit("_", 1)[0] if name[-1].isdigit() else name
        return 1e-6 * max(abs(float(self.constants[name].value)), self.FD_FLOOR[base])

    def _sensitivity_names(self, sensitivities) -> tuple[list[str], list[str]]:
        """(model constants, artefacts) to differentiate for ``sensitivities``."""
        if not sensitivities:
            return [], []
        if sensitivities is True:
            return list(self.constants), []
        names = list(sensitivities)
        unknown = [n for n in names if n not in self.constants and n not in _art.NAMES]
        if unknown:
            raise ValueError(f"no sensitivity for {', '.join(unknown)}; this model has "
                             f"{', '.join(list(self.constants) + list(_art.NAMES))}")
        return ([n for n in names if n in self.constants],
                [n for n in names if n in _art.NAMES])

    def run(self, protocol: Protocol, params: MaterialParameters, *,
            max_cutbacks: int = 6, field_output: str | None = None,
            callback: Callable[[int, int], None] | None = None,
            sensitivities: bool | Sequence[str] = False,
            artefacts: Artefacts | None = None) -> pd.DataFrame:
        """Follow ``protocol`` from the undeformed state; one row per output point.

        Columns: ``time_s, cycle, branch, stretch|shear`` and then
        ``nominal_stress_kPa, axial_force_mN`` (compression/tension) or
        ``torque_mNmm, shear_stress_kPa, axial_force_mN`` (torsion).
        Raises :class:`ConvergenceError` when Newton fails after ``max_cutbacks`` halvings.

        ``sensitivities`` (True for every parameter constant of the model, or a list of
        names, which may include the artefact names) adds companions ``d_c/d_<name>`` to
        every output column ``c``: partial derivatives (kappa held fixed in ``d/d_mu_p``).
        Hyperelastic models differentiate by direct differentiation at each output point;
        models with history (or interface springs) follow the sensitivities along the path:
        z_n = -K^-1 dR/dtheta (with the history sensitivities), and the history
        sensitivities are carried step by step, the partial derivatives of the residual and
        of the history update taken by central differences of the compiled forms.
        Geometric artefacts are differentiated by central differences of whole runs.
        """
        art = artefacts or Artefacts()
        names, art_names = self._sensitivity_names(sensitivities)
        if protocol.test == "torsion" and self.ends == "slip":
            raise ValueError("torsion needs glued ends (frictionless plates cannot twist)")
        with _art.scaled_mesh(self.geometry, art):
            df = self._run(protocol, params, art, names, max_cutbacks, field_output, callback)
        R = self.geometry.radius_mm
        outputs = list(_art.offset_channels(protocol.test, R, art))
        for name in art_names:
            if name in _art.GEOMETRIC:
                h = 1e-5
                runs = []
                for sign in (1, -1):
                    a = art.replace(name, art.values()[name] + sign * h)
                    with _art.scaled_mesh(self.geometry, a):
                        runs.append(self._run(protocol, params, a, [], max_cutbacks, None, None))
                for c in outputs:
                    df[f"d_{c}/d_{name}"] = (runs[0][c] - runs[1][c]) / (2 * h)
            else:
                unit = _art.offset_channels(protocol.test, R, Artefacts(force_offset_mN=1.0)
                                            if name == "force_offset"
                                            else Artefacts(torque_offset_mNmm=1.0))
                for c in outputs:
                    df[f"d_{c}/d_{name}"] = unit[c]
        return df

    def _run(self, protocol, params, art, names, max_cutbacks, field_output, callback):
        if names and not self.path_sensitivities:
            self._compile_sensitivities()
        self.set_parameters(params)
        x = _compat.petsc_vec(self.u)
        x.set(0.0)
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        if self.history:
            self.state.x.array[:] = 0.0
        path = self.path_sensitivities and bool(names)
        if path:
            self._z = {n: x.duplicate() for n in names}
            for z in self._z.values():
                z.set(0.0)
            self._ds = {n: np.zeros_like(self.state.x.array) for n in names} if self.history \
                else {}
        prev = x.duplicate()
        saved = x.duplicate()
        x.copy(prev)
        steps = protocol.steps()
        R = self.geometry.radius_mm
        area = math.pi * R**2
        offsets = _art.offset_channels(protocol.test, R, art)

        def channels(fz, tq, offset=True):
            """Reported outputs of one test from the top-plate force and torque."""
            if protocol.test == "compression_tension":
                out = {"nominal_stress_kPa": fz / area, "axial_force_mN": fz}
            else:
                out = {"torque_mNmm": tq, "shear_stress_kPa": shear_stress_kPa(tq, R),
                       "axial_force_mN": fz}
            if offset:
                out = {k: v + offsets[k] for k, v in out.items()}
            return out

        writer = _FieldWriter(self, field_output) if field_output else None
        rows = []
        self.iterations = 0
        self.cutbacks = 0
        self.newton_log: list[tuple[float, list[float]]] = []  # (control value, |r| history)

        def converged(step: Step | None):
            """Book-keeping after a converged (sub)step: sensitivities, outputs, history."""
            sens = {}
            if path:
                sens = self._path_sensitivities(names, record=step is not None)
            elif names and step is not None:
                sens = self._sensitivities()
            if step is not None:
                fz, torque = self.reactions()
                row = {"time_s": step.time_s, "cycle": step.cycle, "branch": step.branch,
                       CONTROL[protocol.test]: step.value}
                row.update(channels(fz, torque))
                for name, (dfz, dtq) in sens.items():  # the channels are linear
                    row.update({f"d_{k}/d_{name}": v
                                for k, v in channels(dfz, dtq, offset=False).items()})
                rows.append(row)
                if writer:
                    writer.write(step.time_s)
            if self.history:
                self._update_state()

        pre = art.stretch_offset
        t_cur, q_cur, p_cur = steps[0].time_s, steps[0].value, 0.0
        q_prev = q_cur
        targets = [(t_cur, q_cur, pre, 0)]
        if pre:
            t_cur -= abs(pre) / protocol.rate_per_s  # the preload ends when the protocol starts
        else:
            self._set_control(protocol.test, q_cur)
            converged(steps[0])
            targets = []
        targets += [(s.time_s, s.value, pre, k) for k, s in enumerate(steps) if k > 0]
        for t_tg, q_tg, p_tg, k in targets:
            step = steps[k]
            while not (np.isclose(q_cur, q_tg, rtol=0, atol=1e-14)
                       and np.isclose(p_cur, p_tg, rtol=0, atol=1e-14)
                       and np.isclose(t_cur, t_tg, rtol=0, atol=1e-9)):
                frac = 1.0
                for _ in range(max_cutbacks + 1):
                    t_new = t_cur + frac * (t_tg - t_cur)
                    q_new = q_cur + frac * (q_tg - q_cur)
                    p_new = p_cur + frac * (p_tg - p_cur)
                    x.copy(saved)
                    dq = q_new - q_cur
                    if dq and q_cur != q_prev:  # linear extrapolation along the path
                        x.axpy(dq / (q_cur - q_prev), saved)
                        x.axpy(-dq / (q_cur - q_prev), prev)
                        x.ghostUpdate(addv=PETSc.InsertMode.INSERT,
                                      mode=PETSc.ScatterMode.FORWARD)
                    self.c_dt.value = max(t_new - t_cur, 1e-12)
                    self._set_control(protocol.test, q_new, p_new)
                    rep = self.newton.solve()
                    self.iterations += rep.iterations
                    self.newton_log.append((q_new, rep.residuals))
                    if rep.converged:
                        break
                    log.info("Newton failed at %s = %.5g (%s); cutting the step back",
                             protocol.control, q_new, rep.reason)
                    saved.copy(x)
                    x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
                    frac /= 2
                    self.cutbacks += 1
                else:
                    raise ConvergenceError(
                        f"{protocol.test}: Newton failed at {protocol.control} = {q_new:.5g} "
                        f"after {max_cutbacks} step cut-backs ({rep.reason}); "
                        f"parameters mu={params.mu}, alpha={params.alpha}, "
                        f"kappa={params.kappa_kPa:.4g} kPa")
                if dq:
                    saved.copy(prev)
                    q_prev = q_cur
                t_cur, q_cur, p_cur = t_new, q_new, p_new
                last = frac == 1.0
                converged(step if last else None)
            if callback:
                callback(k + 1, len(steps))
        if writer:
            writer.close()
        return pd.DataFrame(rows)

    # ------------------------------------------------------------------ history
    def _eval_state(self) -> np.ndarray:
        """The history update G(u, state, parameters) at every quadrature point."""
        vals = _compat.eval_expression(self._state_expr, self.geometry.mesh, self._cells)
        return np.asarray(vals).reshape(len(self._cells), -1)

    def _update_state(self) -> None:
        self.state.x.array[self._state_index] = self._eval_state()

    def _path_sensitivities(self, names, record: bool) -> dict[str, tuple[float, float]]:
        """Carry z = du/dtheta and the history sensitivities over a converged (sub)step.

        With D the derivative along the path direction (theta + e, state + ds, u + z):
        K z = -(dR/dtheta + dR/dstate ds), d reaction = D reaction, ds <- D G. The partial
        derivatives are central differences of the compiled residual and history update.
        """
        self.newton.ensure_factorised()
        x = _compat.petsc_vec(self.u)
        u0 = x.copy()
        s0 = self.state.x.array.copy() if self.history else None
        r_plus = x.duplicate()
        out, new_ds = {}, {}
        theta0 = {n: float(self.constants[n].value) for n in names}

        def perturb(name, h, with_u):
            c = self.constants[name]
            c.value = theta0[name] + h
            if self.history:
                self.state.x.array[:] = s0 + h * self._ds[name]
            if with_u:
                u0.copy(x)
                x.axpy(h, self._z[name])
                x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)

        def restore(name):
            self.constants[name].value = theta0[name]
            if self.history:
                self.state.x.array[:] = s0
            u0.copy(x)
            x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)

        for name in names:
            eps = self._fd_step(name)
            # right-hand side: -(explicit + history) derivative of the residual at fixed u
            perturb(name, eps, False)
            self.newton.assemble_residual(with_bcs=False).copy(r_plus)
            perturb(name, -eps, False)
            rhs = self.newton.assemble_residual(with_bcs=False).copy()
            rhs.axpy(-1.0, r_plus)
            rhs.scale(1.0 / (2 * eps))
            restore(name)
            _compat.set_bc(rhs, self.bcs, x, 0.0)
            z = self._z[name]
            self.newton.ksp.solve(rhs, z)
            z.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            if record:
                perturb(name, eps, True)
                fp = np.array(self.reactions())
                perturb(name, -eps, True)
                fm = np.array(self.reactions())
                out[name] = tuple((fp - fm) / (2 * eps))
            if self.history:
                perturb(name, eps, True)
                gp = self._eval_state()
                perturb(name, -eps, True)
                gm = self._eval_state()
                ds = np.empty_like(s0)
                ds[self._state_index] = (gp - gm) / (2 * eps)
                new_ds[name] = ds
            restore(name)
        self._ds.update(new_ds)
        return out


class _FieldWriter:
    """Displacement (and twist) field per output step, XDMF on a P1 interpolation."""

    def __init__(self, model: ForwardModel, path: str):
        self.file = _compat.xdmf_file(model.comm, path)
        self.file.write_mesh(model.geometry.mesh)
        self.model = model
        self.out = fem.Function(_compat.vector_space(model.geometry.mesh, 1, 3),
                                name="u_r,u_z,phi" if model.geometry.kind == "axisymmetric"
                                else "displacement")

    def write(self, t: float):
        self.out.interpolate(self.model.u)
        self.file.write_function(self.out, t)

    def close(self):
        self.file.close()


def simulate(geometry: Geometry, protocols: Sequence[Protocol], params: MaterialParameters,
             *, volumetric: str = "quadratic", ends: str = "glued") -> dict[str, pd.DataFrame]:
    """Convenience wrapper: one compiled model, several protocols."""
    model = ForwardModel(geometry, n_terms=len(params.mu), volumetric=volumetric, ends=ends)
    out = {}
    for p in protocols:
        key = p.test if p.test == "compression_tension" else f"torsion_{p.amplitude:.2f}"
        out[key] = model.run(p, params)
    return out
