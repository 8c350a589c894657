"""The controller's conventions of a record (hil.identify.conventions, TraceController).

References:
* the header's keys: trace-format.md's table (units, ranges, what each key sets);
* TraceController against the emulator's own Controller fed the same feedback (open loop,
  so both see identical inputs): with every key at its default the two are the same; each
  convention changes exactly what it names, checked against an independent computation
  (scipy's lfilter for the speed filter, np.interp for the fine interpolation, a shifted
  array for the computation delay, the integrator by hand for the anti-windup modes);
* the pre-roll: a lock-step run that dwells before its trace starts is given back exactly
  by a replay told the dwell, not without it (a constant force sags the axis meanwhile).
"""

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from hil.controller.blocks import PI, ClampPI, WindupPI
from hil.controller.config import axis_limits, load_controller
from hil.controller.interpolator import ProfileSamples, plan
from hil.controller.nc import Controller
from hil.controller.program import parse_program
from hil.drive import EmulatedDrive
from hil.identify.conventions import (
    ConventionError,
    apply_conventions,
    read_conventions,
)
from hil.identify.record import Record, load_record
from hil.identify.replay import replay
from hil.identify.trace_controller import TraceController
from hil.sim import LockStep
from hil.trace_file import write_trace
from io_adapters.messages import Feedback, Setpoint
from plant import Plant
from plant import layout as L
from plant.config import load_machine
from tests.test_identify_replay import trace_columns

DATA = Path(__file__).parent / "data"
BASE = DATA / "ident_screw.toml"
ARROW = Path(__file__).parents[1] / "configs" / "arrow500_x.toml"


def _record(meta: dict) -> Record:
    t = np.arange(10) * 1e-3
    return Record(source="trace.csv", t=t, pos_set=t, pos=t, effort=t, effort_kind="iq",
                  meta=meta)


def test_header_keys_become_machine_file_keys():
    """trace-format.md's keys: cycle times in whole PWM periods (4 kHz here), the ADC's
    step 2 FS / 2^bits and its clipping at FS, the feed-forward factor as weight, the rest
    by name (``encoder_zero_at_start``'s true/false as a boolean)."""
    cfg = load_machine(BASE)
    conv = read_conventions(_record({
        "position_loop_sample_time_s": "0.002", "speed_loop_sample_time_s": "0.0005",
        "current_loop_sample_time_s": "0.00025", "feedforward_interpolation": "linear",
        "velocity_feedforward_factor": "0.8", "speed_actual_filter_s": "0.0008",
        "speed_antiwindup": "clamp", "current_delay_cycles": "1", "current_adc_bits": "12",
        "current_adc_full_scale_a": "20", "encoder_counts_per_rev": "4096",
        "scale_resolution_m": "1e-6", "preroll_s": "0.5", "vel_set_column": "speed_command",
        "encoder_rounding": "round", "encoder_zero_at_start": "true",
        "voltage_limit": "vector", "karnopp_reversal": "stop"}),
        cfg)
    assert conv.overrides == {
        "controller": {"position_cycle_ratio": 8, "ipo_cycle_ratio": 8, "speed_cycle_ratio": 2,
                       "feedforward_interpolation": "linear", "speed_ff": True,
                       "speed_ff_weight": 0.8, "speed_actual_filter_s": 0.0008,
                       "speed_antiwindup": "clamp", "current_delay_cycles": 1},
        "sensors": {"current_lsb_a": 40.0 / 4096, "current_full_scale_a": 20.0,
                    "encoder_counts_per_rev": 4096, "scale_resolution_m": 1e-6,
                    "encoder_rounding": "round", "encoder_zero_at_start": True},
        "motor": {"voltage_limit": "vector"}, "friction": {"karnopp_reversal": "stop"}}
    applied = apply_conventions(cfg, conv)
    assert (applied.sensors.current_full_scale_a, applied.sensors.encoder_zero_at_start,
            applied.motor.voltage_limit, applied.friction.karnopp_reversal) == (
        20.0, True, "vector", "stop")
    assert read_conventions(_record({"encoder_zero_at_start": "false"}), cfg).overrides == {
        "sensors": {"encoder_zero_at_start": False}}
    dq = read_conventions(_record({"voltage_limit": "q"}), load_machine(ARROW))
    assert dq.overrides == {"motor": {"voltage_limit": "q"}}
    assert conv.preroll_s == 0.5 and conv.vel_set_column == "speed_command"
    plain = read_conventions(_record({"machine": "x.toml"}), cfg)
    assert plain.overrides == {} and plain.preroll_s == 0.0
    assert plain.vel_set_column == "feedforward"


@pytest.mark.parametrize("meta,match", [
    ({"position_loop_sample_time_s": "0.0013"}, "position_loop_sample_time_s = 0.0013 s is "
                                                "not a whole number of the machine file's PWM"),
    ({"position_loop_sample_time_s": "0.0015"}, "neither is a whole multiple"),
    ({"current_loop_sample_time_s": "0.0005"}, "current loop runs once per PWM period"),
    ({"feedforward_interpolation": "spline"}, "feedforward_interpolation = 'spline': must be "
                                              "one of 'hold', 'linear'"),
    ({"speed_actual_filter_s": "-1"}, "speed_actual_filter_s = '-1': must be a number >= 0"),
    ({"current_adc_bits": "12"}, "current_adc_full_scale_a missing"),
    ({"current_adc_bits": "12.5", "current_adc_full_scale_a": "20"}, "must be a whole number"),
    ({"preroll_s": "soon"}, "preroll_s = 'soon'"),
    ({"vel_set_column": "command"}, "vel_set_column = 'command'"),
    ({"encoder_rounding": "nearest"}, ("encoder_rounding = 'nearest': must be one of "
                                       "'floor', 'round'")),
    ({"encoder_zero_at_start": "yes"}, ("encoder_zero_at_start = 'yes': must be one of "
                                        "'true', 'false'")),
    ({"current_adc_bits": "12", "current_adc_full_scale_a": "0"},
     "current_adc_full_scale_a = '0': must be a number >= 0.01"),
    ({"voltage_limit": "d"}, "voltage_limit = 'd': must be one of 'vector', 'q'"),
    ({"voltage_limit": "q"}, "ident_screw.toml has \\[motor\\] model = 'first_order'"),
    ({"karnopp_reversal": "slip"}, ("karnopp_reversal = 'slip': must be one of "
                                    "'breakaway', 'stop'")),
])
def test_a_convention_the_replay_cannot_honour_is_refused_naming_the_key(meta, match):
    with pytest.raises(ConventionError, match=match) as err:
        read_conventions(_record(meta), load_machine(BASE))
    assert str(err.value).startswith("trace.csv: ")  # the record's file


def test_plant_keys_of_the_header_reach_the_plants_kernel():
    """The header's voltage_limit and karnopp_reversal, applied to the machine file, set
    the kernel parameters the machine-file keys set (tests/test_plant_conventions.py
    checks those against analytic cases); without them the defaults (0) stay."""
    cfg = load_machine(ARROW)
    conv = read_conventions(_record({"voltage_limit": "q", "karnopp_reversal": "stop"}), cfg)
    params = Plant(apply_conventions(cfg, conv)).params
    assert params[L.P_U_Q_ONLY] == 1.0 and params[L.P_FR_REVERSAL_STOP] == 1.0
    plain = Plant(apply_conventions(cfg, read_conventions(_record({}), cfg))).params
    assert plain[L.P_U_Q_ONLY] == 0.0 and plain[L.P_FR_REVERSAL_STOP] == 0.0


def test_karnopp_reversal_stop_is_refused_without_karnopp_friction():
    """As the machine-file key is: 'stop' needs a Coulomb or breakaway level and no
    presliding model; 'breakaway' (the default) is accepted on any file."""
    frictionless = load_machine(BASE, {"friction": {"coulomb_n": 0.0}})
    with pytest.raises(ConventionError, match="karnopp_reversal = 'stop' needs Karnopp "
                                              "stick-slip friction.*no Coulomb"):
        read_conventions(_record({"karnopp_reversal": "stop"}), frictionless)
    assert read_conventions(_record({"karnopp_reversal": "breakaway"}), frictionless) \
        .overrides == {"friction": {"karnopp_reversal": "breakaway"}}


def test_identify_cli_refuses_a_bad_header_in_one_line(tmp_path):
    """`hil identify` prints the error naming the key and exits 2: no traceback."""
    n = 500
    cols = {"t_s": np.arange(n) * 1e-3, "pos_set_mm": np.zeros(n), "pos_mm": np.zeros(n),
            "iq_a": np.zeros(n)}
    trace = write_trace(tmp_path / "t.csv", cols, {"position_loop_sample_time_s": "0.0015"})
    done = subprocess.run([sys.executable, "-m", "hil.cli", "identify", str(trace), "--config",
                           str(BASE), "--out", str(tmp_path / "out"), "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "position_loop_sample_time_s" in done.stderr and "Traceback" not in done.stderr


def _open_loop(sec_over: dict, ticks: int = 400, rows=None, compiled: bool = True,
               turns_rad: float = 30.0):
    """The base Controller and a TraceController with ``sec_over``, both fed the same
    feedback sequence (a motor turning at a varying speed, counts of the config's
    encoder, ``turns_rad`` its amplitude) and the same setpoint ramp; the TraceController
    with the feed-forward ``rows`` = (values, ticks per row) when given.  Returns per tick (w_act, w_set,
    iq_ref, tick, v_set, ticks since the first position cycle of the points) of each."""
    cfg = load_machine(BASE)
    sec = load_controller(cfg)
    pwm = 1.0 / cfg.motor.pwm_frequency_hz
    base = Controller(cfg, pwm, 0.0, section=sec, compiled=compiled)
    mine = TraceController(cfg, pwm, 0.0, dataclasses.replace(sec, **sec_over),
                           compiled=compiled)
    n_ipo = ticks // sec.ipo_cycle_ratio + 2
    t = np.arange(n_ipo) * pwm * sec.ipo_cycle_ratio
    v = 0.05 * np.sin(2 * np.pi * 20 * t)
    ipo = ProfileSamples(t, np.cumsum(v) * pwm * sec.ipo_cycle_ratio, v, np.gradient(v, t))
    counts_per_rad = cfg.sensors.encoder_counts_per_rev / (2 * np.pi)
    out = {}
    for name, ctrl in (("base", base), ("mine", mine)):
        fb, sp = Feedback(), Setpoint()
        drive = EmulatedDrive(Plant(cfg))
        while not ctrl.enabled:  # a real drive enables; the feedback is synthetic after
            ctrl.tick(fb, sp)
            drive.cycle(sp, fb)
        if name == "mine" and rows is not None:
            ctrl.follow_feed_forward(*rows)
        n_pos = sec.position_cycle_ratio
        first = -(-ctrl.tick_count // n_pos) * n_pos
        ctrl.run_points(ipo)
        samples = []
        for k in range(ticks):
            theta = turns_rad * np.sin(2 * np.pi * 7 * k * pwm)
            fb.encoder_counts = float(np.floor(theta * counts_per_rad))
            fb.scale_counts = float(np.floor(theta * 0.01 / (2 * np.pi) / 5e-8))
            ctrl.tick(fb, sp)
            samples.append((ctrl.w_act, ctrl.w_set, sp.iq_ref_a, ctrl.tick_count - 1,
                            ctrl.v_set, ctrl.tick_count - 1 - first))
        out[name] = np.array(samples)
    return out, sec, pwm


def test_trace_controller_with_defaults_is_the_controller():
    out, _, _ = _open_loop({})
    np.testing.assert_array_equal(out["mine"], out["base"])


def test_speed_actual_filter_is_a_first_order_lag_of_the_measured_speed():
    tau = 0.002
    out, sec, pwm = _open_loop({"speed_actual_filter_s": tau})
    a = np.exp(-pwm * sec.speed_cycle_ratio / tau)
    raw = out["base"][:, 0]
    np.testing.assert_allclose(out["mine"][:, 0], lfilter([1 - a], [1, -a], raw), atol=1e-9)


def test_current_delay_shifts_the_current_setpoint_by_whole_pwm_periods():
    out, _, _ = _open_loop({"current_delay_cycles": 2})
    np.testing.assert_array_equal(out["mine"][2:, 2], out["base"][:-2, 2])
    assert np.all(out["mine"][:2, 2] == 0.0)


@pytest.mark.parametrize("mode", ["hold", "linear"])
@pytest.mark.parametrize("compiled", [True, False])
def test_feed_forward_follows_the_trace_rows_at_every_speed_cycle(mode, compiled):
    """trace-format.md: the speed loop takes ``vel_set`` per record row, held or linearly
    interpolated between the rows that bracket each speed sample, whatever the position
    cycle (4 PWM periods here; the rows every 2, each a step off its neighbours).  Against
    the base Controller fed the same feedback and setpoints (the same P part), the speed
    setpoint differs by the feed-forward factor times (the rows' value by np.interp or by
    index - the fine interpolator's held one) at every speed cycle from the points' first
    position cycle on; before it, not at all."""
    every = 2
    steps = np.where(np.arange(300) % 3 == 1, 0.02, -0.01)  # steps on odd and even rows
    # small turns: the speed command stays within the velocity limit
    out, sec, _ = _open_loop({"feedforward_interpolation": mode}, rows=(steps, every),
                             compiled=compiled, turns_rad=0.3)
    mine, base = out["mine"], out["base"]
    since = mine[:, 5].astype(int)
    started = since >= 0
    np.testing.assert_array_equal(mine[~started, 1], base[~started, 1])
    s = since[started]
    if mode == "linear":
        expected = np.interp(s, np.arange(steps.size) * every, steps)
    else:
        expected = steps[s // every]
    ratio = load_machine(BASE).mechanics.lead_m / (2 * np.pi)
    w_ff = sec.speed_ff_weight
    np.testing.assert_allclose((mine[started, 1] - base[started, 1]) * ratio,
                               w_ff * (expected - base[started, 4]), rtol=0, atol=1e-12)


def test_pi_antiwindup_modes_by_hand():
    """kp 1, ki T 0.5, limit 1, error 4 then -1: conditional (the emulator's PI) stops
    integrating into the limit, clamp holds the integrator at the limit, none winds up."""
    for cls, integ in ((PI, [0.0, -0.5]), (ClampPI, [1.0, 0.5]), (WindupPI, [2.0, 1.5])):
        pi = cls(1.0, 2.0, 1.0, 1.0)
        assert pi.step(4.0) == 1.0 and pi.integ == integ[0]
        pi.step(-1.0)
        assert pi.integ == integ[1], cls.__name__


def test_preroll_gives_back_a_trace_that_starts_after_a_dwell(tmp_path):
    """A 150 N constant force on the test screw axis: the lock-step run dwells 0.3 s, its
    trace is cut 0.2 s in.  The replay told ``preroll_s: 0.2`` gives it back to the
    current noise (positions exactly); without it the axis starts unsettled and the
    positions differ by the sag the speed integrator has not yet taken out."""
    over = {"table": {"external_force_n": 150.0}, "sensors": {"current_noise_a": 0.0}}
    cfg = load_machine(BASE, over)
    sec = load_controller(cfg)
    profile_prog = "G90 G71\nG4 F0.3\nG1 X10 F3000\nG4 F0.05\nM30\n"
    profile = plan(parse_program(profile_prog, "X", 0.0), axis_limits(cfg, sec))
    ls = LockStep(cfg, 0.0)
    ls.enable()
    ls.ctrl.run_profile(profile)
    res = ls.run(profile.duration_s + 0.05)
    cols = trace_columns(res, sec.position_cycle_ratio, cycle=sec.position_cycle_ratio)
    cut = int(round(0.2 / (sec.position_cycle_ratio / cfg.motor.pwm_frequency_hz)))
    cols = {k: (v[cut:] - v[cut]) if k == "t_s" else v[cut:] for k, v in cols.items()}
    preroll = float(cols["t_s"][1]) * cut  # the cut's time, a whole number of cycles
    rec = load_record(write_trace(tmp_path / "t.csv", cols,
                                  {"vel_set_column": "feedforward",
                                   "preroll_s": repr(preroll)}))
    rep = replay(cfg, rec)
    np.testing.assert_allclose(rep.pos, rec.pos, rtol=0, atol=1e-12)
    cold = replay(cfg, dataclasses.replace(rec, meta={**rec.meta, "preroll_s": "0"}))
    assert np.abs(cold.pos - rec.pos).max() > 20 * cfg.sensors.scale_resolution_m


def test_a_sample_time_off_the_pwm_clock_is_refused_naming_it():
    t = np.arange(200) * 1.3e-3  # 5.2 periods of 4 kHz
    rec = Record(source="trace.csv", t=t, pos_set=np.zeros(200), pos=np.zeros(200),
                 effort=np.zeros(200), effort_kind="iq")
    with pytest.raises(ConventionError, match="sample_time_s 0.0013 s is not a whole number"):
        replay(load_machine(BASE), rec)
