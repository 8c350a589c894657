"""The drive's own trajectories -- profile position, profile velocity, homing -- and the
interpolation of cyclic setpoints between communication cycles, on the Arrow 500 X.

References: the trapezoid's closed form (time to cover a distance D at speed v with
acceleration a = deceleration: D/v + v/a; the ramp to a speed: v/a); CiA 402-2's
set-point handshake (bit 4 -> statusword bit 12, bit 5, bit 6, halt) and homing status
bits; the plant's own sensors, located independently of the drive: the home switch's
edge half the 10 mm lead above the start of travel, the encoder's index mark once per
motor revolution (4194304 increments), so homing on the index must land on a whole
revolution exactly; and linear interpolation's formula for CSP at a 1 ms interpolation
time period over 125 µs drive cycles.
"""

import math

import pytest

from hil.cia402 import (
    CW_CHANGE_SET_IMMEDIATELY,
    CW_HALT,
    CW_NEW_SET_POINT,
    CW_RELATIVE,
    SW_HOMING_ATTAINED,
    SW_HOMING_ERROR,
    SW_SET_POINT_ACK,
    SW_SPEED_ZERO,
    SW_TARGET_REACHED,
    EnableSequencer,
)
from hil.drive import EmulatedDrive
from hil.drive.homing import METHODS, Phase
from hil.drive.objects import DriveObjects
from hil.drive.profile import ProfileGenerator
from io_adapters.cia402_objects import ObjectAccessError
from io_adapters.messages import MODE_CSP, Feedback, Setpoint
from plant import Plant
from plant import layout as L
from plant.config import load_machine
from plant.errors import ConfigError
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
MODE_PP, MODE_PV, MODE_HM = 1, 3, 6
ENABLED = 0x000F
REV = 4194304  # encoder increments per motor revolution = 10 mm of table travel
DT = 125e-6    # the Arrow 500 X's PWM period, s


class Axis:
    """An Arrow 500 X drive brought to OPERATION ENABLED, then cycled with a controlword
    of its own (bits 4-8 on top of enable operation)."""

    def __init__(self, x0_m: float = 0.25):
        self.plant = Plant(load_machine(ARROW), table_pos=x0_m)
        self.drive = EmulatedDrive(self.plant)
        self.sp, self.fb = Setpoint(), Feedback()
        seq = EnableSequencer(timeout_cycles=50)
        seq.enable()
        for _ in range(50):
            self.sp.controlword = seq.next_controlword(self.fb.statusword)
            self.drive.cycle(self.sp, self.fb)
            if seq.done:
                break
        assert seq.done, seq.reason
        self.p = self.drive.params
        self.rpc = self.drive.rad_per_count

    def cycle(self, bits: int = 0, n: int = 1) -> int:
        """``n`` cycles with controlword 000Fh | ``bits``; the last statusword."""
        self.sp.controlword = ENABLED | bits
        for _ in range(n):
            self.drive.cycle(self.sp, self.fb)
        return self.fb.statusword

    def until(self, predicate, bits: int = 0, limit: int = 100_000) -> int:
        """Cycles until ``predicate(statusword)``; how many it took."""
        for k in range(1, limit + 1):
            if predicate(self.cycle(bits)):
                return k
        raise AssertionError(f"not within {limit} cycles: statusword {self.fb.statusword:04X}")


# -- profile position -------------------------------------------------------------------

def test_profile_generator_runs_the_trapezoid_and_the_triangle():
    """Distance D at v_max, a = d: the trapezoid takes D/v + v/a; a move too short to
    reach v_max peaks at sqrt(a D) and takes 2 sqrt(D/a)."""
    for distance, v_max, a in ((10.0, 50.0, 500.0), (1.0, 50.0, 500.0)):
        gen = ProfileGenerator(DT)
        n, peak = 0, 0.0
        while not gen.to_position(distance, v_max, a, a):
            n += 1
            peak = max(peak, gen.v)
        if distance > v_max ** 2 / a:
            expected, expected_peak = distance / v_max + v_max / a, v_max
        else:
            expected, expected_peak = 2 * math.sqrt(distance / a), math.sqrt(a * distance)
        assert n * DT == pytest.approx(expected, abs=3 * DT)
        assert peak == pytest.approx(expected_peak, rel=1e-3)
        assert (gen.x, gen.v) == (distance, 0.0)


def test_profile_position_moves_with_the_set_point_handshake():
    axis = Axis()
    p, rpc = axis.p, axis.rpc
    p.profile_velocity, p.profile_acceleration, p.profile_decel = 50.0, 500.0, 500.0
    axis.sp.mode = MODE_PP
    start = axis.fb.encoder_counts
    axis.until(lambda sw: sw & SW_TARGET_REACHED)  # standing on its own position (6068h)
    axis.sp.target_position_counts = REV  # relative: one revolution, 10 mm
    sw = axis.cycle(CW_NEW_SET_POINT | CW_RELATIVE)
    assert sw & SW_SET_POINT_ACK and not sw & SW_TARGET_REACHED
    assert axis.cycle(CW_NEW_SET_POINT | CW_RELATIVE) & SW_SET_POINT_ACK  # held while bit 4
    assert not axis.cycle(CW_RELATIVE) & SW_SET_POINT_ACK  # bit 4 low: ready for the next
    demand_done = axis.until(lambda sw: axis.drive.modes.demand == (start + REV) * rpc)
    trapezoid = REV * rpc / 50.0 + 50.0 / 500.0
    assert (demand_done + 3) * DT == pytest.approx(trapezoid, abs=3 * DT)
    axis.until(lambda sw: sw & SW_TARGET_REACHED)
    assert abs(axis.fb.encoder_counts - (start + REV)) <= p.position_window / rpc


def profile_position_axis() -> tuple[Axis, float]:
    """An axis in PP at 50 rad/s, 500 rad/s² both ways; where it starts, increments."""
    axis = Axis()
    axis.p.profile_velocity, axis.p.profile_acceleration = 50.0, 500.0
    axis.p.profile_decel = 500.0
    axis.sp.mode = MODE_PP
    return axis, axis.fb.encoder_counts


def test_a_second_set_point_waits_unless_it_changes_the_set_at_once():
    axis, start = profile_position_axis()
    axis.sp.target_position_counts = start + REV  # absolute
    axis.cycle(CW_NEW_SET_POINT)
    axis.cycle(0, 200)
    axis.sp.target_position_counts = start - REV
    assert axis.cycle(CW_NEW_SET_POINT) & SW_SET_POINT_ACK
    # buffered: the axis still heads for +REV; the acknowledge stays while the buffer is full
    assert axis.cycle(0, 100) & SW_SET_POINT_ACK and axis.drive.modes.profile.v > 0.0
    axis.until(lambda sw: not sw & SW_SET_POINT_ACK)  # the buffered set started ...
    assert axis.drive.modes.demand == pytest.approx((start + REV) * axis.rpc)  # ... at +REV
    axis.until(lambda sw: axis.drive.modes.profile.v < 0.0)
    # change set immediately: heads for the new target from where it is
    axis.sp.target_position_counts = start
    axis.cycle(CW_NEW_SET_POINT | CW_CHANGE_SET_IMMEDIATELY)
    axis.until(lambda sw: sw & SW_TARGET_REACHED)
    assert axis.drive.modes.demand == start * axis.rpc


def test_halt_stops_profile_position_and_releasing_it_resumes():
    axis, start = profile_position_axis()
    axis.sp.target_position_counts = start + REV
    axis.cycle(CW_NEW_SET_POINT)
    axis.cycle(0, 400)
    speed = axis.drive.modes.profile.v
    assert speed == pytest.approx(500.0 * 400 * DT, rel=0.01)  # still accelerating
    stopped = axis.until(lambda sw: sw & SW_TARGET_REACHED, CW_HALT)  # halted at rest
    assert axis.drive.modes.profile.v == 0.0
    assert stopped * DT == pytest.approx(speed / 500.0, abs=3 * DT)  # at 6084h
    assert axis.drive.modes.demand < (start + REV) * axis.rpc
    axis.until(lambda sw: sw & SW_TARGET_REACHED and axis.drive.modes.demand == (
        start + REV) * axis.rpc)


def test_profile_targets_are_held_inside_the_software_limits():
    axis = Axis()
    axis.sp.mode = MODE_PP
    axis.sp.target_position_counts = 1e9  # 2.4 m: beyond the travel
    axis.cycle(CW_NEW_SET_POINT)
    axis.cycle(0, 10)
    assert axis.drive.modes._target == axis.p.limit_max


# -- profile velocity ------------------------------------------------------------------

def test_profile_velocity_ramps_to_the_target_speed():
    axis = Axis()
    axis.p.profile_acceleration, axis.p.profile_decel = 300.0, 600.0
    axis.sp.mode = MODE_PV
    assert axis.cycle() & SW_SPEED_ZERO
    axis.sp.target_velocity_counts_s = 30.0 / axis.rpc
    ramp = axis.until(lambda sw: axis.drive.modes.profile.v == 30.0)
    assert ramp * DT == pytest.approx(30.0 / 300.0, abs=2 * DT)
    axis.until(lambda sw: sw & SW_TARGET_REACHED)
    assert axis.drive.velocity_counts_s * axis.rpc == pytest.approx(30.0, rel=0.01)
    axis.sp.target_velocity_counts_s = 0.0
    down = axis.until(lambda sw: axis.drive.modes.profile.v == 0.0)
    assert down * DT == pytest.approx(30.0 / 600.0, abs=2 * DT)
    axis.until(lambda sw: sw & SW_SPEED_ZERO)


# -- homing -------------------------------------------------------------------------------

def homed(method: int, x0_m: float, offset_counts: int = 0) -> Axis:
    axis = Axis(x0_m)
    p = axis.p
    p.homing_method, p.home_offset = method, offset_counts * axis.rpc
    p.homing_speed_switch, p.homing_speed_zero, p.homing_acceleration = 20.0, 2.0, 400.0
    axis.sp.mode = MODE_HM
    assert axis.cycle() & SW_TARGET_REACHED  # not started
    axis.until(lambda sw: sw & SW_HOMING_ATTAINED and sw & SW_TARGET_REACHED,
               CW_NEW_SET_POINT)
    assert not axis.fb.statusword & SW_HOMING_ERROR
    return axis


@pytest.mark.parametrize("method, x0_mm, mark", [
    (5, 2.0, 1),    # below the edge (switch on): up across the edge to the next mark above
    (5, 20.0, 1),   # above: down onto the switch first, then up across the edge
    (6, 20.0, 0),   # above: down across the edge to the next mark below
    (6, 2.0, 0),    # below: up off the switch first, then down across the edge
])
def test_homing_on_the_home_switch_and_index_lands_on_the_mark_exactly(method, x0_mm, mark):
    """The edge is at 5 mm (half a lead), the marks at whole revolutions (0, 10 mm):
    method 5 homes on the mark at 10 mm, method 6 on the one at 0 mm.  The position actual
    value is then 607Ch at that mark, to the increment."""
    axis = homed(method, x0_mm * 1e-3, offset_counts=1234)
    assert axis.drive.modes.shift_counts == 1234 - mark * REV
    encoder = axis.plant.out[L.O_ENCODER]
    assert axis.fb.encoder_counts == encoder + 1234 - mark * REV


@pytest.mark.parametrize("method, x0_mm", [(21, 2.0), (22, 20.0)])
def test_homing_on_the_home_switch_edge(method, x0_mm):
    """Without the index, home is the edge as met: 5 mm, i.e. half a revolution of
    encoder increments, within the travel of one cycle at 6099h:02 plus the screw's
    elastic offset (a few µm)."""
    axis = homed(method, x0_mm * 1e-3)
    edge_counts = -axis.drive.modes.shift_counts
    assert edge_counts == pytest.approx(REV / 2, abs=2e-3 / 0.01 * REV / 1000)  # 2 µm
    assert axis.plant.params[L.P_HOME_SWITCH] == pytest.approx(5e-3)


@pytest.mark.parametrize("method", [35, 37])
def test_homing_on_the_current_position(method):
    axis = Axis(0.1)
    axis.p.homing_method, axis.p.home_offset = method, -500 * axis.rpc
    axis.sp.mode = MODE_HM
    here = axis.plant.out[L.O_ENCODER]
    axis.until(lambda sw: sw & SW_HOMING_ATTAINED, CW_NEW_SET_POINT)
    assert axis.drive.modes.shift_counts == -500 - here


def test_homing_is_interrupted_by_releasing_bit_4_and_methods_are_checked():
    axis = Axis(0.02)
    axis.p.homing_method = 6
    axis.sp.mode = MODE_HM
    axis.cycle(CW_NEW_SET_POINT, 100)
    assert axis.drive.modes.homing.phase == Phase.APPROACH
    axis.cycle(0)
    assert axis.drive.modes.homing.phase == Phase.IDLE
    axis.until(lambda sw: sw & SW_TARGET_REACHED)  # stopped
    objects = DriveObjects([axis.drive], 28.0)
    assert METHODS == {0, 5, 6, 21, 22, 35, 37}
    with pytest.raises(ObjectAccessError, match="homing methods offered"):
        objects.write(0, 0x6098, 0, 3)  # a positive home switch: the plant has none


# -- interpolation of cyclic setpoints ---------------------------------------------------------

def test_csp_targets_are_interpolated_linearly_over_60c2h():
    """60C2h = 1 ms over 125 µs cycles: a new target every 8 cycles, and the position
    demand on each cycle the straight line from the previous target, reaching the new one
    on the 8th; with 60C2h = 0 each target is taken as it comes."""
    axis = Axis()
    axis.p.interpolation_value, axis.p.interpolation_index = 1, -3
    axis.sp.mode = MODE_CSP
    start = axis.fb.encoder_counts
    axis.sp.target_position_counts = start
    axis.cycle(0, 8)
    targets = [start + 80.0 * k * k for k in range(1, 6)]
    previous = start
    for k, target in enumerate(targets):
        axis.sp.seq, axis.sp.target_position_counts = k + 1, target
        for j in range(1, 9):
            axis.cycle()
            line = (previous + (target - previous) * j / 8) * axis.rpc
            assert axis.drive.modes.demand == pytest.approx(line, rel=1e-15), (k, j)
        previous = target
    axis.p.interpolation_value = 0
    axis.sp.seq, axis.sp.target_position_counts = 99, start
    axis.cycle()
    assert axis.drive.modes.demand == start * axis.rpc


def test_a_silent_master_leaves_the_axis_at_its_last_target():
    """CSP at 60C2h = 1 ms with the speed feed-forward (60B1h) of its ramp: when the targets
    stop, the demand runs one period past the last one and holds there, and from then on
    the feed-forward is 0, so the axis stops near that point (a held demand with the last
    feed-forward kept would drive it on at that speed, held back only by the position
    loop: v / K_v, 1.5 mm here)."""
    axis = Axis()
    axis.p.interpolation_value, axis.p.interpolation_index = 1, -3
    axis.sp.mode = MODE_CSP
    start = axis.fb.encoder_counts
    per_ms = 0.05e-3 / (axis.rpc * 1.5915494309189536e-3)  # 50 mm/s in counts per ms
    axis.sp.velocity_offset_counts_s = per_ms * 1e3
    for k in range(1, 201):  # 200 ms ramp at 50 mm/s
        axis.sp.seq, axis.sp.target_position_counts = k, start + per_ms * k
        axis.cycle(0, 8)
    last = axis.sp.target_position_counts
    speeds, demands = [], []
    for _ in range(40):  # 5 ms without a new target
        axis.cycle()
        speeds.append(axis.drive.modes.speed)
        demands.append(axis.drive.modes.demand)
    assert speeds[7] > 0.0 and speeds[8:] == [0.0] * 32  # extrapolated 1 ms, then held
    assert demands[-1] == pytest.approx((last + per_ms) * axis.rpc, rel=1e-12)
    axis.cycle(0, 400)  # 50 ms more: at rest within a period's travel of the held demand
    assert abs(axis.fb.encoder_counts - (last + per_ms)) < per_ms


@pytest.mark.parametrize("cycle_s, match", [
    (0.0003, "communication_cycle_s = 0.0003 s must be a whole number of PWM periods"),
    (0.02, "communication_cycle_s"),
])
def test_a_communication_cycle_the_drive_cannot_keep_is_refused(cycle_s, match):
    """1006h from the machine file: whole PWM periods (125 µs here), 0.25 to 10 ms."""
    with pytest.raises(ConfigError, match=match):
        EmulatedDrive(Plant(load_machine(ARROW, overrides={
            "drive": {"communication_cycle_s": cycle_s}})))
    drive = EmulatedDrive(Plant(load_machine(ARROW, overrides={
        "drive": {"communication_cycle_s": 0.002}})))
    assert drive.params.communication_cycle_s == 0.002
