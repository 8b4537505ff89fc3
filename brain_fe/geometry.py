"""Specimen geometries: the (R, Z) half-plane of the axisymmetric model and the 3D gmsh cylinder.

Both are dataclasses holding the mesh, named facet markers, the integration measure with an
explicit quadrature degree (the automatic estimate explodes for spectral materials) and
their kinematics: the deformation gradient of the displacement unknowns and the volume
weight.  Lengths in mm.

Axisymmetric with twist (DESIGN.md section 3): unknowns w = (u_r, u_z, phi) on the (R, Z)
rectangle, r = R + u_r, z = Z + u_z; with rows (e_r, e_theta, e_z) and columns
(E_R, E_Theta, E_Z)::

    F = [[1 + du_r/dR,  0,    du_r/dZ    ],
         [r dphi/dR,    r/R,  r dphi/dZ  ],
         [du_z/dR,      0,    1 + du_z/dZ]]      dV = 2 pi R dR dZ
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import ufl
from dolfinx import mesh as dmesh
from mpi4py import MPI

from . import _compat

log = logging.getLogger(__name__)

BOTTOM, TOP, LATERAL, AXIS = 1, 2, 3, 4
GRADING_R, GRADING_Z = 0.9, 0.95
RIM_SIZE_FACTOR = 0.15  # 3D: element size at the glued rims relative to the bulk
# <= 1 % force error on the default protocols (BENCHMARKS.md)
DEFAULT_REFINEMENT = {"axisymmetric": 2, "3d": 2}
KINDS = tuple(DEFAULT_REFINEMENT)


@dataclass(frozen=True)
class Marker:
    name: str
    tag: int
    dim: int


@dataclass
class Geometry:
    """Mesh with named facet markers. ``kind`` is ``"axisymmetric"`` or ``"3d"``."""

    kind: str
    mesh: object
    facet_tags: object
    radius_mm: float
    height_mm: float
    refinement: int
    quadrature_degree: int
    markers: dict[str, Marker] = field(default_factory=dict)

    def __post_init__(self):
        _compat.equispaced_coordinates(self.mesh)  # stable JIT cache keys of its forms

    @property
    def dx(self):
        return ufl.Measure("dx", domain=self.mesh,
                           metadata={"quadrature_degree": self.quadrature_degree})

    def facets(self, name: str) -> np.ndarray:
        return self.facet_tags.find(self.markers[name].tag)

    @property
    def fdim(self) -> int:
        return self.mesh.topology.dim - 1

    def deformation_gradient(self, u):
        """F of the displacement unknowns ``u`` (axisymmetric: (u_r, u_z, phi))."""
        if self.kind != "axisymmetric":
            return ufl.Identity(3) + ufl.grad(u)
        R = ufl.SpatialCoordinate(self.mesh)[0]
        g = ufl.grad(u)
        r = R + u[0]
        return ufl.as_matrix([[1 + g[0, 0], 0, g[0, 1]],
                              [r * g[2, 0], r / R, r * g[2, 1]],
                              [g[1, 0], 0, 1 + g[1, 1]]])

    def volume_weight(self):
        """dV / (dx of the mesh): 2 pi R on the axisymmetric half-plane, 1 in 3D."""
        if self.kind != "axisymmetric":
            return 1.0
        return 2 * math.pi * ufl.SpatialCoordinate(self.mesh)[0]


def _tag_facets(msh, locators: dict[int, callable]):
    fdim = msh.topology.dim - 1
    idx, vals = [], []
    for tag, where in locators.items():
        f = dmesh.locate_entities_boundary(msh, fdim, where)
        idx.append(f)
        vals.append(np.full(len(f), tag, dtype=np.int32))
    idx = np.concatenate(idx)
    vals = np.concatenate(vals)
    order = np.argsort(idx, kind="stable")
    # A corner facet cannot belong to two lines in 2D; keep the first tag seen.
    idx, first = np.unique(idx[order], return_index=True)
    return dmesh.meshtags(msh, fdim, idx.astype(np.int32), vals[order][first])


def _check(radius_mm: float, height_mm: float, refinement) -> int:
    if not (math.isfinite(radius_mm) and math.isfinite(height_mm)
            and radius_mm > 0 and height_mm > 0):
        raise ValueError("radius and height must be positive numbers")
    if int(refinement) != refinement or refinement < 1:
        raise ValueError(f"refinement must be a whole number >= 1, got {refinement}")
    return int(refinement)


def axisymmetric(radius_mm: float = 4.0, height_mm: float = 5.0,
                 refinement: int = DEFAULT_REFINEMENT["axisymmetric"],
                 comm=MPI.COMM_WORLD, quadrature_degree: int = 4) -> Geometry:
    """Structured quadrilateral mesh of the (R, Z) rectangle, graded towards the glued
    rim (R = radius, Z in {0, H}) where the edge singularity sits.

    ``refinement`` k gives 4k x 5k cells (Q2 displacement + twist on top of it).
    """
    k = _check(radius_mm, height_mm, refinement)
    nr, nz = 4 * k, max(2, round(5 * k * height_mm / (1.25 * radius_mm)))
    msh = dmesh.create_rectangle(comm, [np.array([0.0, 0.0]), np.array([1.0, 1.0])], [nr, nz],
                                 cell_type=dmesh.CellType.quadrilateral)
    x = msh.geometry.x
    xi, eta = x[:, 0].copy(), x[:, 1].copy()
    # Radial cells 1.9x the mean at the axis, 0.1x at the rim; axial cells 0.05x at both
    # ends, 1.95x at mid-height: the force error at the glued rim (an edge singularity)
    # drops from 0.9 % to 0.3 % at k = 2 compared with a mild grading (BENCHMARKS.md).
    x[:, 0] = radius_mm * (xi + GRADING_R * xi * (1.0 - xi))
    x[:, 1] = height_mm * (eta - GRADING_Z * np.sin(2 * np.pi * eta) / (2 * np.pi))
    tol = 1e-9 * max(radius_mm, height_mm)
    ft = _tag_facets(msh, {
        BOTTOM: lambda p: np.isclose(p[1], 0.0, atol=tol),
        TOP: lambda p: np.isclose(p[1], height_mm, atol=tol),
        AXIS: lambda p: np.isclose(p[0], 0.0, atol=tol),
        LATERAL: lambda p: np.isclose(p[0], radius_mm, atol=tol),
    })
    markers = {m.name: m for m in (Marker("bottom", BOTTOM, 1), Marker("top", TOP, 1),
                                   Marker("axis", AXIS, 1), Marker("lateral", LATERAL, 1))}
    return Geometry("axisymmetric", msh, ft, radius_mm, height_mm, k, quadrature_degree, markers)


def cylinder3d(radius_mm: float = 4.0, height_mm: float = 5.0, refinement: int = 1,
               comm=MPI.COMM_WORLD, quadrature_degree: int = 2, order: int = 2) -> Geometry:
    """gmsh cylinder (axis z, bottom at z = 0), curved second-order tetrahedra.

    ``refinement`` k gives a target element size of radius / (2 k), reduced by
    ``RIM_SIZE_FACTOR`` at the glued rims (edge singularity). Built on rank 0 with one
    gmsh thread and distributed by DOLFINx.
    """
    import gmsh

    k = _check(radius_mm, height_mm, refinement)
    h = radius_mm / (2.0 * k)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("cylinder")
        if comm.rank == 0:
            gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, height_mm, radius_mm)
            # Nodes at the centres of the end faces (rigid-motion constraints, slip ends)
            centres = [gmsh.model.occ.addPoint(0, 0, z) for z in (0.0, height_mm)]
            gmsh.model.occ.synchronize()
            vol = gmsh.model.getEntities(3)
            bottom, top, lateral = [], [], []
            for dim, tag in gmsh.model.getEntities(2):
                z = gmsh.model.occ.getCenterOfMass(dim, tag)[2]
                if np.isclose(z, 0.0):
                    bottom.append(tag)
                elif np.isclose(z, height_mm):
                    top.append(tag)
                else:
                    lateral.append(tag)
            for pt, face in zip(centres, bottom + top, strict=True):
                gmsh.model.mesh.embed(0, [pt], 2, face)
            gmsh.model.addPhysicalGroup(3, [t for _, t in vol], 1)
            gmsh.model.addPhysicalGroup(2, bottom, BOTTOM)
            gmsh.model.addPhysicalGroup(2, top, TOP)
            gmsh.model.addPhysicalGroup(2, lateral, LATERAL)
            # Finer at the two rims (circles), where glued ends concentrate strain.
            rims = [t for _, t in gmsh.model.getEntities(1)
                    if gmsh.model.occ.getMass(1, t) > 1.0 * radius_mm]
            fdist = gmsh.model.mesh.field.add("Distance")
            gmsh.model.mesh.field.setNumbers(fdist, "CurvesList", rims)
            fth = gmsh.model.mesh.field.add("Threshold")
            gmsh.model.mesh.field.setNumber(fth, "InField", fdist)
            gmsh.model.mesh.field.setNumber(fth, "SizeMin", h * RIM_SIZE_FACTOR)
            gmsh.model.mesh.field.setNumber(fth, "SizeMax", h)
            gmsh.model.mesh.field.setNumber(fth, "DistMin", 0.02 * radius_mm)
            gmsh.model.mesh.field.setNumber(fth, "DistMax", 0.6 * radius_mm)
            gmsh.model.mesh.field.setAsBackgroundMesh(fth)
            gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
            gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
            gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
            gmsh.model.mesh.generate(3)
            gmsh.model.mesh.setOrder(order)
        msh, _, ft = _compat.model_to_mesh(gmsh.model, comm, 0, gdim=3)
    finally:
        gmsh.finalize()
    markers = {m.name: m for m in (Marker("bottom", BOTTOM, 2), Marker("top", TOP, 2),
                                   Marker("lateral", LATERAL, 2))}
    ncells = msh.topology.index_map(3).size_global
    log.info("3D cylinder R=%g H=%g k=%d: %d cells", radius_mm, height_mm, k, ncells)
    return Geometry("3d", msh, ft, radius_mm, height_mm, k, quadrature_degree, markers)


def make(kind: str = "axisymmetric", radius_mm: float = 4.0, height_mm: float = 5.0,
         refinement: int | None = None, comm=MPI.COMM_WORLD) -> Geometry:
    """The geometry of ``kind`` (``axisymmetric`` or ``3d``) at its default refinement."""
    if kind not in KINDS:
        raise ValueError(f"model must be 'axisymmetric' or '3d', got {kind!r}")
    k = DEFAULT_REFINEMENT[kind] if refinement is None else refinement
    return (axisymmetric if kind == "axisymmetric" else cylinder3d)(radius_mm, height_mm, k,
                                                                      comm=comm)
