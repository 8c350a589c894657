"""The drive's control of the motor's holding brake (a servo drive's simple brake control):
the brake opens with the pulses and closes when they go off.

The brake ([brake] section of the machine file, :mod:`plant.effects.brake`) holds once the
power stage has been off for its ``closing_time_s`` (its coil's decay); it opens in the
cycle the pulses come on (the opening time is not modelled: the drive's enable takes
longer).  So every way the torque goes off -- a disable, a fault reaction's end, the
pulses inhibited when a braking reaction fails (FF04h) -- leaves an axis with a brake
held.  Without a brake (holding torque 0) the input stays open.
"""

import math


class HoldingBrake:
    """The brake command of one drive, advanced once per drive cycle.

    Args:
        present: the machine has a holding brake.
        closing_time_s: from the command to the brake holding, s.
        period_s: the drive cycle, s.
    """

    def __init__(self, present: bool, closing_time_s: float, period_s: float):
        self.present = present
        self.closing_time_s = closing_time_s
        self.period_s = period_s
        self._off_s = math.inf  # the pulses have been off since before the start

    def update(self, pulses_on: bool) -> float:
        """The plant's brake input for this cycle (1.0 holds, 0.0 open)."""
        if pulses_on:
            self._off_s = 0.0
            return 0.0
        self._off_s += self.period_s
        return 1.0 if self.present and self._off_s >= self.closing_time_s else 0.0
