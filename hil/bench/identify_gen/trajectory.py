"""The bench's setpoint: minimum-jerk moves between waypoints, with dwells.

Each move of distance d and duration T follows x(s) = d (10 s^3 - 15 s^4 + 6 s^5),
s = t / T, whose peak speed is 1.875 d / T; so a move "at speed V" lasts 1.875 |d| / V.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Trajectory:
    """Piecewise minimum-jerk setpoint.

    Attributes:
        t0: start time of each segment, s, shape (k,).
        x0: start position of each segment (m or rad), shape (k,).
        dx: displacement of each segment (0 for a dwell), shape (k,).
        dur: duration of each segment, s, shape (k,).
    """
    t0: np.ndarray
    x0: np.ndarray
    dx: np.ndarray
    dur: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.t0[-1] + self.dur[-1])

    def at(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) at the times ``t`` (s); held after the end."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        k = np.clip(np.searchsorted(self.t0, t, side="right") - 1, 0, self.t0.size - 1)
        s = np.clip((t - self.t0[k]) / self.dur[k], 0.0, 1.0)
        shape = s ** 3 * (10 - 15 * s + 6 * s * s)
        dshape = 30 * s * s * (1 - s) ** 2
        return self.x0[k] + self.dx[k] * shape, self.dx[k] * dshape / self.dur[k]


def moves(start: float, steps: list[tuple[float, float]]) -> Trajectory:
    """A trajectory from ``start``: each step (displacement, speed) is a move at that speed
    (peak), or with displacement 0 a dwell of ``speed`` seconds."""
    t0, x0, dx, dur = [], [], [], []
    t, x = 0.0, start
    for d, speed in steps:
        length = speed if d == 0.0 else 1.875 * abs(d) / speed
        t0.append(t)
        x0.append(x)
        dx.append(d)
        dur.append(length)
        t += length
        x += d
    return Trajectory(np.array(t0), np.array(x0), np.array(dx), np.array(dur))


#: speed factors of the program's repetitions when a longer trace is asked for: the
#: friction map at more speeds
REPEAT_SPEEDS = (1.0, 0.6, 0.8, 0.4)


def bench_moves(travel: float, speed: float, start: float,
                duration_s: float | None = None) -> Trajectory:
    """The bench's program on an axis of usable ``travel`` and top ``speed`` (table units):
    moves in both directions at several speeds (the friction map), a slow move (periodic
    effects below the filter corner), reversals of 2e-4 of the travel (presliding,
    backlash), dwells between.  With ``duration_s`` the program is repeated, back at its
    start after each pass and at the speeds scaled by :data:`REPEAT_SPEEDS` in turn, move
    by move until it lasts at least that long."""
    L, V = travel, speed
    small = 2e-4 * L

    def program(f: float) -> list[tuple[float, float]]:
        v = f * V
        return [(0.0, 0.2), (0.5 * L, v), (0.0, 0.1), (-0.5 * L, v), (0.0, 0.1),
                (0.4 * L, 0.5 * v), (0.0, 0.1), (-0.2 * L, 0.25 * v), (0.0, 0.1),
                (small, 0.002 * v), (-small, 0.002 * v), (small, 0.002 * v),
                (-small, 0.002 * v), (0.05 * L, 0.1 * v), (0.0, 0.1), (-0.35 * L, 0.8 * v),
                (0.0, 0.2)]

    steps = program(1.0)
    if duration_s is None:
        return moves(start, steps)
    k, total = 0, moves(start, steps).duration_s
    while total < duration_s:
        k += 1
        f = REPEAT_SPEEDS[k % len(REPEAT_SPEEDS)]
        # back to the start (the pass ends 0.1 L short of it), then the pass again, move by
        # move until long enough
        for step in [(0.1 * L, 0.5 * f * V)] + program(f):
            steps.append(step)
            total = moves(start, steps).duration_s
            if total >= duration_s:
                break
    return moves(start, steps)
