"""The inverter's voltage limit (issue 14 part 5): space-vector PWM, U_dc/sqrt(3), by
default; sine PWM, U_dc/2, as the option [motor] modulation = "spwm".

Against analytic results: the largest d-q voltage a saturating current step reaches and the
circle a voltage request is scaled onto; the PMSM's steady q current at a held speed above
its corner speed, where the voltage limit sets it,
(omega_e L i_q)^2 + (R i_q + omega_e psi)^2 = U_max^2 with i_d = 0, and the corner speed
itself, which SVPWM moves up (345 against 298 rad/s at I_max on the Arrow 500 X's motor);
the commutation model keeps seed 001 eq. 2's |U| <= U_Z, and refuses the key.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from plant import Plant
from plant import layout as L
from plant.config import load_machine
from plant.errors import ConfigError

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
U_DC = 600.0
LIMITS = {"svpwm": U_DC / math.sqrt(3.0), "spwm": U_DC / 2.0}
#: the Arrow 500 X's motor on a rotor held by a huge inertia (rotary, rigid), no noise
HELD_MOTOR = """
[machine]
name = "Arrow 500 X motor, rotor held"
source = "configs/arrow500_x.toml [motor] and [current_loop]"
kind = "rotary"

[motor]
model = "dq"
pole_pairs = 3
resistance_ohm = 0.36
inductance_d_h = 0.0045
inductance_q_h = 0.0045
torque_constant_nm_per_a = 1.35
inertia_kgm2 = 1.0e6
current_max_a = 28.0
dc_link_v = 600.0
pwm_frequency_hz = 8000.0
{modulation}

[current_loop]
kp_v_per_a = 12.0
ti_s = 0.0125

[mechanics]
model = "rigid"

[sensors]
encoder_counts_per_rev = 4194304
"""
R, L_DQ, PSI, POLES = 0.36, 0.0045, 1.35 / 4.5, 3


def held_motor(tmp_path, modulation: str | None) -> Plant:
    text = HELD_MOTOR.format(modulation=f'modulation = "{modulation}"' if modulation else "")
    path = tmp_path / f"held_{modulation}.toml"
    path.write_text(text)
    return Plant.from_file(path)


def steady_iq(omega: float, u_max: float) -> float:
    """A: the q current (i_d = 0) whose steady d-q voltage at ``omega`` (rad/s) is u_max."""
    we = POLES * omega
    a = (we * L_DQ) ** 2 + R * R
    b = 2.0 * R * we * PSI
    c = (we * PSI) ** 2 - u_max * u_max
    return (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)


def corner_speed(current: float, u_max: float) -> float:
    """rad/s: the speed up to which ``current`` (A, on the q axis) still fits in u_max."""
    a = (L_DQ * current) ** 2 + PSI ** 2
    b = 2.0 * R * current * PSI
    c = (R * current) ** 2 - u_max * u_max
    return (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a) / POLES


def run_at_speed(plant: Plant, omega: float, iq_ref: float, periods: int = 1600):
    p = plant.params
    ro, nr = int(p[L.P_SOFF_ROT]), int(p[L.P_N_ROT])
    plant.state[ro + nr:ro + 2 * nr] = omega
    plant.set_input(iq_ref_a=iq_ref)
    return plant.run(periods, plant.sub_per_pwm)


def test_svpwm_is_the_default_and_both_limits_are_the_analytic_ones(tmp_path):
    assert load_machine(CONFIGS / "arrow500_x.toml").motor.modulation == "svpwm"
    for modulation, expected in ((None, LIMITS["svpwm"]), ("svpwm", LIMITS["svpwm"]),
                                 ("spwm", LIMITS["spwm"])):
        assert held_motor(tmp_path, modulation).params[L.P_U_MAX] == pytest.approx(
            expected, rel=1e-15)


@pytest.mark.parametrize("modulation", ["svpwm", "spwm"])
def test_a_saturating_step_reaches_exactly_the_limit(tmp_path, modulation):
    """id 20 A, iq 28 A on the held rotor: |u_dq| reaches U_max and never exceeds it."""
    plant = held_motor(tmp_path, modulation)
    plant.set_input(id_ref_a=20.0, iq_ref_a=28.0)
    tr = plant.run(400, plant.sub_per_pwm)
    u = np.hypot(tr["ud_v"], tr["uq_v"])
    assert u.max() <= LIMITS[modulation] * (1.0 + 1e-12)
    assert u.max() >= LIMITS[modulation] * (1.0 - 1e-9)


@pytest.mark.parametrize("modulation", ["svpwm", "spwm"])
def test_a_voltage_request_is_scaled_onto_the_limits_circle(tmp_path, modulation):
    """500 V asked for at (400, 300) V: applied on the circle |u| = U_max, direction kept."""
    plant = held_motor(tmp_path, modulation)
    plant.set_input(mode=1, ud_v=400.0, uq_v=300.0)
    tr = plant.run(2, plant.sub_per_pwm)
    scale = LIMITS[modulation] / 500.0
    assert tr["ud_v"][1] == pytest.approx(400.0 * scale, rel=1e-12)
    assert tr["uq_v"][1] == pytest.approx(300.0 * scale, rel=1e-12)


@pytest.mark.parametrize("modulation", ["svpwm", "spwm"])
def test_above_the_corner_the_voltage_limit_sets_the_steady_current(tmp_path, modulation):
    """Held at 1.05 times the corner speed of I_max, full demand: the steady q current is the
    analytic one of the voltage circle (0.2 %), i_d stays 0, |u| sits on the limit."""
    u_max = LIMITS[modulation]
    omega = 1.05 * corner_speed(28.0, u_max)
    tr = run_at_speed(held_motor(tmp_path, modulation), omega, 28.0)
    tail = slice(-160, None)
    assert tr["iq_a"][tail].mean() == pytest.approx(steady_iq(omega, u_max), rel=2e-3)
    assert tr["iq_a"][tail].mean() < 27.0
    assert abs(tr["id_a"][tail].mean()) < 0.05
    assert np.hypot(tr["ud_v"], tr["uq_v"])[tail].mean() == pytest.approx(u_max, rel=1e-6)


def test_svpwm_moves_the_corner_speed_up(tmp_path):
    """Between the two corner speeds (analytic) I_max is reached with SVPWM, not with sine
    PWM; the SVPWM corner lies about 2/sqrt(3) higher (back-EMF dominated)."""
    low, high = corner_speed(28.0, LIMITS["spwm"]), corner_speed(28.0, LIMITS["svpwm"])
    assert 1.1 < high / low < 2.0 / math.sqrt(3.0) * 1.01
    omega = 0.5 * (low + high)
    sv = run_at_speed(held_motor(tmp_path, "svpwm"), omega, 28.0)
    sp = run_at_speed(held_motor(tmp_path, "spwm"), omega, 28.0)
    assert sv["iq_a"][-160:].mean() == pytest.approx(28.0, abs=0.05)
    assert sp["iq_a"][-160:].mean() == pytest.approx(steady_iq(omega, LIMITS["spwm"]), rel=2e-3)


def test_the_commutation_model_keeps_seed_001s_link_voltage():
    """Seed 001 eq. 2: the coil's |U| <= U_Z = the DC link; modulation is a dq-model key."""
    geiss = CONFIGS / "geiss_c_axis.toml"
    plant = Plant.from_file(geiss)
    assert plant.params[L.P_U_MAX] == plant.config.motor.dc_link_v
    with pytest.raises(ConfigError, match=r"\[motor\] modulation does not apply here"):
        load_machine(geiss, {"motor": {"modulation": "spwm"}})
