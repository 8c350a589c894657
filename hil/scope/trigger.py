"""A scope's trigger on a recorded channel: where a signal crosses a level, rising,
falling or either way, like the edge trigger of a bench scope.

The times are the recording's (tick times the period), so a trigger falls on the tick
whose sample first reached the level, whatever the moment the page saw it.
"""

from dataclasses import dataclass

import numpy as np

#: the slopes a trigger may wait for
SLOPES = ("rising", "falling", "either")
#: normal: re-arms after each capture; single: holds the first capture until armed again
MODES = ("normal", "single")


@dataclass(frozen=True)
class Trigger:
    """What fires the trigger.

    Attributes:
        channel: the recording column it watches.
        level: the level in the column's unit.
        slope: one of :data:`SLOPES`.
        pre: the part of the window before the trigger, 0..1.
        mode: one of :data:`MODES`.
    """
    channel: str
    level: float
    slope: str = "rising"
    pre: float = 0.2
    mode: str = "normal"

    def __post_init__(self):
        if self.slope not in SLOPES:
            raise ValueError(f"trigger slope {self.slope!r}: one of {', '.join(SLOPES)}")
        if self.mode not in MODES:
            raise ValueError(f"trigger mode {self.mode!r}: one of {', '.join(MODES)}")
        if not 0.0 <= self.pre <= 1.0:
            raise ValueError(f"pre-trigger {self.pre}: a fraction of the window, 0..1")
        if not np.isfinite(self.level):
            raise ValueError(f"trigger level {self.level}: a finite number")

    def first(self, t_s: np.ndarray, y: np.ndarray, after_s: float) -> float | None:
        """The time of the first sample later than ``after_s`` at which ``y`` (at times
        ``t_s``, s) reached the level from the other side in the chosen direction; None
        when there is none.  The sample before it may be earlier than ``after_s``."""
        y = np.asarray(y, dtype=np.float64)
        if y.size < 2:
            return None
        before, now = y[:-1], y[1:]
        rising = (before < self.level) & (now >= self.level)
        falling = (before > self.level) & (now <= self.level)
        hit = rising if self.slope == "rising" else falling if self.slope == "falling" \
            else rising | falling
        hit &= t_s[1:] > after_s
        rows = np.flatnonzero(hit)
        return float(t_s[rows[0] + 1]) if rows.size else None

    def window(self, at_s: float, window_s: float) -> tuple[float, float]:
        """The capture around a trigger at ``at_s``: (start, end), s."""
        return at_s - self.pre * window_s, at_s + (1.0 - self.pre) * window_s
