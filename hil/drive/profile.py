"""The drive's own trajectory: the profile generator of profile position (PP), profile
velocity (PV) and homing, in the motor coordinate (rad, rad/s, rad/s²; m on linear
motors), one step per drive cycle.

:class:`ProfileGenerator` moves a demand position x and velocity v:

* **to a position** (:meth:`~ProfileGenerator.to_position`): a trapezoid computed online,
  so a new target may come at any time (CiA 402's "change set immediately"): the speed it
  aims at for the distance e to go is the profile velocity, or the speed from which the
  deceleration d just stops it at the target once this step is done (the discrete form
  of ``sqrt(2 d |e|)``, so that braking starts on the step it must, not one late), and it
  reaches that speed at the acceleration a when speeding up and at d when slowing down
  (or reversing).  The position advances by the mean of the two speeds
  (trapezoidal rule).  It arrives exactly: when the step would reach or pass the target
  at no more than one cycle's deceleration, it stands on the target at rest.
* **at a speed** (:meth:`~ProfileGenerator.to_velocity`): v ramps to the target speed at
  a (away from zero) or d (toward zero); x integrates it.
"""

import math


class ProfileGenerator:
    """Demand position and velocity (see the module docstring).

    Args:
        cycle_s: the drive cycle, s.

    Attributes:
        x: demand position, motor units.
        v: demand velocity, motor units/s.
    """

    def __init__(self, cycle_s: float):
        self.cycle_s = cycle_s
        self.x = 0.0
        self.v = 0.0

    def reset(self, x: float, v: float = 0.0) -> None:
        """Start from position ``x`` at speed ``v``."""
        self.x, self.v = x, v

    def _ramp(self, desired: float, acceleration: float, deceleration: float) -> float:
        """v moved one cycle toward ``desired``: at the acceleration while speeding up in
        the same direction, at the deceleration otherwise."""
        v = self.v
        speeding_up = v * desired >= 0.0 and abs(desired) > abs(v)
        step = (acceleration if speeding_up else deceleration) * self.cycle_s
        return v + min(max(desired - v, -step), step)

    def to_velocity(self, target: float, acceleration: float, deceleration: float) -> None:
        """One cycle toward the speed ``target``."""
        v = self._ramp(target, acceleration, deceleration)
        self.x += 0.5 * (self.v + v) * self.cycle_s
        self.v = v

    def to_position(self, target: float, v_max: float, acceleration: float,
                    deceleration: float) -> bool:
        """One cycle toward ``target``; True once standing on it."""
        e = target - self.x
        if e == 0.0 and self.v == 0.0:
            return True
        # the fastest speed at the end of this step from which the deceleration still
        # stops on the target: (v + v') dt / 2 + v'^2 / 2d = |e|, v' the unknown
        half = 0.5 * deceleration * self.cycle_s
        left = abs(e) - 0.5 * math.copysign(self.v, e) * self.cycle_s
        stop = -half + math.sqrt(half * half + 2.0 * deceleration * max(left, 0.0))
        desired = math.copysign(min(v_max, stop), e)
        v = self._ramp(desired, acceleration, deceleration)
        x = self.x + 0.5 * (self.v + v) * self.cycle_s
        if (target - x) * e <= 0.0 and abs(v) <= deceleration * self.cycle_s * 2.0:
            self.x, self.v = target, 0.0
            return True
        self.x, self.v = x, v
        return False

    def stopped(self) -> bool:
        return self.v == 0.0
