"""The simulated NC with its drive control: one ``tick`` per basic clock (PWM period).

Per tick, in the order a SINUMERIK 840D with SINAMICS runs them:

* the feedback checked (a NaN or infinite value: alarm 25000, the last valid values kept)
  and the drive's state (the enabled drive left OPERATION ENABLED: alarm 25201 with its
  error code 603Fh);
* until the drive reports OPERATION ENABLED, the CiA 402 enable sequence;
* every IPO cycle the next interpolator point; every position cycle the fine
  interpolated setpoint, the axis monitoring (:mod:`hil.controller.monitoring`: contour,
  standstill, clamping) and the position loop;
* every speed cycle the speed loop on the speed measured from the motor
  encoder (difference over the speed cycle, through the first-order filter of
  ``speed_actual_filter_s``); with ``feedforward_interpolation = "linear"`` the speed
  feed-forward between position cycles moved linearly towards the next cycle's (the P
  part held); a trace-fed controller (:meth:`Controller.trace_feed_forward`) takes the
  trace's feed-forward of every speed cycle instead;
* the current setpoint delayed by ``current_delay_cycles`` PWM periods (the drive's
  computation delay);
* every tick, when the plant takes voltage, the current loop;
* the NC's own state checked: a NaN or infinite loop state is alarm 1000, the loops are
  cleared; it never raises.

The software limit switches (:mod:`hil.controller.limits`) are checked before a program
or a setpoint sequence moves (alarm 10720: the program ends before the first block beyond
them, a setpoint sequence does not start); in the test modes, which no end point bounds,
the speed is limited so that the axis stops on them (alarm 10620).

An alarm (:mod:`hil.controller.alarms`, the list in :attr:`Controller.alarms`) stops the
axis as an NC does (:mod:`hil.controller.stop`): the program is abandoned, the position
loop opened and the speed setpoint set to zero, so the speed controller brakes at its
current limit; once the axis stands still, after MD36620 at the latest, or at once when
the speed actual value is invalid or the drive no longer enabled, the drive is disabled
(controlword disable voltage) and the axis stays in follow-up until
:meth:`Controller.reset_alarms`.

The controller sees the axis only through :class:`~io_adapters.messages.Feedback` (raw
counts and sampled currents) and answers with a :class:`~io_adapters.messages.Setpoint`.
Test modes for the measuring functions replace the position loop by a speed
setpoint (``"speed"``) or the speed loop by a current setpoint (``"current"``),
each given as a function of the controller time plus an optional additive
excitation; the axis monitoring runs in position control only.

The ticks of the steady state (position control, the drive enabled, no alarm) run
compiled (:mod:`hil.controller.compiled`, packed and handed back by
:mod:`hil.controller.compiled_path`), with the same results bit for bit; whatever they
meet that is not steady (an alarm, a clamp block, a test mode, the enable sequence) runs
here.
"""

import math
from collections.abc import Callable

from hil.cia402 import STATUS_PATTERNS, EnableSequencer, State
from hil.controller.alarms import (
    AlarmList,
    AlarmNumber,
    drive_fault_detail,
    feedback_detail,
)
from hil.controller.blocks import PT1, Delay
from hil.controller.compiled_path import CompiledAxis
from hil.controller.config import (
    ControllerSection,
    axis_limits,
    load_controller,
    motor_constant,
)
from hil.controller.interpolator import (
    ClampEvent,
    FineInterpolator,
    Profile,
    ProfileSamples,
)
from hil.controller.limits import LimitViolation, software_limits
from hil.controller.loops import CurrentLoop, PositionLoop, SpeedLoop
from hil.controller.monitoring import AxisMonitor
from hil.controller.stop import Braking, Phase
from io_adapters.messages import MODE_CST, MODE_VOLTAGE, Feedback, Setpoint
from plant.assemble import reflected_inertia, transmission_ratio, voltage_limit
from plant.config import MachineConfig

MODES = ("position", "speed", "current")
#: time the drive may take to reach OPERATION ENABLED before the NC reports a failure, s
ENABLE_TIMEOUT_S = 0.5
_OPERATION_ENABLED = STATUS_PATTERNS[State.OPERATION_ENABLED]


class Controller:
    """Interpolation, position, speed and current control of one axis, with its
    monitoring and alarms.

    Args:
        cfg: the axis's machine file.
        period_s: the basic clock (the PWM period), s.
        x0: the table position at start, m or rad.
        section: its ``[controller]`` machine data (default: the file's).
        axis: the axis name in alarms (default X, or C on a rotary table).
        compiled: run the ticks of a steady state compiled
            (:mod:`hil.controller.compiled_path`; the same results, bit for bit; False:
            every tick in Python, the reference it equals).

    Signals of the last tick (SI, table units unless named otherwise) are
    attributes: ``x_set, v_set, a_set, x_act, theta_act (motor encoder, rad), v_act, v_cmd,
    w_set, w_act, iq_set`` (``w_act`` the measured speed through ``speed_actual_filter_s``,
    ``iq_set`` the speed loop's output before ``current_delay_cycles``),
    ``following_error`` (x_set - x_act, taken at the position-control cycle like the
    NC's own, and held between cycles) and ``contour_deviation`` (actual minus the
    contour model's position, at the position-control cycle).  ``alarms`` is the axis's
    :class:`~hil.controller.alarms.AlarmList`, ``phase`` its :class:`Phase`, ``monitored``
    whether position control runs with the axis monitoring (:meth:`run_points`),
    ``soft_limits`` its :class:`~hil.controller.limits.SoftwareLimits` and ``at_limit``
    whether a test mode's speed is being limited by them.  ``compiled`` is the compiled
    path (None: every tick in Python); while it holds the state, a reader of the loops'
    or the monitor's state calls :meth:`settle` first.
    """

    def __init__(self, cfg: MachineConfig, period_s: float, x0: float = 0.0,
                 section: ControllerSection | None = None, axis: str | None = None,
                 compiled: bool = True):
        self.compiled: CompiledAxis | None = None
        self.cfg = cfg
        self.sec = sec = section or load_controller(cfg)
        self.period = period_s
        kind = cfg.machine.kind
        kt = motor_constant(cfg)
        i_max = cfg.motor.current_max_a
        self.ratio = transmission_ratio(cfg)
        self.limits = axis_limits(cfg, sec)
        self.pos_loop = PositionLoop(sec, period_s * sec.position_cycle_ratio,
                                     self.limits.velocity)
        self.speed_loop = SpeedLoop(sec, period_s * sec.speed_cycle_ratio, kind, kt, i_max)
        self.cur_loop = None
        if sec.plant_input == "voltage":
            mo = cfg.motor
            poles = math.pi / mo.pole_pitch_m if kind == "linear" else mo.pole_pairs
            motor = (poles, kt / (1.5 * poles), mo.inductance_d_h, mo.inductance_q_h)
            self.cur_loop = CurrentLoop(sec, period_s, voltage_limit(cfg), motor)
        self.i_ff_gain = reflected_inertia(cfg) / (self.ratio * kt) if sec.torque_ff else 0.0
        self.speed_filter = PT1(sec.speed_actual_filter_s, period_s * sec.speed_cycle_ratio)
        self.filter_speed = sec.speed_actual_filter_s > 0.0
        self.ff_linear = sec.feedforward_interpolation == "linear" and sec.speed_ff
        self.iq_delay = Delay(sec.current_delay_cycles)
        if kind == "linear":
            self.rad_per_count = cfg.sensors.encoder_resolution_m
        else:
            self.rad_per_count = 2.0 * math.pi / cfg.sensors.encoder_counts_per_rev
        self.scale_res = cfg.sensors.scale_resolution_m if sec.feedback == "scale" else 0.0
        self.polarity = -1.0 if sec.encoder_feedback_polarity < 0 else 1.0
        self.axis = axis or ("C" if kind == "rotary" else "X")
        self.alarms = AlarmList(self.axis)
        self.soft_limits = software_limits(cfg, sec)
        self.at_limit = False
        self.monitor = AxisMonitor(cfg, sec, period_s)
        self.monitored = True
        self.braking = Braking(self.monitor.limits, period_s, sec.speed_cycle_ratio,
                               sec.position_cycle_ratio)
        self.enable_timeout_ticks = max(1, round(ENABLE_TIMEOUT_S / period_s))
        self.enable = EnableSequencer(timeout_cycles=self.enable_timeout_ticks)
        self.enable.enable()
        self.mode = "position"
        self.fine: FineInterpolator | None = None
        self.clamps: tuple[ClampEvent, ...] = ()
        self.source: Callable[[float], float] | None = None
        self.excitation: Callable[[float], float] | None = None
        self.reset(x0)
        self.compiled = CompiledAxis(self) if compiled else None

    def settle(self) -> None:
        """Bring the state the compiled path holds back into the controller's objects (its
        loops, filters, monitor, interpolator), for a reader outside the tick."""
        if self.compiled is not None:
            self.compiled.leave()

    def trace_feed_forward(self):
        """The speed feed-forward (m/s or rad/s) of every speed cycle from the first
        position cycle of the points followed, when a trace gives it
        (:class:`hil.identify.trace_controller.TraceController`), shape (n,); else None:
        the fine interpolator's."""

    def reset(self, x0: float) -> None:
        """At rest at table position ``x0``, drive disabled, program cleared."""
        self.settle()
        self.tick_count = 0
        self.t = 0.0
        self.x_set = self.x_act = x0
        self.theta_act = x0 / self.ratio
        self.v_set = self.a_set = self.v_act = self.v_cmd = 0.0
        self.w_set = self.w_act = self.iq_set = self.i_ff = self.following_error = 0.0
        self.id_meas = self.iq_meas = self.contour_deviation = 0.0
        self.theta_prev = None
        self.phase = Phase.RUN
        self.feedback_ok = True
        self._fine_cycles = 0
        self._clear_loops()

    @property
    def enabled(self) -> bool:
        """True once the drive reported OPERATION ENABLED (and until an alarm's stop
        disables it)."""
        return self.enable.done and self.enable.target == State.OPERATION_ENABLED

    @property
    def stopped(self) -> bool:
        """An alarm's stop reaction is complete: the drive reported SWITCH ON DISABLED (or
        FAULT), or the disable request timed out."""
        return self.phase is Phase.HALT and (self.enable.done or self.enable.failed)

    @property
    def ipo_period_s(self) -> float:
        """The interpolation cycle in s."""
        return self.period * self.sec.ipo_cycle_ratio

    def run_profile(self, profile: Profile) -> Profile:
        """Follow an interpolator profile: its IPO points, fine-interpolated to the
        position cycle, and its clamp and unclamp blocks, starting at the next enabled
        tick (unclamped), with the axis monitoring; up to the first block beyond the
        software limits (alarm 10720, :meth:`limit_violation`).  Returns the profile run."""
        violation = self.limit_violation(profile)
        if violation is None:
            return self.start_program(profile)
        return self.start_program(profile, violation.t_s, violation)

    def limit_violation(self, profile: Profile) -> LimitViolation | None:
        """Block preparation: the first move block of ``profile`` beyond the software
        limits; while alarm 10720 is pending (until :meth:`reset_alarms`) NC start is
        refused: a violation at the program's start."""
        if self.alarms.count(AlarmNumber.SOFTWARE_LIMIT):
            return LimitViolation(0.0, "NC start refused: alarm 10720 is pending (RESET)")
        return self.soft_limits.first_violation(profile, self.axis)

    def start_program(self, profile: Profile, stop_s: float = math.inf,
                      violation: LimitViolation | None = None) -> Profile:
        """Follow ``profile`` as :meth:`run_profile` does, ended at ``stop_s`` (s, the start
        of a block: nothing of it moves), raising alarm 10720 for ``violation``.  Returns
        the profile run."""
        runs = profile.until(stop_s) if stop_s < profile.duration_s else profile
        self._follow(runs.ipo_points(self.ipo_period_s), monitored=True)
        self.clamps = runs.clamps
        if violation is not None:
            self.alarms.raise_alarm(AlarmNumber.SOFTWARE_LIMIT, violation.detail,
                                    self.tick_count, self.t)
        return runs

    def run_points(self, ipo: ProfileSamples, monitored: bool = False) -> None:
        """Follow IPO points (at the IPO period) in position mode.  Points that no
        interpolator planned (a measuring function's setpoint step, a recorded trace) run
        without contour and standstill monitoring unless ``monitored``: the contour model
        holds for motion within the axis's dynamics only.  A point beyond the software
        limits, or NC start refused, raises alarm 10720 and none of them runs."""
        beyond = (self.soft_limits.first_setpoint_beyond(ipo, self.axis)
                  if not self.alarms.count(AlarmNumber.SOFTWARE_LIMIT)
                  else "NC start refused: alarm 10720 is pending (RESET)")
        if beyond is None:
            self._follow(ipo, monitored)
            return
        self._follow(None, monitored)
        self.alarms.raise_alarm(AlarmNumber.SOFTWARE_LIMIT, beyond, self.tick_count, self.t)

    def _follow(self, ipo: ProfileSamples | None, monitored: bool) -> None:
        """Position mode on the IPO points ``ipo`` (None: the setpoint stays)."""
        self.settle()
        self.mode = "position"
        ratio = self.sec.ipo_cycle_ratio // self.sec.position_cycle_ratio
        self.fine = None if ipo is None else FineInterpolator(ipo, ratio)
        self.clamps = ()
        self._fine_cycles = 0
        self.monitored = monitored
        self.monitor.active = False
        self.monitor.unclamp()
        self.t = 0.0

    def run_source(self, mode: str, source: Callable[[float], float],
                   excitation: Callable[[float], float] | None = None) -> None:
        """Test mode: ``source(t)`` gives the speed setpoint (rad/s, m/s for linear motors)
        in mode "speed", or the q-current setpoint (A) in mode "current"; ``excitation(t)``
        is added to it."""
        if mode not in MODES[1:]:
            raise ValueError(f"test mode must be 'speed' or 'current', not {mode!r}")
        self.settle()
        self.mode = mode
        self.source = source
        self.excitation = excitation
        self.monitor.active = False
        self.at_limit = False
        self.t = 0.0

    def stop(self) -> None:
        """Stop the axis as for an alarm (without one: another axis's alarm stops this
        one too): the program is abandoned; an enabled axis brakes, then its drive is
        disabled; otherwise it is disabled at once."""
        self.settle()
        self.fine = None
        self.clamps = ()
        if self.phase is not Phase.RUN:
            return
        if self.enabled:
            self.phase = Phase.BRAKE
            self.braking.start()
        else:
            self._halt()

    def reset_alarms(self) -> None:
        """The NC's RESET: clear the alarm list and, after a stop, request OPERATION
        ENABLED again (a faulted drive gets the fault-reset pulse first)."""
        self.settle()
        self.alarms.clear()
        if self.phase is not Phase.RUN:
            self.phase = Phase.RUN
            self.enable.enable()

    def _alarm(self, number: AlarmNumber, detail: str) -> None:
        self.alarms.raise_alarm(number, detail, self.tick_count - 1, self.t)
        self.stop()

    def _halt(self) -> None:
        self.phase = Phase.HALT
        self.iq_set = 0.0
        self.enable.disable()

    def _read(self, fb: Feedback, k: int) -> None:
        """Take the feedback's values, or keep the last valid ones and raise alarm 25000
        when one is NaN or infinite (x * 0.0 is 0.0 for finite x only)."""
        ok = (fb.encoder_counts * 0.0 + fb.scale_counts * 0.0 + fb.velocity_counts_s * 0.0
              + fb.iq_a * 0.0 + fb.id_a * 0.0) == 0.0
        if ok:
            self._measure(fb, k)
        else:
            self.theta_prev = None  # the speed restarts from the next valid sample
            if self.feedback_ok:
                self._alarm(AlarmNumber.ENCODER_HW_FAULT, feedback_detail(fb))
        self.feedback_ok = ok

    def _measure(self, fb: Feedback, k: int) -> None:
        """The actual values of tick ``k``: the speed every speed cycle (the encoder
        difference over it), position and currents every tick."""
        theta = fb.encoder_counts * self.rad_per_count
        n_speed = self.sec.speed_cycle_ratio
        if k % n_speed == 0:
            if self.theta_prev is not None:
                self.w_act = (theta - self.theta_prev) / (self.period * n_speed)
            self.theta_prev = theta
            if self.filter_speed:
                self.w_act = self.speed_filter.step(self.w_act)
            self.v_act = self.w_act * self.ratio
        self.theta_act = theta
        x = fb.scale_counts * self.scale_res if self.scale_res else theta * self.ratio
        self.x_act = self.polarity * x
        self.id_meas, self.iq_meas = fb.id_a, fb.iq_a

    def _watch_drive(self, fb: Feedback) -> None:
        """Alarm 25201 when the drive, enabled at the last tick, no longer reports
        OPERATION ENABLED; it can no longer be braked, so it is disabled at once."""
        if not self.enabled or _OPERATION_ENABLED.matches(fb.statusword):
            return
        self._alarm(AlarmNumber.DRIVE_FAULT, drive_fault_detail(fb))
        self._halt()

    def _follow_up(self) -> None:
        """While the drive is not enabled (start-up, after an alarm): the setpoint follows
        the actual position, every loop is cleared and a running program is abandoned, as an
        NC's follow-up mode does; so a fault's bad feedback never reaches a loop's state."""
        self._hold_setpoint()
        self.iq_set = self.w_act = self.v_act = self.following_error = 0.0
        self.contour_deviation = 0.0
        self.theta_prev = None
        self.fine = None
        self.clamps = ()
        self._clear_loops()

    def _hold_setpoint(self) -> None:
        """No motion commanded: the position setpoint at the actual position, speed,
        acceleration, speed command and current feed-forward zero."""
        self.x_set = self.x_act
        self.v_set = self.a_set = self.v_cmd = self.w_set = self.i_ff = 0.0

    def _clear_loops(self) -> None:
        self.pos_loop.reset(self.x_act)
        self.speed_loop.reset()
        self.speed_filter.reset()
        self.iq_delay.reset()
        if self.cur_loop is not None:
            self.cur_loop.reset()
        self.monitor.active = False

    def _position_cycle(self) -> None:
        if self.mode == "position":
            monitor = self.monitor
            if self.monitored and not monitor.active:
                monitor.start(self.x_act, self.w_act, self.pos_loop.sym.y)
            if self.fine is not None:
                self._clamp_events()
                self.fine.step()
                self.x_set, self.v_set, self.a_set = self.fine.pos, self.fine.vel, self.fine.acc
            self.following_error = self.x_set - self.x_act
            self.i_ff = self.i_ff_gain * self.a_set
            if monitor.active:
                violation = monitor.check(self.x_set, self.v_set, self.i_ff, self.x_act)
                self.contour_deviation = monitor.deviation
                if violation is not None:
                    self._alarm(violation.number, violation.detail)
                    return
            self.v_cmd = self.pos_loop.step(self.x_set, self.v_set, self.x_act)
            self.w_set = self.v_cmd / self.ratio
        elif self.mode == "speed":
            w = self.source(self.t)
            if self.excitation is not None:
                w += self.excitation(self.t)
            self.w_set = self._within_limits(w)

    def _within_limits(self, w: float) -> float:
        """The speed setpoint ``w`` (motor rad/s; m/s on linear motors) held within the
        speeds from which the axis can stop on its software limits at its maximum
        acceleration (:meth:`~hil.controller.limits.SoftwareLimits.speed_range`); alarm
        10620 each time that bound starts to act."""
        lo, hi = self.soft_limits.speed_range(self.x_act, self.limits.acceleration)
        v = self.polarity * w * self.ratio  # in the frame of x_act
        limited = not lo <= v <= hi
        if limited and not self.at_limit:
            side = "+" if v > hi else "-"
            self.alarms.raise_alarm(
                AlarmNumber.SOFTWARE_LIMIT_REACHED,
                f"speed toward the {self.soft_limits.limit(side)} limited at "
                f"{self.axis}{self.x_act * self.soft_limits.per_si:.3f} "
                f"{self.soft_limits.unit}", self.tick_count - 1, self.t)
        self.at_limit = limited
        return self.polarity * min(max(v, lo), hi) / self.ratio if limited else w

    def _guard_current_mode(self) -> None:
        """Current mode has no speed loop to limit the speed: once the axis is faster toward
        a software limit than it can stop from, the NC takes it over in speed mode at the
        speed it has, which :meth:`_within_limits` then brakes onto the limit."""
        lo, hi = self.soft_limits.speed_range(self.x_act, self.limits.acceleration)
        v = self.polarity * self.v_act
        if lo <= v <= hi:
            return
        w_now = self.w_act
        self.mode = "speed"
        self.source = lambda t: w_now
        self.excitation = None
        self.speed_loop.reset()

    def _clamp_events(self) -> None:
        """Clamp or unclamp on the blocks the fine interpolator's setpoint has reached."""
        t_fine = self._fine_cycles * self.period * self.sec.position_cycle_ratio
        self._fine_cycles += 1
        while self.clamps and self.clamps[0].t_s <= t_fine:
            if self.clamps[0].clamped:
                self.monitor.clamp(self.x_act)
            else:
                self.monitor.unclamp()
            self.clamps = self.clamps[1:]

    def _run(self, k: int) -> None:
        """The program or test mode's cycles due at tick ``k``."""
        sec = self.sec
        if self.mode == "current" and k % sec.speed_cycle_ratio == 0:
            self._guard_current_mode()
        trace = self.trace_feed_forward() if self.mode == "position" else None
        if (trace is None and self.ff_linear and self.mode == "position"
                and k % sec.position_cycle_ratio and k % sec.speed_cycle_ratio == 0):
            self._interpolate_feed_forward(k)
        due = sec.speed_cycle_ratio if self.mode == "speed" else sec.position_cycle_ratio
        if k % due == 0:
            self._position_cycle()
            if self.phase is not Phase.RUN:
                return
        if k % sec.speed_cycle_ratio == 0:
            if trace is not None:
                self._given_feed_forward(trace, k)
            if self.mode == "current":
                self.iq_set = self.source(self.t)
                if self.excitation is not None:
                    self.iq_set += self.excitation(self.t)
            else:
                self.iq_set = self.speed_loop.step(self.w_set, self.w_act, self.i_ff)
            if self.monitor.active:
                self.monitor.model.speed_cycle()

    def _interpolate_feed_forward(self, k: int) -> None:
        """A speed cycle between position cycles: the speed command of the held P part
        with the feed-forward on the line from this position cycle's value to the next's."""
        n_pos = self.sec.position_cycle_ratio
        frac = (k % n_pos) / n_pos
        v_ff = self.v_set + (self._next_feed_forward() - self.v_set) * frac
        self.v_cmd = self.pos_loop.command(v_ff)
        self.w_set = self.v_cmd / self.ratio

    def _given_feed_forward(self, trace, k: int) -> None:
        """A speed cycle of a trace-fed controller: the speed command of the P part of the
        last position cycle with the trace's feed-forward of this speed cycle (none before
        the points' first position cycle; IndexError past the trace's end)."""
        sec = self.sec
        n_pos, n_speed = sec.position_cycle_ratio, sec.speed_cycle_ratio
        j = (self._fine_cycles - 1) * (n_pos // n_speed) + (k % n_pos) // n_speed
        if j < 0:
            return
        self.v_cmd = self.pos_loop.command(float(trace[j]))
        self.w_set = self.v_cmd / self.ratio

    def _next_feed_forward(self) -> float:
        """The next position cycle's speed feed-forward (m/s or rad/s): the fine
        interpolator's, or this cycle's when no program runs."""
        return self.v_set if self.fine is None else self.fine.next_vel

    def _brake(self, k: int) -> None:
        """Speed setpoint zero, position loop open (the following error and the contour
        deviation hold their values of the alarm's cycle), until :class:`~hil.controller.
        stop.Braking` says the drive is to be disabled."""
        self._hold_setpoint()
        speed_cycle = k % self.sec.speed_cycle_ratio == 0
        if speed_cycle and self.feedback_ok:
            self.iq_set = self.speed_loop.step(0.0, self.w_act, 0.0)
        if self.braking.over(speed_cycle, self.v_act, self.feedback_ok):
            self._halt()

    def _state_finite(self, ud: float, uq: float) -> bool:
        """Every loop's state and this tick's outputs are finite."""
        return (self.pos_loop.finite() and self.speed_loop.finite()
                and self.monitor.model.finite()
                and (self.cur_loop is None or self.cur_loop.finite())
                and (self.iq_set * 0.0 + self.w_set * 0.0 + self.v_cmd * 0.0 + ud * 0.0
                     + uq * 0.0) == 0.0)

    def _state_alarm(self) -> None:
        """Alarm 1000 for a non-finite loop state; the loops are cleared and the setpoints
        zeroed, so nothing non-finite leaves the tick or stays in a loop."""
        names = ("position loop", "speed loop", "contour model", "current loop")
        parts = (self.pos_loop, self.speed_loop, self.monitor.model, self.cur_loop)
        bad = [n for n, part in zip(names, parts) if part is not None and not part.finite()]
        braking = self.phase is Phase.BRAKE
        self._alarm(AlarmNumber.SYSTEM_ERROR, "non-finite state: " + (
            ", ".join(bad) or "speed or current setpoint"))
        self._hold_setpoint()
        self.iq_set = self.following_error = self.contour_deviation = 0.0
        self._clear_loops()
        if braking:
            self._halt()  # it failed while braking: the braking cannot be trusted

    def tick(self, fb: Feedback, sp: Setpoint) -> None:
        """One basic-clock cycle: read ``fb``, write ``sp``."""
        if self.compiled is not None and self.compiled.run(fb, sp):
            return
        sp.seq = (sp.seq + 1) & 0xFFFFFFFF
        k = self.tick_count
        self.tick_count += 1
        self._read(fb, k)
        self._watch_drive(fb)
        sp.controlword = self.enable.next_controlword(fb.statusword)
        if not self.enabled:
            self._follow_up()
            sp.mode = MODE_CST
            sp.iq_ref_a = sp.id_ref_a = sp.ud_v = sp.uq_v = 0.0
            self.t += self.period
            return
        if self.phase is Phase.RUN:
            self._run(k)
        if self.phase is Phase.BRAKE:
            self._brake(k)
        iq_ref = self.iq_delay.step(self.iq_set)
        ud = uq = 0.0
        if self.cur_loop is not None:
            ud, uq = self.cur_loop.step(0.0, iq_ref, self.id_meas, self.iq_meas, self.w_act)
        if not self._state_finite(ud, uq):
            self._state_alarm()
            ud = uq = iq_ref = 0.0
        if self.cur_loop is None:
            sp.mode = MODE_CST
            sp.iq_ref_a = iq_ref
            sp.id_ref_a = 0.0
        else:
            sp.mode = MODE_VOLTAGE
            sp.ud_v, sp.uq_v = ud, uq
        self.t += self.period
