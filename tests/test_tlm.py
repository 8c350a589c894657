"""Tests of the TLM chain solver (plant.effects.tlm) against independent references."""

import numpy as np
import pytest
import scipy.linalg
from numba import njit

from plant.effects import chain, tlm

# Torsional steel rod of the mode test: shear modulus (Pa), density (kg/m³),
# diameter (m), length (m) and polar area moment (m⁴).
G = 81e9
RHO = 7850.0
D = 0.032
L = 0.8
J_P = np.pi * D**4 / 32.0


def rod_chain(n_seg, j_first=0.0, j_last=0.0, k_gnd0=0.0, c_link=0.0, c_gnd=0.0):
    """Params and zero state of the steel rod lumped into ``n_seg`` segments.

    Node inertia rho*J_p*L/n_seg (half of it at the two end nodes) plus the
    extra end inertias ``j_first``, ``j_last`` (kg·m²); link stiffness
    n_seg*G*J_p/L (N·m/rad); ground spring ``k_gnd0`` at node 0 only; the same
    link damping ``c_link`` and ground damping ``c_gnd`` everywhere.
    Layout of plant.effects.chain with ``po = so = 0``.  Returns (p, s, n).
    """
    n = n_seg + 1
    j = np.full(n, RHO * J_P * L / n_seg)
    j[0] = 0.5 * j[0] + j_first
    j[-1] = 0.5 * j[-1] + j_last
    p = np.zeros(chain.params_size(n))
    p[:n] = j
    p[n : 2 * n] = c_gnd
    p[2 * n] = k_gnd0
    p[3 * n : 4 * n - 1] = n_seg * G * J_P / L
    p[4 * n - 1 : 5 * n - 2] = c_link
    return p, np.zeros(chain.state_size(n)), n


def stiffness_and_mass(p, n):
    """Stiffness and inertia matrices (n x n) of the chain in ``p``."""
    k_mat = np.diag(p[2 * n : 3 * n].copy())
    for i, k in enumerate(p[3 * n : 4 * n - 1]):
        k_mat[i : i + 2, i : i + 2] += k * np.array([[1.0, -1.0], [-1.0, 1.0]])
    return k_mat, np.diag(p[:n])


def omegas(p, n):
    """Natural angular frequencies (rad/s, ascending) of the lumped chain, by eigh."""
    k_mat, m_mat = stiffness_and_mass(p, n)
    return np.sqrt(np.abs(scipy.linalg.eigh(k_mat, m_mat, eigvals_only=True)))


@njit
def run(p, s, n, dt, steps, use_tlm, f_ext, tip, energy):
    """Step the chain ``steps`` times with constant external forces ``f_ext``.

    ``use_tlm``: tlm_step, else the lumped chain stepper.  Records the last
    node's position in ``tip`` and the energy after every step in ``energy``
    (tlm_energy for TLM, chain_energy for the lumped stepper).
    """
    for k in range(steps):
        if use_tlm:
            s[2 * n : 3 * n] = f_ext
            tlm.tlm_step(p, 0, s, 0, n, dt)
            energy[k] = tlm.tlm_energy(p, 0, s, 0, n, dt)
        else:
            chain.chain_internal_forces(p, 0, s, 0, n)
            s[2 * n : 3 * n] += f_ext
            chain.chain_step(p, 0, s, 0, n, dt, -1)
            energy[k] = chain.chain_energy(p, 0, s, 0, n)
        tip[k] = s[n - 1]


def simulate(p, s, n, dt, steps, use_tlm=True, f_ext=None):
    """Run from the present x, v (waves initialised for TLM).

    Returns (tip, energy): the last node's position after every step and the
    energy before the first and after every step (``steps + 1`` values).
    """
    if f_ext is None:
        f_ext = np.zeros(n)
    tip = np.zeros(steps)
    energy = np.zeros(steps + 1)
    if use_tlm:
        tlm.tlm_init(p, 0, s, 0, n, dt)
        energy[0] = tlm.tlm_energy(p, 0, s, 0, n, dt)
    else:
        energy[0] = chain.chain_energy(p, 0, s, 0, n)
    run(p, s, n, dt, steps, use_tlm, f_ext, tip, energy[1:])
    return tip, energy


def period(y, dt):
    """Mean period (s) of ``y`` sampled every ``dt``, from interpolated zero crossings."""
    neg = np.signbit(y)
    idx = np.nonzero(neg[1:] != neg[:-1])[0]
    t = (idx + y[idx] / (y[idx] - y[idx + 1])) * dt
    return 2.0 * (t[-1] - t[0]) / (len(t) - 1)


def static_chain():
    """Five nodes, unequal links, stiff ground spring at node 0, damped; (p, s, n, k_links)."""
    n = 5
    k_links = np.array([2.0e4, 5.0e4, 1.0e4, 3.0e4])
    p = np.zeros(chain.params_size(n))
    p[:n] = [1e-3, 2e-4, 5e-4, 2e-4, 1e-3]
    p[n : 2 * n] = 0.05
    p[2 * n] = 1.0e6
    p[3 * n : 4 * n - 1] = k_links
    p[4 * n - 1 : 5 * n - 2] = 0.5
    return p, np.zeros(chain.state_size(n)), n, k_links


def test_static_deflection_is_series_springs():
    """Reference: analytic series-spring deflection F*(1/k_gnd + sum 1/k_link) at the free end.

    Damped chain started with non-zero velocities (so the waves must be
    initialised consistently with them), constant force on the last node, dt
    at half the lumped stability limit; settled to 1e-9 relative.
    """
    p, s, n, k_links = static_chain()
    force = 3.0
    f_ext = np.zeros(n)
    f_ext[-1] = force
    s[n : 2 * n] = [0.0, 0.02, -0.01, 0.03, 0.01]
    dt = 1.0 / omegas(p, n)[-1]
    tip, _ = simulate(p, s, n, dt, 20000, f_ext=f_ext)
    expected = force * (1.0 / p[2 * n] + np.sum(1.0 / k_links))
    assert tip[-1] == pytest.approx(expected, rel=1e-9)


def test_init_keeps_prestressed_chain_at_rest():
    """Reference: the analytic static solution; started there, the chain must not move (1e-12)."""
    p, s, n, k_links = static_chain()
    force = 3.0
    f_ext = np.zeros(n)
    f_ext[-1] = force
    x = force * (1.0 / p[2 * n] + np.concatenate(([0.0], np.cumsum(1.0 / k_links))))
    s[:n] = x
    dt = 3.0 / omegas(p, n)[-1]
    simulate(p, s, n, dt, 1000, f_ext=f_ext)
    assert np.max(np.abs(s[:n] - x)) <= 1e-12 * x[-1]
    assert np.max(np.abs(s[n : 2 * n])) <= 1e-12 * x[-1] / dt


@pytest.mark.parametrize("n_seg", [4, 8, 16, 32])
def test_first_mode_matches_lumped_eigenvalue(n_seg):
    """Reference: scipy.linalg.eigh of the assembled K, M (same discrete chain).

    Clamped-free rod (ground spring 1e6 k_link at node 0), free vibration
    from the continuous first mode shape sin(pi z / 2L), dt = 0.1/omega_max of
    the rod's links (omega_max = 2 sqrt(k_link/J_node)); the period from ten
    cycles agrees with 2 pi/omega_1 to 2e-5 relative.
    """
    p, s, n = rod_chain(n_seg, k_gnd0=1e6 * n_seg * G * J_P / L)
    w1 = omegas(p, n)[0]
    dt = 0.05 / np.sqrt(p[3 * n] / p[1])
    s[:n] = np.sin(np.pi * np.arange(n) / (2 * n_seg))
    tip, _ = simulate(p, s, n, dt, int(10.25 * 2 * np.pi / w1 / dt))
    assert 2 * np.pi / period(tip, dt) == pytest.approx(w1, rel=2e-5)


def test_first_mode_converges_to_continuous_rod():
    """Reference: continuous clamped-free rod, f1 = sqrt(G/rho)/(4L).

    The TLM error must fall by a factor 3.5..4.5 per halving of the segment
    length (second order) and be below 2e-4 at 32 segments.
    """
    f1 = np.sqrt(G / RHO) / (4 * L)
    errors = []
    for n_seg in (4, 8, 16, 32):
        p, s, n = rod_chain(n_seg, k_gnd0=1e6 * n_seg * G * J_P / L)
        dt = 0.05 / np.sqrt(p[3 * n] / p[1])
        s[:n] = np.sin(np.pi * np.arange(n) / (2 * n_seg))
        tip, _ = simulate(p, s, n, dt, int(10.25 / f1 / dt))
        errors.append(abs(1.0 / period(tip, dt) / f1 - 1.0))
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratios > 3.5) & (ratios < 4.5)), errors
    assert errors[-1] < 2e-4


def test_trajectory_agrees_with_lumped_stepper():
    """Reference: the lumped semi-implicit Euler stepper of plant.effects.chain.

    Rod of 8 segments with a load inertia twice the rod's at the free end,
    ground spring 100 k_link at node 0, released from a linear twist of
    1 mrad.  Over five periods of the first mode the free ends differ by less
    than 1 % of the amplitude at dt = 0.1/omega_max, and the difference is
    first order in dt (at least 2.5 times smaller at dt/3).
    """
    errors = []
    for r in (0.1, 0.1 / 3):
        p, s, n = rod_chain(8, j_last=2 * RHO * J_P * L, k_gnd0=100 * 8 * G * J_P / L)
        w = omegas(p, n)
        dt = r / w[-1]
        steps = int(5 * 2 * np.pi / w[0] / dt)
        x0 = 1e-3 * np.arange(n) / (n - 1)
        s[:n] = x0
        tip_tlm, _ = simulate(p, s, n, dt, steps)
        s[:] = 0.0
        s[:n] = x0
        tip_lumped, _ = simulate(p, s, n, dt, steps, use_tlm=False)
        errors.append(np.max(np.abs(tip_tlm - tip_lumped)) / np.max(np.abs(tip_lumped)))
    assert errors[0] < 0.01
    assert errors[1] < errors[0] / 2.5


def test_unconditionally_stable_where_lumped_blows_up():
    """Reference: the lumped stepper's stability limit dt < 2/omega_max (omega_max by eigh).

    Undamped rod of 8 segments, ground spring 100 k_link at node 0, at ten
    times that limit: over 1e4 steps the TLM energy never exceeds its initial
    value by more than 1e-12 relative, while the lumped stepper's energy
    grows by more than 1e6 within 200 steps.
    """
    p, s, n = rod_chain(8, k_gnd0=100 * 8 * G * J_P / L)
    dt = 10 * 2.0 / omegas(p, n)[-1]
    x0 = 1e-3 * np.arange(n) / (n - 1)
    s[:n] = x0
    tip, energy = simulate(p, s, n, dt, 10000)
    assert np.all(np.isfinite(tip))
    assert np.max(energy) <= energy[0] * (1 + 1e-12)
    s[:] = 0.0
    s[:n] = x0
    _, energy_lumped = simulate(p, s, n, dt, 200, use_tlm=False)
    blown_up = ~(energy_lumped < 1e6 * energy_lumped[0])  # NaN counts as blown up
    assert np.any(blown_up)


@pytest.mark.parametrize("dt_factor", [0.1, 20.0])
def test_energy_never_increases_with_damping(dt_factor):
    """Reference: passivity; with link and ground dampers and no external force
    the TLM energy is non-increasing every step (1e-12 relative rounding), at
    dt = 0.1/omega_max and at ten times the lumped limit, and the dampers
    remove at least a fifth of it over twenty periods.
    """
    j_seg = RHO * J_P * L / 8
    k_seg = 8 * G * J_P / L
    p, s, n = rod_chain(
        8,
        j_first=3 * j_seg,
        k_gnd0=10 * k_seg,
        c_link=0.1 * np.sqrt(k_seg * j_seg),
        c_gnd=0.01 * np.sqrt(k_seg * j_seg),
    )
    w = omegas(p, n)
    dt = dt_factor / w[-1]
    s[:n] = 1e-3 * np.arange(n) / (n - 1)
    s[n : 2 * n] = 0.3 * w[0] * s[:n][::-1]
    _, energy = simulate(p, s, n, dt, int(20 * 2 * np.pi / w[0] / dt) + 1)
    assert np.all(np.diff(energy) <= 1e-12 * energy[0])
    assert energy[-1] < 0.8 * energy[0]
