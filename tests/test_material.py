"""Spectral Ogden energy in UFL against numpy (eigvalsh / matrix functions).

Evaluated on a one-cell mesh with the tensor as a ``fem.Constant``, so one compiled form
serves every case. Energies to 1e-12 relative, stresses to 1e-11, directional tangents to
1e-7 (central differences of numpy's exact stress, step 1e-6).
"""

import numpy as np
import pytest
import ufl
from mpi4py import MPI

CASES = {
    "distinct": [0.8, 1.0, 1.3],
    "double_upper": [0.8, 1.2, 1.2],
    "double_lower": [0.85, 0.85, 1.3],
    "triple": [1.1, 1.1, 1.1],
    "reference": [1.0, 1.0, 1.0],
    "near_triple": [1 + 1e-5, 1.0, 1 - 2e-5],
    "near_double": [0.9, 1.2, 1.2 + 1e-7],
    "switch_double": [0.9, 1.2, 1.2 + 2e-3],
}
EXPONENTS = [-20.0, -1.0, 1.0, 2.5, 5.0]


@pytest.fixture(scope="module")
def spectral_forms():
    from dolfinx import fem, mesh

    from brain_fe import _compat
    from brain_fe.materials.spectral import power_derivative, spectral_sum

    msh = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1)
    C = fem.Constant(msh, np.eye(3))
    p = fem.Constant(msh, 1.0)
    D = fem.Constant(msh, np.zeros((3, 3)))
    Cv = ufl.variable(C)
    f = spectral_sum(Cv, power_derivative(p))
    S = ufl.diff(f, Cv)
    H = ufl.diff(ufl.inner(S, D), Cv)
    dx = ufl.dx(domain=msh, metadata={"quadrature_degree": 0})
    forms = {"f": _compat.form(f * dx), "S": _compat.form(ufl.inner(S, D) * dx),
             "H": _compat.form(ufl.inner(H, D) * dx)}

    def evaluate(name, Cval, pval, Dval=None):
        C.value[:] = Cval
        p.value = pval
        D.value[:] = np.zeros((3, 3)) if Dval is None else Dval
        return fem.assemble_scalar(forms[name])

    return evaluate


def _random_rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q


def _matfun(C, fn):
    w, V = np.linalg.eigh(C)
    return V @ np.diag(fn(w)) @ V.T


@pytest.mark.parametrize("case", list(CASES))
def test_eigen_sum_energy_stress_tangent(spectral_forms, case):
    rng = np.random.default_rng(abs(hash(case)) % 2**32)
    Q = _random_rotation(rng)
    C = Q @ np.diag(CASES[case]) @ Q.T
    for pexp in EXPONENTS:
        ref = np.sum(np.linalg.eigvalsh(C) ** pexp)
        assert spectral_forms("f", C, pexp) == pytest.approx(ref, rel=1e-12)
        # stress d/dC sum c_i^p = p C^(p-1), checked along two symmetric directions
        Sref = _matfun(C, lambda w, q=pexp: q * w ** (q - 1))
        for _ in range(2):
            D = rng.normal(size=(3, 3))
            D = (D + D.T) / 2
            assert spectral_forms("S", C, pexp, D) == pytest.approx(np.sum(Sref * D), rel=1e-11,
                                                                   abs=1e-12)
            h = 1e-6
            Hfd = (np.sum(_matfun(C + h * D, lambda w, q=pexp: q * w ** (q - 1)) * D)
                   - np.sum(_matfun(C - h * D, lambda w, q=pexp: q * w ** (q - 1)) * D)) / (2 * h)
            assert spectral_forms("H", C, pexp, D) == pytest.approx(Hfd, rel=1e-7, abs=1e-7)


def test_alpha_two_is_neo_hooke():
    """One-term Ogden with alpha = 2 equals neo-Hooke mu/2 (I1bar - 3) + U(J)."""
    from dolfinx import fem, mesh

    from brain_fe import _compat
    from brain_fe.materials import MaterialModel
    from brain_fe.parameters import KAPPA, alpha
    from brain_fe.parameters import mu as mu_

    msh = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1)
    F = fem.Constant(msh, np.eye(3))
    mu, kappa = 1.7, 40.0
    Fv = ufl.variable(F)
    C = Fv.T * Fv
    J = ufl.det(Fv)
    W = MaterialModel.build().strain_energy(C, J, {mu_(0): mu, alpha(0): 2.0, KAPPA: kappa})
    Wnh = mu / 2 * (J ** (-2 / 3) * ufl.tr(C) - 3) + kappa / 2 * (J - 1) ** 2
    dx = ufl.dx(domain=msh, metadata={"quadrature_degree": 0})
    P, Pnh = ufl.diff(W, Fv), ufl.diff(Wnh, Fv)
    fW = _compat.form((W - Wnh) * dx)
    fP = _compat.form(ufl.inner(P - Pnh, P - Pnh) * dx)
    fPn = _compat.form(ufl.inner(Pnh, Pnh) * dx)
    rng = np.random.default_rng(7)
    for _ in range(5):
        F.value[:] = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
        assert abs(fem.assemble_scalar(fW)) < 1e-12
        assert np.sqrt(fem.assemble_scalar(fP) / fem.assemble_scalar(fPn)) < 1e-12


def test_kappa_from_nu0():
    from brain_fe.materials import kappa_from_nu0

    # kappa = 2 mu (1 + nu) / (3 (1 - 2 nu)); nu = 0.49 -> 49.6667 mu
    assert kappa_from_nu0(1.0, 0.49) == pytest.approx(2 * 1.49 / (3 * 0.02))
    with pytest.raises(ValueError):
        kappa_from_nu0(1.0, 0.5)
