"""The one place for DOLFINx / UFL version differences.

Tested with DOLFINx 0.5.2 (Debian 12) and 0.9.0 (Debian 13). Every switch is decided by
feature detection, never by comparing version strings, so a new release only needs the
branch for the feature that changed (0.10 moved ``gmshio`` to ``dolfinx.io.gmsh`` and
``model_to_mesh`` returns a ``MeshData`` object; both are handled below).
"""

from __future__ import annotations

import inspect
import itertools
import os
import platform
from typing import Any

import dolfinx
import dolfinx.fem as fem
import dolfinx.fem.petsc as fem_petsc
import numpy as np
import ufl

from . import jit_cache

DOLFINX_VERSION: str = dolfinx.__version__
jit_cache.install()  # every compilation of this process under the JIT cache's lock

__all__ = [
    "DOLFINX_VERSION",
    "vector_space",
    "scalar_space",
    "stable_constant_counts",
    "fresh_label_counts",
    "equispaced_coordinates",
    "form",
    "petsc_vec",
    "apply_lifting",
    "set_bc",
    "model_to_mesh",
    "xdmf_file",
]


def vector_space(mesh, degree: int, dim: int):
    """Continuous Lagrange space of ``dim`` components (any dim, e.g. 3 on a 2D mesh)."""
    if hasattr(fem, "functionspace"):  # >= 0.8
        return fem.functionspace(mesh, ("Lagrange", degree, (dim,)))
    return fem.VectorFunctionSpace(mesh, ("Lagrange", degree), dim=dim)


def scalar_space(mesh, degree: int):
    if hasattr(fem, "functionspace"):
        return fem.functionspace(mesh, ("Lagrange", degree))
    return fem.FunctionSpace(mesh, ("Lagrange", degree))


# UFL sorts the operands of sums and products into a canonical order and compares two
# Constants there by their repr, which ends in the object's global count: as text, so that
# count 10 sorts before count 9.  A form's structure, and with it its signature (the key of
# the JIT cache), then depended on how many Constants the process had made before: the same
# model built after others compiled again (measured: every diagnosis on a fresh cache
# compiled 2-3 forms it had compiled before, 20-30 s each, in the second round's scores).
# With every count of the same number of digits the text order is the creation order, which
# within a model is fixed.
CONSTANT_COUNT_START = 10**12


def stable_constant_counts() -> None:
    """Let UFL Constants be counted from ``CONSTANT_COUNT_START`` on (idempotent): call it
    before a model creates its Constants."""
    from ufl.constant import Constant as C

    if hasattr(C, "_globalcount"):  # UFL <= 2023: an integer
        C._globalcount = max(C._globalcount, CONSTANT_COUNT_START)
        return
    # UFL 2024: an itertools.count per class, None before the first Constant
    nxt = CONSTANT_COUNT_START if C._counter is None else next(C._counter)
    C._counter = itertools.count(max(nxt, CONSTANT_COUNT_START))


# The key of a compiled expression (a history update) in FFCx 0.9 renumbers its
# coefficients and constants but not its Labels (the tags of ``ufl.variable``), which UFL
# 2024 then signs by their global count: the same model's update got another key after
# other models had made variables, and was compiled again (measured in the rootfs lane: the
# same update under five keys). UFL 2022 numbers Labels by their order in the expression.
# A Label only has to be unique within the expressions of one model.
def fresh_label_counts() -> None:
    """Let the next UFL Label be counted from 0 again (UFL 2024's counter; a no-op for UFL
    2022, whose signatures do not hold the count): call it before a model makes its
    variables."""
    from ufl.variable import Label

    if not hasattr(Label, "_globalcount"):
        Label._counter = itertools.count()


# FFCx 0.5 gives a mesh's coordinate element the point variant "equispaced" when it first
# compiles a form on that mesh (``ffcx.analysis``: it replaces the element of the form's
# domain, which is the mesh's own UFL domain). The signature of a form (the key of the JIT
# cache) includes that element, so every form made on the mesh after the first compilation
# had another key than the same form made before it: a diagnosis on a warm cache that met
# one new form compiled the later ones again (measured: 2 forms of 20-60 s in each of
# several runs in a row on a cache warmed by a run). Setting the variant when the mesh is
# made keys every form as FFCx compiles it anyway (the generated code is the same: FFCx
# uses equispaced points for the coordinate map either way).
def equispaced_coordinates(mesh) -> None:
    """Give ``mesh``'s UFL coordinate element the variant FFCx would (DOLFINx 0.5's UFL
    elements; a no-op for basix elements, DOLFINx >= 0.7)."""
    legacy = getattr(ufl, "VectorElement", None)  # gone from UFL 2023.2 on
    domain = mesh.ufl_domain()
    element = domain.ufl_coordinate_element()
    if legacy is None or not isinstance(element, legacy) or element.variant() is not None:
        return
    equi = ufl.FiniteElement(element.family(), element.cell(), element.degree(),
                             element.quadrature_scheme(), variant="equispaced")
    domain._ufl_coordinate_element = ufl.VectorElement(equi)  # as ffcx.analysis makes it


_FORM_KW = inspect.signature(fem.form).parameters
_FCP = "form_compiler_options" if "form_compiler_options" in _FORM_KW else "form_compiler_params"
_JITP = "jit_options" if "jit_options" in _FORM_KW else "jit_params"


def _cpu_flags() -> set[str]:
    """The instruction-set flags of this machine's first CPU (Linux; empty elsewhere)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


# AVX2 where the CPU has it: the Ogden tangent's element matrices (27 x 27 at 9 points)
# cost 0.45 ms instead of 0.59 ms per assembly on the working mesh (BENCHMARKS.md); the
# numbers move at the rounding (vectorised sums). The flag is part of FFCx's module name,
# so a machine without AVX2 never loads such a kernel from a shared cache. Not -mfma or
# -march=x86-64-v3: 0.51 and 0.47 ms here.
# BRAINMECH_JIT_ARCH replaces them (its words as flags; empty: none), e.g. for a cluster
# whose nodes share one cache and should share its kernels too.
ARCH_FLAGS = (os.environ["BRAINMECH_JIT_ARCH"].split() if "BRAINMECH_JIT_ARCH" in os.environ
              else ["-mavx2"] if platform.machine() in ("x86_64", "AMD64")
              and "avx2" in _cpu_flags() else [])


def _jit(fast_math: bool = True) -> dict:
    """JIT options: C flags tuned for the long expressions of spectral materials and
    their history updates, FFCx's timeout as the project's lock allows (the flags are part
    of FFCx's module name, so kernels compiled with other flags are never reused)."""
    cflags = ["-O3", "-g0"] + (["-ffast-math"] if fast_math else []) + ARCH_FLAGS
    return {"cffi_extra_compile_args": cflags, "timeout": jit_cache.TIMEOUT_S}


def form(expr: ufl.Form, *, fast_math: bool = True):
    """Compile a UFL form with the flags of :func:`_jit`.

    ``-ffast-math`` halves the kernel cost of the spectral Ogden tangent; the accuracy of
    the compiled kernels is checked by the tests (eigen-sums to 1e-12 against numpy).
    """
    return fem.form(expr, **{_JITP: _jit(fast_math)})


_EXPR_KW = inspect.signature(fem.Expression.__init__).parameters
_EXPR_JITP = "jit_options" if "jit_options" in _EXPR_KW else "jit_params"


def expression(expr, points):
    """Compile a UFL expression at reference ``points`` with the flags of :func:`form`:
    the history update of a Maxwell branch or a softening costs 0.3-0.4 ms instead of
    0.8 ms per evaluation with them (20 cells, 9 points each)."""
    return fem.Expression(expr, points, **{_EXPR_JITP: _jit()})


def petsc_vec(u: fem.Function):
    """The PETSc vector wrapping a Function's degrees of freedom."""
    x = u.x
    if hasattr(x, "petsc_vec"):  # >= 0.8
        return x.petsc_vec
    return u.vector


_LIFT_KW = inspect.signature(fem_petsc.apply_lifting).parameters
_LIFT_SCALE = "alpha" if "alpha" in _LIFT_KW else "scale"


def apply_lifting(b, a, bcs, x0, scale: float) -> None:
    """b <- b + scale * A (g - x0) for the Dirichlet rows of ``bcs``."""
    fem_petsc.apply_lifting(b, [a], bcs=[bcs], x0=[x0], **{_LIFT_SCALE: scale})


def set_bc(b, bcs, x0, scale: float) -> None:
    """b[bc dofs] <- scale * (g - x0)."""
    if hasattr(fem_petsc, "set_bc"):
        fem_petsc.set_bc(b, bcs, x0, scale)
    else:  # pragma: no cover - future API
        for bc in bcs:
            bc.set(b.array_w, x0.array_r, scale)


def model_to_mesh(model, comm, rank: int = 0, gdim: int = 3) -> tuple[Any, Any, Any]:
    """gmsh model -> (mesh, cell_tags, facet_tags) for every DOLFINx version."""
    try:
        from dolfinx.io import gmshio as _gmsh  # <= 0.9
    except ImportError:  # pragma: no cover - 0.10+
        from dolfinx.io import gmsh as _gmsh
    out = _gmsh.model_to_mesh(model, comm, rank, gdim=gdim)
    if isinstance(out, tuple):
        return out[0], out[1], out[2]
    return out.mesh, out.cell_tags, out.facet_tags  # pragma: no cover - 0.10+


def xdmf_file(comm, path: str):
    from dolfinx.io import XDMFFile

    return XDMFFile(comm, path, "w")


def interpolate_to(u_src: fem.Function, space) -> fem.Function:
    """Interpolate ``u_src`` into ``space`` (same mesh), for output on P1."""
    out = fem.Function(space, name=u_src.name)
    out.interpolate(u_src)
    return out


def scalar_type():
    from petsc4py import PETSc

    return PETSc.ScalarType


def owned_size(V) -> int:
    """Number of owned (not ghost) dofs, counting block components."""
    im = V.dofmap.index_map
    return im.size_local * V.dofmap.index_map_bs


def locate_dofs(V, sub: int | None, fdim: int, facets: np.ndarray) -> np.ndarray:
    space = V if sub is None else V.sub(sub)
    return fem.locate_dofs_topological(space, fdim, facets)


def quadrature_space(mesh, degree: int, n: int):
    """Space of ``n`` values per quadrature point of the default ``degree`` rule, and the
    reference points of that rule (the points ``dx(metadata={"quadrature_degree": degree})``
    integrates at), for internal variables of history-dependent materials."""
    import basix

    if hasattr(fem, "functionspace"):  # >= 0.8: basix.ufl elements
        import basix.ufl

        el = basix.ufl.quadrature_element(mesh.basix_cell(), value_shape=(n,), degree=degree)
        V = fem.functionspace(mesh, el)
        return V, V.element.interpolation_points()
    el = ufl.VectorElement("Quadrature", mesh.ufl_cell(), degree=degree, dim=n,
                           quad_scheme="default")
    V = fem.FunctionSpace(mesh, el)
    cell = basix.cell.string_to_type(mesh.topology.cell_type.name)
    points, _ = basix.make_quadrature(cell, degree)
    return V, points


def num_local_cells(mesh) -> int:
    """Owned plus ghost cells on this rank."""
    im = mesh.topology.index_map(mesh.topology.dim)
    return im.size_local + im.num_ghosts


def eval_expression(expr, mesh, cells: np.ndarray) -> np.ndarray:
    """Values of a compiled ``fem.Expression`` on ``cells``: (cells, points * components)."""
    try:
        return expr.eval(mesh, cells)  # >= 0.6
    except TypeError:
        return expr.eval(cells)


def dofmap_array(V) -> np.ndarray:
    """Cell -> dof (block) indices as a 2D array."""
    dm = V.dofmap.list
    if hasattr(dm, "array"):  # <= 0.6: AdjacencyList
        return dm.array.reshape(-1, V.dofmap.cell_dofs(0).size)
    return np.asarray(dm)


def facet_measure(geometry, degree: int):
    """Boundary measure with the geometry's facet tags and an explicit quadrature degree."""
    return ufl.Measure("ds", domain=geometry.mesh, subdomain_data=geometry.facet_tags,
                       metadata={"quadrature_degree": degree})


def assemble_scalar(form, comm) -> float:
    """A compiled scalar form, summed over ranks."""
    return float(comm.allreduce(fem.assemble_scalar(form)))
