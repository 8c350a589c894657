"""The simulated NC with its drive control: one ``tick`` per basic clock (PWM period).

Per tick, in the order a SINUMERIK 840D with SINAMICS runs them:

* until the drive reports OPERATION ENABLED, the CiA 402 enable sequence;
* every IPO cycle the next interpolator point; every position cycle the fine
  interpolated setpoint and the position loop;
* every speed cycle the speed loop on the speed measured from the motor
  encoder (difference over the speed cycle);
* every tick, when the plant takes voltage, the current loop.

The controller sees the axis only through :class:`~io_adapters.messages.Feedback` (raw
counts and sampled currents) and answers with a :class:`~io_adapters.messages.Setpoint`.
Test modes for the measuring functions replace the position loop by a speed
setpoint (``"speed"``) or the speed loop by a current setpoint (``"current"``),
each given as a function of the controller time plus an optional additive
excitation.
"""

import math
from collections.abc import Callable

from hil.cia402 import EnableSequencer
from hil.controller.config import ControllerSection, axis_limits, load_controller
from hil.controller.interpolator import FineInterpolator, Profile, ProfileSamples
from hil.controller.loops import CurrentLoop, PositionLoop, SpeedLoop
from io_adapters.messages import MODE_CST, MODE_VOLTAGE, Feedback, Setpoint
from plant.assemble import reflected_inertia, transmission_ratio
from plant.config import MachineConfig

MODES = ("position", "speed", "current")
#: time the drive may take to reach OPERATION ENABLED before the NC reports a failure, s
ENABLE_TIMEOUT_S = 0.5


class Controller:
    """Interpolation, position, speed and current control of one axis.

    Signals of the last tick (SI, table units unless named otherwise) are
    attributes: ``x_set, v_set, a_set, x_act, theta_act (motor encoder, rad), v_act, v_cmd,
    w_set, w_act, iq_set`` and
    ``following_error`` (x_set - x_act, taken at the position-control cycle like the
    NC's own, and held between cycles).
    """

    def __init__(self, cfg: MachineConfig, period_s: float, x0: float = 0.0,
                 section: ControllerSection | None = None):
        self.cfg = cfg
        self.sec = sec = section or load_controller(cfg)
        self.period = period_s
        kind = cfg.machine.kind
        kt = cfg.motor.force_constant_n_per_a if kind == "linear" else (
            cfg.motor.torque_constant_nm_per_a)
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
            self.cur_loop = CurrentLoop(sec, period_s, 0.5 * mo.dc_link_v, motor)
        self.i_ff_gain = reflected_inertia(cfg) / (self.ratio * kt) if sec.torque_ff else 0.0
        if kind == "linear":
            self.rad_per_count = cfg.sensors.encoder_resolution_m
        else:
            self.rad_per_count = 2.0 * math.pi / cfg.sensors.encoder_counts_per_rev
        self.scale_res = cfg.sensors.scale_resolution_m if sec.feedback == "scale" else 0.0
        self.enable_timeout_ticks = max(1, round(ENABLE_TIMEOUT_S / period_s))
        self.enable = EnableSequencer(timeout_cycles=self.enable_timeout_ticks)
        self.enable.enable()
        self.mode = "position"
        self.fine: FineInterpolator | None = None
        self.source: Callable[[float], float] | None = None
        self.excitation: Callable[[float], float] | None = None
        self.reset(x0)

    def reset(self, x0: float) -> None:
        """At rest at table position ``x0``, drive disabled, program cleared."""
        self.tick_count = 0
        self.t = 0.0
        self.x_set = self.x_act = x0
        self.theta_act = x0 / self.ratio
        self.v_set = self.a_set = self.v_act = self.v_cmd = 0.0
        self.w_set = self.w_act = self.iq_set = self.i_ff = self.following_error = 0.0
        self.theta_prev = None
        self.pos_loop.reset(x0)
        self.speed_loop.reset()
        if self.cur_loop is not None:
            self.cur_loop.reset()

    @property
    def enabled(self) -> bool:
        """True once the drive reported OPERATION ENABLED."""
        return self.enable.done

    @property
    def ipo_period_s(self) -> float:
        """The interpolation cycle in s."""
        return self.period * self.sec.ipo_cycle_ratio

    def run_profile(self, profile: Profile) -> None:
        """Follow an interpolator profile: its IPO points, fine-interpolated to the
        position cycle, starting at the next enabled tick."""
        self.run_points(profile.ipo_points(self.ipo_period_s))

    def run_points(self, ipo: ProfileSamples) -> None:
        """Follow IPO points (at the IPO period) in position mode."""
        self.mode = "position"
        self.fine = FineInterpolator(ipo, self.sec.ipo_cycle_ratio // self.sec.position_cycle_ratio)
        self.t = 0.0

    def run_source(self, mode: str, source: Callable[[float], float],
                   excitation: Callable[[float], float] | None = None) -> None:
        """Test mode: ``source(t)`` gives the speed setpoint (rad/s, m/s for linear motors)
        in mode "speed", or the q-current setpoint (A) in mode "current"; ``excitation(t)``
        is added to it."""
        if mode not in MODES[1:]:
            raise ValueError(f"test mode must be 'speed' or 'current', not {mode!r}")
        self.mode = mode
        self.source = source
        self.excitation = excitation
        self.t = 0.0

    def _measure(self, fb: Feedback) -> None:
        theta = fb.encoder_counts * self.rad_per_count
        n_speed = self.sec.speed_cycle_ratio
        if self.tick_count % n_speed == 0:
            if self.theta_prev is not None:
                self.w_act = (theta - self.theta_prev) / (self.period * n_speed)
                self.v_act = self.w_act * self.ratio
            self.theta_prev = theta
        self.theta_act = theta
        self.x_act = fb.scale_counts * self.scale_res if self.scale_res else theta * self.ratio

    def _follow_up(self) -> None:
        """While the drive is not enabled (start-up, fault): the setpoint follows the actual
        position, every loop is cleared and a running program is abandoned, as an NC's
        follow-up mode does; so a fault's bad feedback never reaches a loop's state."""
        self.x_set = self.x_act
        self.v_set = self.a_set = self.v_cmd = self.w_set = self.iq_set = self.i_ff = 0.0
        self.w_act = self.v_act = self.following_error = 0.0
        self.theta_prev = None
        self.fine = None
        self.pos_loop.reset(self.x_act)
        self.speed_loop.reset()
        if self.cur_loop is not None:
            self.cur_loop.reset()

    def _position_cycle(self) -> None:
        if self.mode == "position":
            if self.fine is not None:
                self.fine.step()
                self.x_set, self.v_set, self.a_set = self.fine.pos, self.fine.vel, self.fine.acc
            self.following_error = self.x_set - self.x_act
            self.v_cmd = self.pos_loop.step(self.x_set, self.v_set, self.x_act)
            self.w_set = self.v_cmd / self.ratio
            self.i_ff = self.i_ff_gain * self.a_set
        elif self.mode == "speed":
            self.w_set = self.source(self.t)
            if self.excitation is not None:
                self.w_set += self.excitation(self.t)

    def tick(self, fb: Feedback, sp: Setpoint) -> None:
        """One basic-clock cycle: read ``fb``, write ``sp``."""
        sp.seq = (sp.seq + 1) & 0xFFFFFFFF
        sp.controlword = self.enable.next_controlword(fb.statusword)
        self._measure(fb)
        sec = self.sec
        k = self.tick_count
        self.tick_count += 1
        if not self.enable.done:
            self._follow_up()
            sp.mode = MODE_CST
            sp.iq_ref_a = sp.id_ref_a = sp.ud_v = sp.uq_v = 0.0
            return
        due = sec.speed_cycle_ratio if self.mode == "speed" else sec.position_cycle_ratio
        if k % due == 0:
            self._position_cycle()
        if k % sec.speed_cycle_ratio == 0:
            if self.mode == "current":
                self.iq_set = self.source(self.t)
                if self.excitation is not None:
                    self.iq_set += self.excitation(self.t)
            else:
                self.iq_set = self.speed_loop.step(self.w_set, self.w_act, self.i_ff)
        if self.cur_loop is None:
            sp.mode = MODE_CST
            sp.iq_ref_a = self.iq_set
            sp.id_ref_a = 0.0
        else:
            sp.mode = MODE_VOLTAGE
            sp.ud_v, sp.uq_v = self.cur_loop.step(0.0, self.iq_set, fb.id_a, fb.iq_a,
                                                  self.w_act)
        self.t += self.period
