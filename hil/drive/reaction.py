"""How the drive brakes: the speed reference of a quick stop (605Ah) or a fault reaction
(605Eh), for its speed controller to follow, and the watch on the speed actually falling.

A ramp starts from the speed actual when the reaction starts and runs to zero at the
deceleration given (6084h slow down ramp, 6085h quick stop ramp); braking "at the current
limit" (and at the voltage limit, which this drive treats the same) asks for zero speed at
once, so the speed controller brakes as hard as its current limit lets it.

Every cycle :meth:`BrakeRamp.verdict` judges the speed actual against the envelope of
:mod:`hil.drive.braking` (:func:`~hil.drive.braking.envelope`): the reaction is done when
the reference has reached zero and the axis stands still; it has *failed* when the speed
is above the envelope (the axis does not slow down: a load pushing it, a current limit too
low for the ramp, a drive loop that does not answer), which includes not standing still
once the envelope has fallen to the standstill speed.  The drive then inhibits the pulses (:mod:`hil.drive.core`).
"""

import math

#: :meth:`BrakeRamp.verdict`: still braking, done, failed
BRAKING, DONE, FAILED = 0, 1, 2


class BrakeRamp:
    """The speed reference of one braking reaction and its watch, advanced once per drive
    cycle.

    Args:
        period_s: the drive cycle, s.

    Attributes:
        active: a reaction is running.
        reference: the speed reference of this cycle, motor units/s.
        elapsed_s: time since the reaction started, s.
    """

    def __init__(self, period_s: float):
        self.period_s = period_s
        self.active = False
        self.reference = 0.0
        self.elapsed_s = 0.0
        self._step = 0.0
        self._done = False
        self._ceiling = 0.0
        self._slope = 0.0
        self._delay_s = 0.0

    def start(self, w: float, deceleration: float, envelope: tuple[float, float, float]
              ) -> None:
        """Start braking from speed ``w`` on a ramp of ``deceleration`` (inf: at the current
        limit, a zero reference at once), watched under ``envelope`` (ceiling, slope,
        delay: :func:`hil.drive.braking.envelope`); motor units/s, /s², s."""
        self.active = True
        self._done = False
        self.elapsed_s = 0.0
        finite = math.isfinite(deceleration)
        self.reference = w if finite else 0.0
        self._step = deceleration * self.period_s if finite else math.inf
        self._ceiling, self._slope, self._delay_s = envelope

    def stop(self) -> None:
        """No reaction running."""
        self.active = False
        self.reference = 0.0

    def advance(self) -> float:
        """The reference of this cycle (moved one cycle's deceleration toward zero)."""
        r = self.reference
        self.reference = 0.0 if abs(r) <= self._step else r - math.copysign(self._step, r)
        self.elapsed_s += self.period_s
        return self.reference

    def envelope(self) -> float:
        """The highest speed allowed now, motor units/s (before the standstill floor)."""
        late = self.elapsed_s - self._delay_s
        return self._ceiling - self._slope * late if late > 0.0 else self._ceiling

    def verdict(self, w: float, standstill: float) -> int:
        """:data:`DONE` (the reference at zero and ``|w|`` at most ``standstill``; it stays
        done), :data:`FAILED` (``|w|`` above the envelope, or above ``standstill`` once the
        envelope has fallen to it) or :data:`BRAKING`."""
        if self._done or (self.reference == 0.0 and abs(w) <= standstill):
            self._done = True
            return DONE
        if abs(w) > max(self.envelope(), standstill):
            return FAILED
        return BRAKING
