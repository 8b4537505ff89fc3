"""First end-to-end check on both lanes: a hyperelastic solve on a gmsh mesh against a
closed-form value.

With frictionless (slip) ends the compressed cylinder deforms homogeneously, so the
quadratic elements represent the exact solution and the nominal stress must equal the
semi-analytic uniaxial value (lateral stretch root-solved in references.py). Tolerance
1e-4 relative: the curved second-order boundary approximates pi R^2 to ~1e-5.
"""

import pytest
from mpi4py import MPI
from references import homogeneous_uniaxial


@pytest.mark.mpi
def test_gmsh_cylinder_slip_compression_matches_closed_form():
    from brain_fe import geometry
    from brain_fe.materials import MaterialParameters
    from brain_fe.model import ForwardModel
    from brain_fe.protocols import Protocol

    g = geometry.cylinder3d(refinement=1, comm=MPI.COMM_WORLD)
    model = ForwardModel(g, ends="slip")
    params = MaterialParameters(mu=(1.0,), alpha=(-20.0,), kappa=100.0)
    df = model.run(Protocol("compression_tension", (1.0, 0.85), max_increment=0.05), params)
    for lam, p in zip(df.stretch, df.nominal_stress_kPa, strict=True):
        if lam < 1.0:
            assert p == pytest.approx(homogeneous_uniaxial(lam), rel=1e-4)
