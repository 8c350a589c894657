"""The plant's fault terms (issue 14 part 6, plant.effects.faults) against independent
results: the two-sensor Clarke/Park transform written out from its definition, the
closed current loop's quasi-static solution (the loop makes the measurement equal the
reference), Sheppard's quantization variance, the Bernoulli sum of lost counts, the
ripple formula, and the healthy kernel (every fault value 0 on the fault path against
P_FAULTS = 0; P_FAULTS = 0 against the reference trajectories is
tests/test_kernel_speed.py's).

The Arrow 500 X runs with a rotor of 1e6 kg·m² (hil.validate.experiments.electrical's
LOCKED): it keeps the speed it is given, so the electrical angle sweeps at a constant
rate while the current loop and the sensors do their work; current noise and cogging
are off where they would blur the comparison.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.bench.csubstep import CStep, compiler
from hil.validate.experiments import electrical as E
from plant import Plant
from plant import layout as L
from plant.effects.faults import faults_active, first_order_target, two_sensor_dq
from tests.conftest import CONFIGS
from tests.kernel_reference import START_POS_M, cases, set_inputs

ARROW = CONFIGS / "arrow500_x.toml"
GEISS = CONFIGS / "geiss_c_axis.toml"  # the commutation model
#: the fault terms' state (S_ENC_PREV follows the encoder on the fault path)
FAULT_STATE = (L.S_ENC_LOST, L.S_ENC_PREV, L.S_ENC_NOISE)
TABLE_M = 0.25  # table start: mid travel


def two_sensor_reference(i_d, i_q, theta, offset_a, gain_err):
    """The measured (i_d, i_q) of the task's definition, step by step: phase currents,
    the faulty phase-a sensor, Clarke (alpha = a, beta = (a + 2 b)/sqrt(3)), Park."""
    i_a = i_d * math.cos(theta) - i_q * math.sin(theta)
    i_b = i_d * math.cos(theta - 2 * math.pi / 3) - i_q * math.sin(theta - 2 * math.pi / 3)
    a = (1.0 + gain_err) * i_a + offset_a
    alpha, beta = a, (a + 2.0 * i_b) / math.sqrt(3.0)
    return (alpha * math.cos(theta) + beta * math.sin(theta),
            -alpha * math.sin(theta) + beta * math.cos(theta))


def with_faults(plant: Plant, **values: float) -> Plant:
    """``plant`` with the fault parameters ``values`` (names of plant.layout) and P_FAULTS
    as the injector sets it."""
    for name, value in values.items():
        plant.params[getattr(L, name)] = value
    plant.params[L.P_FAULTS] = faults_active(plant.params)
    return plant


def spinning(config, omega_m: float, *extra: dict, **faults: float) -> Plant:
    """The machine file ``config`` with the locked rotor turning at ``omega_m`` (rad/s):
    every torsional node and the table move together, so the chain starts without strain."""
    plant = Plant.from_file(config, table_pos=TABLE_M if config == ARROW else 0.0,
                            overrides=E.merged(E.LOCKED, E.QUIET, E.NO_COGGING, *extra))
    p, s = plant.params, plant.state
    ro, nr = int(p[L.P_SOFF_ROT]), int(p[L.P_N_ROT])
    s[ro + nr:ro + 2 * nr] = omega_m
    s[L.S_TABLE_V] = omega_m * p[L.P_LEAD_RATIO]
    return with_faults(plant, **faults)


def run_periods(plant: Plant, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta_e, true i_q) at the end of each of ``n`` PWM periods."""
    theta = np.empty(n)
    iq = np.empty(n)
    for k in range(n):
        plant.step(plant.sub_per_pwm)
        theta[k] = plant.params[L.P_POLE_PAIRS] * plant.out[L.O_MOTOR_POS]
        iq[k] = plant.out[L.O_IQ]
    return theta, iq


def harmonics(theta: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least-squares [mean, cos, sin, cos 2x, sin 2x] coefficients of y(theta)."""
    basis = np.column_stack([np.ones_like(theta), np.cos(theta), np.sin(theta),
                             np.cos(2 * theta), np.sin(2 * theta)])
    return np.linalg.lstsq(basis, y, rcond=None)[0]


# --- zero error -------------------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@given(st.floats(-30, 30), st.floats(-30, 30), st.floats(-50, 50))
def test_two_sensor_transform_without_error_is_the_identity(i_d, i_q, theta):
    """Offset 0 and gain error 0 give back (i_d, i_q) to 1e-12 A, in the kernel's form and
    in the task's definition (which checks the sign conventions of Clarke and Park)."""
    assert two_sensor_dq(i_d, i_q, theta, 0.0, 0.0) == (i_d, i_q)
    d, q = two_sensor_reference(i_d, i_q, theta, 0.0, 0.0)
    assert abs(d - i_d) < 1e-12 and abs(q - i_q) < 1e-12


@settings(max_examples=200, deadline=None)
@given(st.floats(-30, 30), st.floats(-30, 30), st.floats(-50, 50), st.floats(-1, 1),
       st.floats(-0.2, 0.2))
def test_two_sensor_transform_against_its_definition(i_d, i_q, theta, offset_a, gain_err):
    """The kernel's error form (the sensor error rotated into d-q) against phase currents,
    Clarke and Park written out: to 1e-12 A."""
    got = two_sensor_dq(i_d, i_q, theta, offset_a, gain_err)
    want = two_sensor_reference(i_d, i_q, theta, offset_a, gain_err)
    assert abs(got[0] - want[0]) < 1e-12 and abs(got[1] - want[1]) < 1e-12


@pytest.mark.parametrize("name", sorted(cases()))
def test_fault_path_with_zero_values_matches_the_healthy_kernel(name):
    """P_FAULTS = 1 with every fault value 0 runs the fault code (sensor transform, ripple,
    first-order target, encoder sampling) and must agree with the healthy path to 1e-12
    (relative, or absolute below 1) under the reference stimulus."""
    cfg, overrides = cases()[name]
    healthy = Plant.from_file(cfg, table_pos=START_POS_M, overrides=overrides)
    faulty = Plant.from_file(cfg, table_pos=START_POS_M, overrides=overrides)
    faulty.params[L.P_FAULTS] = 1.0
    rng_a, rng_b = np.random.default_rng(12), np.random.default_rng(12)
    keep = np.ones(healthy.state.size, bool)
    keep[list(FAULT_STATE)] = False
    for k in range(300):
        set_inputs(k, healthy, rng_a)
        set_inputs(k, faulty, rng_b)
        healthy.step(healthy.sub_per_pwm)
        faulty.step(faulty.sub_per_pwm)
    np.testing.assert_allclose(faulty.state[keep], healthy.state[keep], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(faulty.out, healthy.out, rtol=1e-12, atol=1e-12)
    assert faulty.state[L.S_ENC_LOST] == 0.0 and faulty.state[L.S_ENC_NOISE] == 0.0


def test_faults_active_names_each_term():
    """Each acting term switches P_FAULTS on; order and phase without amplitude do not."""
    p = Plant.from_file(ARROW).params
    assert faults_active(p) == 0.0
    for name in ("P_ENC_NOISE", "P_ENC_LOST", "P_I_OFFSET", "P_I_GAIN_ERR", "P_RIPPLE_AMP"):
        q = p.copy()
        q[getattr(L, name)] = 0.01
        assert faults_active(q) == 1.0, name
    q = p.copy()
    q[L.P_RIPPLE_ORDER], q[L.P_RIPPLE_PHASE] = 2.0, 1.0
    assert faults_active(q) == 0.0


@pytest.mark.skipif(compiler() is None, reason="no C compiler on PATH: the C port cannot "
                    "be built (apt-get install gcc)")
def test_c_port_runs_only_the_healthy_machine():
    """The C sub-step (hil bench plant's baseline) carries no fault term: it declines an
    axis with P_FAULTS set."""
    cstep = CStep()
    params = Plant.from_file(ARROW).params
    assert cstep.supports(params)
    params[L.P_FAULTS] = 1.0
    assert not cstep.supports(params)


# --- current sensor ---------------------------------------------------------------------

#: motor speed of the current-sensor tests: 30 rad/s electrical, 1 % of the current
#: loop's ~2.7e3 rad/s bandwidth (K_p / L), so the loop follows the error quasi-statically
#: (its lag turns the ripple's phase by about 1 %; the tolerances below are 2 %)
OMEGA_SLOW = 10.0
SETTLE = 200  # PWM periods (25 ms: the loop settles within a few ms)
PERIODS = 3400  # 0.425 s: two electrical revolutions at OMEGA_SLOW


@pytest.mark.parametrize("config, omega_m, periods", [
    (ARROW, OMEGA_SLOW, PERIODS),
    # the commutation model's coil current, no field weakening at this speed (gamma = 0):
    # 11 rad/s electrical against a loop of ~2.7e3 rad/s, two revolutions
    (GEISS, 0.5, 9200)])
def test_offset_gives_the_analytic_1x_ripple(config, omega_m, periods):
    """Offset o on phase a: the loop holds the measurement at (0, i_ref), so the true q
    current is i_ref - o (cos/sqrt(3) - sin) (the error's opposite): mean i_ref, a 1x
    ripple of amplitude 2 o / sqrt(3), no 2x; least-squares fit over two electrical
    revolutions within 2 % of the amplitude."""
    o, i_ref = 0.5, 2.0
    plant = spinning(config, omega_m, P_I_OFFSET=o)
    plant.set_input(iq_ref_a=i_ref)
    run_periods(plant, SETTLE)
    c = harmonics(*run_periods(plant, periods))
    amp = 2.0 * o / math.sqrt(3.0)
    assert math.hypot(c[1], c[2]) == pytest.approx(amp, rel=0.02)
    np.testing.assert_allclose(c, [i_ref, -o / math.sqrt(3.0), o, 0.0, 0.0], atol=0.02 * amp)


def test_gain_error_gives_the_analytic_mean_and_2x_ripple():
    """Gain error g on phase a: solving (I + g v a^T) i = (0, i_ref) (Sherman-Morrison,
    a.v = 1) gives i_q = i_ref (1 + g/(1+g) (sin 2x/(2 sqrt 3) + cos 2x/2 - 1/2)): mean
    i_ref (1 - g/(2 (1+g))), a 2x ripple of amplitude i_ref g/((1+g) sqrt 3), no 1x; the
    fit within 2 % of the ripple's amplitude."""
    g, i_ref = 0.05, 10.0
    plant = spinning(ARROW, OMEGA_SLOW, P_I_GAIN_ERR=g)
    plant.set_input(iq_ref_a=i_ref)
    run_periods(plant, SETTLE)
    c = harmonics(*run_periods(plant, PERIODS))
    k = i_ref * g / (1.0 + g)
    amp = k / math.sqrt(3.0)
    assert math.hypot(c[3], c[4]) == pytest.approx(amp, rel=0.02)
    np.testing.assert_allclose(c, [i_ref - k / 2.0, 0.0, 0.0, k / 2.0, k / (2 * math.sqrt(3))],
                               atol=0.02 * amp)


def test_first_order_target_is_measured_as_the_reference():
    """The first-order model's target current, put through the sensors, reads as the
    reference (the definition of the two-sensor measurement, i_d = 0)."""
    p = with_faults(Plant.from_file(CONFIGS / "xy_table_004.toml"),
                    P_I_OFFSET=0.3, P_I_GAIN_ERR=-0.04).params
    for theta in np.linspace(-7.0, 7.0, 57):
        target = first_order_target(p, 1.5, theta)
        _, q = two_sensor_reference(0.0, target, theta, 0.3, -0.04)
        assert q == pytest.approx(1.5, abs=1e-12)


# --- encoder ----------------------------------------------------------------------------

def resting_arrow(**faults: float) -> Plant:
    """The locked Arrow at rest, the motor angle half a count above a whole count (the
    noisy reading's floor then has mean 0 around the noise-free count), power stage off."""
    cfg_plant = Plant.from_file(ARROW, overrides=E.merged(E.LOCKED, E.QUIET, E.NO_COGGING))
    per_rad = cfg_plant.params[L.P_ENC_COUNTS_PER_RAD]
    table = (math.floor(TABLE_M / cfg_plant.built.ratio * per_rad) + 0.5) / per_rad \
        * cfg_plant.built.ratio
    plant = Plant.from_file(ARROW, table_pos=table,
                            overrides=E.merged(E.LOCKED, E.QUIET, E.NO_COGGING))
    plant.set_input(enable=0.0)
    return with_faults(plant, **faults)


def encoder_error(plant: Plant, n: int) -> np.ndarray:
    """encoder - floor(theta cpr) at the end of each of ``n`` PWM periods (counts)."""
    per_rad = plant.params[L.P_ENC_COUNTS_PER_RAD]
    err = np.empty(n)
    for k in range(n):
        plant.step(plant.sub_per_pwm)
        err[k] = plant.out[L.O_ENCODER] - math.floor(plant.out[L.O_MOTOR_POS] * per_rad)
    return err


@pytest.mark.parametrize("sigma", [0.7, 2.0, 6.0])
def test_encoder_noise_rms_is_noise_plus_quantization(sigma):
    """Motor at rest, noise sigma counts: the rms of encoder - floor(theta cpr) over 4000
    samples within 5 % of sqrt(sigma^2 + 1/12) (a continuous noisy reading floored:
    Sheppard's correction; the sampling error of the rms is about 1.1 %); mean 0."""
    err = encoder_error(resting_arrow(P_ENC_NOISE=sigma), 4000)
    assert np.all(err == np.round(err))
    assert math.sqrt(np.mean(err ** 2)) == pytest.approx(math.sqrt(sigma ** 2 + 1 / 12), rel=0.05)
    assert abs(np.mean(err)) < 4.0 * sigma / math.sqrt(4000)


@pytest.mark.parametrize("omega_m", [10.0, -10.0])
def test_lost_counts_are_a_bernoulli_sum_against_the_motion(omega_m):
    """At constant speed over N counts with P_ENC_LOST = 1e-4 per count: the lost total
    (encoder - floor(theta cpr), and S_ENC_LOST) within 4 sigma of 1e-4 N, sigma =
    sqrt(1e-4 N) bounding the Bernoulli sum's spread; its sign opposite to the motion."""
    lost_per_count = 1e-4
    plant = spinning(ARROW, omega_m, P_ENC_LOST=lost_per_count)
    per_rad = plant.params[L.P_ENC_COUNTS_PER_RAD]
    start = math.floor(plant.out[L.O_MOTOR_POS] * per_rad)
    err = encoder_error(plant, 8000)
    n = abs(math.floor(plant.out[L.O_MOTOR_POS] * per_rad) - start)
    lost = -math.copysign(1.0, omega_m) * err[-1]
    assert err[-1] == plant.state[L.S_ENC_LOST]
    assert abs(lost - lost_per_count * n) < 4.0 * math.sqrt(lost_per_count * n)
    assert lost > 0 and np.all(np.sign(err[err != 0]) == -math.copysign(1.0, omega_m))
    assert np.all(np.diff(err) * math.copysign(1.0, omega_m) <= 0)  # lost counts persist


def test_no_counts_lost_at_rest():
    """Even a loss probability of 1/2 per count loses nothing while nothing moves."""
    err = encoder_error(resting_arrow(P_ENC_LOST=0.5), 500)
    assert np.all(err == 0.0)


# --- torque ripple ----------------------------------------------------------------------

def test_torque_ripple_is_proportional_to_the_motor_torque():
    """Constant q current (ripple changing it only a little), the motor turning slowly, no
    cogging: the last sub-step's torque equals K_t i_q (1 + a cos(k theta_e + phi)) with
    i_q and theta_e at that sub-step's start, to 1e-9 relative (L_d = L_q: no reluctance
    torque)."""
    a, k, phi = 0.08, 1.5, 0.7
    plant = spinning(ARROW, OMEGA_SLOW, P_RIPPLE_AMP=a, P_RIPPLE_ORDER=k, P_RIPPLE_PHASE=phi)
    p, s = plant.params, plant.state
    ro = int(p[L.P_SOFF_ROT])
    plant.set_input(iq_ref_a=5.0)
    plant.step(SETTLE * plant.sub_per_pwm)
    for _ in range(300):
        plant.step(plant.sub_per_pwm - 1)
        theta_e, i_q = p[L.P_POLE_PAIRS] * s[ro], s[L.S_IQ]
        plant.step(1)
        want = p[L.P_KT] * i_q * (1.0 + a * math.cos(k * theta_e + phi))
        assert plant.out[L.O_TORQUE] == pytest.approx(want, rel=1e-9)


# --- determinism ------------------------------------------------------------------------

ALL_FAULTS = {"P_ENC_NOISE": 1.5, "P_ENC_LOST": 1e-4, "P_I_OFFSET": 0.2, "P_I_GAIN_ERR": 0.03,
              "P_RIPPLE_AMP": 0.05, "P_RIPPLE_ORDER": 2.0, "P_RIPPLE_PHASE": 0.3}


def _faulty_run(seed: int) -> np.ndarray:
    plant = spinning(ARROW, OMEGA_SLOW, {"sensors": {"current_noise_a": 0.01, "seed": seed}},
                           **ALL_FAULTS)
    plant.set_input(iq_ref_a=3.0)
    plant.step(400 * plant.sub_per_pwm)
    return plant.state.copy()


def test_same_seed_same_faulty_run():
    """Every fault on and current noise: the same seed gives the same state bit for bit;
    another seed a different one (the draws come from the axis's own stream)."""
    first = _faulty_run(1)
    assert first.tobytes() == _faulty_run(1).tobytes()
    assert first[L.S_ENC_NOISE] != _faulty_run(2)[L.S_ENC_NOISE]
