"""The machine-file keys for another simulator's conventions (issue 30 item 4), each against
an analytic case: encoder rounding and zero at the start, the current ADC's full scale, the
voltage-limit form, the Karnopp reversal and the rigid screw.  Each key's default is
today's behaviour, which the other plant tests hold bit for bit."""

import math
import tomllib

import numpy as np
import pytest

from plant import ConfigError, Plant
from plant import layout as L
from plant.assemble import natural_frequencies
from plant.config import parse_machine
from plant.effects.friction import karnopp_friction
from plant.effects.pmsm import dq_current_control
from plant.effects.sensors import counts, measure_current
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
LINEAR = CONFIGS / "ld386_linear.toml"
#: the Arrow without measurement delay or noise: its counts are those of the true positions
QUIET = {"sensors": {"delay_s": 0.0, "current_noise_a": 0.0}}


def _sensors(**keys) -> dict:
    return {"sensors": {**QUIET["sensors"], **keys}}


def test_count_rounding_against_floor_and_nearest():
    """Definition: floor(x) and floor(x + 1/2) of the position in counts x, on either side
    of zero (-0.25 counts: -1 by floor, 0 rounded; 2.5: 2 and 3)."""
    per = 4.0
    for x, floor, nearest in ((-0.25, -1.0, 0.0), (2.5, 2.0, 3.0), (2.49, 2.0, 2.0),
                              (-1.75, -2.0, -2.0)):
        assert counts(x / per, per, 0.0) == floor
        assert counts(x / per, per, 1.0) == nearest
    assert counts(1.0, 0.0, 1.0) == 0.0  # no such encoder


@pytest.mark.parametrize("rounding", ["floor", "round"])
def test_encoder_and_scale_count_a_known_position(rounding):
    """Analytic: the Arrow's table at rest at x shows the motor-encoder count of
    x / (lead/2pi) * counts/rev / 2pi and the scale count of x / resolution, floored or
    rounded; x is chosen 3/4 of a count past a whole motor count, where the two differ by
    one (and 0.3 of a scale count: the same scale count either way, by arithmetic)."""
    plant = Plant.from_file(ARROW, overrides=_sensors(encoder_rounding=rounding))
    se, ratio = plant.config.sensors, plant.built.ratio
    per_rad = se.encoder_counts_per_rev / (2.0 * math.pi)
    x = (1234567.75 / per_rad) * ratio
    plant.reset(x)
    whole = {"floor": math.floor, "round": lambda c: math.floor(c + 0.5)}[rounding]
    assert plant.output("encoder_counts") == whole(x / ratio * per_rad)
    assert plant.output("encoder_counts") == 1234567 + (rounding == "round")
    assert plant.output("scale_counts") == whole(x / se.scale_resolution_m)


def test_encoders_count_from_the_start_position():
    """Analytic: with encoder_zero_at_start the first counts are 0 at any start position
    (also through a measurement delay), and after a move the counts are those of the
    travel since the start, q((theta - theta_0) per rad) and q((x - x_0) / resolution);
    without it the first counts are those of the position itself."""
    x0 = 0.123456789
    for rounding in ("floor", "round"):
        plant = Plant.from_file(ARROW, x0, _sensors(encoder_zero_at_start=True,
                                                    encoder_rounding=rounding))
        assert plant.output("encoder_counts") == 0.0
        assert plant.output("scale_counts") == 0.0
    delayed = Plant.from_file(ARROW, x0, {"sensors": {"encoder_zero_at_start": True,
                                                      "delay_s": 0.000375}})
    delayed.set_input(iq_ref_a=5.0)
    first = delayed.run(3, delayed.sub_per_pwm)
    assert np.all(first["encoder_counts"] == 0.0) and np.all(first["scale_counts"] == 0.0)
    plant = Plant.from_file(ARROW, x0, _sensors(encoder_zero_at_start=True))
    theta0 = plant.output("motor_pos")
    plant.set_input(iq_ref_a=5.0)
    plant.run(200, plant.sub_per_pwm)
    se = plant.config.sensors
    per_rad = se.encoder_counts_per_rev / (2.0 * math.pi)
    travel = plant.output("motor_pos") - theta0
    assert travel * per_rad > 1000.0  # it moved
    assert plant.output("encoder_counts") == math.floor(travel * per_rad)
    assert plant.output("scale_counts") == math.floor(
        (plant.output("table_pos") - x0) / se.scale_resolution_m)
    absolute = Plant.from_file(ARROW, x0, QUIET)
    assert absolute.output("encoder_counts") == math.floor(theta0 * per_rad)


def test_current_adc_clips_at_full_scale():
    """Definition: after noise and quantization the reading is limited to +-full scale: 5 A
    and -5 A read +-2 A, 1.5 A reads 1.5 A; 0 (the default) never clips."""
    p = np.zeros(L.P_COUNT)
    s = np.zeros(L.S_COUNT)
    assert measure_current(p, s, 5000.0) == 5000.0
    p[L.P_I_FULL_SCALE] = 2.0
    assert [measure_current(p, s, i) for i in (5.0, -5.0, 1.5)] == [2.0, -2.0, 1.5]


def test_plant_measures_no_current_beyond_full_scale():
    """Analytic: the Arrow's current loop asked for 6 A with a 4 A full scale drives the
    true current past 4 A, and the measured current is at most 4 A, reaching it exactly."""
    plant = Plant.from_file(ARROW, overrides=_sensors(current_full_scale_a=4.0,
                                                      current_lsb_a=0.0))
    plant.set_input(iq_ref_a=6.0)
    run = plant.run(40, plant.sub_per_pwm)
    assert run["iq_a"].max() > 4.5
    assert np.abs(run["iq_meas_a"]).max() == 4.0


def _controller(q_only: bool) -> tuple[float, float]:
    """(u_d, u_q) of one current-controller event asked for 30 A on both axes from rest,
    K_p = 10 V/A, no integral or precontrol, a 100 V limit."""
    p = np.zeros(L.P_COUNT)
    s = np.zeros(L.S_COUNT)
    p[L.P_DT], p[L.P_SUB_PER_PWM], p[L.P_I_MAX], p[L.P_U_MAX] = 1e-5, 10.0, 50.0, 100.0
    p[L.P_KP_I] = 10.0
    p[L.P_U_Q_ONLY] = 1.0 if q_only else 0.0
    dq_current_control(p, s, 30.0, 30.0, 0.0)
    return s[L.S_UD_NEXT], s[L.S_UQ_NEXT]


def test_voltage_limit_vector_or_q_alone():
    """Analytic: K_p e = 300 V on both axes against a 100 V limit.  The vector limit serves
    d first: u_d = 100 V, u_q = sqrt(100^2 - 100^2) = 0.  The q clamp leaves u_d = 300 V
    and limits u_q to 100 V."""
    assert _controller(q_only=False) == (100.0, 0.0)
    assert _controller(q_only=True) == (300.0, 100.0)


def test_voltage_limit_key_sets_the_kernel_and_applies_to_dq_only():
    """The key reaches the kernel's parameters (0 by default) and is refused where the
    plant has no voltage controller (a first-order current loop)."""
    assert Plant.from_file(ARROW).params[L.P_U_Q_ONLY] == 0.0
    plant = Plant.from_file(ARROW, overrides={"motor": {"voltage_limit": "q"}})
    assert plant.params[L.P_U_Q_ONLY] == 1.0
    with pytest.raises(ConfigError, match="voltage_limit does not apply here"):
        Plant.from_file(LINEAR, overrides={"motor": {"voltage_limit": "q"}})


def _friction(stop: bool) -> np.ndarray:
    p = np.zeros(L.P_COUNT)
    p[L.P_FR_COULOMB], p[L.P_FR_STATIC] = 25.0, 37.5
    p[L.P_FR_REVERSAL_STOP] = 1.0 if stop else 0.0
    return p


def test_karnopp_reversal_breakaway_or_stop():
    """Analytic, one sub-step of 1e-3 s on 1 kg moving at +0.01 m/s: 20 N against it
    (below F_H = 37.5 N) would reverse it, and either variant stops it (friction -f_app);
    100 N against it (above F_H) reverses it under Coulomb friction (-25 N) with the
    default, and stops it with 'stop'."""
    for stop in (False, True):
        assert karnopp_friction(_friction(stop), 0.01, -20.0, 1.0, 1e-3) == (20.0, True)
    assert karnopp_friction(_friction(False), 0.01, -100.0, 1.0, 1e-3) == (-25.0, False)
    assert karnopp_friction(_friction(True), 0.01, -100.0, 1.0, 1e-3) == (100.0, True)
    # at rest the next step breaks away against F_H either way
    assert karnopp_friction(_friction(True), 0.0, -100.0, 1.0, 1e-3) == (37.5, False)


def test_stop_reversal_needs_karnopp_friction():
    """Refusal: 'stop' on a machine whose friction has no stick-slip (presliding, or no
    Coulomb and breakaway level) would change nothing, and the loader says why."""
    no_level = {"friction": {"coulomb_n": 0.0, "breakaway_n": 0.0,
                             "karnopp_reversal": "stop"}}
    with pytest.raises(ConfigError, match="no Coulomb or breakaway level"):
        Plant.from_file(LINEAR, overrides=no_level)
    presliding = {"friction": {"karnopp_reversal": "stop"}}
    with pytest.raises(ConfigError, match=r"\[presliding\] replaces it"):
        Plant.from_file(CONFIGS / "xy_table_004.toml", overrides=presliding)


LINEAR_BARE = {"cogging": {"orders": [], "amplitudes_n": [], "phases_deg": []},
               "friction": {"viscous_ns_per_m": 0.0, "coulomb_n": 20.0, "breakaway_n": 30.0,
                            "zero_velocity_band_m_s": 0.0}}


def _linear_table(reversal: str, v0: float, load_n: float) -> Plant:
    """The LD386 table (no cogging, F_C = 20 N, F_H = 30 N, no band) moving at ``v0`` m/s
    with the power stage off (no motor force) and ``load_n`` N on it."""
    over = {**LINEAR_BARE, "friction": {**LINEAR_BARE["friction"],
                                        "karnopp_reversal": reversal}}
    plant = Plant.from_file(LINEAR, 0.5, over)
    s, p = plant.state, plant.params
    s[int(p[L.P_SOFF_ROT]) + int(p[L.P_N_ROT])] = v0
    plant.set_input(enable=0.0, load=load_n)
    return plant


@pytest.mark.parametrize("reversal", ["breakaway", "stop"])
def test_table_below_breakaway_stays_at_exactly_zero(reversal):
    """Analytic: at rest under 25 N (< F_H = 30 N) the table's velocity stays exactly 0."""
    plant = _linear_table(reversal, 0.0, 25.0)
    run = plant.run(50, plant.sub_per_pwm)
    assert np.all(run["table_vel"] == 0.0)


def test_table_reversal_stops_it_for_one_sub_step():
    """Analytic, on the LD386's m = 14.5 kg: moving at v0 with 100 N against it, a step of dt
    would reach v0 - dt (100 + 20)/m < 0.  The default reverses within the step to that
    value; 'stop' ends the step at exactly 0 and the next one breaks away from rest against
    F_H: -dt (100 - 30)/m."""
    mass = 14.5
    probe = Plant.from_file(LINEAR, 0.5, LINEAR_BARE)
    dt = probe.dt
    v0 = 0.5 * dt * 120.0 / mass
    default = _linear_table("breakaway", v0, -100.0)
    default.step(1)
    assert default.output("table_vel") == pytest.approx(v0 - dt * 120.0 / mass, rel=1e-9)
    stop = _linear_table("stop", v0, -100.0)
    stop.step(1)
    assert stop.output("table_vel") == 0.0
    stop.step(1)
    assert stop.output("table_vel") == pytest.approx(-dt * 70.0 / mass, rel=1e-9)


def test_rigid_screw_follows_the_motor_through_the_lead():
    """Analytic: a screw axis with [mechanics] model = "rigid" (the Arrow's motor, lead and
    table friction; no [coupling] or [screw]) is one body: the table stands at
    x = lead theta / 2pi at every sample of a move, and the mechanics have no elastic
    mode (the only natural frequency is the rigid body's 0)."""
    raw = tomllib.loads(ARROW.read_text())
    raw["mechanics"]["model"] = "rigid"
    raw.pop("pitch_error", None)
    del raw["coupling"], raw["screw"]
    plant = Plant(parse_machine(raw, "rigid screw"), 0.1)
    lead = plant.config.mechanics.lead_m
    assert natural_frequencies(plant.config).tolist() == [0.0]
    plant.set_input(iq_ref_a=5.0)
    run = plant.run(400, plant.sub_per_pwm)
    assert run["table_pos"][-1] - 0.1 > 1e-3  # it moved a millimetre and more
    np.testing.assert_allclose(run["table_pos"], lead * run["motor_pos"] / (2.0 * math.pi),
                               rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(run["table_vel"], lead * run["motor_vel"] / (2.0 * math.pi),
                               rtol=1e-15, atol=0.0)
