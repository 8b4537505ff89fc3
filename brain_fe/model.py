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
from .geometry import Geometry
from .material import VOLUMETRIC, CompressibleMaterial, Ogden, kappa_from_nu0
from .protocols import CONTROL, Protocol
from .solver import ConvergenceError, NewtonSolver

log = logging.getLogger(__name__)

ENDS = ("glued", "slip")


@dataclass(frozen=True)
class MaterialParameters:
    """N-term Ogden parameters (mu_p in kPa, alpha_p dimensionless) and compressibility.

    ``kappa`` [kPa] wins over ``nu0``; otherwise kappa = 2 mu (1 + nu0) / (3 (1 - 2 nu0))
    with mu = sum(mu_p).
    """

    mu: tuple[float, ...]
    alpha: tuple[float, ...]
    nu0: float | None = 0.49
    kappa: float | None = None

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

    @property
    def mu_total(self) -> float:
        return float(sum(self.mu))

    @property
    def kappa_kPa(self) -> float:
        if self.kappa is not None:
            return float(self.kappa)
        return kappa_from_nu0(self.mu_total, float(self.nu0))


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
    ends: ``glued`` (no slip at the plates) or ``slip`` (frictionless plates).
    degree: polynomial degree of the displacement (and twist) field.
    """

    def __init__(self, geometry: Geometry, n_terms: int = 1, volumetric: str = "quadratic",
                 ends: str = "glued", degree: int = 2):
        if ends not in ENDS:
            raise ValueError(f"ends must be one of {', '.join(ENDS)}, got {ends!r}")
        if volumetric not in VOLUMETRIC:
            raise ValueError(f"volumetric must be one of {', '.join(VOLUMETRIC)}")
        self.geometry = geometry
        self.ends = ends
        self.n_terms = int(n_terms)
        msh = geometry.mesh
        self.comm = msh.comm
        self.V = _compat.vector_space(msh, degree, 3)
        self.u = fem.Function(self.V, name="displacement")
        v = ufl.TestFunction(self.V)
        du = ufl.TrialFunction(self.V)
        st = _compat.scalar_type()
        self.c_mu = [fem.Constant(msh, st(1.0)) for _ in range(self.n_terms)]
        self.c_alpha = [fem.Constant(msh, st(-20.0)) for _ in range(self.n_terms)]
        self.c_kappa = fem.Constant(msh, st(100.0))
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
        self.energy_density = self.material.strain_energy(C, J=ufl.det(F))
        self._weight = weight
        Pi = self.energy_density * weight * geometry.dx
        R = ufl.derivative(Pi, self.u, v)
        self._residual_ufl = R
        Jac = ufl.derivative(R, self.u, du)
        t0 = time.perf_counter()
        self.residual_form = _compat.form(R)
        self.jacobian_form = _compat.form(Jac)
        self.energy_form = _compat.form(Pi)
        self.compile_time_s = time.perf_counter() - t0
        log.debug("compiled %s forms in %.1f s", geometry.kind, self.compile_time_s)
        self._setup_bcs()
        self.newton = NewtonSolver(self.comm, self.residual_form, self.jacobian_form, self.u,
                                   self.bcs)
        self._sens_forms = None

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
        self.c_top_axial = fem.Constant(msh, st(0.0))  # top axial displacement [mm]
        self.c_top_twist = fem.Constant(msh, st(0.0))  # top rotation angle [rad]
        zero = fem.Constant(msh, st(0.0))
        self.g_top = None  # 3D glued: top displacement field (rotation + axial shift)
        bcs = []
        if self.geometry.kind == "axisymmetric":
            UR, UZ, PHI = 0, 1, 2
            bcs.append(fem.dirichletbc(zero, self._dofs(UR, "axis"), self.V.sub(UR)))
            bottom = [UZ, PHI] + ([UR] if self.ends == "glued" else [])
            for c in bottom:
                bcs.append(fem.dirichletbc(zero, self._dofs(c, "bottom"), self.V.sub(c)))
            if self.ends == "glued":
                bcs.append(fem.dirichletbc(zero, self._dofs(UR, "top"), self.V.sub(UR)))
            top_uz, top_phi = self._dofs(UZ, "top"), self._dofs(PHI, "top")
            bcs.append(fem.dirichletbc(self.c_top_axial, top_uz, self.V.sub(UZ)))
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

    def _set_control(self, test: str, value: float):
        H, R = self.geometry.height_mm, self.geometry.radius_mm
        if test == "compression_tension":
            uz, twist = (value - 1.0) * H, 0.0
        else:
            uz, twist = 0.0, value * H / R
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
    def set_parameters(self, params: MaterialParameters):
        if len(params.mu) != self.n_terms:
            raise ValueError(f"model compiled for {self.n_terms} Ogden term(s), "
                             f"got {len(params.mu)}")
        for c, v in zip(self.c_mu, params.mu, strict=True):
            c.value = v
        for c, v in zip(self.c_alpha, params.alpha, strict=True):
            c.value = v
        self.c_kappa.value = params.kappa_kPa
        scale = params.mu_total * math.pi * self.geometry.radius_mm ** 2  # mN
        self.newton.atol = 1e-10 * scale

    # ------------------------------------------------------------------ outputs
    def reactions(self) -> tuple[float, float]:
        """(axial force [mN], torque [mN mm]) on the top plate at the current state."""
        b = self.newton.assemble_residual(with_bcs=False)
        return float(b.dot(self._w_axial)), float(b.dot(self._w_torque()))

    # ------------------------------------------------------------------ protocol
    def run(self, protocol: Protocol, params: MaterialParameters, *,
            max_cutbacks: int = 6, field_output: str | None = None,
            callback: Callable[[int, int], None] | None = None,
            sensitivities: bool = False) -> pd.DataFrame:
        """Follow ``protocol`` from the undeformed state; one row per output point.

        Columns: ``time_s, cycle, branch, stretch|shear`` and then
        ``nominal_stress_kPa, axial_force_mN`` (compression/tension) or
        ``torque_mNmm, shear_stress_kPa, axial_force_mN`` (torsion).
        Raises :class:`ConvergenceError` when Newton fails after ``max_cutbacks`` halvings.

        With ``sensitivities``, every output column ``c`` gets companions ``d_c/d_mu_0``,
        ``d_c/d_alpha_0`` ..., ``d_c/d_kappa`` (partial derivatives with respect to the
        parameter constants; kappa is held fixed in ``d/d_mu_p``).
        """
        if sensitivities:
            self._compile_sensitivities()
        if protocol.test == "torsion" and self.ends == "slip":
            raise ValueError("torsion needs glued ends (frictionless plates cannot twist)")
        self.set_parameters(params)
        x = _compat.petsc_vec(self.u)
        x.set(0.0)
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        prev = x.duplicate()
        saved = x.duplicate()
        x.copy(prev)
        q_prev = q_cur = protocol.steps()[0].value
        self._set_control(protocol.test, q_cur)
        R = self.geometry.radius_mm
        area = math.pi * R**2

        def channels(fz, tq):
            """Reported outputs of one test from the top-plate force and torque."""
            if protocol.test == "compression_tension":
                return {"nominal_stress_kPa": fz / area, "axial_force_mN": fz}
            return {"torque_mNmm": tq, "shear_stress_kPa": shear_stress_kPa(tq, R),
                    "axial_force_mN": fz}

        writer = _FieldWriter(self, field_output) if field_output else None
        rows = []
        steps = protocol.steps()
        self.iterations = 0
        self.cutbacks = 0
        self.newton_log: list[tuple[float, list[float]]] = []  # (control value, |r| history)
        for i, step in enumerate(steps):
            target = step.value
            while not np.isclose(q_cur, target, rtol=0, atol=1e-14):
                dq = target - q_cur
                for _ in range(max_cutbacks + 1):
                    q_new = q_cur + dq
                    x.copy(saved)
                    if q_cur != q_prev:  # linear extrapolation along the path
                        x.axpy(dq / (q_cur - q_prev), saved)
                        x.axpy(-dq / (q_cur - q_prev), prev)
                        x.ghostUpdate(addv=PETSc.InsertMode.INSERT,
                                      mode=PETSc.ScatterMode.FORWARD)
                    self._set_control(protocol.test, q_new)
                    rep = self.newton.solve()
                    self.iterations += rep.iterations
                    self.newton_log.append((q_new, rep.residuals))
                    if rep.converged:
                        break
                    log.info("Newton failed at %s = %.5g (%s); cutting the step back",
                             protocol.control, q_new, rep.reason)
                    saved.copy(x)
                    x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
                    dq /= 2
                    self.cutbacks += 1
                else:
                    raise ConvergenceError(
                        f"{protocol.test}: Newton failed at {protocol.control} = {q_new:.5g} "
                        f"after {max_cutbacks} step cut-backs ({rep.reason}); "
                        f"parameters mu={params.mu}, alpha={params.alpha}, "
                        f"kappa={params.kappa_kPa:.4g} kPa")
                saved.copy(prev)
                q_prev, q_cur = q_cur, q_new
            fz, torque = self.reactions()
            row = {"time_s": step.time_s, "cycle": step.cycle, "branch": step.branch,
                   CONTROL[protocol.test]: step.value}
            row.update(channels(fz, torque))
            if sensitivities:  # the channels are linear in (force, torque)
                for name, (dfz, dtq) in self._sensitivities().items():
                    row.update({f"d_{k}/d_{name}": v for k, v in channels(dfz, dtq).items()})
            rows.append(row)
            if writer:
                writer.write(step.time_s)
            if callback:
                callback(i + 1, len(steps))
        if writer:
            writer.close()
        return pd.DataFrame(rows)


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
