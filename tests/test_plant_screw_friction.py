"""Friction where the seeds put it (issue 14 part 4): Coulomb and viscous torque in the
screw's support bearings and in its nut, beside the table's, acting on the screw's rotation
(plant.effects.screw_friction).

Against analytic results: at constant speed the motor's torque is the sum of the friction
torques reflected to the motor (bearings, nut with its load-dependent part, the table's
viscous force through the lead, the motor's own drag); at rest a torque below the sum of the
Coulomb torques holds (stiction, no creep) and one above it breaks the axis away.
"""

from pathlib import Path

import numpy as np
import pytest

from plant import Plant
from plant.assemble import mechanics_matrices
from plant.config import load_machine
from plant.errors import ConfigError

ARROW = Path(__file__).resolve().parent.parent / "configs" / "arrow500_x.toml"
#: N·m, N·m·s/rad, 1: the screw's friction under test (catalogue-class values)
BEARING_NM, BEARING_NMS, NUT_NM, NUT_NMS, NUT_LOAD = 0.05, 0.002, 0.15, 4e-4, 0.05
#: N·s/m: the table's only friction, viscous (it loads the nut with F = B v)
TABLE_NS_PER_M = 8000.0
#: the motor's own viscous drag, N·m·s/rad (the file's)
MOTOR_NMS = 0.0005


def axis(**screw) -> Plant:
    """The Arrow 500 X without cogging, measurement noise and table Coulomb friction, the
    screw's friction as given (default: all of it under test)."""
    keys = {"bearing_coulomb_nm": BEARING_NM, "bearing_viscous_nms_per_rad": BEARING_NMS,
            "nut_coulomb_nm": NUT_NM, "nut_viscous_nms_per_rad": NUT_NMS,
            "nut_load_friction": NUT_LOAD}
    keys.update(screw)
    return Plant.from_file(ARROW, table_pos=0.1, overrides={
        "screw": keys, "cogging": {"orders": [], "amplitudes_nm": [], "phases_deg": []},
        "friction": {"viscous_ns_per_m": TABLE_NS_PER_M, "coulomb_n": 0.0, "breakaway_n": 0.0,
                     "stribeck_velocity_m_s": 0.0, "zero_velocity_band_m_s": 0.0},
        "sensors": {"current_noise_a": 0.0, "current_lsb_a": 0.0}})


def coulomb_total() -> float:
    """N·m: the breakaway torque at rest, two bearings and the unloaded nut."""
    return 2 * BEARING_NM + NUT_NM


def steady_speed(torque: float, r: float) -> float:
    """rad/s where the motor torque ``torque`` (N·m) balances the friction at constant speed:
    T = 2 T_b + T_n + omega (b_m + 2 b_b + c_n + r^2 B (1 + mu)), the nut's load part
    mu r |F| with F = B r omega the table's viscous force (r = lead / 2 pi)."""
    return (torque - coulomb_total()) / (MOTOR_NMS + 2 * BEARING_NMS + NUT_NMS
                                         + r * r * TABLE_NS_PER_M * (1.0 + NUT_LOAD))


def run_torque(plant: Plant, torque: float, seconds: float, ramp_s: float = 0.05):
    """The motor's q current ramped to ``torque`` (N·m) over ``ramp_s`` and held; the
    trace of one call per PWM period."""
    kt = plant.config.motor.torque_constant_nm_per_a
    n_ramp = round(ramp_s / plant.pwm_period)

    def stimulus(k, p):
        p.set_input(iq_ref_a=torque / kt * min(1.0, (k + 1) / n_ramp))

    return plant.run(round(seconds / plant.pwm_period), plant.sub_per_pwm, stimulus)


def test_constant_speed_motor_torque_is_the_sum_of_the_reflected_frictions():
    """Analytic steady state: speed and torque balance to 0.1 %, the table's speed through
    the lead, the nut's force the table's viscous force."""
    plant = axis()
    r = plant.built.ratio
    torque = 0.5
    tr = run_torque(plant, torque, 1.5)
    assert tr["status"].max() == 0
    omega = tr["motor_vel"][-400:].mean()
    assert omega == pytest.approx(steady_speed(torque, r), rel=1e-3)
    assert np.ptp(tr["motor_vel"][-400:]) < 1e-3 * omega
    assert tr["table_vel"][-1] == pytest.approx(r * omega, rel=1e-3)
    assert tr["nut_force_n"][-1] == pytest.approx(TABLE_NS_PER_M * r * omega, rel=1e-3)
    friction = (coulomb_total() + NUT_LOAD * r * TABLE_NS_PER_M * r * omega
                + omega * (MOTOR_NMS + 2 * BEARING_NMS + NUT_NMS + r * r * TABLE_NS_PER_M))
    assert tr["torque"][-1] == pytest.approx(friction, rel=1e-3)


def test_without_the_screws_friction_the_same_torque_runs_faster():
    """The keys at 0 (the machine files' values): only the table's and the motor's viscous
    friction and the bearings' viscous drag remain."""
    plant = axis(bearing_coulomb_nm=0.0, nut_coulomb_nm=0.0, nut_viscous_nms_per_rad=0.0,
                 nut_load_friction=0.0)
    r = plant.built.ratio
    tr = run_torque(plant, 0.5, 1.5)
    expected = 0.5 / (MOTOR_NMS + 2 * BEARING_NMS + r * r * TABLE_NS_PER_M)
    assert tr["motor_vel"][-1] == pytest.approx(expected, rel=1e-3)


@pytest.mark.parametrize("share", [0.5, 0.9])
def test_below_the_coulomb_torques_the_screw_sticks_without_creeping(share):
    """At rest a torque below 2 T_b + T_n holds: once the current loop has settled on the
    torque (its integral time is 12.5 ms) the screw stands still over 0.15 s: its angle
    within 1e-10 rad (the coupling's wind-up is ~1e-5 rad, a creep at the 1e-3 rad/s of a
    slipping screw would be 1e-4 rad)."""
    plant = axis()
    tr = run_torque(plant, share * coulomb_total(), 0.5, ramp_s=0.1)
    assert tr["status"].max() == 0
    settled = round(0.35 / plant.pwm_period)
    assert np.ptp(tr["motor_pos"][settled:]) < 1e-10
    assert np.ptp(tr["table_pos"][settled:]) < 1e-10  # m: the axial modes' ringing only


def test_above_the_coulomb_torques_the_screw_breaks_away():
    """10 % above 2 T_b + T_n the axis starts and reaches the analytic steady speed."""
    plant = axis()
    torque = 1.1 * coulomb_total()
    tr = run_torque(plant, torque, 1.5, ramp_s=0.1)
    assert tr["motor_vel"][-1] == pytest.approx(steady_speed(torque, plant.built.ratio),
                                                rel=2e-3)


def test_the_nuts_viscous_torque_is_a_damper_on_the_screws_rotation_at_the_nut():
    """In the linearised mechanics (the sub-step's choice) it dissipates c_n omega^2 for a
    rigid rotation of the whole screw at omega, wherever the nut is, and nothing axial."""
    cfg = load_machine(ARROW, {"screw": {"nut_viscous_nms_per_rad": NUT_NMS}})
    base = load_machine(ARROW)
    for x in (0.0, 0.13, 0.25, 0.5):
        c = mechanics_matrices(cfg, x)[1] - mechanics_matrices(base, x)[1]
        n_rot = cfg.screw.segments + 2
        q_dot = np.zeros(c.shape[0])
        q_dot[:n_rot] = 3.0
        assert q_dot @ c @ q_dot == pytest.approx(NUT_NMS * 9.0, rel=1e-12)
        assert not c[n_rot:, :].any()


def test_the_tlm_solver_refuses_the_screws_friction_naming_the_key():
    with pytest.raises(ConfigError, match=r"\[screw\] nut_coulomb_nm = 0.1 needs "
                                          r"\[mechanics\] solver = 'lumped'"):
        load_machine(ARROW.parent / "tlm_rig.toml", {"screw": {"nut_coulomb_nm": 0.1}})


def test_the_bearing_friction_acts_on_both_support_bearings():
    """Each support bearing holds T_b: with the nut's friction off, 1.9 T_b holds and 2.1
    T_b turns the screw (the table frictionless but for its viscous force)."""
    for share, moves in ((0.95, False), (1.05, True)):
        plant = axis(nut_coulomb_nm=0.0, nut_load_friction=0.0)
        tr = run_torque(plant, share * 2 * BEARING_NM, 0.4, ramp_s=0.1)
        assert bool(abs(tr["motor_vel"][-1]) > 1e-3) is moves, share
