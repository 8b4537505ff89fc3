"""End conditions at the plates, and the reactions measured on the top plate.

* ``glued`` (default): every displacement component fixed on the bottom; on the top u_r = 0
  (u_x = u_y = 0 in 3D) and the axial displacement or the rotation prescribed.
* ``slip``: frictionless plates, only the axial component constrained (plus what removes
  rigid motion); torsion is impossible.
* ``springs`` (axisymmetric): a glue layer of finite tangential stiffness per area, energy
  1/2 k_r u_r^2 + 1/2 k_theta (R (phi - phi_plate))^2 on both end faces; k -> infinity is
  glued, k_r = 0 is slip radially.  Its stiffnesses are the parameters ``k_r``, ``k_theta``
  (:class:`Interface`).
* ``unglued`` (a shorthand of the forward model): glued tangentially, but the plate cannot
  pull: rough (sandblasted) plates without glue, where the top plate lifts off instead of
  pulling and touches the specimen again on reloading (:mod:`brain_fe.contact`).  Any
  end condition can be made unable to pull (``ForwardModel(..., lift_off=True)``).

The reactions (axial force, torque) are the action of the assembled residual on the virtual
rigid motion of the top plate (reaction by virtual work), reduced over MPI ranks; with
springs the torque is the glue layer's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import dolfinx.fem as fem
import numpy as np
import ufl

from . import _compat
from .parameters import K_R, K_THETA, Param, Parameters

ENDS = ("glued", "slip", "springs")
UNGLUED = "unglued"  # = glued tangentially + lift-off (:func:`resolve`)
UR, UZ, PHI = 0, 1, 2  # components of the axisymmetric unknown


@dataclass(frozen=True)
class Interface:
    """Tangential stiffness per area of the glue layer [kPa/mm] (``ends="springs"``)."""

    k_r_kPa_mm: float
    k_theta_kPa_mm: float

    def __post_init__(self):
        for k in (self.k_r_kPa_mm, self.k_theta_kPa_mm):
            if not (math.isfinite(k) and k >= 0):
                raise ValueError("interface stiffnesses must be finite and >= 0")

    def values(self) -> Parameters:
        return Parameters({K_R: self.k_r_kPa_mm, K_THETA: self.k_theta_kPa_mm})


def resolve(ends: str, lift_off: bool = False) -> tuple[str, bool]:
    """(tangential end condition, whether the plate cannot pull) of ``ends``."""
    return ("glued", True) if ends == UNGLUED else (ends, lift_off)


def check_ends(ends: str, geometry_kind: str, test: str | None = None) -> None:
    """The one check of an end condition against the geometry and the test."""
    ends = resolve(ends)[0]
    if ends not in ENDS:
        raise ValueError(f"ends must be one of {', '.join((*ENDS, UNGLUED))}, "
                         f"got {ends!r}")
    if ends == "springs" and geometry_kind != "axisymmetric":
        raise ValueError("interface springs are implemented for the axisymmetric model")
    if test == "torsion" and ends == "slip":
        raise ValueError("torsion needs glued ends (frictionless plates cannot twist)")


class EndConditions:
    """Dirichlet conditions, glue-layer energy and top-plate reactions of one model.

    ``c_axial``/``c_twist``: constants of the top plate's axial displacement [mm] and
    rotation [rad]; ``consts``: the model's parameter constants (k_r, k_theta for springs).
    """

    def __init__(self, kind: str, geometry, V, u, c_axial, c_twist, consts: dict):
        check_ends(kind, geometry.kind)
        self.kind, self.geometry, self.V, self.u = kind, geometry, V, u
        self.c_axial, self.c_twist, self.consts = c_axial, c_twist, consts
        self.g_top = None  # 3D glued: top displacement field (rotation + axial shift)
        self.spring_torque_form = None
        zero = fem.Constant(geometry.mesh, _compat.scalar_type()(0.0))
        self.bcs = (self._axisymmetric(zero) if geometry.kind == "axisymmetric"
                    else self._three_d(zero))

    @staticmethod
    def parameters(kind: str) -> tuple[Param, ...]:
        return (K_R, K_THETA) if kind == "springs" else ()

    def glue_energy(self):
        """Energy of the glue layer on both end faces (axisymmetric, dA = 2 pi R dR), and
        the compiled form of its torque on the top plate; None without springs."""
        if self.kind != "springs":
            return None
        g = self.geometry
        ds = _compat.facet_measure(g, g.quadrature_degree)
        top, bottom = (g.markers[n].tag for n in ("top", "bottom"))
        Rr = ufl.SpatialCoordinate(g.mesh)[0]
        u_r, phi = self.u[0], self.u[2]
        k_r, k_t = self.consts[K_R], self.consts[K_THETA]
        w = 2 * math.pi * Rr
        e_top = 0.5 * (k_r * u_r**2 + k_t * (Rr * (phi - self.c_twist)) ** 2)
        e_bot = 0.5 * (k_r * u_r**2 + k_t * (Rr * phi) ** 2)
        # torque of the glue layer on the top plate, in the sense of the twist
        self.spring_torque_form = _compat.form(
            k_t * Rr**2 * (self.c_twist - phi) * w * ds(top))
        return e_top * w * ds(top) + e_bot * w * ds(bottom)

    def top_cells(self) -> np.ndarray:
        """The owned cells with a degree of freedom on the top face: the only cells that
        add to the reactions (the rows of the top plate's dofs)."""
        top = self._dofs(None, "top")  # block indices, owned and ghost
        owned = self.geometry.mesh.topology.index_map(self.geometry.mesh.topology.dim)
        cells = _compat.dofmap_array(self.V)[:owned.size_local]
        return np.flatnonzero(np.isin(cells, top).any(axis=1)).astype(np.int32)

    # ------------------------------------------------------------------ conditions
    def _dofs(self, sub: int | None, facet_name: str) -> np.ndarray:
        return _compat.locate_dofs(self.V, sub, self.geometry.fdim,
                                   self.geometry.facets(facet_name))

    def _indicator(self, dofs: np.ndarray, values: np.ndarray | float = 1.0):
        """PETSc vector with ``values`` at the owned entries of ``dofs``, zero elsewhere."""
        w = _compat.petsc_vec(self.u).duplicate()  # the residual's layout
        w.set(0.0)
        arr = w.getArray()
        vals = np.broadcast_to(np.asarray(values, dtype=float), dofs.shape)
        keep = dofs < len(arr)
        arr[dofs[keep]] = vals[keep]
        w.setArray(arr)
        return w

    def _axisymmetric(self, zero):
        V = self.V
        bcs = [fem.dirichletbc(zero, self._dofs(UR, "axis"), V.sub(UR))]
        # springs: the glue layer, not a constraint, holds u_r and phi on both ends
        bottom = {"glued": [UZ, PHI, UR], "slip": [UZ, PHI], "springs": [UZ]}[self.kind]
        for c in bottom:
            bcs.append(fem.dirichletbc(zero, self._dofs(c, "bottom"), V.sub(c)))
        if self.kind == "glued":
            bcs.append(fem.dirichletbc(zero, self._dofs(UR, "top"), V.sub(UR)))
        top_uz, top_phi = self._dofs(UZ, "top"), self._dofs(PHI, "top")
        bcs.append(fem.dirichletbc(self.c_axial, top_uz, V.sub(UZ)))
        if self.kind != "springs":
            bcs.append(fem.dirichletbc(self.c_twist, top_phi, V.sub(PHI)))
        self.w_axial = self._indicator(top_uz)
        self._w_torque_axi = self._indicator(top_phi)
        return bcs

    def _three_d(self, zero):
        st = _compat.scalar_type()
        V, msh = self.V, self.geometry.mesh
        bcs = []
        coords = V.tabulate_dof_coordinates()
        if self.kind == "glued":
            self.g_top = fem.Function(V)
            top = self._dofs(None, "top")
            bcs.append(fem.dirichletbc(fem.Constant(msh, np.zeros(3, dtype=st)),
                                       self._dofs(None, "bottom"), V))
            bcs.append(fem.dirichletbc(self.g_top, top))
            self._top_nodes = top  # blocked space: these are node (block) indices
            self._top_xy = coords[top, :2]
        else:
            bcs.append(fem.dirichletbc(zero, self._dofs(2, "bottom"), V.sub(2)))
            # Rigid in-plane motion removed at points where the symmetric solution has
            # zero lateral displacement: the bottom centre (u_x = u_y = 0) and the bottom
            # rim point on the x axis (u_y = 0). Both are mesh nodes (see cylinder3d).
            R = self.geometry.radius_mm
            for sub, where in ((0, lambda p: np.isclose(p[0], 0) & np.isclose(p[1], 0)),
                              (1, lambda p: np.isclose(p[1], 0) & (np.isclose(p[0], 0)
                                                                   | np.isclose(p[0], R)))):
                pts = lambda p, w=where: w(p) & np.isclose(p[2], 0.0)  # noqa: E731
                Vs, _ = V.sub(sub).collapse()
                dofs = fem.locate_dofs_geometrical((V.sub(sub), Vs), pts)[0]
                bcs.append(fem.dirichletbc(zero, dofs, V.sub(sub)))
        top_z = self._dofs(2, "top")
        if self.kind == "slip":
            bcs.append(fem.dirichletbc(self.c_axial, top_z, V.sub(2)))
        self.w_axial = self._indicator(top_z)
        self._top_x_dofs, self._top_y_dofs = self._dofs(0, "top"), self._dofs(1, "top")
        self._coords = coords
        return bcs

    # ------------------------------------------------------------------ plate motion
    def set_top(self, uz: float, twist: float) -> None:
        """Axial displacement [mm] and rotation [rad] of the top plate."""
        self.c_axial.value = uz
        self.c_twist.value = twist
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

    def set_axial(self, uz: float) -> None:
        """Axial displacement [mm] of the top face at the current rotation (off the plate,
        :mod:`brain_fe.contact`)."""
        self.set_top(uz, float(self.c_twist.value))

    def w_torque(self):
        """Virtual rotation of the top plate (3D: about z at the current twist)."""
        if self.geometry.kind == "axisymmetric":
            return self._w_torque_axi
        th = float(self.c_twist.value)
        c, s = math.cos(th), math.sin(th)
        X = self._coords[self._top_x_dofs // 3]
        Y = self._coords[self._top_y_dofs // 3]
        w = self._indicator(self._top_x_dofs, -(X[:, 0] * s + X[:, 1] * c))
        w.axpy(1.0, self._indicator(self._top_y_dofs, Y[:, 0] * c - Y[:, 1] * s))
        return w

    def reactions(self, residual, comm) -> tuple[float, float]:
        """(axial force [mN], torque [mN mm]) from the assembled residual (no BC rows)."""
        fz = float(residual.dot(self.w_axial))
        if self.kind == "springs":
            return fz, _compat.assemble_scalar(self.spring_torque_form, comm)
        return fz, float(residual.dot(self.w_torque()))

    @staticmethod
    def tension(fz: float) -> float:
        """The pull of the top plate on the specimen in an axial reaction ``fz`` (> 0:
        tensile; the reactions count tension positive)."""
        return fz

    def directional(self, vector) -> tuple[float, float]:
        """(axial, torque) components of a residual-like vector (sensitivities)."""
        return float(vector.dot(self.w_axial)), float(vector.dot(self.w_torque()))
