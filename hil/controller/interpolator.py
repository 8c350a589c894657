"""The interpolator: a jerk-limited (7-phase S-curve) or trapezoidal profile per block.

Every move block starts and ends at rest (exact stop, Sinumerik G60 behaviour: no
blending between blocks).  A move of length d at v = min(feed, v_max) with limits a_max,
j_max is planned in closed form:

* long move (reaches v): duration d/v + v/a + a/j when v >= a²/j (a_max is reached),
  d/v + 2 sqrt(v/j) otherwise; trapezoidal (no jerk limit): d/v + v/a;
* short move that never reaches v: the peak velocity solves d = v_p (v_p/a + a/j)
  (a_max reached) or, below d = 2 a³/j², never reaches a_max either:
  v_p = j^(1/3) (d/2)^(2/3), duration 4 (d / 2j)^(1/3); trapezoidal: v_p = sqrt(d a),
  duration 2 sqrt(d/a).

The profile is a list of constant-jerk segments (constant-acceleration for the
trapezoid), each holding its start time, position, velocity, acceleration and jerk;
the state entering each block is set to the block's start exactly, so every block ends
on its programmed target.  The controller samples the profile once per interpolation
cycle (:meth:`Profile.ipo_points`) and a :class:`FineInterpolator` interpolates those
points linearly for every position-control cycle; the position error of that linear
interpolation is at most a_max T_ipo² / 8.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hil.controller.config import AxisLimits
from hil.controller.program import Block, BlockKind, Program, ProgramError, _scales

#: seconds run after the profile's end so the axis settles (``hil sim``'s lock-step and
#: ``hil controller``'s loop alike)
SETTLE_S = 0.2
#: the longest program the interpolator plans, s: the NC samples the whole profile at
#: every IPO cycle before the axis moves (and ``hil sim`` records every PWM period of
#: it), so a block of years -- a feed of 1e-6 mm/min -- would ask for terabytes; an hour
#: is 900 000 IPO cycles of 4 ms
MAX_PROGRAM_S = 3600.0

_Phase = tuple[float, float, float]
"""(duration s, acceleration at the phase start, jerk) of one phase, for a positive move."""


class ClampEvent(NamedTuple):
    """A clamp (``clamped`` True) or unclamp block at ``t_s`` (s) of the profile."""
    t_s: float
    clamped: bool


class MoveBlock(NamedTuple):
    """A move block of the profile: its start ``t_s`` (s), its ``line`` in the program
    text and its programmed end point ``target`` (m or rad)."""
    t_s: float
    line: int
    target: float


class Setpoint(NamedTuple):
    """The profile at one instant: position (m or rad), velocity (/s), acceleration (/s²)."""
    pos: float
    vel: float
    acc: float


@dataclass(frozen=True, eq=False)
class ProfileSamples:
    """The profile sampled at the times ``t`` (s); every array has shape (n,).

    ``pos`` in m or rad, ``vel`` in m/s or rad/s, ``acc`` in m/s² or rad/s².
    """
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray


def _check_limits(limits: AxisLimits) -> None:
    """Refuse limits the planner cannot use, naming the value."""
    for name in ("velocity", "acceleration"):
        value = getattr(limits, name)
        if not (0.0 < value < math.inf):
            raise ValueError(f"axis limit {name} = {value} must be finite and > 0")
    if not limits.jerk >= 0.0:
        raise ValueError(f"axis limit jerk = {limits.jerk} must be >= 0 (0 or inf: no limit)")


def _peak_velocity(d: float, v: float, a: float, j: float) -> float:
    """Highest velocity of a rest-to-rest S-curve move of length d > 0 (closed form)."""
    full = v * (v / a + a / j) if v * j >= a * a else 2.0 * v * math.sqrt(v / j)
    if d >= full:
        return v
    if d <= 2.0 * a**3 / (j * j):
        return j ** (1.0 / 3.0) * (0.5 * d) ** (2.0 / 3.0)
    c = a * a / j
    return 2.0 * a * d / (c + math.sqrt(c * c + 4.0 * a * d))


def _trapezoid_phases(d: float, v: float, a: float) -> list[_Phase]:
    """Accelerate, cruise, decelerate at constant acceleration (no jerk limit)."""
    vp = min(v, math.sqrt(d * a))
    ta = vp / a
    tv = max(d / vp - ta, 0.0) if vp == v else 0.0
    return [(ta, a, 0.0), (tv, 0.0, 0.0), (ta, -a, 0.0)]


def _scurve_phases(d: float, v: float, a: float, j: float) -> list[_Phase]:
    """The seven phases of a jerk-limited move: jerk up, constant acceleration, jerk down,
    cruise, and the mirror image to rest."""
    vp = _peak_velocity(d, v, a, j)
    if vp * j >= a * a:
        tj, ap, tc = a / j, a, max(vp / a - a / j, 0.0)
    else:
        tj = math.sqrt(vp / j)
        ap, tc = j * tj, 0.0
    tv = max(d / vp - (2.0 * tj + tc), 0.0) if vp == v else 0.0
    return [(tj, 0.0, j), (tc, ap, 0.0), (tj, ap, -j), (tv, 0.0, 0.0),
            (tj, 0.0, -j), (tc, -ap, 0.0), (tj, -ap, j)]


def _move_phases(distance: float, feed: float, limits: AxisLimits) -> list[_Phase]:
    """The phases (duration s, start acceleration, jerk) of a rest-to-rest move.

    ``distance`` in m or rad (either sign), ``feed`` in m/s or rad/s (clipped to the
    axis's maximum velocity; ``inf`` for rapid).  Zero-length phases are left out.
    """
    d = abs(distance)
    if d == 0.0:
        return []
    v = min(feed, limits.velocity)
    j = limits.jerk
    if j == 0.0 or math.isinf(j):
        phases = _trapezoid_phases(d, v, limits.acceleration)
    else:
        phases = _scurve_phases(d, v, limits.acceleration, j)
    s = math.copysign(1.0, distance)
    return [(t, s * a, s * jk) for t, a, jk in phases if t > 0.0]


@dataclass(frozen=True, eq=False)
class Profile:
    """The axis's planned motion: piecewise-cubic position over ``duration_s`` seconds.

    Built by :func:`plan`.  Segment i starts at ``knots_s[i]`` (s) with position
    ``pos0[i]`` (m or rad), velocity ``vel0[i]``, acceleration ``acc0[i]`` and constant
    jerk ``jerk[i]`` (SI, per second); every array has shape (n,).  The last segment starts
    at ``duration_s`` and holds the end position at rest; times before 0 read as 0.
    ``clamps`` are the program's clamp and unclamp blocks in time order, ``moves`` its
    move blocks (the software limits' block preparation checks their end points).
    """
    knots_s: np.ndarray
    pos0: np.ndarray
    vel0: np.ndarray
    acc0: np.ndarray
    jerk: np.ndarray
    duration_s: float
    clamps: tuple[ClampEvent, ...] = ()
    moves: tuple[MoveBlock, ...] = ()

    def until(self, t_s: float) -> "Profile":
        """The profile ended at ``t_s`` (s), the start of a block, where the axis is at rest
        on the end point of the block before: the segments before it, then rest there; the
        clamp events up to it and the move blocks before it."""
        k = int(np.searchsorted(self.knots_s, t_s, side="left"))
        keep = slice(0, k)

        def cut(column: np.ndarray, last: float) -> np.ndarray:
            return np.append(column[keep], last)

        return Profile(cut(self.knots_s, t_s), cut(self.pos0, self.pos0[k]),
                       cut(self.vel0, 0.0), cut(self.acc0, 0.0), cut(self.jerk, 0.0),
                       duration_s=t_s, clamps=tuple(c for c in self.clamps if c.t_s <= t_s),
                       moves=tuple(m for m in self.moves if m.t_s < t_s))

    def sample(self, t_s: float) -> Setpoint:
        """Position, velocity and acceleration at time ``t_s`` (s)."""
        s = self.sample_array(np.array([t_s], dtype=float))
        return Setpoint(float(s.pos[0]), float(s.vel[0]), float(s.acc[0]))

    def sample_array(self, t_s: np.ndarray) -> ProfileSamples:
        """The profile at every time of ``t_s`` (s, shape (n,)), vectorised."""
        t = np.asarray(t_s, dtype=float)
        tc = np.clip(t, 0.0, None)
        k = np.searchsorted(self.knots_s, tc, side="right") - 1
        tau = tc - self.knots_s[k]
        p0, v0, a0, j = self.pos0[k], self.vel0[k], self.acc0[k], self.jerk[k]
        pos = p0 + tau * (v0 + tau * (0.5 * a0 + tau * j / 6.0))
        vel = v0 + tau * (a0 + 0.5 * tau * j)
        acc = a0 + tau * j
        return ProfileSamples(t, pos, vel, acc)

    def ipo_points(self, ipo_period_s: float) -> ProfileSamples:
        """Samples at t = k T_ipo (s), k = 0 .. n, n T_ipo the first IPO instant at or after
        the end: the last point holds the final position at rest."""
        if not ipo_period_s > 0.0:
            raise ValueError(f"IPO period {ipo_period_s} s must be > 0")
        n = math.ceil(self.duration_s / ipo_period_s)
        if n * ipo_period_s < self.duration_s:
            n += 1
        elif n > 0 and (n - 1) * ipo_period_s >= self.duration_s:
            n -= 1
        return self.sample_array(np.arange(n + 1) * ipo_period_s)


def plan(program: Program, limits: AxisLimits) -> Profile:
    """Plan every block of ``program`` with the axis ``limits`` (SI, jerk 0 or inf: no
    jerk limit, trapezoidal) into one :class:`Profile`; rapid moves run at the maximum
    velocity, every feed is clipped to it."""
    _check_limits(limits)
    rows: list[tuple[float, float, float, float, float]] = []
    clamps = []
    moves = []
    t = 0.0
    for block in program.blocks:
        if block.kind in (BlockKind.CLAMP, BlockKind.UNCLAMP):
            clamps.append(ClampEvent(t, block.kind is BlockKind.CLAMP))
            continue
        if block.kind is BlockKind.DWELL:
            phases = [(block.dwell_s, 0.0, 0.0)] if block.dwell_s > 0.0 else []
        else:
            moves.append(MoveBlock(t, block.line, block.target))
            phases = _move_phases(block.target - block.start, block.feed, limits)
        p, v = block.start, 0.0
        for dur, a, j in phases:
            rows.append((t, p, v, a, j))
            p += dur * (v + dur * (0.5 * a + dur * j / 6.0))
            v += dur * (a + 0.5 * dur * j)
            t += dur
        check_duration(program.source, block, abs(block.target - block.start),
                       program.rotary, t)
    rows.append((t, program.end, 0.0, 0.0, 0.0))
    columns = [np.ascontiguousarray(c) for c in np.array(rows, dtype=float).T]
    return Profile(*columns, duration_s=t, clamps=tuple(clamps), moves=tuple(moves))


def check_duration(source: str, block: Block, length: float, rotary: bool,
                   t_end: float) -> None:
    """Refuse a program whose move or dwell ``block`` ends ``t_end`` s into it, beyond
    :data:`MAX_PROGRAM_S`: a :class:`ProgramError` naming the block's line and its words
    in program units.  ``length``: the block's path length, m (rad when ``rotary``);
    ``block`` is a :class:`~hil.controller.program.Block` or a path block."""
    if t_end <= MAX_PROGRAM_S:
        return
    pos_scale, feed_scale = _scales(rotary)
    unit = "deg" if rotary else "mm"
    move = f"move of {length / pos_scale:g} {unit}"
    if block.kind is BlockKind.DWELL:
        what, fix = f"dwell 'G4 F{block.dwell_s:g}' ({block.dwell_s:g} s)", "shorten it"
    elif block.rapid:
        what, fix = f"rapid (G0) {move}", "shorten it"
    else:
        what, fix = f"{move} at 'F{block.feed / feed_scale:g}' ({unit}/min)", "raise F"
    raise ProgramError(source, block.line, f"the {what} ends {t_end:.3g} s into the program; "
                       f"a program runs at most {MAX_PROGRAM_S:g} s (the NC samples all of "
                       f"it at every interpolation cycle before the axis moves): {fix}")


class FineInterpolator:
    """Position-control-cycle setpoints between IPO points, by linear interpolation.

    ``ipo`` are the IPO points (:meth:`Profile.ipo_points`), ``ratio`` the number of
    position-control cycles per IPO cycle.  Each :meth:`step` sets ``pos``, ``vel`` and
    ``acc`` (SI) for the current cycle, k T_ipo + m T_ipo / ratio, and advances a cursor;
    nothing is allocated per call.  After the last IPO point the setpoint holds it and
    ``done`` is True.  ``points`` holds the IPO points as an array of shape (3, n)
    (position, velocity, acceleration), for the compiled tick
    (:mod:`hil.controller.compiled`).  The setpoint follows the IPO points without the one-IPO-cycle
    delay of a real NC; the caller adds a delay if it models one.
    """

    def __init__(self, ipo: ProfileSamples, ratio: int):
        if not (ratio >= 1 and int(ratio) == ratio):
            raise ValueError(f"fine-interpolation ratio {ratio!r} must be an integer >= 1")
        ratio = int(ratio)
        self.points = np.array((ipo.pos, ipo.vel, ipo.acc), dtype=np.float64)
        self._p = ipo.pos.tolist()
        self._v = ipo.vel.tolist()
        self._a = ipo.acc.tolist()
        self._last = len(self._p) - 1
        self._frac = [m / ratio for m in range(ratio)]
        self._ratio = ratio
        self.reset()

    def reset(self) -> None:
        """Back to the first IPO point."""
        self._k = 0
        self._m = 0
        self.pos = self._p[0]
        self.vel = self._v[0]
        self.acc = self._a[0]
        self.done = self._last == 0

    def step(self) -> None:
        """Set the setpoint of the current position-control cycle and move to the next."""
        k = self._k
        if k >= self._last:
            self.pos, self.vel, self.acc = self._p[-1], self._v[-1], self._a[-1]
            self.done = True
            return
        f = self._frac[self._m]
        self.pos = self._p[k] + (self._p[k + 1] - self._p[k]) * f
        self.vel = self._v[k] + (self._v[k + 1] - self._v[k]) * f
        self.acc = self._a[k] + (self._a[k + 1] - self._a[k]) * f
        self._m += 1
        if self._m == self._ratio:
            self._m = 0
            self._k = k + 1

    @property
    def next_vel(self) -> float:
        """The velocity (m/s or rad/s) the next :meth:`step` sets: the next position-control
        cycle's, towards which a linear fine interpolation of the feed-forward runs."""
        k = self._k
        if k >= self._last:
            return self._v[-1]
        return self._v[k] + (self._v[k + 1] - self._v[k]) * self._frac[self._m]
