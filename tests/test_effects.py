"""Each small numba effect on its own, against its defining formula or a property."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plant import ConfigError, Plant
from plant import layout as L
from plant.assemble import natural_frequencies
from plant.config import load_machine
from plant.effects.chain import dead_zone
from plant.effects.commutation import field_weakening_k
from plant.effects.friction import karnopp_friction, sliding_friction
from plant.effects.pmsm import limit_voltage, pi_step
from plant.effects.rng import gaussian, uniform
from tests.conftest import CONFIGS

finite = st.floats(-1e3, 1e3, allow_nan=False)


@given(finite, st.floats(0.0, 10.0))
def test_dead_zone_is_the_deflection_beyond_half_the_gap(delta, gap):
    """Definition: zero inside ±gap/2, shifted by gap/2 outside, odd in delta."""
    de = dead_zone(delta, gap)
    if abs(delta) <= gap / 2:
        assert de == 0.0
    else:
        assert de == pytest.approx(delta - math.copysign(gap / 2, delta), abs=1e-9)
    assert dead_zone(-delta, gap) == -de


@given(st.integers(0, 2**31), st.integers(0, 2**40))
def test_uniform_draws_lie_in_the_open_unit_interval(seed, counter):
    """Property: a uniform draw is in (0, 1) and a pure function of (seed, counter)."""
    u = uniform(float(seed), float(counter))
    assert 0.0 < u < 1.0
    assert u == uniform(float(seed), float(counter))


def test_gaussian_draws_have_unit_variance():
    """Statistics: 20 000 Box-Muller draws have mean 0 and standard deviation 1 within
    4 standard errors, and two seeds give different streams."""
    n = 20000
    x = np.array([gaussian(7.0, 2.0 * k) for k in range(n)])
    assert abs(x.mean()) < 4 / math.sqrt(n)
    assert abs(x.std() - 1.0) < 4 / math.sqrt(2 * n)
    assert gaussian(7.0, 0.0) != gaussian(8.0, 0.0)


@given(st.floats(-100, 100), st.floats(-50, 50), st.floats(0.1, 10), st.floats(0, 1e4),
       st.floats(1.0, 400.0))
def test_pi_output_never_exceeds_its_limit(err, integ, kp, ki, umax):
    """Property: the PI output is limited to ±umax, and a saturated PI does not wind up
    further in the saturating direction (conditional integration)."""
    u, new = pi_step(err, integ, kp, ki, 1.25e-4, 0.0, umax)
    assert abs(u) <= umax
    if abs(kp * err + integ) > umax and err * (kp * err + integ) > 0:
        assert new == integ


@given(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(1.0, 500.0))
def test_voltage_vector_limit_keeps_direction(ud, uq, umax):
    """Geometry: the limited vector is no longer than umax and points the same way."""
    d, q = limit_voltage(ud, uq, umax)
    assert math.hypot(d, q) <= umax * (1 + 1e-12)
    assert d * uq == pytest.approx(q * ud, abs=1e-6 * umax * umax)


def test_sliding_friction_is_the_stribeck_curve():
    """Formula (seed 003 §4.1 with a Stribeck dip): -(B v + sign(v)(F_C + (F_H - F_C)
    exp(-(v/v_s)^2)))."""
    p = np.zeros(L.P_COUNT)
    p[L.P_FR_VISCOUS], p[L.P_FR_COULOMB], p[L.P_FR_STATIC] = 50.0, 25.0, 37.5
    p[L.P_FR_STRIBECK_V] = 0.002
    for v in (-0.05, -0.001, 1e-5, 0.002, 0.1):
        expect = -(50.0 * v + math.copysign(25.0 + 12.5 * math.exp(-(v / 0.002) ** 2), v))
        assert sliding_friction(p, v) == pytest.approx(expect, rel=1e-12)


def test_karnopp_sticks_below_breakaway_and_slips_above():
    """Karnopp's law (seed 003 Fig. 5-6): at rest the friction cancels any applied force up
    to F_H; above it the body breaks away against F_H."""
    p = np.zeros(L.P_COUNT)
    p[L.P_FR_COULOMB], p[L.P_FR_STATIC], p[L.P_FR_DV] = 25.0, 37.5, 1e-6
    assert karnopp_friction(p, 0.0, 30.0, 850.0, 1e-5) == (-30.0, True)
    assert karnopp_friction(p, 0.0, 40.0, 850.0, 1e-5) == (-37.5, False)
    ff, stuck = karnopp_friction(p, 0.01, 0.0, 850.0, 1e-5)
    assert (ff, stuck) == (-25.0, False)


@given(st.floats(50.0, 200.0), st.floats(0.0, 300.0))
@settings(max_examples=50)
def test_field_weakening_constant_solves_seed001_eq9(omega, m_set):
    """Seed 001 eq. 9-10: above omega_Mmax the commutation constant K makes the reachable
    torque (U_Z - omega K) K / R equal the demand when the demand is reachable."""
    k0, r, uz, m_max = 7.2, 0.4, 360.0, 360.0
    k = field_weakening_k(k0, r, uz, m_max, omega, m_set)
    assert 0.0 < k <= k0
    reachable = uz * uz / (4 * omega * r)
    if m_set < reachable and k < k0:
        assert (uz - omega * k) * k / r == pytest.approx(m_set, rel=1e-9, abs=1e-9)


def test_automatic_substep_bounds_omega_dt():
    """The sub-step rule (docs/model.md, plant.assemble): omega_max * dt <= 0.5 with omega_max the
    highest eigenfrequency of the linearised mechanics, and the PWM period a whole number
    of sub-steps."""
    cfg = load_machine(CONFIGS / "arrow500_x.toml")
    axis = Plant(cfg)
    w_max = max(natural_frequencies(cfg, x)[-1] for x in np.linspace(0, cfg.table.travel_m, 5))
    assert w_max * axis.dt <= 0.5
    assert w_max * axis.dt * axis.sub_per_pwm / (axis.sub_per_pwm - 1) > 0.5
    assert axis.sub_per_pwm * axis.dt == pytest.approx(1 / cfg.motor.pwm_frequency_hz)


def test_unstable_substep_is_refused():
    """A sub-step beyond the explicit stability limit omega_max * dt < 2 is refused before
    anything runs, naming the key and the limit."""
    with pytest.raises(ConfigError, match=r"substep_s .* unstable"):
        Plant.from_file(CONFIGS / "arrow500_x.toml",
                        overrides={"simulation": {"substep_s": 1.25e-4 / 2}})


def test_kernel_reports_a_fault_instead_of_raising():
    """A non-finite state gives the fault status (plant.layout), never an exception."""
    axis = Plant.from_file(CONFIGS / "arrow500_x.toml")
    axis.state[L.S_IQ] = math.nan
    assert axis.step(axis.sub_per_pwm) == L.STATUS_NONFINITE
    axis.reset()
    axis.state[L.S_TABLE_X] = 1e13
    assert axis.step(1) == L.STATUS_DIVERGED
