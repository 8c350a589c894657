"""The emulated drive: the device side of the wire, around one plant.

Every cycle (one PWM period of the plant) it takes a
:class:`~io_adapters.messages.Setpoint`, monitors the axis (:mod:`hil.drive.monitor`),
latches the fault causes found (:mod:`hil.drive.faults`), runs the CiA 402 state machine on
the controlword, drives the plant as its state says, steps the plant and fills a
:class:`~io_adapters.messages.Feedback` (statusword 6041h, error code 603Fh in ``fault``,
digital inputs 60FDh, the index mark last passed).

What the power stage does in each CiA 402 state:

* OPERATION ENABLED: the mode of operation (:mod:`hil.drive.modes`).  CST passes the q-
  and d-current setpoints, limited to 6072h (``max_current_a``); VOLTAGE passes the d-q
  voltages; CSV and PV close the speed loop, CSP, PP and homing the position loop too, in
  the drive, as a SINAMICS drive does, with the ``[controller]`` machine data of the
  simulated NC (:class:`~hil.drive.loops.DriveLoops`); CSP and CSV targets interpolated
  between communication cycles (60C2h), PP, PV and homing on the drive's own profile; the
  CSP and PP target held inside the software position limits 607Dh, the speed command
  inside 6080h and the current inside 6072h.  Any limit in force sets statusword bit 11
  (internal limit active).
* QUICK STOP ACTIVE: braking as 605Ah says (slow down ramp 6084h, quick stop ramp 6085h,
  or the current limit), then transition 12 (codes 1-4), or holding zero speed (5-8).
* FAULT REACTION ACTIVE: braking as 605Eh says, then transition 14 to FAULT; torque off at
  once for code 0 and for the causes of :data:`~hil.drive.faults.TORQUE_OFF`, also when
  one of them comes while the drive brakes.
* Braking is bounded (:mod:`hil.drive.braking`): a reaction whose speed does not fall
  under its envelope, or does not reach standstill in time, is the cause REACTION_FAILED
  (FF04h): pulses inhibited at once.
* every other state: torque off (the plant's pulses blocked); a holding brake closes
  after its closing time (:mod:`hil.drive.holding_brake`).

Braking needs the drive's speed loop; a drive without ``[controller]`` machine data takes
the torque off instead.  Positions and speeds on the wire are motor-encoder increments
(CiA 402 position factor 1), shifted by the home offset once a homing has ended (the
feedback's ``encoder_counts`` is the position actual value 6064h).  The profile modes (PP,
PV, homing) need the same loops as CSP; :meth:`EmulatedDrive.setpoint_bounds` offers the
cyclic modes only, which are what every link carries (a CANopen node adds the profile
modes, whose parameters it reaches by SDO).

A fault reset (rising edge of controlword bit 7) clears every latched cause that is gone
(:mod:`hil.drive.faults` says when each one is), in every mode; a non-finite or runaway
plant state restarts the emulation at rest where the table was last valid, so that cause is
gone at once.  The lost-master causes (setpoint watchdog, heartbeat, NMT) come from the
runtime through :attr:`EmulatedDrive.link_causes` and act as 6007h says.

The same object serves the lock-step simulator and the real-time loop.  A machine of
several axes is a :class:`DriveSet`: one drive per axis, each with its own CiA 402 state
machine, faults and loops, all cycled once per message.
"""

import math
import threading
from dataclasses import replace

from hil.cia402 import (
    CW_FAULT_RESET,
    DISABLE_VOLTAGE,
    QUICK_STOP,
    SW_FOLLOWING_ERROR,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT_ACTIVE,
    SW_TARGET_REACHED,
    AbortConnectionOption,
    DriveStateMachine,
    FaultReactionOption,
    QuickStopOption,
    State,
)
from hil.controller.config import ControllerSection, load_controller
from hil.drive.braking import envelope
from hil.drive.compiled_path import CompiledPath
from hil.drive.config import DriveParameters, load_drive
from hil.drive.faults import TORQUE_OFF, Cause, FaultLog
from hil.drive.holding_brake import HoldingBrake
from hil.drive.loops import DriveLoops
from hil.drive.modes import MODE_PP, PROFILE_MODES, ModeControl
from hil.drive.monitor import Monitor
from hil.drive.reaction import DONE, FAILED, BrakeRamp
from io_adapters.messages import (
    DI_HOME_SWITCH,
    DI_NEGATIVE_LIMIT,
    DI_POSITIVE_LIMIT,
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    MODE_VOLTAGE,
    Feedback,
    FeedbackGroup,
    Setpoint,
    SetpointBounds,
    axis_records,
)
from plant import Plant
from plant import layout as L


class EmulatedDrive:
    """A plant behind a CiA 402 drive interface (see the module docstring).

    Args:
        plant: the axis.
        section: the ``[controller]`` machine data for the drive's loops (default: the
            machine file's, when it has one).
        params: the drive's parameters (default: the machine file's ``[drive]`` section).
        compiled: run the cycles of a steady state compiled
            (:mod:`hil.drive.compiled_path`; the same results, bit for bit).

    Attributes:
        params: the monitoring and reaction objects in force (writable while running).
        faults: the latched causes and fault events.
        link_causes: lost-master causes present now (WATCHDOG, HEARTBEAT, NMT), set by the
            runtime before each cycle.
        fault: 603Fh of the last cycle (0: no fault latched).
        lock: held by every cycle; hold it to change :attr:`params` from another thread
            (an SDO write: :class:`hil.drive.objects.DriveObjects`), and to read the
            monitor's, modes' or loops' state after :meth:`settle`.
        compiled: the compiled path (None: every cycle in Python).
    """

    def __init__(self, plant: Plant, section: ControllerSection | None = None,
                 params: DriveParameters | None = None, compiled: bool = False):
        self.plant = plant
        cfg = plant.config
        if section is None and cfg.section("controller"):
            section = load_controller(cfg)
        self.params = params or load_drive(cfg, section)
        self.sm = DriveStateMachine(self.params.quick_stop_option)
        self.loops = DriveLoops(plant, section) if section is not None else None
        speed_ratio = section.speed_cycle_ratio if section is not None else 1
        self.speed_period = plant.pwm_period * speed_ratio
        self.speed_ratio = speed_ratio
        self.rad_per_count = 1.0 / plant.params[L.P_ENC_COUNTS_PER_RAD]
        self.monitor = Monitor(self.params, plant.pwm_period,
                               self.rad_per_count / self.speed_period)
        self.brake = BrakeRamp(plant.pwm_period)
        self.holding_brake = HoldingBrake(plant.params[L.P_BRAKE] > 0.0,
                                          cfg.brake.closing_time_s, plant.pwm_period)
        self.modes = ModeControl(self.params, plant.pwm_period, self.rad_per_count,
                                 plant.counts_per_mark)
        bounds = self.setpoint_bounds()
        self._bounds = (replace(bounds, modes=bounds.modes | PROFILE_MODES)
                        if self.loops is not None else bounds)
        self.faults = FaultLog()
        self.link_causes = 0
        self.lock = threading.Lock()
        self.fault = 0
        self.tick = 0
        self.counts_prev = math.nan
        self.velocity_counts_s = 0.0
        self._link_handled = 0      # link causes acted on while still present
        self._override = -1         # controlword forced by 6007h while the link is lost
        self._previous_cw = 0
        self._limited = 0           # statusword bit 11 when a command met a limit
        self._last_good_x = float(plant.out[L.O_TABLE_POS])
        self._counts_per_mark = plant.counts_per_mark
        self._marks = math.nan        # the index marks below the encoder, last cycle
        self._mark_counts = 0.0       # the encoder count of the mark last passed
        self.compiled = CompiledPath(self) if compiled else None

    def setpoint_bounds(self) -> SetpointBounds:
        """What this drive takes at all (an adapter refuses anything else): finite values,
        increments within 2**53, currents within the power stage's peak ([motor]
        current_max_a), voltages within the DC link, CSP and CSV only with the machine
        data for the drive's loops, VOLTAGE only on a motor model fed by voltage."""
        mo = self.plant.config.motor
        modes = {MODE_CST}
        if self.loops is not None:
            modes |= {MODE_CSP, MODE_CSV}
        if mo.model in ("dq", "commutation"):
            modes.add(MODE_VOLTAGE)
        return SetpointBounds(current_a=mo.current_max_a, voltage_v=mo.dc_link_v or math.inf,
                              modes=frozenset(modes))

    def refuse_setpoint(self) -> None:
        """A setpoint for this drive was refused by its adapter this cycle: a fault."""
        self.faults.latch(Cause.SETPOINT_REFUSED, self.tick)

    def _speed_actual(self, counts: float) -> None:
        """The drive's speed from the encoder difference over its speed cycle."""
        if self.tick % self.speed_ratio == 0:
            if self.counts_prev == self.counts_prev:  # not NaN: a previous sample exists
                self.velocity_counts_s = (counts - self.counts_prev) / self.speed_period
            self.counts_prev = counts

    def cycle(self, sp: Setpoint, fb: Feedback) -> None:
        """Apply ``sp``, advance the plant one PWM period, write ``fb``.  Holds
        :attr:`lock`: a parameter written from another thread lands between two cycles."""
        with self.lock:
            self._cycle(sp, fb)

    def settle(self) -> None:
        """Bring the state the compiled path holds back into the drive's objects (its
        monitor, modes, loops, state machine), for a reader outside the cycle; hold
        :attr:`lock`."""
        if self.compiled is not None:
            self.compiled.leave()

    def digital_inputs(self) -> int:
        """60FDh now: the plant's limit switches (bits 0, 1) and home switch (bit 2)."""
        out = self.plant.out
        return ((DI_NEGATIVE_LIMIT if out[L.O_LIMIT_NEG] > 0.0 else 0)
                | (DI_POSITIVE_LIMIT if out[L.O_LIMIT_POS] > 0.0 else 0)
                | (DI_HOME_SWITCH if out[L.O_HOME_SWITCH] > 0.0 else 0))

    def reference_inputs(self, fb: Feedback) -> None:
        """The feedback's 60FDh and index mark latch (:class:`~io_adapters.messages.Feedback`),
        after this drive's cycles (one, or a block of them run elsewhere: :mod:`hil.sim_block`).

        The plant gives the number of marks below the encoder position, so a change from
        k to k' tells exactly which mark was passed: k' moving up, k' + 1 moving down
        (the mark at ``max(k, k')`` for one mark; the last of several passed in one cycle).
        """
        fb.digital_inputs = self.digital_inputs()
        marks, last = self.plant.out[L.O_INDEX], self._marks
        if marks == marks and marks != last:  # NaN while the plant restarts: kept
            if last == last:
                self._mark_counts = (marks if marks > last else marks + 1) \
                    * self._counts_per_mark
            self._marks = marks
        fb.index_marks = int(self._marks) if self._marks == self._marks else 0
        fb.index_counts = self._mark_counts + self.modes.shift_counts

    def _cycle(self, sp: Setpoint, fb: Feedback) -> None:
        if self.compiled is not None and self.compiled.run(sp, fb):
            self.reference_inputs(fb)
            return
        plant, out, p, rpc = self.plant, self.plant.out, self.params, self.rad_per_count
        counts = out[L.O_ENCODER]
        self._speed_actual(counts)
        theta = counts * rpc
        w_act = self.velocity_counts_s * rpc
        operating = self.sm.state == State.OPERATION_ENABLED
        target, w_cmd = math.nan, 0.0
        if operating:
            target, w_cmd = self.modes.command(sp, theta, w_act, out)
            if sp.mode in (MODE_CSP, MODE_PP):
                target = min(max(target, p.limit_min), p.limit_max)
        else:
            self.modes.hold(sp, theta, w_act)
        present = self.monitor.check(operating, target, theta, w_act,
                                     out[L.O_IQ_MEAS] ** 2 + out[L.O_ID_MEAS] ** 2,
                                     (out[L.O_LIMIT_NEG], out[L.O_LIMIT_POS]),
                                     sp.mode == MODE_VOLTAGE)
        controlword = self._controlword(sp.controlword, present)
        standstill = self.monitor.standstill()
        braking = self.brake.active
        if braking and self.faults.latched & TORQUE_OFF:
            self.brake.stop()  # a cause that forbids braking came while it brakes
            braking = False
        verdict = self.brake.verdict(w_act, standstill) if braking else DONE
        if verdict == FAILED:
            self.faults.latch(Cause.REACTION_FAILED, self.tick)
            self.brake.stop()
            braking = False
        braked = braking and verdict == DONE
        before = self.sm.state
        # a fault reaction is over once its braking is (at once when it does not brake)
        statusword = self.sm.update(
            controlword, self.faults.latched != 0,
            stopped=braked if braking else abs(w_act) <= standstill,
            reaction_done=braked or not braking, flags=self._flags(sp.mode, w_act))
        self._limited = 0
        state = self.sm.state
        if state != before:
            self._entered(state, before, w_act)
        if self._bounds.refusal(sp.mode, sp.target_position_counts,
                                sp.target_velocity_counts_s, sp.velocity_offset_counts_s,
                                sp.iq_ref_a, sp.id_ref_a, sp.ud_v, sp.uq_v):
            # an adapter refuses these before they come here; a caller in the same process
            # meets the same refusal: nothing of it reaches the plant, and a fault follows
            self.faults.latch(Cause.SETPOINT_REFUSED, self.tick)
            iq, on = 0.0, False
        else:
            iq, on = self._current(state, sp, target, w_cmd, theta, w_act)
        inp = plant.inp
        voltage = sp.mode == MODE_VOLTAGE and state == State.OPERATION_ENABLED
        inp[L.I_ENABLE] = 1.0 if on else 0.0
        inp[L.I_BRAKE] = self.holding_brake.update(on)
        inp[L.I_MODE] = L.INPUT_VOLTAGE if voltage else L.INPUT_CURRENT
        inp[L.I_IQ_REF] = iq if on else 0.0
        limit = p.max_current_a
        inp[L.I_ID_REF] = min(max(sp.id_ref_a, -limit), limit) if on and not voltage else 0.0
        inp[L.I_UD] = sp.ud_v if voltage else 0.0
        inp[L.I_UQ] = sp.uq_v if voltage else 0.0
        self._step_plant()
        self.tick += 1
        self.fault = self.faults.code
        fb.seq = sp.seq
        fb.statusword = statusword
        fb.time_s = out[L.O_TIME]
        fb.encoder_counts = out[L.O_ENCODER] + self.modes.shift_counts
        fb.scale_counts = out[L.O_SCALE]
        fb.velocity_counts_s = self.velocity_counts_s
        fb.iq_a = out[L.O_IQ_MEAS]
        fb.id_a = out[L.O_ID_MEAS]
        fb.fault = self.fault
        self.reference_inputs(fb)

    # -- faults and the controlword -------------------------------------------------------
    def _controlword(self, controlword: int, present: int) -> int:
        """Latch this cycle's causes, take a fault reset, apply 6007h; the controlword the
        state machine sees."""
        p, sm = self.params, self.sm
        link = self.link_causes
        # 6007h acts on a lost link while the power stage is on (torque may be on): at once,
        # or when the drive is enabled while the link is still lost; once per loss
        new_link = link & ~self._link_handled if sm.power_enabled else 0
        self._link_handled = (self._link_handled | new_link) & link
        option = p.abort_connection_option
        latch = (present if sm.state == State.OPERATION_ENABLED
                 else present & (Cause.OVERSPEED | Cause.OVERCURRENT))
        if new_link and option == AbortConnectionOption.FAULT:
            latch |= new_link
        if new_link and option == AbortConnectionOption.DISABLE_VOLTAGE:
            self._override = DISABLE_VOLTAGE.value
        elif new_link and option == AbortConnectionOption.QUICK_STOP:
            self._override = QUICK_STOP.value
        if not link:
            self._override = -1
        self.faults.latch(latch, self.tick)
        rising = controlword & CW_FAULT_RESET and not self._previous_cw & CW_FAULT_RESET
        self._previous_cw = controlword
        if rising and sm.state == State.FAULT:
            self.faults.reset(present | link, self.tick)
        return controlword if self._override < 0 else self._override

    def _reaction(self) -> int:
        """605Eh in force for the latched causes (torque off where braking is impossible)."""
        if self.loops is None or self.faults.latched & TORQUE_OFF:
            return FaultReactionOption.DISABLE_DRIVE
        return self.params.fault_reaction_option

    def _brake(self, option: int, w_act: float) -> None:
        """Start braking from ``w_act`` as option code ``option`` says: 1 on the slow down
        ramp 6084h, 2 on the quick stop ramp 6085h, 3 and 4 at the current limit; watched
        as :mod:`hil.drive.braking` bounds it."""
        p = self.params
        ramp = {1: p.profile_decel, 2: p.quick_stop_decel}.get(option, math.inf)
        self.brake.start(w_act, ramp, envelope(p, option, w_act, self.monitor.standstill()))

    def _entered(self, state: State, before: State, w_act: float) -> None:
        """Start or end braking on a change of state (a fault reaction brakes only a drive
        whose power stage was on: one faulted while disabled keeps its torque off)."""
        if state == State.QUICK_STOP_ACTIVE and self.loops is not None:
            # 605Ah 1-4 and 5-8 brake alike: 1 and 5 on the slow down ramp, 2 and 6 on the
            # quick stop ramp, 3, 4, 7 and 8 at the current limit
            self._brake((self.sm.quick_stop_option - 1) % 4 + 1, w_act)
        elif (state == State.FAULT_REACTION_ACTIVE and self._reaction()
              and before in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)):
            self._brake(self._reaction(), w_act)
        else:
            self.brake.stop()
        if state != State.OPERATION_ENABLED:
            self.monitor.reset()

    def _flags(self, mode: int, w_act: float) -> int:
        """The statusword bits of this cycle: the monitor's, the limits the last cycle's
        commands met (bit 11), in OPERATION ENABLED the mode's bits 10, 12 and 13."""
        flags = self.monitor.flags
        if self.sm.state == State.OPERATION_ENABLED:
            mode_bits = SW_TARGET_REACHED | SW_FOLLOWS_COMMAND | SW_FOLLOWING_ERROR
            flags = flags & ~mode_bits | self.modes.flags(mode, flags, w_act,
                                                          self.monitor.standstill())
        return flags | self._limited

    # -- the power stage ------------------------------------------------------------------
    def _current(self, state: State, sp: Setpoint, target: float, w_cmd: float,
                 theta: float, w_act: float) -> tuple[float, bool]:
        """This cycle's q-current setpoint (A) and whether the power stage is on, for the
        mode's position demand ``target`` (NaN: speed or current control) and speed
        command or feed-forward ``w_cmd``."""
        loops, tick = self.loops, self.tick
        if state == State.OPERATION_ENABLED:
            if sp.mode in (MODE_CST, MODE_VOLTAGE):
                iq = sp.iq_ref_a
            elif loops is None:  # no machine data for the drive's loops
                return 0.0, True
            elif target == target:
                # a target held at a software limit stands still: no speed feed-forward
                held = target != self.modes.demand
                if held:
                    self._limited = SW_INTERNAL_LIMIT_ACTIVE
                w = loops.position(tick, target, 0.0 if held else w_cmd, theta)
                iq = loops.current(tick, self._speed_limited(w), w_act, sp.iq_ref_a)
            else:
                w = self._speed_limited(w_cmd)
                if (w > 0.0 and theta >= self.params.limit_max) or (
                        w < 0.0 and theta <= self.params.limit_min):
                    w = 0.0  # at a software limit: no further out
                    self._limited = SW_INTERNAL_LIMIT_ACTIVE
                iq = loops.current(tick, w, w_act, sp.iq_ref_a)
            return self._current_limited(iq, theta), True
        if self.brake.active and loops is not None:
            iq = loops.current(tick, self.brake.advance(), w_act, 0.0)
            return self._current_limited(iq, theta), True
        if loops is not None:
            loops.reset(theta)
        return 0.0, False

    def _speed_limited(self, w_cmd: float) -> float:
        limit = self.params.max_speed
        if abs(w_cmd) > limit:
            self._limited = SW_INTERNAL_LIMIT_ACTIVE
            return math.copysign(limit, w_cmd)
        return w_cmd

    def _current_limited(self, iq: float, theta: float) -> float:
        """``iq`` inside 6072h; a non-finite loop output is a fault (the loops restart)."""
        if iq != iq or abs(iq) == math.inf:
            self.faults.latch(Cause.LOOP_NONFINITE, self.tick)
            self.loops.reset(theta)
            return 0.0
        limit = self.params.max_current_a
        if abs(iq) > limit:
            self._limited = SW_INTERNAL_LIMIT_ACTIVE
            return math.copysign(limit, iq)
        return iq

    def _step_plant(self) -> None:
        """One PWM period; a non-finite or runaway state is a fault and the plant restarts
        at rest where the table was last valid."""
        plant = self.plant
        status = plant.step(plant.sub_per_pwm)
        if status == L.STATUS_OK:
            self._last_good_x = plant.out[L.O_TABLE_POS]
            return
        self.faults.latch(Cause.PLANT_NONFINITE if status == L.STATUS_NONFINITE
                          else Cause.PLANT_DIVERGED, self.tick)
        plant.reset(self._last_good_x)
        plant.inp[L.I_ENABLE] = 0.0
        self.counts_prev = math.nan
        self.velocity_counts_s = 0.0
        if self.loops is not None:
            self.loops.reset(plant.out[L.O_ENCODER] * self.rad_per_count)

    def inhibit_pulses(self) -> None:
        """Take the torque off from the next cycle whatever the drive does (a reaction still
        braking when the emulator must stop): the cause REACTION_FAILED (FF04h)."""
        with self.lock:
            self.faults.latch(Cause.REACTION_FAILED, self.tick)

    def set_quick_stop_option(self, code: int) -> None:
        """605Ah: ``code`` (1-8) from the next cycle on."""
        self.sm.set_quick_stop_option(QuickStopOption(code))
        self.params.quick_stop_option = int(code)


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
