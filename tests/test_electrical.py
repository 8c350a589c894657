"""Electrical validation experiments (hil.validate.experiments.electrical) and direct checks
of the current loop, the voltage limit, voltage mode, field weakening, the current
measurement and the motor encoder."""

import math

import numpy as np

from hil.validate.experiments import electrical as E
from plant import Plant


def assert_rows_ok(rows):
    failing = [r for r in rows if not r.ok]
    assert rows and not failing, "\n".join(
        f"{r.experiment}: paper {r.paper} model {r.model} {r.unit} ({r.tolerance})"
        for r in failing)


def quiet_locked_arrow() -> Plant:
    return Plant.from_file(E.ARROW, overrides=E.merged(E.LOCKED, E.QUIET))


# --- current loop ----------------------------------------------------------------------

def test_current_steps_rows_ok(experiment_rows):
    """Kernel current steps of 0.84 A and 2.8 A vs the exact discrete loop built with
    scipy.signal (ZOH R-L plant, discrete PI, one PWM period of delay) and seed 000 §5's
    step heights (3 % and 10 % of I_max)."""
    assert_rows_ok(experiment_rows("current_steps"))


def test_analytic_loop_first_samples_by_hand():
    """The scipy reference itself against a hand calculation: nothing moves for two
    samples (the voltage computed at 0 is applied from T on), then
    i(2T) = Kp i_ref (1 - exp(-R T / L)) / R."""
    cfg = quiet_locked_arrow().config
    mo = cfg.motor
    y = E.analytic_current_step(cfg, 2.8, 5)
    a = math.exp(-mo.resistance_ohm / (mo.inductance_q_h * mo.pwm_frequency_hz))
    expected = cfg.current_loop.kp_v_per_a * 2.8 * (1.0 - a) / mo.resistance_ohm
    assert abs(y[0]) < 1e-12 and abs(y[1]) < 1e-12
    assert abs(y[2] - expected) < 1e-12


def test_current_step_settles_to_setpoint():
    """Noise-free 0.84 A step on a locked rotor: after 100 ms the current equals the
    setpoint (analytic: a PI loop has no steady error on a constant setpoint)."""
    run = E.run_current_step(quiet_locked_arrow(), 0.84, 800)
    assert abs(run.iq[-1] - 0.84) < 1e-6


def test_measured_equals_true_current_at_sampling_instant_without_noise():
    """Without noise and ADC the measured current is the true current at the sampling
    instant kT, held over the period (reference: the true-current trace itself)."""
    run = E.run_current_step(quiet_locked_arrow(), 2.8, 40)
    assert np.array_equal(run.iq_meas, run.iq)
    assert not np.array_equal(run.iq_meas[:-1], run.iq[1:])


def test_voltage_vector_never_exceeds_the_svpwm_limit():
    """A saturating step (id 20 A, iq 28 A): |u_dq| <= U_dc/sqrt(3) = 346 V (space-vector
    PWM, the default, on seed 000's 600 V DC link) in every PWM period, the limit is
    actually reached, and after 100 ms the current is at its setpoint (no integrator
    wind-up left)."""
    plant = quiet_locked_arrow()
    run = E.run_current_step(plant, 28.0, 800, id_ref=20.0)
    umax = plant.config.motor.dc_link_v / math.sqrt(3.0)
    assert run.u_mag.max() <= umax * (1.0 + 1e-12)
    assert run.u_mag.max() >= 0.999 * umax
    assert abs(run.iq[-1] - 28.0) < 1e-3


def test_voltage_mode_applies_voltage_one_period_later():
    """Voltage mode: a voltage set before period 0 is applied from period 1 on (one PWM
    period of dead time, seed 001 eq. 3); the locked-rotor current then follows the
    analytic R-L step i(t) = u/R (1 - exp(-R t / L))."""
    plant = quiet_locked_arrow()
    mo = plant.config.motor
    plant.set_input(mode=1, ud_v=0.0, uq_v=20.0)
    tr = plant.run(6, plant.sub_per_pwm)
    assert tr["uq_v"][0] == 0.0 and np.all(tr["uq_v"][1:] == 20.0)
    t_on = np.arange(6) * plant.pwm_period  # iq_a[k] is at (k+1)T; the voltage is on from T
    expected = 20.0 / mo.resistance_ohm * (1.0 - np.exp(-mo.resistance_ohm * t_on
                                                         / mo.inductance_q_h))
    assert np.max(np.abs(tr["iq_a"] - expected)) < 1e-8


def test_voltage_mode_limits_vector_to_the_svpwm_limit():
    """A voltage request of 500 V (400, 300) is scaled back onto the circle
    |u| = U_dc/sqrt(3) = 346.4 V with its direction kept (reference: that circle)."""
    plant = quiet_locked_arrow()
    plant.set_input(mode=1, ud_v=400.0, uq_v=300.0)
    tr = plant.run(2, plant.sub_per_pwm)
    scale = 600.0 / math.sqrt(3.0) / 500.0
    assert abs(tr["ud_v"][1] - 400.0 * scale) < 1e-9
    assert abs(tr["uq_v"][1] - 300.0 * scale) < 1e-9


# --- field weakening -------------------------------------------------------------------

def test_field_weakening_rows_ok(experiment_rows):
    """Steady torque at held speeds, with and without field weakening, vs the test's own
    implementation of seed 001 eq. 2, 4-6 and 8-10 with the current limit."""
    assert_rows_ok(experiment_rows("field_weakening"))


# --- current measurement ---------------------------------------------------------------

def test_current_noise_quantization_rows_ok(experiment_rows):
    """Standstill measurement statistics vs the configured noise, the exact std of a
    Gaussian rounded to the ADC grid, the grid itself and sample and hold."""
    assert_rows_ok(experiment_rows("current_noise_quantization"))


def test_quantized_gaussian_std_limits():
    """The reference itself: for a fine grid it tends to sigma, for lsb = sigma it agrees
    with Sheppard's correction sqrt(sigma^2 + lsb^2 / 12) (analytic limits)."""
    assert abs(E.quantized_gaussian_std(0.01, 1e-5) - 0.01) < 1e-8
    sheppard = math.sqrt(0.01 ** 2 + 0.01 ** 2 / 12.0)
    assert abs(E.quantized_gaussian_std(0.01, 0.01) / sheppard - 1.0) < 1e-3


def test_measured_current_with_flowing_current_on_grid_and_near_truth():
    """With the default noise and ADC and 2.8 A flowing, every measured value lies on the
    LSB grid and within 5 sigma + lsb/2 of the true current at its sampling instant
    (reference: the configured sigma and LSB)."""
    plant = Plant.from_file(E.ARROW, overrides=E.LOCKED)
    se = plant.config.sensors
    run = E.run_current_step(plant, 2.8, 400)
    grid = run.iq_meas / se.current_lsb_a
    assert np.max(np.abs(grid - np.round(grid))) < 1e-9
    err = run.iq_meas - run.iq
    assert np.max(np.abs(err)) <= 5.0 * se.current_noise_a + 0.5 * se.current_lsb_a
    assert err.std() > 0.5 * se.current_noise_a


# --- encoder ---------------------------------------------------------------------------

def test_encoder_resolution_rows_ok(experiment_rows):
    """Slow coasting on the seed 004 XY table: counts per revolution, lead, 38 nm per
    count (seed 004 §2.1) and count increments of 0 or 1."""
    assert_rows_ok(experiment_rows("encoder_resolution"))


def test_encoder_counts_whole_revolutions():
    """Three motor revolutions plus half a count: 3 * 131072 counts and 15 mm of table
    travel (seed 004 §2.1: 17 bits, 5 mm lead)."""
    plant = Plant.from_file(E.XY_TABLE)
    x = 3 * E.PAPER_LEAD_M + 0.5 * E.PAPER_LEAD_M / E.PAPER_COUNTS_PER_REV
    plant.reset(table_pos=x)
    assert plant.output("encoder_counts") == 3 * E.PAPER_COUNTS_PER_REV
    assert abs(plant.output("motor_pos") - 3 * 2.0 * math.pi) < 1e-4
