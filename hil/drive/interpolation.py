"""The drive's interpolation of cyclic setpoints (CSP, CSV) between communication cycles.

A master on a SYNC-driven link (CANopen) sends a new target once per communication cycle
(1006h), while the drive's loops run every drive cycle (the PWM period).  A drive does not
step its loops' target once per millisecond: it moves it linearly from the previous
target to the new one over the interpolation time period 60C2h, as CiA 402's linear
interpolation does.  A new target is a new setpoint sequence number; the segment it
starts runs from the previous target (not from where the interpolation had got to) to
the new one in ``round(60C2h / drive cycle)`` cycles, reaching the new target on the
cycle before the next is due.  A target that comes late is extrapolated along the last
segment for at most one more period (then held), so one SYNC lost or delayed by the bus
does not stop the axis.  A held target stands still, so from then on the second quantity
(CSP's speed feed-forward 60B1h) is 0: a master that falls silent for longer leaves the
axis at its last target instead of running on at the last feed-forward speed.  With
60C2h = 0, or shorter than a drive cycle, each target is taken as it comes (a link that
delivers one every drive cycle: UDP, serial, the lock-step simulation).
"""

#: how far past its end a segment is extrapolated, in segment lengths (1: to the end)
EXTRAPOLATE = 2.0


class Interpolator:
    """Linear interpolation of two quantities (a target and its feed-forward), one step
    per drive cycle.

    Args:
        cycle_s: the drive cycle, s.
    """

    def __init__(self, cycle_s: float):
        self.cycle_s = cycle_s
        self.seq = -1
        self._start = (0.0, 0.0)
        self._end = (0.0, 0.0)
        self._cycles = 0
        self._length = 1

    def reset(self, a: float, b: float) -> None:
        """Stand at (``a``, ``b``): the next target starts from there (out of a cyclic
        mode, or not enabled)."""
        self.seq = -1
        self._start = self._end = (a, b)
        self._cycles = self._length = 1

    def step(self, seq: int, a: float, b: float, period_s: float) -> tuple[float, float]:
        """This drive cycle's (a, b) for the newest setpoint ``seq`` = (``a``, ``b``) and
        the interpolation time period ``period_s`` (60C2h)."""
        if period_s < self.cycle_s:
            self.reset(a, b)
            return a, b
        if seq != self.seq:
            self.seq = seq
            self._start, self._end = self._end, (a, b)
            self._cycles = 0
            self._length = max(1, round(period_s / self.cycle_s))
        self._cycles += 1
        f = min(self._cycles / self._length, EXTRAPOLATE)
        (a0, b0), (a1, b1) = self._start, self._end
        held = self._cycles > EXTRAPOLATE * self._length
        return a0 + (a1 - a0) * f, 0.0 if held else b0 + (b1 - b0) * f
