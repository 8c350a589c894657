"""The simulated NC honours every controller convention of ``[controller]`` (issue 13 part 1):
``speed_actual_filter_s``, ``feedforward_interpolation``, ``current_delay_cycles`` and
``speed_antiwindup``, as hil identify's replay and the bench's independent generator
(hil/bench/identify_gen/generate.py) define them.

Independent references:

* speed filter: the exact discretisation of a first-order lag, y_k = u_k + (y_{k-1} - u_k)
  exp(-T/tau), computed here from the encoder positions the NC read (u_k their difference
  over the speed cycle);
* feed-forward: the straight line between two position cycles' feed-forward values (or
  the held value), recovered here from the speed command v_cmd = K_v e + w_ff v_ff with
  K_v from MD32200's definition ((m/min)/mm = 1000/60 1/s) and e the position loop's error;
* current delay: the speed loop's output as the NC computed it, N PWM periods earlier;
* anti-windup: the PI's limit K_t I_max (clamp), the conditional modes' peak velocity as
  the validate row computes it (hil.validate.experiments.moves.linear_move), and the
  ordering of the overshoots;
* the drive's own speed loop (CSV): its compiled cycle (hil.drive.compiled) against its
  Python cycle, bit for bit, with 'clamp' and 'none' (the Python path's SpeedLoop honours
  the key, so the compiled one must too);
* identify: a ``hil sim`` trace (a separate process) of a machine file with all four
  non-default conventions, replayed by hil identify's replay through the same file, is
  given back to one scale count; without the conventions the replay misses it by far.
"""

import math
import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pytest

from hil.cia402 import EnableSequencer
from hil.controller.alarms import AlarmNumber
from hil.controller.config import axis_limits, load_controller
from hil.controller.interpolator import ProfileSamples, plan
from hil.controller.program import parse_program
from hil.drive import EmulatedDrive
from hil.identify.config_out import patch_config
from hil.identify.record import load_record
from hil.identify.replay import replay
from hil.sim import LockStep
from hil.validate.experiments import moves
from io_adapters.messages import MODE_CSV, Feedback, Setpoint
from plant import Plant
from plant.config import ConfigError, MachineConfig, load_machine
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
#: a 20 mm move at 6 m/min and back on the Arrow 500 X (jerk limited)
MOVES = "N10 G90\nN20 G1 X20 F6000\nN30 G1 X0 F3000\nN40 M30\n"
#: every convention away from its default
CONVENTIONS = {"feedforward_interpolation": "linear", "speed_actual_filter_s": 0.0008,
               "speed_antiwindup": "clamp", "current_delay_cycles": 2}
SIGNALS = ("theta_act", "w_act", "w_set", "v_set", "v_cmd", "iq_set")


def arrow(**controller) -> MachineConfig:
    return load_machine(ARROW, {"controller": controller})


def run_program(cfg: MachineConfig, program: str = MOVES) -> dict:
    """Lock step (as hil sim) from 0 on ``program``: the NC's signals at every tick after
    the enable, with the position loop's error, the speed loop's last control error and
    the current setpoint sent to the drive."""
    profile = plan(parse_program(program, "X", 0.0), axis_limits(cfg, load_controller(cfg)))
    ls = LockStep(cfg, 0.0)
    ls.enable()
    ctrl = ls.ctrl
    ctrl.run_profile(profile)
    n = int(profile.duration_s / ls.plant.pwm_period) + 200
    rec = {name: np.empty(n) for name in (*SIGNALS, "pos_error", "speed_error", "iq_ref",
                                          "tick")}
    for i in range(n):
        ls.tick()
        for name in SIGNALS:
            rec[name][i] = getattr(ctrl, name)
        ctrl.settle()  # the loops' state, out of the compiled path's arrays
        rec["pos_error"][i] = ctrl.pos_loop.error
        rec["speed_error"][i] = ctrl.speed_loop.e_prev
        rec["iq_ref"][i] = ls.sp.iq_ref_a
        rec["tick"][i] = ctrl.tick_count - 1
    assert not ctrl.alarms.alarms
    return rec


def test_speed_loop_uses_the_filtered_measured_speed():
    """tau = 0.8 ms at the 125 µs speed cycle: w_act is the exact first-order filter of the
    encoder difference (computed here from the positions the NC read), and it is what the
    speed loop's error is formed with (no setpoint filter on this axis: e = w_set - w_act)."""
    tau = 0.0008
    cfg = arrow(speed_actual_filter_s=tau)
    rec = run_program(cfg)
    period = load_controller(cfg).speed_cycle_ratio / cfg.motor.pwm_frequency_hz
    raw = np.diff(rec["theta_act"]) / period
    a = math.exp(-period / tau)
    expected = np.empty_like(raw)
    y = rec["w_act"][0]
    for k, u in enumerate(raw):
        y = u + (y - u) * a
        expected[k] = y
    np.testing.assert_allclose(rec["w_act"][1:], expected, rtol=1e-12, atol=1e-9)
    assert np.abs(raw - rec["w_act"][1:]).max() > 1.0  # rad/s: the filter does something
    np.testing.assert_array_equal(rec["speed_error"], rec["w_set"] - rec["w_act"])


def feed_forward(cfg: MachineConfig, rec: dict) -> np.ndarray:
    """The feed-forward in each speed command, v_ff = (v_cmd - K_v e) / w_ff, m/s."""
    sec = load_controller(cfg)
    kv = sec.kv_m_min_per_mm * 1000.0 / 60.0
    return (rec["v_cmd"] - kv * rec["pos_error"]) / sec.speed_ff_weight


@pytest.mark.parametrize("mode", ["hold", "linear"])
def test_feed_forward_between_position_cycles(mode):
    """Position cycle 16 speed cycles: with 'linear' the feed-forward at speed cycle m of a
    position cycle lies on the straight line from this cycle's v_set to the next's, at
    m/16; with 'hold' it is this cycle's v_set throughout."""
    cfg = arrow(feedforward_interpolation=mode)
    n_pos = load_controller(cfg).position_cycle_ratio
    rec = run_program(cfg)
    v_ff = feed_forward(cfg, rec)
    starts = np.flatnonzero(rec["tick"] % n_pos == 0)
    starts = starts[starts + n_pos < len(v_ff)]
    now, nxt = rec["v_set"][starts], rec["v_set"][starts + n_pos]
    assert np.abs(nxt - now).max() > 1e-3  # m/s per cycle: the feed-forward moves
    for m in range(n_pos):
        line = now + (nxt - now) * m / n_pos if mode == "linear" else now
        np.testing.assert_allclose(v_ff[starts + m], line, rtol=0, atol=1e-12)


@pytest.mark.parametrize("cycles", [0, 3])
def test_current_setpoint_reaches_the_drive_late(cycles):
    """The q-current setpoint sent to the drive is the speed loop's output ``cycles`` PWM
    periods earlier."""
    rec = run_program(arrow(current_delay_cycles=cycles))
    iq, sent = rec["iq_set"], rec["iq_ref"]
    np.testing.assert_array_equal(sent[cycles:], iq[:len(iq) - cycles])
    assert np.abs(iq).max() > 1.0  # A: the move needs current


@dataclass(frozen=True)
class Step:
    """The LD386's 1 m position step (the validate row's move) with one anti-windup."""
    peak_velocity: float  # m/s
    v_max: float          # the speed command's limit (MD32000), m/s
    integ_peak: float     # largest |speed integrator|, N
    limit: float          # the PI's limit K_t I_max, N
    alarms: tuple         # the NC's alarm numbers


def ld386_step(mode: str) -> Step:
    cfg = load_machine(moves.LD386, {"controller": {"speed_antiwindup": mode}})
    ls = LockStep(cfg, moves.LD386_X0)
    ls.enable()
    ctrl = ls.ctrl
    target = moves.LD386_X0 + moves.PAPER_MOVE_M
    zero = np.zeros(2)
    ctrl.run_points(ProfileSamples(np.array([0.0, ctrl.ipo_period_s]), np.full(2, target),
                                   zero, zero))
    pi = ctrl.speed_loop.pi
    v_peak = integ_peak = 0.0
    for _ in range(int(moves.MOVE_DURATION_S / ls.plant.pwm_period)):
        ls.tick()
        ctrl.settle()  # the integrator, out of the compiled path's arrays
        v_peak = max(v_peak, ctrl.v_act)
        integ_peak = max(integ_peak, abs(pi.integ))
    return Step(v_peak, ctrl.limits.velocity, integ_peak, pi.limit,
                tuple(a.number for a in ctrl.alarms.alarms))


@pytest.fixture(scope="module")
def steps() -> dict:
    return {mode: ld386_step(mode)
            for mode in ("conditional", "torque_setpoint", "clamp", "none")}


def test_clamp_keeps_the_integrator_within_the_limit(steps):
    clamp = steps["clamp"]
    assert clamp.integ_peak <= clamp.limit and clamp.alarms == ()
    assert clamp.integ_peak == pytest.approx(clamp.limit)  # the 1 m step reaches it


def test_no_anti_windup_winds_up_and_overshoots_more(steps):
    """Without anti-windup the integrator charges through the whole acceleration at the
    current limit, to beyond the limit, and the speed overshoots the limited speed command
    by far more than with conditional integration: past the drive's overspeed monitoring
    here, so the drive faults (alarm 25201) where the conditional run arrives."""
    none, conditional = steps["none"], steps["conditional"]
    assert none.integ_peak > 2.0 * none.limit
    assert none.peak_velocity - none.v_max > 3.0 * (conditional.peak_velocity
                                                    - conditional.v_max)
    assert none.alarms == (AlarmNumber.DRIVE_FAULT,) and conditional.alarms == ()


def test_conditional_modes_as_the_validate_row_has_them(steps):
    """'conditional' is the NC's PI as before (the validate row's peak to the bit);
    'torque_setpoint' gives the same peak within 1 mm/s (the row's finding: the integrator
    charges after the force has left its limit)."""
    as_is = moves.linear_move(load_machine(moves.LD386))
    assert steps["conditional"].peak_velocity == as_is.peak_velocity
    assert steps["torque_setpoint"].peak_velocity == pytest.approx(as_is.peak_velocity,
                                                                   abs=1e-3)


@pytest.mark.parametrize("mode", ["clamp", "none"])
def test_drive_speed_loop_compiled_is_python_with_the_anti_windup(mode):
    """The drive in CSV, speed steps that hold the current at its limit (the integrator
    winds up with 'none', is held with 'clamp'): the compiled drive cycle gives the Python
    cycle's feedback and plant state to the bit every tick, and ran most of them."""
    cfg = arrow(speed_antiwindup=mode)
    drives = [EmulatedDrive(Plant(cfg, table_pos=0.25), compiled=c) for c in (False, True)]
    fbs = [Feedback(), Feedback()]
    sp = Setpoint()
    enable = EnableSequencer(timeout_cycles=10_000)
    enable.enable()
    sp.mode = MODE_CSV
    integ_peak = 0.0
    for k, target in enumerate([0.0] * 300 + [1.5e8] * 1500 + [-1.5e8] * 1500):
        sp.seq = k
        sp.controlword = enable.next_controlword(fbs[0].statusword)
        sp.target_velocity_counts_s = target
        for drive, fb in zip(drives, fbs):
            drive.cycle(sp, fb)
        assert fbs[0] == fbs[1], k
        assert drives[0].plant.state.tobytes() == drives[1].plant.state.tobytes(), k
        integ_peak = max(integ_peak, abs(drives[0].loops.speed.pi.integ))
    assert drives[1].compiled.cycles > 3000
    limit = drives[0].loops.speed.pi.limit
    assert integ_peak > 1.5 * limit if mode == "none" else integ_peak == limit


def test_the_old_integrator_stop_key_is_refused_naming_the_new_one():
    for old, new in (("pi_output", "'conditional'"), ("torque_setpoint", "'torque_setpoint'")):
        cfg = load_machine(ARROW, {"controller": {"speed_integrator_stop": old}})
        with pytest.raises(ConfigError, match=f"speed_integrator_stop = '{old}'.*moved.*"
                                              f"speed_antiwindup = {new}"):
            load_controller(cfg)
    cfg = load_machine(ARROW, {"controller": {"speed_integrator_stop": "often"}})
    with pytest.raises(ConfigError, match="arrow500_x.toml.*speed_antiwindup, one of "
                                          "'conditional', 'torque_setpoint', 'clamp', 'none'"):
        load_controller(cfg)


def test_hil_sim_and_identify_replay_agree_on_every_convention(tmp_path):
    """``hil sim`` (a separate process) on a machine file with all four conventions away
    from their defaults (current noise off: the dq motor's current loop would carry it);
    hil identify's replay of its trace through the same file gives the position back to
    one scale count.  The same trace replayed without the conventions misses by far more:
    the agreement is the conventions', not a coincidence of small effects."""
    truth = tmp_path / "conventions.toml"
    truth.write_text(patch_config(ARROW.read_text(), {"controller": CONVENTIONS,
                                                      "sensors": {"current_noise_a": 0.0}},
                                  "test: every convention"))
    program = tmp_path / "moves.nc"
    program.write_text(MOVES)
    done = subprocess.run([sys.executable, "-m", "hil.cli", "sim", str(truth), "--program",
                           str(program), "--out", str(tmp_path / "sim")],
                          capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    rec = load_record(tmp_path / "sim" / "trace.csv")
    cfg = load_machine(truth)
    count = cfg.sensors.scale_resolution_m
    same = replay(cfg, rec)
    assert same.status == 0
    assert np.abs(same.pos - rec.pos).max() <= count * (1 + 1e-9)
    plain = load_machine(ARROW, {"sensors": {"current_noise_a": 0.0}})
    assert np.abs(replay(plain, rec).pos - rec.pos).max() > 20 * count
