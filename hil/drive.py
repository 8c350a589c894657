"""The emulated drive: the device side of the wire, around one plant.

Every cycle (one PWM period of the plant) it takes a
:class:`~io_adapters.messages.Setpoint`, runs the CiA 402 state machine on its
controlword, passes the setpoints to the plant only while the state machine
has the power stage on, steps the plant and fills a
:class:`~io_adapters.messages.Feedback`.  A plant fault status latches a
drive fault (CiA 402 FAULT, torque off) until the state is reset and a fault
reset is commanded.  Torque is on only in OPERATION ENABLED; a quick stop
removes it and the axis coasts to rest against its friction (this drive has
no braking ramp of its own), after which transition 12 disables it.

Modes: CST passes the q-current (and d-current) setpoint to the plant's
current loop; VOLTAGE passes d-q voltages; CSV and CSP close the speed loop
(and, for CSP, the position loop) in the drive, as a SINAMICS drive does,
with the loop blocks and the ``[controller]`` machine data of the simulated
NC (speed cycle, K_v, speed PI and filters).  Positions and speeds on the
wire are motor-encoder increments (CiA 402 position factor 1).  The same
object serves the lock-step simulator and the real-time loop.

A machine of several axes is a :class:`DriveSet`: one drive per axis, each with its own
CiA 402 state machine, fault and loops, all cycled once per message.
"""

import math

from hil.cia402 import DriveStateMachine, State
from hil.controller.config import ControllerSection, axis_limits, load_controller
from hil.controller.loops import PositionLoop, SpeedLoop
from io_adapters.messages import (
    MODE_CSP,
    MODE_CSV,
    MODE_VOLTAGE,
    Feedback,
    FeedbackGroup,
    Setpoint,
    axis_records,
)
from plant import Plant
from plant import layout as L

#: motor speed (rad/s, or m/s) below which a quick-stopped axis counts as stopped
STOPPED_SPEED = 1e-3


class DriveLoops:
    """The drive's own speed and position loops for CSV and CSP, in motor units
    (rad and rad/s; m and m/s for linear motors)."""

    def __init__(self, plant: Plant, sec: ControllerSection):
        cfg = plant.config
        kind = cfg.machine.kind
        kt = (cfg.motor.force_constant_n_per_a if kind == "linear"
              else cfg.motor.torque_constant_nm_per_a)
        self.speed_ratio = sec.speed_cycle_ratio
        self.position_ratio = sec.position_cycle_ratio
        period = plant.pwm_period
        w_max = axis_limits(cfg, sec).velocity / plant.built.ratio
        self.pos = PositionLoop(sec, period * sec.position_cycle_ratio, w_max)
        self.speed = SpeedLoop(sec, period * sec.speed_cycle_ratio, kind, kt,
                               cfg.motor.current_max_a)
        self.w_cmd = 0.0
        self.iq = 0.0

    def reset(self, theta: float) -> None:
        """At rest at motor position ``theta``."""
        self.pos.reset(theta)
        self.speed.reset()
        self.w_cmd = 0.0
        self.iq = 0.0

    def step(self, tick: int, sp: Setpoint, rad_per_count: float, theta: float,
             w_act: float) -> float:
        """q-current setpoint (A) of this tick for a CSP or CSV setpoint."""
        if tick % self.speed_ratio:
            return self.iq
        if sp.mode == MODE_CSV:
            self.w_cmd = sp.target_velocity_counts_s * rad_per_count
        elif tick % self.position_ratio == 0:
            self.w_cmd = self.pos.step(sp.target_position_counts * rad_per_count,
                                       sp.velocity_offset_counts_s * rad_per_count, theta)
        self.iq = self.speed.step(self.w_cmd, w_act, sp.iq_ref_a)
        return self.iq


class EmulatedDrive:
    """A plant behind a CiA 402 drive interface."""

    def __init__(self, plant: Plant, section: ControllerSection | None = None):
        self.plant = plant
        self.sm = DriveStateMachine()
        self.fault = 0
        cfg = plant.config
        if section is None and cfg.section("controller"):
            section = load_controller(cfg)
        self.loops = DriveLoops(plant, section) if section is not None else None
        speed_ratio = section.speed_cycle_ratio if section is not None else 1
        self.speed_period = plant.pwm_period * speed_ratio
        self.speed_ratio = speed_ratio
        self.rad_per_count = 1.0 / plant.params[L.P_ENC_COUNTS_PER_RAD]
        self.tick = 0
        self.counts_prev = math.nan
        self.velocity_counts_s = 0.0

    def _speed_actual(self, counts: float) -> None:
        """The drive's speed from the encoder difference over its speed cycle."""
        if self.tick % self.speed_ratio == 0:
            if self.counts_prev == self.counts_prev:  # not NaN: a previous sample exists
                self.velocity_counts_s = (counts - self.counts_prev) / self.speed_period
            self.counts_prev = counts

    def cycle(self, sp: Setpoint, fb: Feedback) -> None:
        """Apply ``sp``, advance the plant one PWM period, write ``fb``."""
        plant = self.plant
        out = plant.out
        stopped = abs(out[L.O_MOTOR_VEL]) < STOPPED_SPEED
        statusword = self.sm.update(sp.controlword, self.fault != 0, stopped=stopped)
        on = self.sm.state == State.OPERATION_ENABLED
        counts = out[L.O_ENCODER]
        self._speed_actual(counts)
        iq = sp.iq_ref_a
        if sp.mode in (MODE_CSP, MODE_CSV):
            iq = self._closed_loop_current(sp, on, counts)
        inp = plant.inp
        inp[L.I_ENABLE] = 1.0 if on else 0.0
        inp[L.I_MODE] = L.INPUT_VOLTAGE if sp.mode == MODE_VOLTAGE else L.INPUT_CURRENT
        inp[L.I_IQ_REF] = iq if on else 0.0
        inp[L.I_ID_REF] = sp.id_ref_a if on else 0.0
        inp[L.I_UD] = sp.ud_v if on else 0.0
        inp[L.I_UQ] = sp.uq_v if on else 0.0
        status = plant.step(plant.sub_per_pwm)
        self.tick += 1
        if status != L.STATUS_OK:
            self.fault = status
        fb.seq = sp.seq
        fb.statusword = statusword
        fb.time_s = out[L.O_TIME]
        fb.encoder_counts = out[L.O_ENCODER]
        fb.scale_counts = out[L.O_SCALE]
        fb.velocity_counts_s = self.velocity_counts_s
        fb.iq_a = out[L.O_IQ_MEAS]
        fb.id_a = out[L.O_ID_MEAS]
        fb.fault = self.fault

    def _closed_loop_current(self, sp: Setpoint, on: bool, counts: float) -> float:
        """The drive's own loops for CSP/CSV; idle (following the actual position) while
        the power stage is off; 0 A without the machine data for them."""
        loops = self.loops
        if loops is None:
            return 0.0
        theta = counts * self.rad_per_count
        if not on:
            loops.reset(theta)
            return 0.0
        w_act = self.velocity_counts_s * self.rad_per_count
        return loops.step(self.tick, sp, self.rad_per_count, theta, w_act)

    def clear_fault(self, table_pos: float = 0.0) -> None:
        """Reset the plant after a fault so that a fault reset can succeed."""
        self.plant.reset(table_pos)
        self.fault = 0
        self.counts_prev = math.nan
        self.velocity_counts_s = 0.0


class DriveSet:
    """The drives of a machine's axes behind one message pair (plain records on one axis,
    :class:`~io_adapters.messages.SetpointGroup`/``FeedbackGroup`` on several).

    One :meth:`cycle` runs every drive's cycle on its axis's setpoint, in axis order; on a
    group the feedback's common fields take the cycle's ``seq`` and axis 0's time (every
    plant advanced the same PWM period).
    """

    def __init__(self, drives: list[EmulatedDrive]):
        if not drives:
            raise ValueError("a DriveSet needs at least one drive")
        self.drives = drives

    def __len__(self) -> int:
        return len(self.drives)

    def __getitem__(self, i: int) -> EmulatedDrive:
        return self.drives[i]

    def cycle(self, sp, fb) -> None:
        """Apply ``sp``, advance every plant one PWM period, write ``fb``."""
        for drive, s, f in zip(self.drives, axis_records(sp), axis_records(fb)):
            drive.cycle(s, f)
        if isinstance(fb, FeedbackGroup):
            fb.seq = sp.seq
            fb.time_s = fb.axes[0].time_s
