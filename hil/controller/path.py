"""Multi-axis part programs: blocks that move several axes on one straight line.

The words and rules of :mod:`hil.controller.program`, with any of the machine's axis
letters in a block::

    G90 G71
    G1 X10 Y5 F1000      ; X and Y on one line to (10 mm, 5 mm), 1000 mm/min along it
    G0 X0 Y0             ; rapid, on the straight line too
    G4 F0.2              ; dwell, every axis holds
    G91 Y-5 F500         ; one axis alone: the others hold
    M10                  ; clamp every axis whose clamp M function is M10
    M30

An axis a block does not name holds its position.  The feed ``F`` is the velocity along
the path: in mm/min over the linear axes (X Y Z U V W; Euclidean length in mm) when any
of them moves, and in deg/min over the rotary axes when only those move (a rotary axis in
a block with linear motion follows in the same time, as SINUMERIK's FGROUP default does).
``G0`` moves on the same straight line (linear interpolation of rapid traverse, RTLION) at
the highest path velocity no axis's maximum velocity exceeds.  A clamp or unclamp M
function (each axis's own, :class:`~hil.controller.program.ClampCodes`; alone in its
block) acts on every axis it is the M function of; a block moving a clamped axis is a
program error.

Planning (:func:`plan_path`): the block runs one rest-to-rest profile in the path
parameter s (length L, the one of :mod:`hil.controller.interpolator`), and axis i moves
x_i = start_i + u_i s with u_i = (target_i - start_i) / L.  Every axis's velocity,
acceleration and jerk are u_i times the path's, so the path's limits are the smallest
v_max,i / |u_i|, a_max,i / |u_i|, j_max,i / |u_i| over the axes that move (the jerk over
the axes that have a jerk limit; none: a trapezoid): every axis keeps its own limits, all
axes start and stop together and stay on the line.  The per-axis profiles share their
knots and are exact piecewise cubics, as a single axis's are.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hil.controller.config import AxisLimits
from hil.controller.interpolator import (
    ClampEvent,
    MoveBlock,
    Profile,
    _check_limits,
    _move_phases,
    check_duration,
)
from hil.controller.program import (
    LINEAR_AXES,
    ROTARY_AXES,
    BlockKind,
    ClampCodes,
    ErrorFactory,
    _check_groups,
    _scales,
    clamped_error,
    program_lines,
    read_program_text,
)


@dataclass(frozen=True)
class PathBlock:
    """One block in SI units per axis (m, or rad on rotary axes).

    ``start`` and ``target`` have one position per axis of the program (equal for a
    dwell and a clamp).  ``feed`` is the programmed path velocity in m/s (over the linear
    axes) or rad/s (rotary axes only), ``inf`` for rapid, 0 otherwise; ``dwell_s`` in s;
    ``m_code`` the M function of a clamp or unclamp block and ``clamp_axes`` the axes it
    acts on (one flag per axis); ``line`` the 1-based line of the program text.
    """
    kind: BlockKind
    line: int
    start: tuple[float, ...]
    target: tuple[float, ...]
    feed: float = 0.0
    rapid: bool = False
    dwell_s: float = 0.0
    m_code: int = 0
    clamp_axes: tuple[bool, ...] = ()


@dataclass(frozen=True)
class PathProgram:
    """A parsed multi-axis program: axis letters, which are rotary, start positions (SI),
    blocks and the source that names it in messages (a file name)."""
    axes: tuple[str, ...]
    rotary: tuple[bool, ...]
    start: tuple[float, ...]
    blocks: tuple[PathBlock, ...]
    source: str = "<program>"

    @property
    def end(self) -> tuple[float, ...]:
        """Positions after the last block."""
        return self.blocks[-1].target if self.blocks else self.start


@dataclass
class _Modal:
    pos: list[float]
    absolute: bool = True
    motion: int | None = None
    feed: float | None = None  # as programmed: mm/min or deg/min
    clamped_at: list[int] = field(default_factory=list)  # per axis: clamping line, 0: none


def _clamp_block(code: int, st: _Modal, clamp: Sequence[ClampCodes], line: int) -> PathBlock:
    """The block of a clamp or unclamp M function; each axis's clamp state updated."""
    closing = any(c.clamp == code for c in clamp)
    acts = tuple((c.clamp if closing else c.unclamp) == code for c in clamp)
    for i, a in enumerate(acts):
        if a:
            st.clamped_at[i] = (st.clamped_at[i] or line) if closing else 0
    here = tuple(st.pos)
    return PathBlock(BlockKind.CLAMP if closing else BlockKind.UNCLAMP, line, here, here,
                     m_code=code, clamp_axes=acts)


def _check_codes(axes: tuple[str, ...], clamp: Sequence[ClampCodes]) -> None:
    """One ClampCodes per axis; no M function clamps one axis and unclamps another."""
    if len(clamp) != len(axes):
        raise ValueError(f"{len(clamp)} clamp M functions for {len(axes)} axes")
    both = {c.clamp for c in clamp} & {c.unclamp for c in clamp}
    if both:
        raise ValueError(f"M{min(both)} clamps one axis and unclamps another; give each "
                         "its own M functions")


def _block(g, moves: dict, f, st: _Modal, axes: str, rotary, line: int,
           err: ErrorFactory) -> PathBlock | None:
    _check_groups(g, err)
    if 90 in g or 91 in g:
        st.absolute = 90 in g
    here = tuple(st.pos)
    if 4 in g:
        if moves:
            raise err(f"G4 must stand in its own block (found {', '.join(moves)})")
        if f is None or f < 0.0:
            raise err(f"G4 needs F<seconds> >= 0 (Sinumerik dwell time), got "
                      f"{'no F' if f is None else f'F{f:g}'}")
        return PathBlock(BlockKind.DWELL, line, here, here, dwell_s=f)
    for code in g:
        if code in (0, 1):
            st.motion = code
    if f is not None:
        if f <= 0.0:
            raise err(f"feed 'F{f:g}' must be > 0")
        st.feed = f
    if not moves:
        return None
    named = " ".join(f"{a}{v:g}" for a, v in moves.items())
    if st.motion is None:
        raise err(f"'{named}' without a motion mode (program G0 or G1 first)")
    if st.motion == 1 and st.feed is None:
        raise err(f"G1 move '{named}' needs a feed: no F programmed yet")
    for i, a in enumerate(axes):
        if a in moves:
            x = moves[a] * _scales(rotary[i])[0]
            st.pos[i] = x if st.absolute else st.pos[i] + x
    target = tuple(st.pos)
    if st.motion == 0:
        return PathBlock(BlockKind.MOVE, line, here, target, feed=math.inf, rapid=True)
    linear = any(t != s and not r for s, t, r in zip(here, target, rotary))
    feed = st.feed * _scales(not linear)[1]
    return PathBlock(BlockKind.MOVE, line, here, target, feed=feed)


def parse_path_program(text: str, axes: Sequence[str], start: Sequence[float] | None = None,
                       source: str = "<program>",
                       clamp: Sequence[ClampCodes] | None = None) -> PathProgram:
    """Parse a program for the axis letters ``axes`` (A, B, C rotary: degrees in the text,
    rad here), starting at ``start`` (SI per axis; default all 0), with each axis's clamp M
    functions ``clamp`` (default M10/M11 for all).  Raises
    :class:`~hil.controller.program.ProgramError` on the first bad line, ValueError for
    bad axis letters or clamp M functions."""
    axes = tuple(axes)
    if not axes or len(set(axes)) != len(axes) or any(
            len(a) != 1 or a not in LINEAR_AXES + ROTARY_AXES for a in axes):
        raise ValueError(f"axis letters {axes!r} must be distinct letters of "
                         f"{LINEAR_AXES + ROTARY_AXES}")
    rotary = tuple(a in ROTARY_AXES for a in axes)
    start = tuple(float(x) for x in (start if start is not None else [0.0] * len(axes)))
    if len(start) != len(axes):
        raise ValueError(f"{len(start)} start positions for {len(axes)} axes")
    clamp = tuple(clamp) if clamp is not None else (ClampCodes(),) * len(axes)
    _check_codes(axes, clamp)
    m_codes = frozenset(c.clamp for c in clamp) | frozenset(c.unclamp for c in clamp)
    st = _Modal(pos=list(start), clamped_at=[0] * len(axes))
    letters = "".join(axes)
    blocks = []
    lines = program_lines(text, source, letters, lambda word: f"axis word '{word}': this "
                          f"machine has the axes {', '.join(axes)}", m_codes)
    for line, err, sw in lines:
        m = sw.m_function(err)
        if m is not None:
            blocks.append(_clamp_block(m, st, clamp, line))
            continue
        moves = dict(sw.values)
        f = moves.pop("F", None)
        for i, a in enumerate(axes):
            if a in moves and st.clamped_at[i]:
                raise err(clamped_error(a, sw.written[a], st.clamped_at[i], clamp[i]))
        block = _block(sw.g, moves, f, st, letters, rotary, line, err)
        if block is not None:
            blocks.append(block)
    return PathProgram(axes, rotary, start, tuple(blocks), source)


def read_path_program(path, axes: Sequence[str], start: Sequence[float] | None = None,
                      clamp: Sequence[ClampCodes] | None = None) -> PathProgram:
    """Read and parse a program file (see :func:`parse_path_program`); ProgramError also
    when the file cannot be read as text (:func:`~hil.controller.program.read_program_text`)."""
    return parse_path_program(read_program_text(path), axes, start, source=str(path),
                              clamp=clamp)


def path_limits(direction: np.ndarray, limits: Sequence[AxisLimits]) -> AxisLimits:
    """The path's limits for unit direction ``direction`` (axis travel per unit of path,
    shape (n,)): the smallest axis limit over |u_i| among the axes that move; jerk among
    those with a jerk limit (0: none has one)."""
    v = a = j = math.inf
    for u, lim in zip(np.abs(direction), limits):
        if u == 0.0:
            continue
        v = min(v, lim.velocity / u)
        a = min(a, lim.acceleration / u)
        if 0.0 < lim.jerk < math.inf:
            j = min(j, lim.jerk / u)
    return AxisLimits(v, a, 0.0 if math.isinf(j) else j)


def path_length(start: Sequence[float], target: Sequence[float],
                rotary: Sequence[bool]) -> float:
    """The block's path length: Euclidean over the linear axes when any moves (m), else
    over the rotary axes (rad)."""
    d = np.subtract(target, start)
    lin = np.array([not r for r in rotary])
    if np.any(d[lin] != 0.0):
        return float(np.linalg.norm(d[lin]))
    return float(np.linalg.norm(d[~lin]))


def plan_path(program: PathProgram, limits: Sequence[AxisLimits]) -> tuple[Profile, ...]:
    """One :class:`~hil.controller.interpolator.Profile` per axis (program order), all on
    the same knots: each block a rest-to-rest move along its straight line (module
    docstring), with ``limits`` per axis (SI, jerk 0 or inf: none)."""
    if len(limits) != len(program.axes):
        raise ValueError(f"{len(limits)} axis limits for {len(program.axes)} axes")
    for lim in limits:
        _check_limits(lim)
    n = len(program.axes)
    rows: list[list[tuple]] = [[] for _ in range(n)]
    clamps: list[list[ClampEvent]] = [[] for _ in range(n)]
    moves: list[list[MoveBlock]] = [[] for _ in range(n)]
    t = 0.0
    for block in program.blocks:
        if block.kind in (BlockKind.CLAMP, BlockKind.UNCLAMP):
            for i in np.flatnonzero(block.clamp_axes):
                clamps[i].append(ClampEvent(float(t), block.kind is BlockKind.CLAMP))
            continue
        length = path_length(block.start, block.target, program.rotary)
        if block.kind is BlockKind.DWELL:
            phases, u = ([(block.dwell_s, 0.0, 0.0)] if block.dwell_s > 0.0 else []), None
        elif length == 0.0:
            phases, u = [], None
        else:
            u = np.subtract(block.target, block.start) / length
            phases = _move_phases(length, block.feed, path_limits(u, limits))
        if block.kind is BlockKind.MOVE:
            for i in range(n):
                moves[i].append(MoveBlock(t, block.line, block.target[i]))
        knots = []
        for dur, _, _ in phases:
            knots.append(t)
            t += dur
        moving_linear = any(e != s and not r
                            for s, e, r in zip(block.start, block.target, program.rotary))
        check_duration(program.source, block, length, not moving_linear, t)
        for i in range(n):
            p, v, ui = block.start[i], 0.0, (0.0 if u is None else float(u[i]))
            for tk, (dur, acc, jerk) in zip(knots, phases):
                a_i, j_i = ui * acc, ui * jerk
                rows[i].append((tk, p, v, a_i, j_i))
                p += dur * (v + dur * (0.5 * a_i + dur * j_i / 6.0))
                v += dur * (a_i + 0.5 * dur * j_i)
    profiles = []
    for i in range(n):
        rows[i].append((t, program.end[i], 0.0, 0.0, 0.0))
        cols = [np.ascontiguousarray(c) for c in np.array(rows[i], dtype=float).T]
        profiles.append(Profile(*cols, duration_s=t, clamps=tuple(clamps[i]),
                                moves=tuple(moves[i])))
    return tuple(profiles)
