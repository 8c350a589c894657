"""The NC's software limit switches (hil.controller.limits): alarm 10720 in block
preparation, the speed limited near them in the test modes (10620), in lock-step with the
emulated drive, and how ``hil sim`` reports them.

Independent references:

* where the limits lie: the drive's own 607Dh (its parameters as the emulated drive runs
  them, in motor units, times the lead) and SINUMERIK's standstill tolerance MD36030
  (0.2 mm, its default): the NC's limits lie that far inside 607Dh;
* the end points: the programs' own numbers (absolute, and incremental sums added here);
* what a drive does beyond 607Dh: its fault 8612h, reported to the NC as alarm 25201; the
  limit switches and end stops of the plant beyond it;
* the speed bound near a limit: rigid-body braking at the axis's maximum acceleration
  (MD32300) stops from v within v^2 / (2 a).
"""

import json
import math

import numpy as np
import pytest

from hil.cli import main
from hil.controller.config import axis_limits, clamp_codes
from hil.controller.interpolator import SETTLE_S, ProfileSamples, plan
from hil.controller.path import parse_path_program
from hil.controller.program import ProgramError, parse_program
from hil.sim import LockStep, MachineLockStep
from plant.assemble import transmission_ratio
from plant.config import load_machine
from plant.machines import load_machine_set
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
GEISS = CONFIGS / "machines" / "geiss_5axis.toml"
#: SINUMERIK MD36030 default: the NC's limits lie this far inside the drive's 607Dh, mm
STANDSTILL_TOL_MM = 0.2
#: SINUMERIK exact stop fine (MD36010 default), mm
EXACT_STOP_FINE_MM = 0.01
#: alarm 10720 (block or setpoint beyond a software limit), 10620 (reaches it)
SOFT_LIMIT, REACHED = 10720, 10620


def drive_limits_mm(ls: LockStep) -> tuple[float, float]:
    """The emulated drive's 607Dh as table positions, mm."""
    ratio = transmission_ratio(ls.cfg) * 1e3
    return ls.drive.params.limit_min * ratio, ls.drive.params.limit_max * ratio


def nc_limits_mm(ls: LockStep) -> tuple[float, float]:
    """The NC's software limits by this file's reference: 607Dh, MD36030 inside."""
    lo, hi = drive_limits_mm(ls)
    return lo + STANDSTILL_TOL_MM, hi - STANDSTILL_TOL_MM


def session(x0_mm: float = 0.0) -> LockStep:
    ls = LockStep(load_machine(ARROW), x0_mm * 1e-3)
    ls.enable()
    return ls


def run_program(ls: LockStep, text: str, x0_mm: float = 0.0):
    """Plan ``text`` from ``x0_mm``, start it and run it to its end and settle: (the
    recording, the profile planned, the profile the NC ran)."""
    sec = ls.ctrl.sec
    planned = plan(parse_program(text, start=x0_mm * 1e-3, clamp=clamp_codes(sec)),
                   axis_limits(ls.cfg, sec))
    runs = ls.ctrl.run_profile(planned)
    return ls.run(runs.duration_s + SETTLE_S), planned, runs


def numbers(res) -> list[int]:
    return [a.number for a in res.alarms]


def motor_mm(res, ls: LockStep) -> np.ndarray:
    """The motor encoder's position as table travel (what 607Dh watches), mm."""
    return res["motor_pos"] * transmission_ratio(ls.cfg) * 1e3


# ---------------------------------------------------------------- where the limits lie


def test_the_nc_limits_lie_md36030_inside_the_drives_607dh():
    """The NC's software limits are the drive's 607Dh pulled in by MD36030, on both sides,
    and lie outside the usable travel [0, travel_m] of the Arrow 500 X."""
    ls = LockStep(load_machine(ARROW))
    lo, hi = nc_limits_mm(ls)
    lim = ls.ctrl.soft_limits
    assert lim.minus * 1e3 == pytest.approx(lo, abs=1e-9)
    assert lim.plus * 1e3 == pytest.approx(hi, abs=1e-9)
    assert lo < 0.0 and hi > ls.cfg.table.travel_m * 1e3


# ---------------------------------------------------------------- block preparation


def test_hil_sim_g0_x10000_raises_10720_and_never_moves(tmp_path, capsys):
    """The attacker's program: G0 X10000 on the Arrow 500 X.  Alarm 10720 only (no drive
    fault 8612h, no 25201), exit status 1, the alarm naming line, axis, limit and the
    programmed value in mm on stderr; the axis never leaves 0."""
    program = tmp_path / "far.nc"
    program.write_text("G0 X10000\nM30\n")
    status = main(["sim", str(ARROW), "--program", str(program), "--out",
                   str(tmp_path / "out"), "--json"])
    out, err = capsys.readouterr()
    summary = json.loads(out)
    assert status == 1
    assert [(a["number"], a["axis"], a["text"]) for a in summary["alarms"]] == [
        (SOFT_LIMIT, "X", "Axis X software limit switch")]
    hi = nc_limits_mm(session())[1]
    detail = f"line 1: X10000 mm beyond the + limit {f'{hi:.6f}'.rstrip('0')} mm"
    assert summary["alarms"][0]["detail"] == detail
    assert (f"hil sim: alarm 10720 axis X software limit switch at t = 0.000 s ({detail})"
            in err)
    assert abs(summary["final_position_mm"]) < EXACT_STOP_FINE_MM
    assert summary["duration_s"] < 1.0  # the run ends with what ran, not the 20 s planned


@pytest.mark.parametrize("side", ["+", "-"])
def test_a_rapid_to_exactly_the_limit_runs_and_stops_inside_607dh(side):
    """G0 at the maximum velocity (MD32000, reached: the move is longer than its ramps)
    from the other end of the travel to exactly the NC's limit: no alarm, the axis ends on
    the limit within the exact-stop window, and the overshoot of the position loop, at
    the scale, the table and the motor encoder, stays within 1 % of MD36030, far inside
    the drive's 607Dh."""
    x0 = 500.0 if side == "-" else 10.0
    ls = session(x0)
    lo, hi = nc_limits_mm(ls)
    target = hi if side == "+" else lo
    res, planned, runs = run_program(ls, f"G0 X{target!r}\nG4 F0.3\nM30\n", x0)
    assert numbers(res) == [] and runs is planned
    v_max = axis_limits(ls.cfg, ls.ctrl.sec).velocity
    assert abs(res["v_set"]).max() == pytest.approx(v_max, rel=1e-9)
    assert res["x_act"][-1] * 1e3 == pytest.approx(target, abs=EXACT_STOP_FINE_MM)
    sign = 1.0 if side == "+" else -1.0
    for pos in (res["x_act"] * 1e3, res["table_pos"] * 1e3, motor_mm(res, ls)):
        assert sign * (pos - target).max() < 0.01 * STANDSTILL_TOL_MM


def test_a_g1_to_the_limit_and_one_micrometre_beyond():
    """G1 to exactly the + limit runs; the next block, 1 um further, raises 10720 naming
    line 3, and the axis stays on the limit."""
    ls = session(400.0)
    hi = nc_limits_mm(ls)[1]
    res, _, runs = run_program(ls, f"G1 X{hi!r} F5000\nG4 F0.1\nG1 X{hi + 0.001!r}\nM30\n",
                               400.0)
    assert numbers(res) == [SOFT_LIMIT]
    assert res.alarms[0].detail.startswith("line 3: X")
    assert runs.moves[-1].line == 1 and len(runs.moves) == 1
    assert res["x_act"][-1] * 1e3 == pytest.approx(hi, abs=EXACT_STOP_FINE_MM)
    assert (res["x_act"] * 1e3 - hi).max() < 0.01 * STANDSTILL_TOL_MM


def test_incremental_blocks_stop_before_the_one_whose_sum_crosses():
    """G91 steps of 200 mm from 0: the third one's end point, 600 mm, lies beyond the +
    limit; 10720 names line 4 and 600 mm; the first two run (the axis ends at 400 mm, at
    rest); nothing of the third moves (never past 400 mm); no drive fault; the drive is
    still enabled."""
    ls = session()
    res, _, _ = run_program(ls, "G91 G0 X200\nX200\nG4 F0.1\nX200\nX-100\nM30\n")
    assert numbers(res) == [SOFT_LIMIT]
    assert res.alarms[0].detail.startswith("line 4: X600 mm beyond the + limit")
    assert res["x_act"][-1] * 1e3 == pytest.approx(400.0, abs=EXACT_STOP_FINE_MM)
    assert res["x_set"].max() * 1e3 == pytest.approx(400.0, abs=1e-9)
    assert res["table_pos"].max() * 1e3 < 400.0 + EXACT_STOP_FINE_MM
    assert ls.ctrl.enabled


def test_nc_start_is_refused_until_reset():
    """After 10720 a program within the limits does not start (the alarm is raised again,
    nothing moves); after the NC's RESET it runs."""
    ls = session()
    run_program(ls, "G0 X900\nM30\n")
    res, _, _ = run_program(ls, "G0 X50\nM30\n")
    assert ls.ctrl.alarms.count(SOFT_LIMIT) == 2
    assert abs(res["x_act"]).max() * 1e3 < EXACT_STOP_FINE_MM
    ls.ctrl.reset_alarms()
    res, _, _ = run_program(ls, "G0 X50\nM30\n")
    assert numbers(res) == []
    assert res["x_act"][-1] * 1e3 == pytest.approx(50.0, abs=EXACT_STOP_FINE_MM)


@pytest.mark.parametrize("word", ["G2 X10 I5", "G3 X10 I5"])
def test_circles_are_refused_before_they_could_pass_a_limit_between_end_points(word):
    """Every block moves on a straight line, so checking end points covers its extent:
    this NC has no circular interpolation, and both parsers refuse G2/G3."""
    with pytest.raises(ProgramError, match="unknown word"):
        parse_program(f"G90\n{word}\nM30\n")
    with pytest.raises(ProgramError, match="unknown word"):
        parse_path_program(f"G90\n{word.replace('I5', 'Y5')}\nM30\n", ("X", "Y"))


def test_setpoints_whose_arc_crosses_a_limit_between_inside_end_points_do_not_run():
    """Setpoints no interpolator planned (a circle's points, as the circularity study feeds
    them): a half circle from 480 mm out to 530 mm and back, both ends inside the limits;
    its extent crosses the + limit, so 10720 names the setpoint and none of it moves."""
    ls = session(480.0)
    t = np.arange(0, 101) * ls.ctrl.ipo_period_s
    pos = 0.505 - 0.025 * np.cos(np.linspace(0.0, 2.0 * math.pi, t.size))
    zero = np.zeros(t.size)
    ls.ctrl.run_points(ProfileSamples(t, pos, zero, zero), monitored=False)
    res = ls.run(0.5)
    assert numbers(res) == [SOFT_LIMIT]
    assert res.alarms[0].detail.startswith("setpoint X")
    assert abs(res["x_act"] * 1e3 - 480.0).max() < EXACT_STOP_FINE_MM


# ---------------------------------------------------------------- several axes


def test_a_block_beyond_y_stops_x_and_y_before_it():
    """The Arrow 500 XY: the second block takes Y beyond its + limit.  10720 on Y only;
    both axes end where the first block ended, at rest, still enabled, Y never past it."""
    m = load_machine_set(CONFIGS / "machines" / "arrow500_xy.toml")
    ls = MachineLockStep(m)
    ls.enable()
    profiles = ls.ctrl.plan(parse_path_program("G1 X100 Y100 F6000\nG0 X200 Y600\nM30\n",
                                               m.names))
    runs = ls.ctrl.run_profiles(profiles)
    assert runs[0].duration_s == runs[1].duration_s < profiles[0].duration_s
    res = ls.run(runs[0].duration_s + SETTLE_S)
    assert [(a.number, a.axis) for a in ls.ctrl.alarms] == [(SOFT_LIMIT, "Y")]
    assert ls.ctrl.alarms[0].detail.startswith("line 2: Y600 mm beyond the + limit")
    for axis in ("X", "Y"):
        assert res[axis]["x_act"][-1] * 1e3 == pytest.approx(100.0, abs=EXACT_STOP_FINE_MM)
        assert res[axis]["x_set"].max() * 1e3 == pytest.approx(100.0, abs=1e-9)
    assert ls.ctrl.enabled


def xc_machine(tmp_path, c_drive: str = ""):
    """The GEISS machine's X and C axes alone (C: its [controller] overrides), ``c_drive``
    the C axis's [drive] overrides."""
    text = GEISS.read_text()
    c = text[text.index('[[axis]]\nname = "C"'):]
    c = c.replace('file = "../geiss_c_axis.toml"', f'file = "{CONFIGS / "geiss_c_axis.toml"}"')
    if c_drive:
        c += f"\n[axis.overrides.drive]\n{c_drive}\n"
    manifest = tmp_path / "xc.toml"
    manifest.write_text(f'[machine]\nname = "X and C"\nsource = "test"\n[[axis]]\nname = "X"\n'
                        f'file = "{ARROW}"\n{c}')
    return load_machine_set(manifest)


def test_a_rotary_axis_without_limits_turns_freely(tmp_path):
    """The GEISS C table has no 607Dh (off by default): two turns run without an alarm and
    the table ends on 720 deg; X moves along within its limits."""
    m = xc_machine(tmp_path)
    ls = MachineLockStep(m)
    ls.enable()
    c_ctrl = ls.ctrl.ctrls[1]
    assert math.isinf(c_ctrl.soft_limits.minus) and math.isinf(c_ctrl.soft_limits.plus)
    runs = ls.ctrl.run_profiles(ls.ctrl.plan(parse_path_program("G0 X50 C720\nM30\n",
                                                                m.names)))
    res = ls.run(runs[1].duration_s + SETTLE_S)
    assert ls.ctrl.alarms == []
    assert math.degrees(res["C"]["x_act"][-1]) == pytest.approx(720.0, abs=0.01)


def test_a_rotary_axis_with_limits_is_checked_in_degrees(tmp_path):
    """The C table given 607Dh of +-90 deg: the NC's limits lie MD36030 (0.2 deg) inside;
    a block to 100 deg raises 10720 in degrees, the block before it runs."""
    m = xc_machine(tmp_path, "software_limit_min_deg = -90.0\nsoftware_limit_max_deg = 90.0")
    ls = MachineLockStep(m)
    ls.enable()
    c_ctrl = ls.ctrl.ctrls[1]
    assert math.degrees(c_ctrl.soft_limits.plus) == pytest.approx(90.0 - STANDSTILL_TOL_MM)
    runs = ls.ctrl.run_profiles(ls.ctrl.plan(parse_path_program(
        "G0 C89.8\nG0 C100\nM30\n", m.names)))
    res = ls.run(runs[1].duration_s + SETTLE_S)
    assert [(a.number, a.axis) for a in ls.ctrl.alarms] == [(SOFT_LIMIT, "C")]
    assert ls.ctrl.alarms[0].detail == "line 2: C100 deg beyond the + limit 89.8 deg"
    assert math.degrees(res["C"]["x_act"][-1]) == pytest.approx(89.8, abs=0.01)


# ---------------------------------------------------------------- motion without end point


def held_toward_limit(mode: str, x0_mm: float, value: float, duration_s: float):
    """Run test mode ``mode`` with ``value`` held (rad/s at the motor, or A) from
    ``x0_mm``: (session, recording)."""
    ls = session(x0_mm)
    ls.ctrl.run_source(mode, lambda t: value)
    return ls, ls.run(duration_s)


def assert_stops_on_the_limit(ls, res, side: str):
    """Alarm 10620 only, the axis at rest within 10 % of MD36030 of the NC's limit
    (never further out at the scale, the table or the motor), so well inside 607Dh."""
    assert numbers(res) == [REACHED]
    lo, hi = nc_limits_mm(ls)
    limit, sign = (hi, 1.0) if side == "+" else (lo, -1.0)
    for pos in (res["x_act"] * 1e3, res["table_pos"] * 1e3, motor_mm(res, ls)):
        assert sign * (pos - limit).max() < 0.1 * STANDSTILL_TOL_MM
    assert res["x_act"][-1] * 1e3 == pytest.approx(limit, abs=0.1 * STANDSTILL_TOL_MM)
    assert abs(res["v_act"][-200:]).max() < 1e-4  # at rest
    assert ls.ctrl.enabled


@pytest.mark.parametrize("side", ["+", "-"])
def test_speed_mode_at_the_drives_top_speed_is_braked_onto_the_limit(side):
    """Speed mode with the setpoint held at the drive's maximum motor speed 6080h toward a
    limit (the worst value the drive takes): the NC limits the speed so the axis stops on
    the limit (10620), no drive fault; before the bound acts it runs at that speed, and it
    acts no earlier than the braking distance at MD32300, v^2 / (2 a)."""
    sign = 1.0 if side == "+" else -1.0
    cfg = load_machine(ARROW)
    probe = LockStep(cfg)
    w_max = probe.drive.params.max_speed
    x0 = 400.0 if side == "+" else 110.0
    ls, res = held_toward_limit("speed", x0, sign * w_max, 0.6)
    assert_stops_on_the_limit(ls, res, side)
    v_top = w_max * ls.ctrl.ratio
    a_max = axis_limits(cfg, ls.ctrl.sec).acceleration
    limit = nc_limits_mm(ls)[0 if side == "-" else 1]
    reached = res.alarms[0].t_s
    at = int(np.searchsorted(res["t_s"], reached))
    assert abs(res["v_act"][at]) == pytest.approx(v_top, rel=0.02)
    assert abs(limit - res["x_act"][at] * 1e3) == pytest.approx(
        v_top ** 2 / (2.0 * a_max) * 1e3, rel=0.02)


@pytest.mark.parametrize("side", ["+", "-"])
def test_current_mode_at_the_current_limit_is_taken_over_and_braked_onto_the_limit(side):
    """Current mode with the current held at 6072h (the drive's limit, the worst value)
    toward a limit, started where the axis passes the speed bound below the drive's
    overspeed: the NC takes the axis over and stops it on the limit (10620), no drive
    fault."""
    sign = 1.0 if side == "+" else -1.0
    probe = LockStep(load_machine(ARROW))
    i_max = probe.drive.params.max_current_a
    x0 = 430.0 if side == "+" else 80.0
    ls, res = held_toward_limit("current", x0, sign * i_max, 0.5)
    assert_stops_on_the_limit(ls, res, side)
    assert ls.ctrl.mode == "speed"


def test_speed_mode_away_from_the_limits_is_not_limited():
    """A speed step in mid travel (hil measure's speed step) is left as it is."""
    ls, res = held_toward_limit("speed", 250.0, 0.05 / transmission_ratio(load_machine(ARROW)),
                                0.2)
    assert numbers(res) == []
    assert res["w_set"][-1] * ls.ctrl.ratio == pytest.approx(0.05, rel=1e-12)


# ---------------------------------------------------------------- machine data


def test_a_607dh_too_narrow_for_the_nc_limits_is_refused(tmp_path, capsys):
    """607Dh 0.3 mm wide leaves no travel MD36030 inside each limit: hil sim exits 2 with
    one line naming the file, the section and the key."""
    machine = tmp_path / "narrow.toml"
    machine.write_text(ARROW.read_text() + "\n[drive]\nsoftware_limit_min_m = 0.2\n"
                       "software_limit_max_m = 0.2003\n")
    program = tmp_path / "p.nc"
    program.write_text("G0 X200.1\nM30\n")
    status = main(["sim", str(machine), "--program", str(program), "--out",
                   str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 2
    assert str(machine) in err and "[drive] software limits (607Dh) 200 to 200.3 mm" in err
    assert "standstill_pos_tol_mm" in err and "Traceback" not in err
