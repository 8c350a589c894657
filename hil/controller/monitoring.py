"""The NC's axis monitoring: contour (alarm 25050), standstill (25040) and clamping
(26000), as SINUMERIK's axis monitoring does them, once per position-control cycle.

**Contour monitoring** compares the actual position with the one a model of the closed
position loop expects from the setpoint alone (SINUMERIK compares the measured following
error with the one its model predicts; the difference of the two following errors is that
of the two positions).  The model is the loop as this NC builds it: its own position
controller (P with K_v, speed feed-forward with the symmetrising delay of MD32810, the
speed command limited to the maximum velocity) and its own speed controller (PI with the
filters, the torque feed-forward and the current limit, at the speed cycle, on the speed
measured as the encoder difference over the speed cycle), both with the axis's machine
data, closed around a rigid axis of the inertia the torque feed-forward uses, driven by
the current setpoint without lag.  What the model leaves out is what the NC does not
know: friction, load, elasticity, the drive's current loop, the feedback's transport;
normal motion shows those as a deviation of micrometres, while an axis that is blocked,
pushed or runs away leaves the model by the tolerance within a few position cycles.

SINUMERIK's own model takes the closed speed loop as the first-order lag of MD32810, T_eq:
with speed feed-forward the expected motion is then the setpoint through 1 / (1 + s T_eq).
A PI speed loop, though, follows a speed ramp without that lag (it is of type 2): with
the ideal speed loop the position loop's response is 1 / (1 + s T_eq) + s^2 T_eq /
((K_v + s) (1 + s T_eq)), ahead of the first-order model by a T_eq / K_v at a constant
acceleration a.  That is 0.15 mm at the Arrow 500 X's 2 m/s^2 and 0.54 deg on the GEISS
C axis (half its tolerance), so this NC runs its speed controller in the model instead.

**Standstill monitoring** starts MD36040 after the interpolator's setpoint last moved and
holds the following error within MD36030 while the setpoint stands; **clamping
monitoring** replaces it while the axis is clamped and holds the actual position within
MD36050 of where it was clamped.  None of them runs outside position control.
"""

import math
from dataclasses import dataclass

from hil.controller.alarms import AlarmNumber
from hil.controller.config import (
    ControllerSection,
    axis_limits,
    cnc_unit,
    monitoring_limits,
    motor_constant,
)
from hil.controller.loops import PositionLoop, SpeedLoop
from plant.assemble import reflected_inertia, transmission_ratio
from plant.config import MachineConfig


@dataclass(frozen=True)
class Violation:
    """A monitoring limit exceeded: the alarm it raises and what was measured (CNC units)."""
    number: AlarmNumber
    detail: str


class ContourModel:
    """The NC's position and speed controllers around a rigid axis: the actual position
    the closed loop should reach (see the module docstring).

    Args:
        cfg: the axis's machine file (inertia, motor constant, current limit, lead).
        sec: its machine data.
        period_s: the basic clock, s.

    Attributes:
        theta, w: the rigid axis's motor angle (rad; m on linear motors) and speed (/s).
    """

    def __init__(self, cfg: MachineConfig, sec: ControllerSection, period_s: float):
        self.speed_period = period_s * sec.speed_cycle_ratio
        self.pos = PositionLoop(sec, period_s * sec.position_cycle_ratio,
                                axis_limits(cfg, sec).velocity)
        kt = motor_constant(cfg)
        self.speed = SpeedLoop(sec, self.speed_period, cfg.machine.kind, kt,
                               cfg.motor.current_max_a)
        self.accel_per_amp = kt / reflected_inertia(cfg)  # rad/s² (m/s²) per A
        self.ratio = transmission_ratio(cfg)
        self.theta = self.w = self.w_cmd = self.i_ff = 0.0
        self.theta_prev = 0.0

    @property
    def x(self) -> float:
        """The expected actual position, m or rad."""
        return self.theta * self.ratio

    def reset(self, x: float, w: float, x_sym: float) -> None:
        """Start at position ``x`` (m or rad) at motor speed ``w`` (rad/s, m/s), the
        symmetrising filter at ``x_sym``, the controllers cleared (the model knows no load
        an integrator would hold)."""
        self.theta = self.theta_prev = x / self.ratio
        self.w = self.w_cmd = w
        self.i_ff = 0.0
        self.pos.reset(x_sym)
        self.speed.reset()

    def position_cycle(self, x_set: float, v_set: float, i_ff: float) -> None:
        """The model's position controller on this cycle's setpoint (and the current
        feed-forward ``i_ff``, A)."""
        self.w_cmd = self.pos.step(x_set, v_set, self.x) / self.ratio
        self.i_ff = i_ff

    def speed_cycle(self) -> None:
        """The model's speed controller, then the rigid axis over one speed cycle at the
        current it gives (exact for a held current)."""
        dt = self.speed_period
        w_measured = (self.theta - self.theta_prev) / dt  # as the NC measures: a difference
        self.theta_prev = self.theta
        accel = self.accel_per_amp * self.speed.step(self.w_cmd, w_measured, self.i_ff)
        self.theta += dt * (self.w + 0.5 * accel * dt)
        self.w += accel * dt

    def finite(self) -> bool:
        """Every state is finite."""
        return ((self.theta * 0.0 + self.w * 0.0 + self.w_cmd * 0.0) == 0.0
                and self.pos.finite() and self.speed.finite())


class AxisMonitor:
    """Contour, standstill and clamping monitoring of one axis.

    Args:
        cfg: the axis's machine file.
        sec: its machine data (the tolerances: :func:`~hil.controller.config.
            monitoring_limits`).
        period_s: the basic clock, s.

    Attributes:
        active: monitoring runs (position control since :meth:`start`).
        model: the contour model.
        deviation: actual minus expected position at the last position cycle, m or rad.
        clamped: the axis is clamped; ``clamp_position`` where, m or rad.
    """

    def __init__(self, cfg: MachineConfig, sec: ControllerSection, period_s: float):
        self.limits = limits = monitoring_limits(cfg, sec)
        self.model = ContourModel(cfg, sec, period_s)
        self.delay_cycles = math.ceil(
            limits.standstill_delay_s / (period_s * sec.position_cycle_ratio) - 1e-9)
        self.k_cnc, self.unit = cnc_unit(cfg)
        self.active = False
        self.deviation = 0.0
        self.clamped = False
        self.clamp_position = 0.0
        self._x_set_prev = math.nan
        self._still_cycles = 0

    def start(self, x_act: float, w_act: float, x_sym: float) -> None:
        """Position control begins (or resumes) at ``x_act`` (motor speed ``w_act``, the
        position loop's symmetrised setpoint ``x_sym``): the model starts there, the
        standstill delay from now."""
        self.model.reset(x_act, w_act, x_sym)
        self.active = True
        self.deviation = 0.0
        self._x_set_prev = math.nan
        self._still_cycles = 0

    def clamp(self, x_act: float) -> None:
        """The axis is clamped at ``x_act``."""
        self.clamped = True
        self.clamp_position = x_act

    def unclamp(self) -> None:
        """The clamp is released: standstill monitoring again."""
        self.clamped = False

    def check(self, x_set: float, v_set: float, i_ff: float, x_act: float) -> Violation | None:
        """One position cycle: compare ``x_act`` with the model, then run the model's
        position controller on this cycle's setpoint (``x_set``, ``v_set``, ``i_ff``)."""
        model = self.model
        self.deviation = x_act - model.x
        model.position_cycle(x_set, v_set, i_ff)
        if x_set == self._x_set_prev:
            self._still_cycles += 1
        else:
            self._still_cycles = 0
        self._x_set_prev = x_set
        lim = self.limits
        if abs(self.deviation) > lim.contour_tol:
            return self._violation(AlarmNumber.CONTOUR, "deviation", self.deviation,
                                   lim.contour_tol)
        if self.clamped:
            moved = x_act - self.clamp_position
            if abs(moved) > lim.clamp_tol:
                return self._violation(AlarmNumber.CLAMPING, "moved while clamped", moved,
                                       lim.clamp_tol)
        elif self._still_cycles >= self.delay_cycles:
            error = x_set - x_act
            if abs(error) > lim.standstill_tol:
                return self._violation(AlarmNumber.STANDSTILL, "following error at rest",
                                       error, lim.standstill_tol)
        return None

    def _violation(self, number: AlarmNumber, what: str, value: float,
                   limit: float) -> Violation:
        k, u = self.k_cnc, self.unit
        return Violation(number, f"{what} {abs(value) * k:.4g} {u} > {limit * k:g} {u}")
