"""Every braking reaction of the emulated drive is bounded (issue 27, item 1 and 2), cycle by
cycle in one process: the Arrow 500 X at 8 kHz, the CiA 402 enable sequence as a master
sends it (``Bench`` of test_drive_faults.py).

Each path a drive brakes on is driven at speed: quick stop (605Ah), the setpoint watchdog
and an NMT stop (6007h = 1, then 605Eh), a software limit (607Dh) and a limit switch in
each cyclic mode at its worst held value, I²t during braking.  The references are
independent of the drive's code: the machine file's stroke (limit switch, end stop), the
drive's parameters as a commissioning engineer reads them (v²/2a for a braking distance,
v/a for its time) and the CiA 402 state table.  A reaction that cannot brake (a load
pushing harder than 6072h can hold) must end in FF04h with the pulses inhibited within
the bound :mod:`hil.drive.braking` states.
"""

import math

import pytest

from hil.cia402 import State
from hil.drive import Cause
from hil.drive.braking import RAMP_TIME_FACTOR, SPEED_TOLERANCE_SHARE
from hil.drive.faults import ERROR_CODE
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_CSV, MODE_VOLTAGE
from plant import layout as L
from tests.test_drive_faults import CYCLE_S, Bench
from tests.test_runtime import slow_config, stepped  # noqa: F401 (fixtures)

#: 1 m/s of table speed in motor-encoder increments/s (2**22 per rev, 10 mm lead)
M_S_COUNTS = 1.0 / 0.01 * 2**22
QUICK_STOP = 0x0002


def at_speed(b: Bench, v_m_s: float, cycles: int = 4000) -> None:
    """CSV at ``v_m_s`` (table, m/s) until steady."""
    b.run(cycles, mode=MODE_CSV, target_velocity_counts_s=v_m_s * M_S_COUNTS)


def until_torque_off(b: Bench, limit_s: float = 10.0) -> float:
    """Cycles until the power stage is off; the time they took, s."""
    n = b.run(round(limit_s / CYCLE_S), until=lambda b: not b.torque_on)
    assert not b.torque_on, f"torque still on after {limit_s} s"
    return n * CYCLE_S


def ideal_distance(b: Bench, v_m_s: float, decel_m_s2: float) -> float:
    """The distance a drive braking from ``v_m_s`` at ``decel_m_s2`` (table units) runs,
    its reaction time t_r included: v t_r + v²/2a, m."""
    return v_m_s * b.drive.params.reaction_time_s + v_m_s ** 2 / (2 * decel_m_s2)


def table_decel(b: Bench, field: str = "quick_stop_decel") -> float:
    """A deceleration parameter of the drive in table units, m/s²."""
    return getattr(b.drive.params, field) * b.plant.built.ratio


def switch_and_stop(b: Bench) -> tuple[float, float]:
    """The positive limit switch and end stop of the machine file, m."""
    t = b.plant.config.table
    return t.travel_m + t.limit_switch_overtravel_m, t.travel_m + t.end_stop_overtravel_m


@pytest.mark.parametrize("cause", ["quick stop", "watchdog", "nmt"])
def test_a_lost_master_or_quick_stop_brakes_within_its_bound(cause):
    """At 100 mm/s: the quick stop ramp (605Ah = 2, or 6007h = 1 then 605Eh = 2) stops the
    axis within t_r + 1.5 v/a and within 1.05 (t_r v + v²/2a) (5 % for the speed loop's
    lag), then the torque is off."""
    b = Bench(x0=0.1)
    b.enable()
    v = 0.1
    at_speed(b, v)
    x0 = b.x
    if cause == "quick stop":
        b.hold = QUICK_STOP
    else:
        b.drive.link_causes = Cause.WATCHDOG if cause == "watchdog" else Cause.NMT
    t = until_torque_off(b)
    t_r = b.drive.params.reaction_time_s
    d_ideal = ideal_distance(b, v, table_decel(b))
    assert t <= t_r + RAMP_TIME_FACTOR * v / table_decel(b)
    assert b.x - x0 <= 1.05 * d_ideal
    assert abs(b.plant.output("table_vel")) < 1e-3
    expected = State.SWITCH_ON_DISABLED if cause == "quick stop" else State.FAULT
    assert b.state == expected
    assert not b.drive.faults.latched & Cause.REACTION_FAILED


def test_the_slowest_ramp_allowed_is_still_bounded():
    """6085h at its lower bound (a stop from 1.1 x 6080h in 2 s): a lost master at 100 mm/s
    still stops the axis within t_r + 1.5 v/a, where the attack with 1e-6 m/s² kept the
    speed for 3 s (the file refuses 1e-6: test_drive_faults)."""
    from hil.drive.braking import min_deceleration
    b = Bench(x0=0.1)
    b.drive.params.quick_stop_decel = min_deceleration(b.drive.params.max_speed)
    b.enable()
    at_speed(b, 0.1)
    b.drive.link_causes = Cause.WATCHDOG
    t = until_torque_off(b)
    assert 0.1 / table_decel(b) > 0.25  # a slow ramp indeed
    assert t <= b.drive.params.reaction_time_s + RAMP_TIME_FACTOR * 0.1 / table_decel(b)
    assert b.state == State.FAULT and b.fb.fault == ERROR_CODE[Cause.WATCHDOG]


def _push(b: Bench, force_n: float) -> None:
    b.plant.inp[L.I_LOAD] = force_n


def test_a_reaction_that_cannot_brake_inhibits_the_pulses():
    """A load of 3 kN pushing the table on, and 6072h lowered to 2 A (1.7 kN) while it
    runs: the quick stop cannot slow the axis.  The drive gives up no later than the
    envelope allows (t_r, then 1.5 times the braking time at 6072h) with FF04h, torque
    off."""
    b = Bench(x0=0.1)
    b.enable()
    _push(b, 3000.0)
    at_speed(b, 0.05)
    b.drive.params.max_current_a = 2.0
    b.hold = QUICK_STOP
    t = until_torque_off(b, 2.0)
    p = b.drive.params
    a_cl = p.max_current_a * p.accel_per_amp * b.plant.built.ratio  # m/s² at 2 A
    w0 = 0.05
    still = b.drive.monitor.standstill() * b.plant.built.ratio
    tol = max(SPEED_TOLERANCE_SHARE * w0, still) + a_cl * p.reaction_time_s
    assert t <= p.reaction_time_s + RAMP_TIME_FACTOR * (w0 + tol - still) / a_cl
    assert b.drive.faults.latched & Cause.REACTION_FAILED
    b.run(10)
    assert b.state == State.FAULT and not b.torque_on
    assert b.fb.fault == ERROR_CODE[Cause.REACTION_FAILED]


@pytest.mark.parametrize("brake_nm", [0.0, 10.0])
def test_after_a_failed_reaction_the_holding_brake_holds_the_pushed_axis(brake_nm):
    """The same push (3 kN: 4.8 N m at the motor) after FF04h: without a brake the axis
    runs on under it; a 10 N m holding brake closes 30 ms after the pulses went off
    ([brake] closing_time_s) and holds it, within the distance v (t_close + v / a) the
    push and the slip allow."""
    b = Bench(x0=0.1, overrides={"brake": {"holding_torque_nm": brake_nm}} if brake_nm
              else None)
    b.enable()
    _push(b, 3000.0)
    at_speed(b, 0.05)
    b.drive.params.max_current_a = 2.0
    b.hold = QUICK_STOP
    until_torque_off(b, 2.0)
    x_off = b.x
    b.run(round(0.5 / CYCLE_S))
    if brake_nm:
        closing = b.plant.config.brake.closing_time_s
        assert b.plant.inp[L.I_BRAKE] == 1.0
        assert b.plant.output("table_vel") == pytest.approx(0.0, abs=1e-6)
        assert b.x - x_off < 0.1 * (closing + 0.05)  # at most twice the speed meanwhile
    else:
        assert b.plant.inp[L.I_BRAKE] == 0.0
        assert b.plant.output("table_vel") > 0.5
    assert b.state == State.FAULT and b.fb.fault == ERROR_CODE[Cause.REACTION_FAILED]


def test_i2t_during_braking_takes_the_torque_off_at_once():
    """The NMT attack's second half: I²t trips while the fault reaction brakes (the drive
    hot from before, braking at the current limit, 605Eh = 3).  The braking stops at
    once, the torque goes off, FAULT."""
    b = Bench(x0=0.1, fault_reaction_option=3)
    b.enable()
    at_speed(b, 0.1)
    m = b.drive.monitor
    m.i2t_a2s = 0.9999 * b.drive.params.i2t_trip_a2s
    b.drive.link_causes = Cause.NMT
    b.run(4000, until=lambda b: b.drive.faults.latched & Cause.OVERCURRENT)
    assert b.drive.faults.latched & Cause.OVERCURRENT
    assert abs(b.plant.output("table_vel")) > 0.01  # still braking when it tripped
    b.run(2)
    assert not b.torque_on and b.state == State.FAULT


def _worst(b: Bench, mode: int) -> None:
    """Hold ``mode``'s worst value toward +x from 450 mm on: CSV 1e15 increments/s (the
    drive limits it to 6080h), CST the peak current, CSP a target 1e12 increments away,
    voltage mode 100 V on the q axis (the attack.s value)."""
    if mode == MODE_CSV:
        b.sp.target_velocity_counts_s = 1e15
    elif mode == MODE_CST:
        b.sp.iq_ref_a = b.plant.config.motor.current_max_a
    elif mode == MODE_CSP:
        b.sp.target_position_counts = 1e12
    else:
        b.sp.uq_v = 100.0
    b.sp.mode = mode


@pytest.mark.parametrize("mode, causes", [
    (MODE_CSV, Cause.SOFTWARE_LIMIT), (MODE_CST, Cause.OVERSPEED | Cause.SOFTWARE_LIMIT),
    (MODE_CSP, Cause.FOLLOWING_ERROR), (MODE_VOLTAGE, Cause.PEAK_CURRENT)])
def test_each_mode_at_its_worst_held_value_stops_before_the_limit_switch(mode, causes):
    """From 450 mm at each cyclic mode's worst value toward the end: the axis stops
    before the limit switch (the room 607Dh leaves, derived by hil.drive.braking), never
    touches the end stop, and ends in FAULT with the torque off: CSV at the software
    limit, CST on overspeed or the software limit, CSP on the following error of the
    target's jump (held at 607Dh), voltage mode on its current trip."""
    b = Bench(x0=0.45)
    b.enable()
    b.sp.target_position_counts = b.fb.encoder_counts
    _worst(b, mode)
    switch, _ = switch_and_stop(b)
    peak = b.x
    for _ in range(round(3.0 / CYCLE_S)):
        b.run(1)
        peak = max(peak, b.x)
        assert b.plant.output("end_stop_force_n") == 0.0
    assert peak < switch
    assert abs(b.plant.output("table_vel")) < 1e-3
    assert b.state == State.FAULT and not b.torque_on
    assert b.drive.faults.latched & ~causes == 0, b.drive.faults.as_dict()["latched"]


def test_with_the_software_limits_off_the_limit_switch_leaves_room_to_the_end_stop():
    """607Dh off: CST at the peak current from 450 mm trips the limit switch (or
    overspeed), and the quick stop ends before the end stop."""
    b = Bench(x0=0.45, limit_min=-math.inf, limit_max=math.inf)
    b.enable()
    _worst(b, MODE_CST)
    _, stop = switch_and_stop(b)
    peak = b.x
    for _ in range(round(2.0 / CYCLE_S)):
        b.run(1)
        peak = max(peak, b.x)
    assert peak < stop
    assert b.state == State.FAULT and not b.torque_on


# -- the emulator's safe state at its end ----------------------------------------------

def _braking_after_watchdog(stepped) -> tuple:
    """The stepped emulator of test_runtime enabled, at 0.3 A, then silent until its
    watchdog trips: the fault reaction brakes (torque on)."""
    from tests.test_runtime import LIMIT
    emu, _, _, master = stepped
    master.enable()
    for _ in range(200):
        master.tick(iq=0.3)
    for _ in range(LIMIT + 1):
        master.tick(send=False)
    assert emu.drive.sm.state == State.FAULT_REACTION_ACTIVE and emu.plant.inp[L.I_ENABLE]
    return emu


def test_the_safe_state_waits_for_a_braking_reaction_then_the_torque_is_off(stepped):
    """SIGTERM's safe state in FAULT REACTION ACTIVE: the reaction runs to its end (FAULT,
    8250h), the report's plant_enable 0."""
    emu = _braking_after_watchdog(stepped)
    safe = emu.safe_state()
    assert (safe["state"], safe["plant_enable"], safe["error_code"]) == ("FAULT", 0.0,
                                                                         "0x8250")


def test_the_safe_state_inhibits_the_pulses_of_a_reaction_still_braking(stepped, monkeypatch):
    """A reaction longer than the safe state's SAFE_STATE_MAX_S (here shortened to one
    cycle): the pulses go off anyway, FF04h latched, plant_enable 0."""
    import hil.runtime.emulator as emulator
    emu = _braking_after_watchdog(stepped)
    monkeypatch.setattr(emulator, "SAFE_STATE_MAX_S", emu.plant.pwm_period)
    safe = emu.safe_state()
    assert (safe["state"], safe["plant_enable"]) == ("FAULT", 0.0)
    assert emu.drive.faults.latched & Cause.REACTION_FAILED


def test_hil_run_refuses_a_ramp_without_bound_before_the_kernels_compile(tmp_path):
    """The attack's file, 6085h at 1e-6 m/s²: one line, exit 2, before `hil run` loads
    the plant's kernels (nothing compiles, nothing opens)."""
    import subprocess
    import sys

    from tests.conftest import ROOT
    from tests.runtime_helpers import ENV
    path = tmp_path / "slow.toml"
    path.write_text((ROOT / "configs" / "arrow500_x.toml").read_text()
                    + "\n[drive]\nquick_stop_deceleration_m_s2 = 1e-6\n")
    run = subprocess.run([sys.executable, "-m", "hil.runtime.emulator", str(path),
                          "--adapter", "udp://127.0.0.1:0", "--record", str(tmp_path / "run")],
                         capture_output=True, text=True, timeout=60, env=ENV, check=False)
    assert run.returncode == 2
    assert run.stderr.splitlines() == [
        f"hil run: {path}: [drive] quick_stop_deceleration_m_s2 = 1e-06 m/s^2 is below 0.33 "
        "m/s^2, the least that stops the axis from its top speed 0.66 m/s (1.1 x 6080h) "
        "within 2 s"]
    assert not (tmp_path / "run").exists()
