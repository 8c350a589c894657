"""Seed 001's commutation model with the omega_e L cross term (issue 14 part 5): the
coil's voltage limit against the d-q voltage equations, and the held-speed torque against
the validation's own d-q steady state."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.validate.experiments import electrical as E
from plant import Plant
from plant.effects.commutation import coil_voltage_limit

K0, R, L, P, UZ = 12.0, 1.2, 0.012, 22.0, 600.0


def dq_split(k: float, omega: float, current: float) -> tuple[float, float]:
    """(V along the current, V across it) of the d-q voltage vector of a synchronous machine
    whose current ``current`` (A) stands at arccos(K/K_0) ahead of the q axis with i_d <= 0,
    written out from u_d = R i_d - omega_e L i_q, u_q = R i_q + omega_e L i_d + K_0 omega."""
    sin_g = math.sqrt(1.0 - (k / K0) ** 2)
    i_d, i_q = -abs(current) * sin_g, current * k / K0
    we = P * omega
    u = np.array([R * i_d - we * L * i_q, R * i_q + we * L * i_d + K0 * omega])
    unit = np.array([i_d, i_q]) / math.hypot(i_d, i_q)
    along = float(u @ unit)
    return along, float(np.linalg.norm(u - along * unit))


@settings(max_examples=200, deadline=None)
@given(k=st.floats(0.5, K0), omega=st.floats(-120.0, 120.0),
       current=st.floats(-60.0, 60.0).filter(lambda i: abs(i) > 1e-3))
def test_coil_limit_is_what_the_cross_voltage_leaves_of_u_z(k, omega, current):
    """The coil's equation is the d-q vector's component along the current (R I + K omega,
    seed 001 eq. 1-4), and its limit is sqrt(U_Z^2 - U_across^2) (reference: the d-q
    voltage equations projected with numpy)."""
    along, across = dq_split(k, omega, current)
    assert math.isclose(along * math.copysign(1.0, current), R * current + k * omega,
                        rel_tol=1e-9, abs_tol=1e-9)
    expected = math.sqrt(max(UZ * UZ - across * across, 0.0))
    limit = coil_voltage_limit(UZ, K0, k, P, L, omega, current)
    assert math.isclose(limit, expected, rel_tol=1e-9, abs_tol=1e-6)


def test_full_demand_below_omega_max_is_held_down_by_the_cross_term():
    """At 0.9 omega_max without field weakening the d-q vector, not eq. 9, limits the
    current: (R I + K_0 omega)^2 + (p omega L I)^2 = U_Z^2 (reference: that quadratic solved
    by hand), well below I_max, where eq. 9 alone would give the full 30 A."""
    drive = E.SeedOneDrive.from_config(Plant.from_file(E.GEISS).config)
    omega = 0.9 * drive.omega_max
    a = drive.r ** 2 + (drive.pole_pairs * omega * drive.inductance) ** 2
    b = 2.0 * drive.r * drive.k0 * omega
    c = (drive.k0 * omega) ** 2 - drive.uz ** 2
    current = (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    assert (drive.uz - drive.k0 * omega) / drive.r > drive.i_max  # eq. 9 alone: no limit
    run = E.held_speed_run(E.GEISS, omega, drive.i_max, weakening=False)
    assert abs(run["iq_a"] - current) <= 1e-3 * current
    assert current < 0.7 * drive.i_max


def test_beyond_omega_max_field_weakening_agrees_with_the_dq_steady_state():
    """At 1.1 omega_max the back-EMF alone exceeds U_Z.  The commutation angle of eq. 10,
    chosen without the cross term, no longer keeps a driving torque with this file's
    inductance (the honest envelope); the kernel's torque is what the validation's d-q
    steady state (SeedOneDrive, its own root search on the projected d-q voltage) gives."""
    drive = E.SeedOneDrive.from_config(Plant.from_file(E.GEISS).config)
    omega = 1.1 * drive.omega_max
    on = E.held_speed_torque(E.GEISS, omega, drive.i_max, weakening=True)
    reference = drive.steady_torque(omega, drive.k0 * drive.i_max, weakening=True)
    assert abs(on - reference) <= 1e-3 * drive.k0 * drive.i_max


def test_the_validation_grid_is_the_scalar_voltage_excess():
    """SeedOneDrive.voltage_excess_grid (the root search's grid, at once) against
    voltage_excess point by point, on both sides of 0 A, with and without weakening."""
    drive = E.SeedOneDrive.from_config(Plant.from_file(E.GEISS).config)
    currents = np.linspace(-2.0 * drive.i_max, 2.0 * drive.i_max, 401)
    for omega in (0.3 * drive.omega_max, 1.1 * drive.omega_max):
        for k in (drive.k0, 0.6 * drive.k0):
            grid = drive.voltage_excess_grid(omega, k, currents)
            scalar = [drive.voltage_excess(omega, k, i) for i in currents]
            np.testing.assert_allclose(grid, scalar, rtol=1e-12, atol=1e-9)
