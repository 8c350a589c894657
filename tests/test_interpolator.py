"""The controller's part-program parser and interpolator (hil.controller.program,
hil.controller.interpolator)."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from hil.controller.config import AxisLimits
from hil.controller.interpolator import ClampEvent, FineInterpolator, plan
from hil.controller.path import parse_path_program, plan_path
from hil.controller.program import (
    Block,
    BlockKind,
    ClampCodes,
    Program,
    ProgramError,
    format_program,
    parse_program,
    read_program,
)

PROGRAMS = Path(__file__).resolve().parent.parent / "programs"
INF = math.inf


def one_move(distance: float, feed: float, start: float = 0.0) -> Program:
    """A program of one G1 move, built directly in SI."""
    block = Block(BlockKind.MOVE, 1, start, start + distance, feed=feed)
    return Program("X", False, start, (block,))


def reference_duration(d: float, v: float, a: float, j: float) -> float:
    """Duration of a rest-to-rest move by bisection on the distance the accelerate/decelerate
    pair covers (textbook acceleration times), independent of the planner's closed forms."""
    def accel_time(vp: float) -> float:
        if j in (0.0, INF):
            return vp / a
        return vp / a + a / j if vp * j >= a * a else 2.0 * math.sqrt(vp / j)

    vp = v
    if vp * accel_time(vp) > d:
        lo, hi = 0.0, v
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if mid * accel_time(mid) < d else (lo, mid)
        vp = 0.5 * (lo + hi)
    return accel_time(vp) + d / vp


# ---------------------------------------------------------------- parser

def test_parse_every_word_by_hand():
    """Hand-computed blocks: mm -> m, mm/min -> m/s (6000 mm/min = 0.1 m/s), F modal,
    G91 incremental from the last target, G4 F in seconds leaving the feed alone,
    comments of both kinds and block numbers ignored."""
    text = ("; header comment\n"
            "N10 G90 G71 (absolute, metric)\n"
            "N20 G0 X250\n"
            "N30 G4 F0.5\n"
            "N40 G1 X250.5 F6000 ; linear\n"
            "\n"
            "g91 x-50.5\n"
            "G1X.25F120\n"
            "N90 M30\n")
    p = parse_program(text, start=0.01)
    assert p.axis == "X" and not p.rotary and p.start == 0.01
    assert p.blocks == (
        Block(BlockKind.MOVE, 3, 0.01, 0.25, feed=INF, rapid=True),
        Block(BlockKind.DWELL, 4, 0.25, 0.25, dwell_s=0.5),
        Block(BlockKind.MOVE, 5, 0.25, 0.2505, feed=0.1),
        Block(BlockKind.MOVE, 7, 0.2505, pytest.approx(0.2, abs=1e-15), feed=0.1),
        Block(BlockKind.MOVE, 8, pytest.approx(0.2, abs=1e-15), pytest.approx(0.20025),
              feed=pytest.approx(0.002)),
    )
    assert p.end == pytest.approx(0.20025)


def test_rotary_axis_takes_degrees():
    """Hand-computed: C90 is pi/2 rad, F3600 deg/min is 60 deg/s = pi/3 rad/s."""
    p = parse_program("G1 C90 F3600\nG91 G0 C-45", axis="C")
    assert p.rotary
    assert p.blocks[0].target == pytest.approx(math.pi / 2)
    assert p.blocks[0].feed == pytest.approx(math.pi / 3)
    assert p.blocks[1].target == pytest.approx(math.pi / 4) and p.blocks[1].rapid


_op = st.one_of(
    st.tuples(st.just("G0"), st.integers(-500_000, 500_000)),
    st.tuples(st.just("G1"), st.integers(-500_000, 500_000), st.integers(1, 30_000)),
    st.tuples(st.just("G4"), st.integers(0, 5000)),
    st.tuples(st.just("G91 G1"), st.integers(-1000, 1000), st.integers(1, 30_000)),
    st.tuples(st.just("M10 M11")),
)


@settings(max_examples=150, deadline=None)
@given(ops=st.lists(_op, max_size=12), start_um=st.integers(-1000, 1000))
def test_format_then_parse_round_trips(ops, start_um):
    """Text in micrometres -> blocks -> format_program -> blocks gives the same blocks
    (line numbers aside; positions to 1e-12 m, the rounding of incremental sums)."""
    lines = []
    for op in ops:
        if op[0] == "G4":
            lines.append(f"G4 F{op[1] / 1000}")
        elif op[0] == "M10 M11":
            lines += ["M10", "M11"]  # clamp and unclamp, each alone in its block
        else:
            mode = op[0] if op[0].startswith("G91") else "G90 " + op[0]
            lines.append(f"{mode} X{op[1] / 1000}" + (f" F{op[2]}" if len(op) > 2 else ""))
    first = parse_program("\n".join(lines), start=start_um * 1e-6)
    again = parse_program(format_program(first), start=first.start)
    assert len(again.blocks) == len(first.blocks)
    for a, b in zip(first.blocks, again.blocks, strict=True):
        assert dataclasses.replace(b, line=a.line, start=a.start, target=a.target) == a
        assert b.start == pytest.approx(a.start, abs=1e-12)
        assert b.target == pytest.approx(a.target, abs=1e-12)


@pytest.mark.parametrize("name", ["seed000_moves.nc", "seed003_trapezoid.nc"])
def test_example_programs_parse_within_travel(name):
    """The shipped programs parse and stay inside 0..500 mm."""
    p = read_program(PROGRAMS / name)
    assert p.blocks
    assert all(0.0 <= b.target <= 0.5 for b in p.blocks)


@pytest.mark.parametrize("text, line, fragment", [
    ("G0 X10\nG1 X20 Q5", 2, "Q5"),
    ("G70 G0 X1", 1, "G70"),
    ("G0 X5\n\nG1 X20", 3, "X20"),
    ("G0 X5\nG1 Y20 F100", 2, "Y20"),
    ("G0 X1.2.3", 1, "X1.2.3"),
    ("G0 X-", 1, "X-"),
    ("G0 #1", 1, "#1"),
    ("G4 F0.5 X10", 1, "G4"),
    ("G4 P500", 1, "P500"),
    ("G4", 1, "G4"),
    ("X10", 1, "X10"),
    ("G1 X10 F-5", 1, "F-5"),
    ("G0 X1 (rapid", 1, "(rapid"),
    ("G0 X1 )", 1, "')'"),
    ("G0 G1 X1", 1, "G0 and G1"),
    ("G90 G91 X1", 1, "G90 and G91"),
    ("G0 X1 X2", 1, "X2"),
    ("G0 X1 N10", 1, "N10"),
    ("G0 X1\nM30\nG0 X2", 3, "G0 X2"),
    ("G0 X1 M3", 1, "M3"),
    ("G64 G1 X1 F10", 1, "G64"),
    ("M10\nG4 F1\nG0 X5", 3, "'X5' moves axis X, clamped since line 1 (M10)"),
    ("M10\nG91 G1 X0 F100", 2, "unclamp it with M11 first"),
    ("G0 X1 M10", 1, "M10 (clamping) must stand alone"),
    ("M10 M11", 1, "M10 (clamping) must stand alone"),
    ("M12", 1, "unknown word 'M12'"),
])
def test_errors_name_line_and_word(text, line, fragment):
    """Each refused program raises ProgramError (a ValueError) with the source, the line
    number and the offending word in its message."""
    with pytest.raises(ValueError) as info:
        parse_program(text, source="part.nc")
    err = info.value
    assert isinstance(err, ProgramError)
    assert err.line == line
    assert f"part.nc line {line}:" in str(err)
    assert fragment in str(err)


def test_clamp_blocks_parse_and_plan_at_their_times():
    """M10 and M11 (the default clamp M functions) become clamp and unclamp blocks at the
    axis's position, and the profile has them at the time the blocks before them end
    (hand-computed: dwells of 0.5 s and 1 s); a machine's own M functions work alike."""
    p = parse_program("G0 X10\nG4 F0.5\nM10\nG4 F1\nM11\nM30", start=0.01)
    assert p.blocks[2] == Block(BlockKind.CLAMP, 3, 0.01, 0.01, m_code=10)
    assert p.blocks[4] == Block(BlockKind.UNCLAMP, 5, 0.01, 0.01, m_code=11)
    assert plan(p, AxisLimits(0.5, 2.0, 0.0)).clamps == (ClampEvent(0.5, True),
                                                         ClampEvent(1.5, False))
    own = parse_program("M12\nG4 F0.25\nM13", clamp=ClampCodes(12, 13))
    assert [b.kind for b in own.blocks] == [BlockKind.CLAMP, BlockKind.DWELL, BlockKind.UNCLAMP]
    with pytest.raises(ValueError, match="two M functions"):
        ClampCodes(12, 12)


def test_a_path_clamp_acts_on_the_axes_it_is_the_m_function_of():
    """X clamps with M10, Y with M12: M10 clamps X only, so Y may move and X may not; the
    clamp is in X's profile alone.  One M function clamping one axis and unclamping another
    is refused."""
    codes = (ClampCodes(10, 11), ClampCodes(12, 13))
    p = parse_path_program("M10\nG1 Y5 F1000\nM11", "XY", clamp=codes)
    assert p.blocks[0].clamp_axes == (True, False)
    limits = [AxisLimits(0.5, 2.0, 0.0)] * 2
    x, y = plan_path(p, limits)
    assert x.clamps == (ClampEvent(0.0, True), ClampEvent(x.duration_s, False)) and not y.clamps
    with pytest.raises(ProgramError, match="line 2: 'X5' moves axis X, clamped since line 1"):
        parse_path_program("M10\nG1 X5 Y5 F1000", "XY", clamp=codes)
    with pytest.raises(ValueError, match="M11 clamps one axis and unclamps another"):
        parse_path_program("", "XY", clamp=(ClampCodes(10, 11), ClampCodes(11, 12)))


def test_unknown_axis_letter_is_refused():
    """The controller's own axis letter must be a known one."""
    with pytest.raises(ValueError, match="'Q'"):
        parse_program("G0 X1", axis="Q")


# ---------------------------------------------------------------- profiles

def check_profile(prof, start, target, v, a, j):
    """Properties every rest-to-rest single-move profile must have."""
    d = abs(target - start)
    jerky = j not in (0.0, INF)
    first = prof.sample(0.0)
    assert first.pos == start and first.vel == 0.0
    assert first.acc == 0.0 if jerky else abs(first.acc) == a  # a trapezoid steps at 0
    assert tuple(prof.sample(prof.duration_s)) == (target, 0.0, 0.0)
    p0, v0, a0, jk = prof.pos0[-2], prof.vel0[-2], prof.acc0[-2], prof.jerk[-2]
    tau = prof.knots_s[-1] - prof.knots_s[-2]  # the end of the last move segment
    end_pos = p0 + tau * (v0 + tau * (a0 / 2 + tau * jk / 6))
    end_vel = v0 + tau * (a0 + tau * jk / 2)
    end_acc = a0 + tau * jk
    t_eps = 4 * np.finfo(float).eps * prof.duration_s  # rounding of the absolute knot times
    assert abs(end_pos - target) <= 1e-9 * max(d, 1e-3) + v * t_eps
    assert abs(end_vel) <= 1e-9 * v + a * t_eps
    assert abs(end_acc) <= 1e-9 * a + j * t_eps if jerky else abs(end_acc) == a
    t = np.union1d(np.linspace(0.0, prof.duration_s, 4001), prof.knots_s)
    s = prof.sample_array(t)
    dt = np.diff(t)
    assert np.all(np.abs(s.vel) <= v * (1 + 1e-12))
    assert np.all(np.abs(s.acc) <= a * (1 + 1e-12))
    sign = math.copysign(1.0, target - start)
    assert np.all(sign * np.diff(s.pos) >= -1e-12 * d)
    if jerky:
        # dt between two absolute sample times is rounded by up to t_eps: on a long move a
        # jerk phase of a few microseconds spans a dt a few 1e-9 short of its length
        assert np.all(np.abs(np.diff(s.acc)) <= j * (dt + t_eps) * (1 + 1e-9) + 1e-12 * a)
    # vel is the derivative of pos, acc that of vel (trapezoidal rule, kink-aware bounds)
    slack_p = a * dt**2 / 4 + (j * dt**3 / 12 if jerky else 0.0) + 1e-12 * max(d, 1e-3)
    assert np.all(np.abs(np.diff(s.pos) - (s.vel[1:] + s.vel[:-1]) / 2 * dt) <= slack_p)
    slack_v = (j * dt**2 / 4 if jerky else a * dt) + 1e-12 * v
    assert np.all(np.abs(np.diff(s.vel) - (s.acc[1:] + s.acc[:-1]) / 2 * dt) <= slack_v)


@settings(max_examples=200, deadline=None)
@given(start=st.floats(-0.5, 0.5), distance=st.floats(1e-6, 0.5), negative=st.booleans(),
       feed=st.floats(1e-3, 2.0), v_max=st.floats(0.01, 2.0), a_max=st.floats(0.05, 50.0),
       j_max=st.one_of(st.just(0.0), st.just(INF), st.floats(0.5, 5000.0)),
       ipo_period_s=st.floats(1e-4, 1e-2))
# found by hypothesis: a 256 s move whose 19 us jerk phases end at rounded absolute times
@example(start=0.0, distance=0.5, negative=False, feed=0.001953125, v_max=1.0,
         a_max=0.0546875, j_max=2818.0, ipo_period_s=0.0078125)
def test_single_move_properties(start, distance, negative, feed, v_max, a_max, j_max,
                                ipo_period_s):
    """For random moves and limits: starts and ends at rest on its points, |v| <= feed,
    |a| <= a_max, |jerk| <= j_max (finite differences), monotonic position, consistent
    derivatives, the duration of the bisection reference, and exactly one IPO point at or
    after the end."""
    target = start - distance if negative else start + distance
    prof = plan(one_move(target - start, feed, start), AxisLimits(v_max, a_max, j_max))
    v = min(feed, v_max)
    check_profile(prof, start, target, v, a_max, j_max)
    assert prof.duration_s == pytest.approx(reference_duration(abs(target - start), v, a_max,
                                                               j_max), rel=1e-9)
    ipo_t = prof.ipo_points(ipo_period_s).t
    assert ipo_t[-1] >= prof.duration_s > ipo_t[-2]


def test_long_trapezoid_duration_by_hand():
    """Hand-computed: 0.4 m at 0.1 m/s with 1 m/s² takes d/v + v/a = 4 + 0.1 = 4.1 s;
    a jerk limit of 0 and of inf both mean trapezoidal."""
    for j in (0.0, INF):
        prof = plan(one_move(0.4, 0.1), AxisLimits(0.5, 1.0, j))
        assert prof.duration_s == pytest.approx(4.1, rel=1e-12)
        assert prof.sample(2.0) == pytest.approx((0.195, 0.1, 0.0))


def test_long_scurve_duration_by_hand():
    """Hand-computed: 0.4 m at 0.1 m/s, 1 m/s², 20 m/s³: d/v + v/a + a/j
    = 4 + 0.1 + 0.05 = 4.15 s; at half time (2.075 s) the symmetric profile is at half
    distance, 0.2 m, cruising at 0.1 m/s."""
    prof = plan(one_move(0.4, 0.1), AxisLimits(0.5, 1.0, 20.0))
    assert prof.duration_s == pytest.approx(4.15, rel=1e-12)
    assert prof.sample(2.075) == pytest.approx((0.2, 0.1, 0.0))


def test_short_move_reaching_neither_feed_nor_acceleration():
    """Closed form: 0.1 mm with 1 m/s², 20 m/s³ (2 a³/j² = 5 mm > 0.1 mm): four jerk
    phases of T_j = (d / 2j)^(1/3) = (2.5e-6)^(1/3) = 0.0135721 s, duration 0.0542884 s,
    peak acceleration j T_j = 0.271442 m/s² at T_j, peak velocity j T_j² = 3.68403e-3 m/s."""
    prof = plan(one_move(1e-4, 0.1), AxisLimits(0.5, 1.0, 20.0))
    tj = 0.013572088082974532
    assert prof.duration_s == pytest.approx(0.0542883523, rel=1e-9)
    assert prof.sample(tj).acc == pytest.approx(0.2714417617, rel=1e-9)
    assert prof.sample(2 * tj) == pytest.approx((5e-5, 3.684031499e-3, 0.0), rel=1e-9, abs=1e-15)


def test_short_move_reaching_acceleration_not_feed():
    """Closed form: 10 mm at 1 m/s², 20 m/s³ reaches a_max but not 0.5 m/s; the peak
    velocity solves v²/a + v a/j = d: v = (-0.05 + sqrt(0.0025 + 0.04)) / 2 = 0.0780776 m/s,
    duration 2 (v/a + a/j) = 0.256155 s.  Trapezoidal: 2 sqrt(d/a) = 0.2 s."""
    prof = plan(one_move(0.01, 0.5), AxisLimits(0.5, 1.0, 20.0))
    vp = (-0.05 + math.sqrt(0.0425)) / 2
    assert prof.duration_s == pytest.approx(2 * (vp + 0.05), rel=1e-12)
    assert prof.sample(prof.duration_s / 2).vel == pytest.approx(vp, rel=1e-12)
    assert plan(one_move(0.01, 0.5), AxisLimits(0.5, 1.0, 0.0)).duration_s == pytest.approx(0.2)


def test_rapid_runs_at_max_velocity_and_feed_is_clipped():
    """G0 moves at v_max; a G1 feed above v_max is clipped to it (same 0.4 m trapezoid:
    0.4/0.2 + 0.2/1 = 2.2 s)."""
    lim = AxisLimits(0.2, 1.0, 0.0)
    rapid = plan(parse_program("G0 X400"), lim)
    fast = plan(parse_program("G1 X400 F60000"), lim)
    assert rapid.duration_s == pytest.approx(2.2) and fast.duration_s == pytest.approx(2.2)


def test_program_with_dwells_ends_every_block_on_target():
    """The seed-000 program: the total duration is the sum of the reference move durations
    and the dwells (0.5 + 0.5 + 0.2 s); during each dwell the axis rests on the previous
    target (exact stop)."""
    lim = AxisLimits(0.5, 2.0, 40.0)
    p = read_program(PROGRAMS / "seed000_moves.nc")
    prof = plan(p, lim)
    t, total = 0.0, 0.0
    for b in p.blocks:
        if b.kind is BlockKind.DWELL:
            assert prof.sample(t + b.dwell_s / 2) == (b.target, 0.0, 0.0)
            t += b.dwell_s
        else:
            t += reference_duration(abs(b.target - b.start), min(b.feed, lim.velocity),
                                    lim.acceleration, lim.jerk)
        total += b.dwell_s
    assert total == pytest.approx(1.2)
    assert prof.duration_s == pytest.approx(t, rel=1e-9)
    assert tuple(prof.sample(prof.duration_s + 1.0)) == (0.48, 0.0, 0.0)


def test_seed003_program_holds_6000_mm_min():
    """Seed 003 §5: the trapezoid runs at a constant 6000 mm/min (0.1 m/s).  With assumed
    limits 1 m/s² and 10 m/s³ each 400 mm move accelerates for v/a + a/j = 0.2 s, so the
    plateau lasts d/v - 0.2 = 3.8 s in each direction (hand-computed)."""
    prof = plan(read_program(PROGRAMS / "seed003_trapezoid.nc"), AxisLimits(0.5, 1.0, 10.0))
    t = np.arange(0.0, prof.duration_s, 1e-3)
    s = prof.sample_array(t)
    for sign in (1.0, -1.0):
        plateau = t[(np.abs(s.vel - sign * 0.1) < 1e-12) & (s.acc == 0.0)]
        assert plateau.size
        assert plateau[-1] - plateau[0] == pytest.approx(3.8, abs=2e-3)


@pytest.mark.parametrize("j_max", [0.0, 40.0])
def test_ipo_and_fine_interpolation_within_the_linear_bound(j_max):
    """Linear interpolation of a function f between points T apart errs by at most
    max|f''| T² / 8, or max|f'| T / 2 where f' jumps: position a_max T_ipo² / 8 (2 µm for
    2 m/s², T_ipo = 4 ms); velocity j_max T² / 8 (S-curve) or a_max T / 2 (trapezoid);
    acceleration j_max T / 2 (S-curve).  The IPO points are exact samples; during
    constant-acceleration phases the position error reaches its bound (so the check is
    not vacuous)."""
    a_max, t_ipo, ratio = 2.0, 4e-3, 8
    prof = plan(read_program(PROGRAMS / "seed000_moves.nc"), AxisLimits(0.5, a_max, j_max))
    ipo = prof.ipo_points(t_ipo)
    assert ipo.t[-1] >= prof.duration_s > ipo.t[-2]
    assert ipo.pos[-1] == 0.48 and ipo.vel[-1] == 0.0
    fine = FineInterpolator(ipo, ratio)
    n = (len(ipo.t) - 1) * ratio + 3
    got = np.empty((3, n))
    for i in range(n):
        fine.step()
        got[:, i] = fine.pos, fine.vel, fine.acc
        if i % ratio == 0 and i // ratio < len(ipo.t):
            assert fine.pos == ipo.pos[i // ratio], i
    assert fine.done and fine.pos == 0.48
    exact = prof.sample_array(np.arange(n) * (t_ipo / ratio))
    err = np.max(np.abs(got - np.array([exact.pos, exact.vel, exact.acc])), axis=1)
    bound = a_max * t_ipo**2 / 8
    assert bound * 0.9 < err[0] <= bound * (1 + 1e-9) + 1e-15
    if j_max:
        assert err[1] <= j_max * t_ipo**2 / 8 * (1 + 1e-9) + 1e-15
        assert err[2] <= j_max * t_ipo / 2 * (1 + 1e-9) + 1e-15
    else:
        assert err[1] <= a_max * t_ipo / 2 * (1 + 1e-9) + 1e-15


def test_bad_limits_and_rates_are_refused():
    """Zero velocity or acceleration, negative jerk, a zero IPO period and a fractional
    fine-interpolation ratio raise ValueError naming the value."""
    p = parse_program("G1 X10 F100")
    for lim in (AxisLimits(0.0, 1.0, 0.0), AxisLimits(1.0, INF, 0.0), AxisLimits(1.0, 1.0, -1.0)):
        with pytest.raises(ValueError, match="axis limit"):
            plan(p, lim)
    prof = plan(p, AxisLimits(1.0, 1.0, 0.0))
    with pytest.raises(ValueError, match="IPO period 0"):
        prof.ipo_points(0.0)
    with pytest.raises(ValueError, match="1.5"):
        FineInterpolator(prof.ipo_points(4e-3), 1.5)
