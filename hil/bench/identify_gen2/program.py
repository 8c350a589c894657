"""The second generator's setpoint: moves whose velocity is a sine-squared pulse.

A move of distance d at peak speed V lasts T = 2 |d| / V; its velocity is
v(t) = V sign(d) sin^2(pi t / T) and its acceleration pi V / T sin(2 pi t / T), continuous
at both ends (unlike a trapezoid), so the interpolator's setpoint needs no jerk limit.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Program:
    """Piecewise setpoint: moves and dwells.

    Attributes:
        start: s, shape (k,): each segment's start time.
        origin: m or rad, shape (k,): each segment's start position.
        distance: m or rad, shape (k,): each segment's travel (0: a dwell).
        length: s, shape (k,): each segment's duration.
    """
    start: np.ndarray
    origin: np.ndarray
    distance: np.ndarray
    length: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.start[-1] + self.length[-1])

    def position(self, t_s: np.ndarray) -> np.ndarray:
        """Setpoint position (m or rad) at the times ``t_s`` (s, any shape); held before the
        start and after the end."""
        k, s = self._segment(t_s)
        return self.origin[k] + self.distance[k] * (s - np.sin(2 * np.pi * s) / (2 * np.pi))

    def velocity(self, t_s: np.ndarray) -> np.ndarray:
        """Setpoint velocity (m/s or rad/s) at the times ``t_s`` (s); 0 outside."""
        k, s = self._segment(t_s)
        return self.distance[k] / self.length[k] * 2.0 * np.sin(np.pi * s) ** 2

    def _segment(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t_s, dtype=float)
        k = np.clip(np.searchsorted(self.start, t, side="right") - 1, 0, self.start.size - 1)
        return k, np.clip((t - self.start[k]) / self.length[k], 0.0, 1.0)


def program(steps: list[tuple[float, float]], x0: float = 0.0) -> Program:
    """Moves from ``x0`` (m or rad): each step is (distance, peak speed) or, with distance
    0, (0, dwell in s)."""
    start, origin, distance, length = [], [], [], []
    t, x = 0.0, x0
    for d, v in steps:
        dur = v if d == 0.0 else 2.0 * abs(d) / v
        start.append(t)
        origin.append(x)
        distance.append(d)
        length.append(dur)
        t += dur
        x += d
    return Program(*(np.array(a, dtype=float) for a in (start, origin, distance, length)))


def bench_program(travel: float, speed: float, duration_s: float, x0: float = 0.0) -> Program:
    """Moves over ``travel`` (m or rad) at speeds up to ``speed`` (per s) from ``x0``: both
    directions at falling speeds with short dwells (the friction map), a slow crawl there and
    back (periodic effects at low frequency), a pass of about 12 s repeated move by move until
    the program lasts at least ``duration_s`` (s)."""
    L, V = travel, speed
    one = [(0.0, 0.15), (0.5 * L, V), (0.0, 0.1), (-0.5 * L, 0.8 * V), (0.0, 0.1),
           (0.25 * L, 0.5 * V), (0.0, 0.1), (-0.25 * L, 0.3 * V), (0.0, 0.1),
           (0.01 * L, 0.05 * V), (-0.01 * L, 0.05 * V), (0.0, 0.15)]
    steps: list[tuple[float, float]] = []
    while not steps or program(steps).duration_s < duration_s:
        steps.append(one[len(steps) % len(one)])
    return program(steps, x0)
