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


def bench_moves(travel: float, speed: float, start: float) -> Trajectory:
    """The bench's program on an axis of usable ``travel`` and top ``speed`` (table units):
    moves in both directions at several speeds (the friction map), a slow move (periodic
    effects below the filter corner), reversals of 2e-4 of the travel (presliding,
    backlash), dwells between."""
    L, V = travel, speed
    small = 2e-4 * L
    return moves(start, [
        (0.0, 0.2), (0.5 * L, V), (0.0, 0.1), (-0.5 * L, V), (0.0, 0.1),
        (0.4 * L, 0.5 * V), (0.0, 0.1), (-0.2 * L, 0.25 * V), (0.0, 0.1),
        (small, 0.002 * V), (-small, 0.002 * V), (small, 0.002 * V), (-small, 0.002 * V),
        (0.05 * L, 0.1 * V), (0.0, 0.1), (-0.35 * L, 0.8 * V), (0.0, 0.2)])
