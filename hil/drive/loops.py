"""The drive's own speed and position loops (CSV, CSP, and the braking of its reactions),
with the loop blocks and the ``[controller]`` machine data of the simulated NC, as a
SINAMICS drive closes them."""

from hil.controller.config import ControllerSection, axis_limits, motor_constant
from hil.controller.loops import PositionLoop, SpeedLoop
from plant import Plant


class DriveLoops:
    """Position (P with K_v and feed-forward) and speed (PI and filters) loops in the motor
    coordinate (rad and rad/s; m and m/s for linear motors), each run on its own cycle and
    held in between.

    Args:
        plant: the axis (its machine file and PWM period).
        sec: the ``[controller]`` machine data (cycles, K_v, speed PI, filters).
    """

    def __init__(self, plant: Plant, sec: ControllerSection):
        cfg = plant.config
        self.speed_ratio = sec.speed_cycle_ratio
        self.position_ratio = sec.position_cycle_ratio
        period = plant.pwm_period
        w_max = axis_limits(cfg, sec).velocity / plant.built.ratio
        self.pos = PositionLoop(sec, period * sec.position_cycle_ratio, w_max)
        self.speed = SpeedLoop(sec, period * sec.speed_cycle_ratio, cfg.machine.kind,
                               motor_constant(cfg),
                               cfg.motor.current_max_a)
        self.w_cmd = 0.0
        self.iq = 0.0

    def reset(self, theta: float) -> None:
        """At rest at motor position ``theta``."""
        self.pos.reset(theta)
        self.speed.reset()
        self.w_cmd = 0.0
        self.iq = 0.0

    def position(self, tick: int, target: float, w_ff: float, theta: float) -> float:
        """The speed command of the position loop for ``target`` with the speed feed-forward
        ``w_ff`` (a new value on position cycles, held in between)."""
        if tick % self.position_ratio == 0:
            self.w_cmd = self.pos.step(target, w_ff, theta)
        return self.w_cmd

    def current(self, tick: int, w_cmd: float, w_act: float, i_ff: float) -> float:
        """The q-current setpoint (A) of the speed loop for ``w_cmd`` with the current
        feed-forward ``i_ff`` (a new value on speed cycles, held in between)."""
        if tick % self.speed_ratio == 0:
            self.iq = self.speed.step(w_cmd, w_act, i_ff)
        return self.iq
