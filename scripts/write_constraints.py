"""Print pip constraints that pin the Debian-provided scientific stack at its system versions.

Debian's DOLFINx is compiled against the system numpy (and uses the system petsc4py,
mpi4py, cffi); pip must never replace them inside the venv.
"""

import importlib.metadata as md

PINNED = ["numpy", "cffi", "mpi4py", "petsc4py", "fenics-ufl", "fenics-ffcx",
          "fenics-basix", "fenics-dolfinx", "gmsh"]

for name in PINNED:
    try:
        print(f"{name}=={md.version(name)}")
    except md.PackageNotFoundError:
        pass
