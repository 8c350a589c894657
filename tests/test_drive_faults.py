"""The emulated drive's monitoring, fault reaction and fault reset, cycle by cycle in one
process (the Arrow 500 X at 8 kHz, the CiA 402 enable sequence as a master sends it).

References: the CiA 402 state table (hil.cia402, itself checked against canopen), the
drive's parameters (the deceleration of a ramp is compared with 6085h/6084h, the I2t trip
time with the integral's closed form), the stroke from the machine file.  The adapters'
refusals and the processes are tested elsewhere (test_drive_safety_processes.py)."""

import math
from dataclasses import replace

import pytest

from hil.cia402 import (
    SW_FOLLOWING_ERROR,
    SW_INTERNAL_LIMIT_ACTIVE,
    SW_TARGET_REACHED,
    SW_WARNING,
    EnableSequencer,
    State,
)
from hil.controller.config import load_controller
from hil.drive import Cause, EmulatedDrive, load_drive
from hil.drive.faults import ERROR_CODE
from hil.drive.monitor import I2T_COOLED
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    MODE_VOLTAGE,
    Feedback,
    Setpoint,
)
from plant import Plant
from plant import layout as L
from plant.config import load_machine
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
X0 = 0.25
CYCLE_S = 125e-6


class Bench:
    """One drive of the Arrow 500 X and a master that enables it and sends setpoints."""

    def __init__(self, x0: float = X0, overrides: dict | None = None, **params):
        cfg = load_machine(ARROW, overrides)
        self.plant = Plant(cfg, table_pos=x0)
        base = load_drive(cfg, load_controller(cfg))
        self.drive = EmulatedDrive(self.plant, params=replace(base, **params))
        self.sp, self.fb = Setpoint(mode=MODE_CST), Feedback()
        self.seq = EnableSequencer(timeout_cycles=2000)
        self.hold: int | None = None  # a controlword sent instead of the sequencer's
        self.rpc = self.drive.rad_per_count

    def run(self, n: int, until=None, **fields) -> int:
        """``n`` cycles (or until ``until(self)``) with ``fields`` set; cycles run."""
        for name, value in fields.items():
            setattr(self.sp, name, value)
        for k in range(n):
            word = self.seq.next_controlword(self.fb.statusword)
            self.sp.controlword = word if self.hold is None else self.hold
            self.drive.cycle(self.sp, self.fb)
            if until is not None and until(self):
                return k + 1
        return n

    def enable(self) -> None:
        self.seq.enable()
        self.run(2000, until=lambda b: b.seq.done)
        assert self.state == State.OPERATION_ENABLED, self.seq.reason

    @property
    def state(self) -> State:
        return self.drive.sm.state

    @property
    def torque_on(self) -> bool:
        return self.plant.inp[L.I_ENABLE] == 1.0

    @property
    def x(self) -> float:
        return self.plant.output("table_pos")

    def counts(self, x: float) -> float:
        """Motor-encoder increments of table position ``x`` (m)."""
        return x / self.plant.built.ratio / self.rpc


def enabled(**params) -> Bench:
    bench = Bench(**params)
    bench.enable()
    return bench


# -- refused setpoints --------------------------------------------------------------------

@pytest.mark.parametrize("mode, field", [
    (MODE_CST, "iq_ref_a"), (MODE_CST, "id_ref_a"), (MODE_CSV, "target_velocity_counts_s"),
    (MODE_CSP, "target_position_counts"), (MODE_CSP, "velocity_offset_counts_s"),
    (MODE_VOLTAGE, "uq_v"), (MODE_VOLTAGE, "ud_v")])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e308])
def test_a_bad_setpoint_in_any_mode_faults_and_resets(mode, field, bad):
    """NaN, infinity or 1e308 never reaches the plant: FF10h, torque off at rest, and a
    fault reset with a good setpoint brings the drive back."""
    b = enabled()
    start = b.x
    b.run(1, mode=mode, **{field: bad})
    assert not b.torque_on
    b.run(2000, until=lambda b: b.state == State.FAULT)
    assert b.state == State.FAULT and b.fb.fault == ERROR_CODE[Cause.SETPOINT_REFUSED]
    assert all(math.isfinite(v) for v in b.plant.state)
    assert abs(b.x - start) < 1e-4
    setattr(b.sp, field, 0.0)
    b.sp.mode = MODE_CST
    b.enable()  # fault reset edge, 2, 3, 4
    assert b.fb.fault == 0 and b.drive.sm.log.recent()[-4:] == (15, 2, 3, 4)


def test_an_unsupported_mode_is_refused():
    b = enabled()
    b.run(1, mode=42)
    b.run(10)
    assert b.fb.fault == ERROR_CODE[Cause.SETPOINT_REFUSED]


def test_currents_beyond_the_power_stage_are_refused_within_it_limited():
    """|iq| above [motor] current_max_a is refused; within it, above 6072h, limited
    (statusword bit 11)."""
    b = enabled(max_current_a=10.0)
    b.run(20, iq_ref_a=20.0)
    assert b.plant.inp[L.I_IQ_REF] == 10.0 and b.fb.statusword & SW_INTERNAL_LIMIT_ACTIVE
    b.run(1, iq_ref_a=28.5)
    assert b.plant.inp[L.I_ENABLE] == 0.0
    b.run(3)
    assert b.fb.fault == ERROR_CODE[Cause.SETPOINT_REFUSED]


# -- fault reaction -----------------------------------------------------------------------

def brake_from_speed(b: Bench, w: float) -> list[float]:
    """CSV at ``w`` rad/s until steady, then a setpoint refusal; the drive's speed actual
    (rad/s) of every cycle until FAULT."""
    b.run(4000, mode=MODE_CSV, target_velocity_counts_s=w / b.rpc)
    b.run(1, target_velocity_counts_s=math.nan)
    b.sp.target_velocity_counts_s = w / b.rpc
    speeds = []
    while b.state != State.FAULT and len(speeds) < 40000:
        b.run(1)
        speeds.append(b.drive.velocity_counts_s * b.rpc)
    return speeds


@pytest.mark.parametrize("option, field", [(2, "quick_stop_decel"), (1, "profile_decel")])
def test_fault_reaction_brakes_on_the_ramp_605Eh_selects(option, field):
    """605Eh 2 (1): the speed falls at 6085h (6084h), torque stays on while braking, then
    transition 14 to FAULT with torque off."""
    b = enabled(x0=0.05, fault_reaction_option=option, quick_stop_decel=2000.0,
                profile_decel=1000.0)
    decel = getattr(b.drive.params, field)
    w0 = 150.0
    speeds = brake_from_speed(b, w0)
    assert b.state == State.FAULT and not b.torque_on
    # the middle of the ramp, clear of the speed loop's lag at its ends
    i, j = round(0.2 * w0 / decel / CYCLE_S), round(0.8 * w0 / decel / CYCLE_S)
    slope = (speeds[i] - speeds[j]) / ((j - i) * CYCLE_S)
    assert slope == pytest.approx(decel, rel=0.05)
    assert len(speeds) * CYCLE_S == pytest.approx(w0 / decel, rel=0.2)
    assert b.drive.sm.log.recent()[-2:] == (13, 14)


def test_fault_reaction_0_takes_torque_off_at_once():
    b = enabled(x0=0.05, fault_reaction_option=0)
    speeds = brake_from_speed(b, 150.0)
    assert len(speeds) <= 2 and not b.torque_on


def test_fault_reaction_at_the_current_limit_brakes_hardest():
    ramp = len(brake_from_speed(enabled(x0=0.05, fault_reaction_option=2,
                                        quick_stop_decel=2000.0), 150.0))
    limit = len(brake_from_speed(enabled(x0=0.05, fault_reaction_option=3), 150.0))
    assert limit < ramp


def test_quick_stop_605Ah_2_ramps_then_disables_and_6_holds():
    for option, end in ((2, State.SWITCH_ON_DISABLED), (6, State.QUICK_STOP_ACTIVE)):
        b = enabled(x0=0.05, quick_stop_option=option, quick_stop_decel=2000.0)
        b.run(4000, mode=MODE_CSV, target_velocity_counts_s=150.0 / b.rpc)
        b.hold = 0x0002  # quick stop
        b.run(4000, until=lambda b: abs(b.drive.velocity_counts_s * b.rpc) < 1.0)
        b.run(2000)
        assert b.state == end
        assert b.torque_on == (option == 6), "5-8 hold the axis with torque on"


# -- monitoring ---------------------------------------------------------------------------

def test_following_error_faults_after_the_window_time():
    """CSP: a target 1 mm away with a 0.1 mm window and 5 ms time: bit 13 at once, 8611h
    after 5 ms (40 cycles), not before; the reaction brakes and the axis stops."""
    b = enabled(fe_window=0.0001 / 0.01 * 2 * math.pi, fe_time_s=0.005)
    here = b.plant.output("encoder_counts")
    b.run(100, mode=MODE_CSP, target_position_counts=here)
    assert b.fb.statusword & SW_TARGET_REACHED
    b.run(1, target_position_counts=here + b.counts(0.001))
    assert b.fb.statusword & SW_FOLLOWING_ERROR and b.fb.fault == 0
    n = b.run(100, until=lambda b: b.fb.fault)
    assert b.fb.fault == ERROR_CODE[Cause.FOLLOWING_ERROR] and n == pytest.approx(41, abs=2)
    b.run(20000, until=lambda b: b.state == State.FAULT)
    assert b.state == State.FAULT and not b.torque_on


def test_csp_target_is_held_inside_the_software_limits():
    """A CSP ramp at 0.1 m/s to 0.6 m, beyond the maximum limit 607Dh:02 (5 mm beyond the
    510 mm travel): the axis stops at the limit (bit 11 set), no fault."""
    b = enabled(x0=0.45)
    v = b.counts(0.1)  # increments/s
    target = b.plant.output("encoder_counts")
    b.sp.mode, b.sp.velocity_offset_counts_s = MODE_CSP, v
    while target < b.counts(0.6):
        target += v * CYCLE_S
        b.run(1, target_position_counts=target)
    b.run(8000, velocity_offset_counts_s=0.0)
    assert b.fb.fault == 0 and b.fb.statusword & SW_INTERNAL_LIMIT_ACTIVE
    assert b.x == pytest.approx(b.drive.params.limit_max * b.plant.built.ratio, abs=2e-5)


@pytest.mark.parametrize("iq", [28.0, -28.0])
def test_a_runaway_is_stopped_and_the_wall_holds(iq):
    """CST at the current limit: the software limit faults the drive (8612h), the quick
    stop ramp brakes it, and the table stops before the end stop (or at the latest on it:
    the stop gives way by micrometres, the stall force over its stiffness is 0.1 µm)."""
    b = enabled(x0=0.25)
    table = b.plant.config.table
    travel, over = table.travel_m, table.end_stop_overtravel_m
    penetration = 1e-5
    xs = []
    b.run(80000, until=lambda b: xs.append(b.x) or b.state == State.FAULT, iq_ref_a=iq)
    assert b.state == State.FAULT and b.fb.fault == ERROR_CODE[Cause.SOFTWARE_LIMIT]
    b.run(8000)
    assert all(math.isfinite(v) for v in b.plant.state)
    assert -over - penetration < min(xs) and max(xs) < travel + over + penetration


def test_limit_switch_faults_when_the_software_limits_are_off():
    b = enabled(limit_min=-math.inf, limit_max=math.inf, fault_reaction_option=0)
    b.run(80000, until=lambda b: b.fb.fault, iq_ref_a=5.0)
    assert b.fb.fault == ERROR_CODE[Cause.LIMIT_SWITCH]
    assert b.plant.output("limit_pos") == 1.0


def test_overspeed_faults_and_csv_commands_are_limited():
    b = enabled(max_speed=100.0)
    b.run(4000, mode=MODE_CSV, target_velocity_counts_s=200.0 / b.rpc)
    assert b.drive.velocity_counts_s * b.rpc == pytest.approx(100.0, rel=0.05)
    assert b.fb.statusword & SW_INTERNAL_LIMIT_ACTIVE and b.fb.fault == 0
    b.run(20000, until=lambda b: b.fb.fault, mode=MODE_CST, iq_ref_a=5.0)
    assert b.fb.fault == ERROR_CODE[Cause.OVERSPEED]
    assert abs(b.drive.velocity_counts_s * b.rpc) > 110.0


def test_i2t_trips_after_the_overload_time_and_blocks_the_reset_until_cooled():
    """At the current limit against a wall, (I_max² - I_cont²) t = (I_max² - I_cont²)
    overload_time: the fault comes after overload_time_s (from cold, within the ramp-up of
    the current); the reset is refused until the integral fell to 90 % at I_cont² per s."""
    overload = 0.2
    b = enabled(overload_time_s=overload, limit_min=-math.inf, limit_max=math.inf,
                fault_reaction_option=0)
    kt, ratio = 1.35, b.plant.built.ratio  # [motor] torque_constant_nm_per_a, lead / 2 pi
    b.plant.set_input(load=-28.0 * kt / ratio)  # holds the axis against I_max: a wall
    n = b.run(40000, until=lambda b: b.fb.fault, iq_ref_a=28.0)
    assert b.fb.fault == ERROR_CODE[Cause.OVERCURRENT]
    assert n * CYCLE_S == pytest.approx(overload, rel=0.05)
    assert b.fb.statusword & SW_WARNING
    b.plant.set_input(load=0.0)
    b.sp.iq_ref_a = 0.0
    p = b.drive.params
    cool_s = (1 - I2T_COOLED) * p.i2t_trip_a2s / p.continuous_current_a ** 2
    b.seq.enable()
    b.run(round(0.5 * cool_s / CYCLE_S))
    assert b.state == State.FAULT, "still hot: the reset is refused"
    b.run(round(cool_s / CYCLE_S), until=lambda b: b.seq.done)
    assert b.state == State.OPERATION_ENABLED and b.fb.fault == 0


def test_a_non_finite_plant_state_restarts_the_emulation_at_rest():
    b = enabled()
    b.run(400, iq_ref_a=1.0)
    where = b.x
    b.plant.state[int(b.plant.params[L.P_SOFF_ROT])] = math.nan
    b.run(1)
    assert b.fb.fault == ERROR_CODE[Cause.PLANT_NONFINITE]
    assert all(math.isfinite(v) for v in b.plant.state) and b.x == pytest.approx(where, abs=1e-4)
    b.run(10, iq_ref_a=0.0)
    assert b.state == State.FAULT and not b.torque_on
    b.enable()
    assert b.fb.fault == 0


# -- the link: 6007h ----------------------------------------------------------------------

@pytest.mark.parametrize("option, state, torque", [
    (0, State.OPERATION_ENABLED, True), (1, State.FAULT, False),
    (2, State.SWITCH_ON_DISABLED, False), (3, State.SWITCH_ON_DISABLED, False)])
def test_a_lost_master_acts_as_6007h_says(option, state, torque):
    b = enabled(abort_connection_option=option)
    b.drive.link_causes = Cause.HEARTBEAT
    b.run(20000, until=lambda b: b.state == state and b.torque_on == torque)
    assert (b.state, b.torque_on) == (state, torque)
    if option == 1:
        assert b.fb.fault == ERROR_CODE[Cause.HEARTBEAT]
        b.seq.enable()
        b.run(200)
        assert b.state == State.FAULT, "no reset while the heartbeat is still missing"
        b.drive.link_causes = 0
        b.enable()
    elif option in (2, 3):
        b.drive.link_causes = 0
        b.enable()  # the master comes back and enables again
    assert b.state == State.OPERATION_ENABLED


def test_a_lost_master_while_disabled_is_no_fault():
    b = Bench()
    b.drive.link_causes = Cause.WATCHDOG
    b.run(100)
    assert b.fb.fault == 0 and b.state == State.SWITCH_ON_DISABLED


# -- the [drive] section ----------------------------------------------------------------

def test_drive_keys_come_from_the_machine_file_in_table_units(tmp_path):
    """[drive] in mm-free SI table units and rpm, converted to the motor coordinate by
    hand: lead 10 mm, so 1 m of table is 2 pi / 0.01 rad of motor."""
    path = tmp_path / "arrow.toml"
    path.write_text(ARROW.read_text() + "\n[drive]\nfollowing_error_window_m = 0.002\n"
                    "software_limit_min_m = 0.01\nsoftware_limit_max_m = 0.5\n"
                    "max_motor_speed_rpm = 3000.0\nmax_current_a = 20.0\n"
                    "quick_stop_deceleration_m_s2 = 5.0\nfault_reaction_option = 3\n")
    cfg = load_machine(path)
    p = load_drive(cfg, load_controller(cfg))
    per_m = 2 * math.pi / 0.01
    assert p.fe_window == pytest.approx(0.002 * per_m)
    assert (p.limit_min, p.limit_max) == pytest.approx((0.01 * per_m, 0.5 * per_m))
    assert p.max_speed == pytest.approx(3000 * 2 * math.pi / 60)
    assert p.quick_stop_decel == pytest.approx(5.0 * per_m)
    assert (p.max_current_a, p.fault_reaction_option) == (20.0, 3)


def test_drive_defaults_are_derived_from_the_machine():
    """Absent keys: the FE window 1.5 v_max / K_v, 6080h 1.2 v_max, 6072h the peak
    current, 6085h half the motor's acceleration at I_max, the software limits halfway
    between the travel's ends and the last point from which the quick stop (605Eh = 2)
    stops the axis at 1.1 x 6080h before the limit switch, after the reaction time (3 ms
    and three time constants L_q / K_p of the current loop), all by hand."""
    cfg = load_machine(ARROW)
    p = load_drive(cfg, load_controller(cfg))
    per_m = 2 * math.pi / 0.01
    v_max, kv = 0.5, 2.0 * 1000 / 60  # 30 m/min; K_v 2 (m/min)/mm in 1/s
    assert p.fe_window == pytest.approx(1.5 * v_max / kv * per_m)
    assert p.max_speed == pytest.approx(1.2 * v_max * per_m)
    assert p.max_current_a == 28.0 and p.continuous_current_a == 14.0
    from plant.assemble import reflected_inertia
    assert p.quick_stop_decel == pytest.approx(0.5 * 28.0 * 1.35 / reflected_inertia(cfg))
    top, a = 1.1 * 1.2 * v_max, p.quick_stop_decel / per_m  # m/s, m/s^2
    need = top * (0.003 + 3 * 0.0045 / 12.0) + top ** 2 / (2 * a)
    spare = cfg.table.limit_switch_overtravel_m - need
    assert spare > 0.0
    assert (p.limit_min, p.limit_max) == pytest.approx((-0.5 * spare * per_m,
                                                        (0.51 + 0.5 * spare) * per_m))


def test_a_heavier_table_raises_the_derived_quick_stop_to_keep_its_room():
    """A 700 kg table halves the motor's acceleration: half of it (6085h's default) would
    need 44 mm from 660 mm/s, more than the 35 mm to the limit switch.  The derived 6085h
    is raised until the quick stop needs 80 % of that room (28 mm: v t_r + v²/2a by hand),
    within what 6072h gives; 607Dh then lies beyond the travel.  A table so heavy that
    even 6072h's deceleration cannot stop it there is refused, naming the numbers."""
    from plant.errors import ConfigError
    cfg = load_machine(ARROW, {"table": {"mass_kg": 700.0}})
    p = load_drive(cfg, load_controller(cfg))
    ratio = 0.01 / (2 * math.pi)
    top, t_r = 0.66, p.reaction_time_s
    a = top ** 2 / (2 * (0.8 * 0.035 - top * t_r))  # m/s^2
    assert p.quick_stop_decel * ratio == pytest.approx(a)
    assert a < p.max_current_a * p.accel_per_amp * ratio
    assert p.limit_max * ratio > 0.51
    heavy = load_machine(ARROW, {"table": {"mass_kg": 5000.0}})
    with pytest.raises(ConfigError, match="the quick stop ramp 6085h, .* runs"):
        load_drive(heavy, load_controller(heavy))


@pytest.mark.parametrize("text, match", [
    ("max_current_a = 40.0", "max_current_a = 40 A must be <= \\[motor\\] current_max_a"),
    ("software_limit_min_m = 0.4\nsoftware_limit_max_m = 0.1", "software_limit_min_m"),
    ("fault_reaction_option = 7", "fault_reaction_option"),
    ("following_error_window_deg = 1.0", "does not apply"),
    ("continuous_current_a = 30.0", "continuous_current_a"),
    ("max_motor_speed = 1.0", "unknown key"),
    ("quick_stop_deceleration_m_s2 = 1e-6", "quick_stop_deceleration_m_s2 = 1e-06 m/s\\^2 is "
     "below 0.33 m/s\\^2, the least that stops the axis from its top speed 0.66 m/s"),
    ("profile_deceleration_m_s2 = 0.1", "profile_deceleration_m_s2 = 0.1 m/s\\^2 is below"),
    ("software_limit_max_m = 0.53", "software_limit_max_m = 0.53 m leaves 0.015 m to the limit "
     "switch, too little: from its top speed 0.66 m/s \\(1.1 x 6080h\\) the fault reaction "
     "\\(605Eh = 2: the quick stop ramp 6085h, 9.422 m/s\\^2, after 4.12 ms\\) runs 0.02584 m"),
    ("max_motor_speed_rpm = 6000", "limit_switch_overtravel_m = 0.035 m leaves no room beyond "
     "the travel"),
    ("fault_reaction_option = 0", "605Eh = 0: torque off, coasting on the friction"),
])
def test_bad_drive_keys_are_refused_naming_file_key_and_unit(tmp_path, text, match):
    from plant.errors import ConfigError
    path = tmp_path / "bad.toml"
    path.write_text(ARROW.read_text() + f"\n[drive]\n{text}\n")
    cfg = load_machine(path)
    with pytest.raises(ConfigError, match=match) as err:
        EmulatedDrive(Plant(cfg))
    assert str(path) in str(err.value)


def test_config_keys_lists_the_drive_and_controller_sections():
    """`hil config-keys` prints every [drive] and [controller] key with its unit and doc."""
    import subprocess
    import sys
    from dataclasses import fields

    from hil.controller.config import ControllerSection
    from hil.drive.config import DriveSection
    out = subprocess.run([sys.executable, "-m", "hil.cli", "config-keys", "--markdown"],
                         capture_output=True, text=True, check=True, timeout=120).stdout
    rows = {tuple(c.strip(" `") for c in line.split("|")[1:3]) for line in out.splitlines()
            if line.startswith("| ")}
    for section, cls in (("drive", DriveSection), ("controller", ControllerSection)):
        for f in fields(cls):
            assert (section, f.name) in rows, f.name
            assert f.metadata["unit"] and f.metadata["doc"], f.name


def test_a_link_lost_before_the_drive_is_enabled_acts_once_it_is():
    """6007h = 1: a master enabling the drive while its link is lost (say, by SDO without
    SYNC) gets the fault as soon as the power stage is on, not never."""
    b = Bench()
    b.drive.link_causes = Cause.WATCHDOG
    b.seq.enable()
    b.run(200, until=lambda b: b.fb.fault)
    assert b.fb.fault == ERROR_CODE[Cause.WATCHDOG] and b.state != State.OPERATION_ENABLED


def test_a_fault_while_disabled_keeps_the_torque_off():
    """A drive coasting with its power stage off that faults (a refused setpoint) does
    not switch the power stage on to brake: FAULT REACTION ACTIVE, then FAULT, torque off
    throughout."""
    b = enabled(x0=0.05)
    b.run(4000, mode=MODE_CSV, target_velocity_counts_s=150.0 / b.rpc)
    b.hold = 0x0000  # disable voltage: the axis coasts
    b.run(2)
    assert b.state == State.SWITCH_ON_DISABLED and not b.torque_on
    b.run(1, target_velocity_counts_s=math.nan)
    torque = []
    b.run(2000, until=lambda b: torque.append(b.torque_on) or b.state == State.FAULT)
    assert b.state == State.FAULT and not any(torque)
