"""What each mode of operation asks of the drive's loops, every drive cycle: a position
demand (position control, with a speed feed-forward) or a speed command, and the
statusword bits 10, 12 and 13 that mean something else in each mode.

=======  ====================================  ==========================================
mode     demand                                bits 10 / 12 / 13
=======  ====================================  ==========================================
CSP 8    607Ah (+ 60B1h feed-forward), linear  target reached (6067h/6068h) / following
         between communication cycles (60C2h,  the command / following error (6065h)
         :mod:`hil.drive.interpolation`)
CSV 9    60FFh, interpolated the same way      - / following the command / -
CST 10   the current itself                    - / following the command / -
PP 1     the profile generator to 607Ah        target reached (the profile done and
         (6081h, 6083h, 6084h;                 6067h/6068h held, or halted at rest) /
         :mod:`hil.drive.profile`)             set-point acknowledge / following error
PV 3     the profile generator at 60FFh        target reached (at the target speed within
         (6083h, 6084h): speed control          1 % or the standstill speed) / speed 0 / -
homing   the profile generator at the homing   :mod:`hil.drive.homing`'s
6        speeds (609Ah)
=======  ====================================  ==========================================

**Profile position set-points** (CiA 402-2 §12.2): a rising edge of controlword bit 4
(new set-point) takes 607Ah -- relative to the previous target with bit 6 -- if the
one-deep buffer is free, and sets statusword bit 12 (set-point acknowledge) until the
master clears bit 4 and the buffer is free again.  With bit 5 (change set immediately)
the new target replaces the one under way at once (the profile replans from where it
is); without it a target taken during a move waits in the buffer and starts when the
move is done.  Halt (bit 8) stops the axis on 6084h and keeps the target; releasing it
resumes the move.  A target beyond the software position limits 607Dh is held at them.

All positions are in the drive's motor coordinate; the home offset's position shift
(:attr:`ModeControl.shift_counts`, set by homing) is taken off the targets that come in
and added to what goes out (:class:`hil.drive.core.EmulatedDrive`).
"""

import math

from hil.cia402 import (
    CW_CHANGE_SET_IMMEDIATELY,
    CW_HALT,
    CW_NEW_SET_POINT,
    CW_RELATIVE,
    SW_FOLLOWING_ERROR,
    SW_FOLLOWS_COMMAND,
    SW_SET_POINT_ACK,
    SW_SPEED_ZERO,
    SW_TARGET_REACHED,
    ModeOfOperation,
)
from hil.drive.config import DriveParameters
from hil.drive.homing import METHODS, Homing, Phase
from hil.drive.interpolation import Interpolator
from hil.drive.profile import ProfileGenerator
from io_adapters.messages import MODE_CSP, MODE_CSV, MODE_VOLTAGE, Setpoint
from plant import layout as L

MODE_PP, MODE_PV, MODE_HM = (int(m) for m in (ModeOfOperation.PP, ModeOfOperation.PV,
                                               ModeOfOperation.HOMING))
PROFILE_MODES = frozenset((MODE_PP, MODE_PV, MODE_HM))
#: PV target reached: the speed actual within this share of the target speed ...
PV_WINDOW_SHARE = 0.01
NAN = math.nan


class ModeControl:
    """The modes of one drive (see the module docstring).

    Args:
        params: the drive's parameters (read every cycle).
        cycle_s: the drive cycle, s.
        rad_per_count: motor units per encoder increment.
        counts_per_mark: encoder increments between two index marks.

    Attributes:
        demand: the position demand value of the last cycle (6062h), motor units (the
            actual position outside the position modes).
        speed: the speed command or feed-forward of the last cycle, motor units/s.
    """

    def __init__(self, params: DriveParameters, cycle_s: float, rad_per_count: float,
                 counts_per_mark: int):
        self.params = params
        self.rpc = rad_per_count
        self.interp = Interpolator(cycle_s)
        self.profile = ProfileGenerator(cycle_s)
        self.homing = Homing(self.profile, counts_per_mark)
        self.demand = 0.0
        self.speed = 0.0
        self._mode = None
        self._previous_cw = 0
        self._target = 0.0
        self._pending: float | None = None
        self._ack = False
        self._done = True
        self._speed_target = 0.0

    @property
    def shift_counts(self) -> float:
        """Increments added to the encoder count for the position actual value (homing)."""
        return self.homing.shift_counts

    def _position(self, counts: float) -> float:
        """A position target on the wire, increments, in the motor coordinate."""
        return (counts - self.shift_counts) * self.rpc

    def hold(self, sp: Setpoint, theta: float, w: float) -> None:
        """Not operating: every mode stands where the axis is, set-points dropped."""
        self.profile.reset(theta)
        self.interp.reset(self._position(sp.target_position_counts),
                          sp.velocity_offset_counts_s * self.rpc)
        self._pending, self._ack, self._done = None, False, True
        self._target = theta
        self.homing.interrupt()
        self.demand, self.speed = theta, 0.0
        self._previous_cw = sp.controlword
        self._mode = sp.mode

    def command(self, sp: Setpoint, theta: float, w: float, plant_out) -> tuple[float, float]:
        """(position demand or NaN for speed and current control, speed command or
        feed-forward) of this cycle in OPERATION ENABLED; ``plant_out`` gives the home
        switch, the index marks and the encoder count (homing)."""
        mode, p, cw = sp.mode, self.params, sp.controlword
        rising = cw & CW_NEW_SET_POINT and not self._previous_cw & CW_NEW_SET_POINT
        falling = self._previous_cw & CW_NEW_SET_POINT and not cw & CW_NEW_SET_POINT
        self._previous_cw = cw
        if mode != self._mode:  # the new mode starts from where the last one left off
            self._mode = mode
            self.profile.reset(theta, w)
            self.interp.reset(self.demand if mode == MODE_CSP else w, 0.0)
            self._target, self._pending, self._done = theta, None, True
        halt = bool(cw & CW_HALT)
        if mode == MODE_CSP:
            x, ff = self.interp.step(sp.seq, self._position(sp.target_position_counts),
                                     sp.velocity_offset_counts_s * self.rpc,
                                     p.interpolation_period_s)
            return self._out(x, ff)
        if mode == MODE_CSV:
            v, _ = self.interp.step(sp.seq, sp.target_velocity_counts_s * self.rpc, 0.0,
                                    p.interpolation_period_s)
            return self._out(NAN, v, theta)
        if mode == MODE_PP:
            self._profile_position(sp, cw, rising, halt)
            return self._out(self.profile.x, self.profile.v)
        if mode == MODE_PV:
            self._speed_target = 0.0 if halt else sp.target_velocity_counts_s * self.rpc
            self.profile.to_velocity(self._speed_target, p.profile_acceleration,
                                     p.profile_decel)
            return self._out(NAN, self.profile.v, theta)
        if mode == MODE_HM:
            self._homing(rising, falling or halt, plant_out)
            return self._out(self.profile.x, self.profile.v)
        return self._out(NAN, 0.0, theta)

    def _out(self, x: float, v: float, theta: float = NAN) -> tuple[float, float]:
        self.demand = x if x == x else theta
        self.speed = v
        return x, v

    def _profile_position(self, sp: Setpoint, cw: int, rising: bool, halt: bool) -> None:
        p = self.params
        if rising and self._pending is None:
            base = self._target if cw & CW_RELATIVE else -self.shift_counts * self.rpc
            new = base + sp.target_position_counts * self.rpc
            new = min(max(new, p.limit_min), p.limit_max)
            if cw & CW_CHANGE_SET_IMMEDIATELY or self._done:
                self._target, self._done = new, False
            else:
                self._pending = new
            self._ack = True
        if not cw & CW_NEW_SET_POINT and self._pending is None:
            self._ack = False
        if halt:
            self.profile.to_velocity(0.0, p.profile_acceleration, p.profile_decel)
            return
        self._done = self.profile.to_position(self._target, min(p.profile_velocity,
                                                                p.max_speed),
                                              p.profile_acceleration, p.profile_decel)
        if self._done and self._pending is not None:
            self._target, self._pending, self._done = self._pending, None, False

    def _homing(self, rising: bool, stop: bool, out) -> None:
        p, homing = self.params, self.homing
        switch, marks, counts = out[L.O_HOME_SWITCH], out[L.O_INDEX], out[L.O_ENCODER]
        if rising and p.homing_method in METHODS:
            homing.start(p.homing_method, switch, counts, round(p.home_offset / self.rpc))
        elif stop:
            homing.interrupt()
        if homing.phase in (Phase.LEAVE, Phase.APPROACH, Phase.INDEX) and (
                out[L.O_LIMIT_NEG] > 0.0 or out[L.O_LIMIT_POS] > 0.0):
            homing.fail()
        speed = homing.speed(switch, marks, counts, (p.homing_speed_switch,
                                                     p.homing_speed_zero))
        self.profile.to_velocity(speed, p.homing_acceleration, p.homing_acceleration)

    def flags(self, mode: int, monitor_flags: int, w: float, standstill: float) -> int:
        """Statusword bits 10, 12 and 13 in OPERATION ENABLED (``monitor_flags`` the
        monitor's: target reached and following error in the position modes)."""
        if mode == MODE_PP:
            if self._previous_cw & CW_HALT:
                reached = SW_TARGET_REACHED if self.profile.stopped() else 0
            elif self._done and self._pending is None:
                reached = monitor_flags & SW_TARGET_REACHED
            else:
                reached = 0
            return (reached | (SW_SET_POINT_ACK if self._ack else 0)
                    | monitor_flags & SW_FOLLOWING_ERROR)
        if mode == MODE_PV:
            target = self._speed_target
            at = self.profile.v == target and abs(w - target) <= max(
                PV_WINDOW_SHARE * abs(target), standstill)
            return ((SW_TARGET_REACHED if at else 0)
                    | (SW_SPEED_ZERO if abs(w) <= standstill else 0))
        if mode == MODE_HM:
            return self.homing.flags()
        return monitor_flags | (SW_FOLLOWS_COMMAND if mode != MODE_VOLTAGE else 0)
