"""How the drive brakes: the speed reference of a quick stop (605Ah) or a fault reaction
(605Eh), for its speed controller to follow.

A ramp starts from the speed actual when the reaction starts and runs to zero at the
deceleration given (6084h slow down ramp, 6085h quick stop ramp); braking "at the current
limit" (and at the voltage limit, which this drive treats the same) asks for zero speed at
once, so the speed controller brakes as hard as its current limit lets it.  The braking is
done when the reference has reached zero and the axis stands still, or, should it not come
to rest (a load pushing it, a wall), after :data:`TIMEOUT_FACTOR` times the ramp's own time
plus :data:`TIMEOUT_EXTRA_S`: then the drive takes the torque off anyway.
"""

import math

#: a reaction that has not stopped the axis after this many times its ramp time ...
TIMEOUT_FACTOR = 2.0
#: ... plus this long, s, ends anyway (torque off)
TIMEOUT_EXTRA_S = 0.5


class BrakeRamp:
    """The speed reference of one braking reaction, advanced once per drive cycle.

    Args:
        period_s: the drive cycle, s.

    Attributes:
        active: a reaction is running.
        reference: the speed reference of this cycle, motor units/s.
    """

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.active = False
        self.reference = 0.0
        self._step = 0.0
        self._left_s = 0.0

    def start(self, w: float, deceleration: float) -> None:
        """Start braking from speed ``w`` at ``deceleration`` (motor units/s²; inf: at the
        current limit, a zero reference at once)."""
        self.active = True
        ramp_s = abs(w) / deceleration if math.isfinite(deceleration) else 0.0
        self.reference = w if math.isfinite(deceleration) else 0.0
        self._step = deceleration * self.period_s
        self._left_s = TIMEOUT_FACTOR * ramp_s + TIMEOUT_EXTRA_S

    def stop(self) -> None:
        """No reaction running."""
        self.active = False
        self.reference = 0.0

    def advance(self) -> float:
        """The reference of this cycle (moved one cycle's deceleration toward zero)."""
        r = self.reference
        self.reference = 0.0 if abs(r) <= self._step else r - math.copysign(self._step, r)
        self._left_s -= self.period_s
        return self.reference

    def done(self, w: float, standstill: float) -> bool:
        """The reaction is over: the reference at zero and ``|w|`` below ``standstill``, or
        its time is up."""
        return self.active and ((self.reference == 0.0 and abs(w) <= standstill)
                                or self._left_s <= 0.0)
