"""Independent references, computed here with numpy/scipy only (no project code).

DESIGN.md section 3: R = 4 mm, H = 5 mm, mu = 1 kPa, alpha = -20, kappa = 100 kPa,
U = kappa/2 (J - 1)^2.
"""

import numpy as np
from scipy.integrate import quad
from scipy.optimize import brentq


def ogden_energy(l1, l2, l3, mu, alpha, kappa):
    """Compressible one-term Ogden energy in principal stretches (complex-step safe)."""
    J = l1 * l2 * l3
    iso = sum((J ** (-1.0 / 3.0) * li) ** alpha for li in (l1, l2, l3))
    return 2 * mu / alpha**2 * (iso - 3) + kappa / 2 * (J - 1) ** 2


def _dW(i, lams, mu, alpha, kappa, h=1e-30):
    """Nominal principal stress dW/dlambda_i by complex-step differentiation."""
    z = [complex(x) for x in lams]
    z[i] += 1j * h
    return ogden_energy(*z, mu, alpha, kappa).imag / h


def homogeneous_uniaxial(lam, mu=1.0, alpha=-20.0, kappa=100.0):
    """Slip-end (homogeneous) uniaxial nominal stress [kPa]: lateral stretch s from
    P_lateral(lam, s, s) = 0 (root-solved), then P_axial."""
    s = brentq(lambda s: _dW(1, (lam, s, s), mu, alpha, kappa), 0.5, 2.0, xtol=1e-15)
    return _dW(0, (lam, s, s), mu, alpha, kappa)


def rivlin_torque(gamma_R, mu=1.0, alpha=-20.0, radius=4.0):
    """Incompressible torsion torque [mN mm]: T = 2 pi int_0^R W'(gamma r/R) r^2 dr,
    W(gamma) = 2 mu/alpha^2 (l^alpha + l^-alpha - 2), l = gamma/2 + sqrt(1 + gamma^2/4)."""

    def dW(g):
        lam = g / 2 + np.sqrt(1 + g * g / 4)
        dlam = 0.5 + g / (4 * np.sqrt(1 + g * g / 4))
        return 2 * mu / alpha * (lam ** (alpha - 1) - lam ** (-alpha - 1)) * dlam

    val, _ = quad(lambda r: dW(gamma_R * r / radius) * r**2, 0, radius, epsabs=1e-13)
    return 2 * np.pi * val


def fibre_energy(l1, l2, l3, k1, k2):
    """Tension-only fibre family along principal direction 1: k1/(2 k2)
    (exp(k2 <I4bar - 1>^2) - 1), I4bar = (J^(-1/3) l1)^2 (complex-step safe)."""
    x = (l1 * l2 * l3) ** (-2.0 / 3.0) * l1**2 - 1
    if x.real <= 0:
        return 0.0 * x
    return k1 / (2 * k2) * (np.exp(k2 * x * x) - 1)


def homogeneous_uniaxial_fibres(lam, k1, k2, mu=1.0, alpha=-20.0, kappa=100.0):
    """Slip-end uniaxial nominal stress [kPa] along an axial fibre family, as
    :func:`homogeneous_uniaxial` with the fibre energy added."""

    def dW(i, lams, h=1e-30):
        z = [complex(x) for x in lams]
        z[i] += 1j * h
        return (ogden_energy(*z, mu, alpha, kappa) + fibre_energy(*z, k1, k2)).imag / h

    s = brentq(lambda s: dW(1, (lam, s, s)), 0.5, 2.0, xtol=1e-15)
    return dW(0, (lam, s, s))


def sls_unilateral(times, plate_strain, modulus, beta, tau):
    """Linear standard solid (E(t) = E (1 + beta e^(-t/tau))) pressed by a plate that
    cannot pull: nominal stress [kPa] at ``times`` and whether the plate touches.

    ``plate_strain(t)``: the plate's strain (< 0 pressing), linear between the entries of
    ``times`` that are its turning points.  In contact sigma = E e_p + q with
    q' = E beta e_p' - q / tau; off the plate sigma = 0, the specimen's strain is
    e_s = -q / E and q' = -q / (tau (1 + beta)).  Lift-off where sigma reaches 0 from below,
    re-contact where the plate comes back down to e_s; both located as events of
    ``solve_ivp`` (rtol 1e-11), each linear piece of the plate's path integrated apart."""
    from scipy.integrate import solve_ivp

    times = np.asarray(times, float)

    def slope(t, h=1e-7):
        return (plate_strain(t + h) - plate_strain(t - h)) / (2 * h)

    def pulls(t, q):  # sigma in contact
        return modulus * plate_strain(t) + q[0]

    def touches(t, q):  # plate above the specimen's top: e_p - e_s
        return plate_strain(t) + q[0] / modulus

    pulls.terminal, pulls.direction = True, 1
    touches.terminal, touches.direction = True, -1
    q_at, on_at = {0: 0.0}, {0: True}
    t, q, in_contact = 0.0, 0.0, True
    pieces = list(times[1:])
    while pieces:
        t_stop = pieces[0]
        mid_slope = slope(0.5 * (t + t_stop))
        rhs = ((lambda _t, y, s=mid_slope: [modulus * beta * s - y[0] / tau]) if in_contact
               else (lambda _t, y: [-y[0] / (tau * (1 + beta))]))
        sol = solve_ivp(rhs, (t, t_stop), [q], events=pulls if in_contact else touches,
                        rtol=1e-11, atol=1e-16, dense_output=True)
        t, q = float(sol.t[-1]), float(sol.y[0, -1])
        if sol.status == 1:  # an event inside the piece: the contact state changes
            in_contact = not in_contact
            continue
        k = int(np.searchsorted(times, t_stop))
        q_at[k], on_at[k] = q, in_contact
        pieces.pop(0)
    q = np.array([q_at[k] for k in range(len(times))])
    on = np.array([on_at[k] for k in range(len(times))])
    sigma = np.where(on, modulus * np.array([plate_strain(t) for t in times]) + q, 0.0)
    return sigma, on
