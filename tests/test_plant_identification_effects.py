"""Plant effects the identification work needs: ball-screw pitch error, a constant external
force on the table, and a measurement delay.  Each against an independent reference:

* pitch error: the table position against the motor angle is the prescribed harmonic
  function (analytic) in a slow constant-speed move; a holding torque through the local
  ratio lead/2pi (1 + e') balances a force exactly (virtual work, analytic);
* external force: constant acceleration a = F / m and static equilibrium with the
  holding current F r / K_t (analytic, Newton) on rigid axes;
* measurement delay: the delayed measured outputs are the undelayed ones of a second
  plant, shifted by exactly N PWM periods; the controller of the lock-step simulation
  sees the scale N periods late;
* the loader refuses what cannot be, naming the file, the key and the unit.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from hil.controller.config import axis_limits, load_controller
from hil.controller.interpolator import plan
from hil.controller.program import parse_program
from hil.sim import LockStep
from plant import ConfigError, Plant, load_machine
from plant import layout as L
from plant.assemble import reflected_inertia, transmission_ratio

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
EMPS = CONFIGS / "emps.toml"
ARROW = CONFIGS / "arrow500_x.toml"
LINEAR = CONFIGS / "ld386_linear.toml"
ROTARY = CONFIGS / "geiss_c_axis.toml"

PITCH = {"periods_m": [0.01, 0.004], "amplitudes_m": [8e-6, 2e-6], "phases_deg": [30.0, -60.0],
         "linear_ppm": 40.0}


def pitch_error_analytic(u):
    """e(u) in m of PITCH at nominal position u (m): sum A sin(2 pi u / P + phi) + c u."""
    e = PITCH["linear_ppm"] * 1e-6 * u
    for period, amp, ph in zip(PITCH["periods_m"], PITCH["amplitudes_m"], PITCH["phases_deg"]):
        e += amp * np.sin(2.0 * np.pi * u / period + np.radians(ph))
    return e


def pitch_slope_analytic(u):
    """de/du (m/m) of PITCH at u."""
    s = PITCH["linear_ppm"] * 1e-6
    for period, amp, ph in zip(PITCH["periods_m"], PITCH["amplitudes_m"], PITCH["phases_deg"]):
        k = 2.0 * np.pi / period
        s += amp * k * np.cos(k * u + np.radians(ph))
    return s


def constant_speed_move(plant: Plant, v_table: float, seconds: float):
    """Drive the motor at v_table / ratio with a PI speed loop on the motor velocity
    (crossover about 30 Hz on the reflected inertia); record motor and table positions
    every PWM period.  Returns (motor_pos, table_pos, scale_counts), each shape (n,)."""
    cfg = plant.config
    r = transmission_ratio(cfg)
    kt = cfg.motor.torque_constant_nm_per_a
    wc = 2.0 * math.pi * 30.0
    kp = reflected_inertia(cfg) * wc / kt
    ki = kp * wc / 4.0
    w_ref = v_table / r
    period = plant.pwm_period
    integ = 0.0
    n = round(seconds / period)
    motor, table, scale = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        err = w_ref - plant.output("motor_vel")
        integ += ki * err * period
        plant.set_input(iq_ref_a=kp * err + integ)
        assert plant.step(plant.sub_per_pwm) == L.STATUS_OK
        motor[k], table[k] = plant.output("motor_pos"), plant.output("table_pos")
        scale[k] = plant.output("scale_counts")
    return motor, table, scale


# --- pitch error ------------------------------------------------------------------------------

def test_pitch_error_rigid_table_is_nominal_plus_harmonics():
    """Rigid EMPS axis with a pitch error, 10 mm/s over 20 mm (five periods of the longest
    harmonic): the table stands at u + e(u), u = lead/2pi * motor angle, with e the
    prescribed harmonics plus the linear lead error (analytic, to rounding); the linear
    scale reads the true table position and the reset puts the table (not the screw) at
    the requested place."""
    x0 = 0.05
    plant = Plant.from_file(EMPS, x0, overrides={"pitch_error": PITCH,
                                                  "sensors": {"scale_resolution_m": 1e-8}})
    assert plant.output("table_pos") == pytest.approx(x0, abs=1e-15)
    r = transmission_ratio(plant.config)
    motor, table, scale = constant_speed_move(plant, 0.01, 2.0)
    u = r * motor
    assert u[-1] - u[0] > 0.019
    np.testing.assert_allclose(table, u + pitch_error_analytic(u), rtol=0.0, atol=1e-14)
    assert np.ptp(table - u) > 15e-6  # the error is there: ~2 (8 + 2) µm peak to peak
    np.testing.assert_allclose(scale * 1e-8, table, rtol=0.0, atol=1.0001e-8)


@pytest.mark.parametrize("variant", ["two_mass", "screw"])
def test_pitch_error_elastic_drive_table_follows_harmonics(variant):
    """Elastic drives at a slow constant speed (10 mm/s, no cogging): the table minus
    (u + e(u)), u = lead/2pi * motor angle, is only the drive train's elastic deflection
    under the steady friction, which barely changes: its spread is below 1 % of the
    error's own spread (analytic e; the deflection's ripple from the error's e'' v^2 and
    the nut's moving place is far smaller).  two_mass: the EMPS axis with a coupling; screw:
    the Arrow 500 X with the error applied at the nut."""
    if variant == "two_mass":
        overrides = {"mechanics": {"model": "two_mass"},
                     "coupling": {"stiffness_nm_per_rad": 2000.0, "damping_nms_per_rad": 0.2}}
        path, x0 = EMPS, 0.05
    else:
        overrides = {"cogging": {"orders": [], "amplitudes_nm": [], "phases_deg": []}}
        path, x0 = ARROW, 0.1
    overrides["pitch_error"] = PITCH
    plant = Plant.from_file(path, x0, overrides=overrides)
    r = transmission_ratio(plant.config)
    motor, table, _ = constant_speed_move(plant, 0.01, 2.5)
    steady = slice(round(0.5 / plant.pwm_period), None)  # the speed loop has settled
    u = r * motor[steady]
    e = pitch_error_analytic(u)
    deflection = table[steady] - u - e
    assert np.ptp(e) > 15e-6
    assert np.ptp(deflection) < 0.01 * np.ptp(e), (np.ptp(deflection), np.ptp(e))


def test_pitch_error_force_maps_through_local_ratio():
    """Rigid EMPS axis, no friction, a pitch error and an external force F = -300 N on the
    table: a motor torque of -F lead/2pi (1 + e'(u0)) holds the table still (virtual work:
    dx = lead/2pi (1 + e') dtheta), while the nominal -F lead/2pi leaves the force
    F e'(u0) unbalanced and the table accelerates by about that over m (Newton)."""
    force, x0, seconds = -300.0, 0.0523, 0.05
    over = {"pitch_error": PITCH, "table": {"external_force_n": force},
            "friction": {"viscous_ns_per_m": 0.0}}
    cfg = load_machine(EMPS, over)
    r, kt = transmission_ratio(cfg), cfg.motor.torque_constant_nm_per_a
    mass = reflected_inertia(cfg) / r ** 2
    moved = {}
    for name, slope in (("local", None), ("nominal", 0.0)):
        plant = Plant(cfg, x0)
        u0 = r * plant.output("motor_pos")
        g = 1.0 + (pitch_slope_analytic(u0) if slope is None else slope)
        iq = -force * r * g / kt
        plant.state[L.S_IQ] = iq  # the first-order current loop starts settled
        plant.set_input(iq_ref_a=iq)
        plant.run(round(seconds / plant.pwm_period), plant.sub_per_pwm)
        moved[name] = plant.output("table_pos") - x0
        unbalanced = force * pitch_slope_analytic(u0)
    assert abs(moved["local"]) < 1e-12
    expected = 0.5 * unbalanced / mass * seconds ** 2
    assert moved["nominal"] == pytest.approx(expected, rel=0.02)
    assert abs(moved["nominal"]) > 1e-6


# --- external force ---------------------------------------------------------------------------

FREE = {  # no friction and no motor torque: the external force alone moves the axis
    "screw": (EMPS, {"friction": {"viscous_ns_per_m": 0.0}}, "table", "external_force_n", 250.0),
    "linear": (LINEAR, {"friction": {"viscous_ns_per_m": 0.0, "coulomb_n": 0.0,
                                     "breakaway_n": 0.0},
                        "cogging": {"orders": [], "amplitudes_n": [], "phases_deg": []}},
               "table", "external_force_n", -40.0),
    "rotary": (ROTARY, {"friction": {"viscous_nms_per_rad": 0.0, "coulomb_nm": 0.0,
                                     "breakaway_nm": 0.0},
                        "motor": {"viscous_nms_per_rad": 0.0},
                        "cogging": {"orders": [], "amplitudes_nm": [], "phases_deg": []}},
               "mechanics", "external_torque_nm", 30.0),
}


@pytest.mark.parametrize("kind", list(FREE))
def test_external_force_gives_constant_acceleration(kind):
    """Power stage off, no friction: the machine file's constant force (torque) F
    accelerates the table at a = F / m (m: every inertia reflected to the table; rotary:
    alpha = T / J), the velocity is a t exactly (constant force) and the position
    x0 + a t (t + dt) / 2, the semi-implicit Euler sum of a t (Newton, analytic)."""
    path, over, sec, key, force = FREE[kind]
    over = {**over, sec: {**over.get(sec, {}), key: force}}
    cfg = load_machine(path, over)
    r = transmission_ratio(cfg)
    mass = reflected_inertia(cfg) / r ** 2
    a = force / mass
    x0 = 0.1
    plant = Plant(cfg, x0)
    plant.set_input(enable=0.0)
    n = 400
    tr = plant.run(n, plant.sub_per_pwm)
    t = tr["time_s"]
    np.testing.assert_allclose(tr["table_vel"], a * t, rtol=1e-9, atol=0.0)
    np.testing.assert_allclose(tr["table_pos"] - x0, 0.5 * a * t * (t + plant.dt), rtol=1e-6,
                               atol=1e-15)


def test_external_force_adds_to_load_input_and_holds_in_equilibrium():
    """EMPS rigid axis, gravity-like F = -400 N from the machine file and +150 N on the
    plant input 'load': the holding current -(F + load) lead/2pi / K_t keeps the table at
    rest (static equilibrium, analytic); without the input 'load' the same current
    accelerates it at load / m."""
    force, load, x0, seconds = -400.0, 150.0, 0.1, 0.05
    cfg = load_machine(EMPS, {"table": {"external_force_n": force},
                              "friction": {"viscous_ns_per_m": 0.0}})
    r, kt = transmission_ratio(cfg), cfg.motor.torque_constant_nm_per_a
    mass = reflected_inertia(cfg) / r ** 2
    iq = -(force + load) * r / kt
    for applied, expected_a in ((load, 0.0), (0.0, -load / mass)):
        plant = Plant(cfg, x0)
        plant.state[L.S_IQ] = iq
        plant.set_input(iq_ref_a=iq, load=applied)
        plant.run(round(seconds / plant.pwm_period), plant.sub_per_pwm)
        assert plant.output("table_vel") == pytest.approx(expected_a * seconds, rel=1e-9,
                                                          abs=1e-13)


# --- measurement delay ------------------------------------------------------------------------

MEASURED = ("encoder_counts", "scale_counts", "id_meas_a", "iq_meas_a")
TRUE = ("motor_pos", "motor_vel", "table_pos", "table_vel", "id_a", "iq_a", "torque")


@pytest.mark.parametrize("n_delay", [1, 3, 32])
def test_delay_shifts_measured_outputs_by_whole_periods(n_delay):
    """Arrow 500 X (d-q current loop, current noise and ADC, linear scale) under a current
    stimulus, once without and once with [sensors] delay_s = N PWM periods: the delayed
    plant's encoder, scale and measured currents at period k are the undelayed plant's at
    k - N exactly (the rest values before), and its true states are identical (second
    plant as the reference; same noise seed)."""
    x0 = 0.25
    fast = Plant.from_file(ARROW, x0)
    delay_s = n_delay / fast.config.motor.pwm_frequency_hz
    slow = Plant.from_file(ARROW, x0, overrides={"sensors": {"delay_s": delay_s}})
    rest = {name: fast.output(name) for name in MEASURED}

    def stimulus(k, plant):
        plant.set_input(iq_ref_a=3.0 * math.sin(2 * math.pi * k / 80.0) + (2.0 if k > 50 else 0),
                        id_ref_a=0.5 if k > 120 else 0.0)

    n = 300
    a = fast.run(n, fast.sub_per_pwm, stimulus)
    b = slow.run(n, slow.sub_per_pwm, stimulus)
    for name in TRUE:
        np.testing.assert_array_equal(b[name], a[name], err_msg=name)
    for name in MEASURED:
        assert np.ptp(a[name]) > 0.0, name
        np.testing.assert_array_equal(b[name][n_delay:], a[name][:-n_delay], err_msg=name)
        np.testing.assert_array_equal(b[name][:n_delay], rest[name], err_msg=name)


def test_delay_is_seen_by_the_controller():
    """Lock-step controller and drive on the Arrow 500 X (scale feedback) during a G1 move
    with a delay of 4 PWM periods: the controller's actual position at tick k is the scale
    reading of the true table position after drive cycle k - 1 - 4 (one cycle of the
    lock-step feedback path plus the delay), so the position loop closes over the delay."""
    n_delay, x0 = 4, 0.1
    cfg = load_machine(ARROW, {"sensors": {"delay_s": n_delay / 8000.0}})
    res_m = cfg.sensors.scale_resolution_m
    profile = plan(parse_program("G1 X110 F3000", start=x0), axis_limits(cfg, load_controller(cfg)))
    ls = LockStep(cfg, x0)
    ls.enable()
    ls.ctrl.run_profile(profile)
    res = ls.run(0.3)
    lag = 1 + n_delay
    seen = np.floor(res["table_pos"][:-lag] * (1.0 / res_m)) * res_m
    np.testing.assert_allclose(res["x_act"][lag:], seen, rtol=0.0, atol=1e-12)
    assert np.ptp(res["table_pos"]) > 0.005


# --- loader refusals --------------------------------------------------------------------------

REFUSED = {
    "delay not whole periods": (ARROW, {"sensors": {"delay_s": 1.5 / 8000.0}},
                                ["[sensors] delay_s", "whole number of PWM periods", " s"]),
    "delay too long": (ARROW, {"sensors": {"delay_s": 33 / 8000.0}},
                       ["[sensors] delay_s", "33 PWM periods", "at most 32"]),
    "negative delay": (ARROW, {"sensors": {"delay_s": -1.25e-4}},
                       ["[sensors] delay_s", "must be >= 0 and <= 0.1 s"]),
    "periods vs amplitudes": (EMPS, {"pitch_error": {"periods_m": [0.01, 0.005],
                                                     "amplitudes_m": [1e-6]}},
                              ["[pitch_error] periods_m (m), amplitudes_m (m)",
                               "same length", "got 2, 1, 0"]),
    "phases length": (EMPS, {"pitch_error": {"periods_m": [0.01], "amplitudes_m": [1e-6],
                                             "phases_deg": [0.0, 1.0]}},
                      ["[pitch_error]", "phases_deg (deg)", "got 1, 1, 2"]),
    "five harmonics": (EMPS, {"pitch_error": {"periods_m": [0.01] * 5,
                                              "amplitudes_m": [1e-7] * 5}},
                       ["[pitch_error] at most 4 harmonics"]),
    "zero period": (EMPS, {"pitch_error": {"periods_m": [0.0], "amplitudes_m": [1e-6]}},
                    ["[pitch_error] periods_m", "every element must be > 0 and <= 10 m"]),
    "slope too steep": (EMPS, {"pitch_error": {"periods_m": [0.001], "amplitudes_m": [1e-5]}},
                        ["[pitch_error]", "slope", "m/m", "<= 0.05"]),
    "pitch error on a linear motor": (LINEAR, {"pitch_error": {"periods_m": [0.01],
                                                               "amplitudes_m": [1e-6]}},
                                      ["[pitch_error] periods_m does not apply",
                                       "kind=screw only", "kind = 'linear'"]),
    "torque on a screw axis": (EMPS, {"mechanics": {"external_torque_nm": 1.0}},
                               ["[mechanics] external_torque_nm does not apply",
                                "kind=rotary only"]),
    "table force on a rotary axis": (ROTARY, {"table": {"external_force_n": 1.0}},
                                     ["section [table] is not used by kind = 'rotary'"]),
    "force not a number": (EMPS, {"table": {"external_force_n": "down"}},
                           ["[table] external_force_n", "expected a number in N"]),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_loader_refuses(case):
    """Each broken machine file is refused before anything runs, the message naming the
    file, the section and key and the unit or range (reference: the declarations in
    plant.sections and the rules in plant.config)."""
    path, over, fragments = REFUSED[case]
    with pytest.raises(ConfigError) as err:
        load_machine(path, over)
    msg = str(err.value)
    assert str(path) in msg
    for fragment in fragments:
        assert fragment in msg, (fragment, msg)
