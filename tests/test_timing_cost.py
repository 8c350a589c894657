"""The timing cost (:mod:`hil.replay.timing`) on a constructed run whose every figure is
known by hand: the drive ticks, setpoint sequence numbers and positions are written so
that the alignment phase, the late and missed setpoints, the following-error difference
each run of them caused and the tolerance can be counted on paper.

The run (Arrow 500 X, 8 kHz: T = 125 µs, position cycle 16 ticks, scale feedback):
controller tick k reads drive tick k + 100 (D); setpoint s is due at drive tick s + 3; the
lock-step's path moves at 0.1 m/s with a constant following error; the replay equals the
lock-step but for +10 scale counts on drive ticks 600..639.  Drive tick 300 receives
nothing and 301 the setpoint after the one due (one missed); drive tick 600 receives
nothing, 601 the one due at 600 (late by one tick) and 602 the one due there (the one due
at 601 missed).
"""

import math

import numpy as np
import pytest

from hil.controller.nc import Controller
from hil.replay.timing import LOOP_PEAK, timing_cost
from hil.trace_file import write_trace
from plant.config import load_machine
from tests.runtime_helpers import ARROW

T = 125e-6
D = 100           # drive tick read - controller tick
E = 3             # drive tick - sequence number of the setpoint due there
N_CTRL = 1000     # controller ticks recorded
N_DRIVE = 1200
V = 0.1           # m/s, the path's speed
FE = 50e-6        # m, the lock-step's following error
BUMP = 10         # scale counts added to the replay on drive ticks 600..639


@pytest.fixture(scope="module")
def cfg():
    return load_machine(ARROW)


def run(cfg, tmp_path, one_way_ns: np.ndarray | None = None, late_ns: int = 30_000,
        emulator_late_ns: int = 0, lost: range = range(0)):
    ctrl = Controller(cfg, T)
    res = ctrl.scale_res
    assert res > 0.0 and ctrl.polarity == 1.0 and ctrl.sec.position_cycle_ratio == 16
    tick = np.arange(N_DRIVE, dtype=np.int64)
    k = np.arange(N_CTRL, dtype=np.int64)
    pos_set = V * k * T
    counts_ls = np.round((pos_set - FE) / res)          # the lock-step's measured position
    counts = np.zeros(N_DRIVE)
    counts[k + D] = counts_ls
    counts[600:640] += BUMP
    seq = tick - E
    new = np.ones(N_DRIVE, dtype=np.uint8)
    # nothing at 300 and 600; 301 takes its own (the one due at 300 missed); 601 takes the
    # one due at 600 (a tick late), 602 its own (the one due at 601 missed)
    for t_none, t_next, seq_next in ((300, 301, 301 - E), (600, 601, 600 - E)):
        new[t_none] = 0
        seq[t_none] = seq[t_none - 1]
        seq[t_next] = seq_next
    sp_t = 10**9 + tick * 125_000
    one_way = np.full(N_DRIVE, 20_000) if one_way_ns is None else one_way_ns
    rec = {"tick": tick, "lateness_ns": np.where(tick == 1000, emulator_late_ns, 0),
           "sp_new": new, "sp_seq": seq.astype(np.uint32),
           "sp_t_ns": np.where(new == 1, sp_t, 0),
           "sp_rx_ns": np.where(new == 1, sp_t + one_way, 0),
           "plant_time_s": (tick + 1) * T, "plant_scale_counts": counts,
           "plant_encoder_counts": np.zeros(N_DRIVE)}
    keep = ~np.isin(tick, lost)  # rows the recording's writer lost
    rec = {name: values[keep] for name, values in rec.items()}
    lateness = np.zeros(N_CTRL, dtype=np.int64)
    lateness[700] = late_ns
    npz = {"k": k, "tick": k.astype(float), "fb_new": np.ones(N_CTRL, dtype=np.int64),
           "lag_ticks": np.zeros(N_CTRL, dtype=np.int64), "fb_time_s": (k + D + 1) * T,
           "lateness_ns": lateness}
    rows = k[k % 16 == 0]
    trace = write_trace(tmp_path / "lockstep.csv", {
        "t_s": rows * T, "pos_set_mm": pos_set[rows] * 1e3,
        "pos_mm": counts_ls[rows] * res * 1e3}, {})
    return timing_cost(rec, npz, trace, cfg, T), res


def test_late_and_missed_setpoints_are_counted_per_run(cfg, tmp_path):
    cost, _ = run(cfg, tmp_path)
    # the program's rows read drive ticks 100 .. 100 + 992: 993 setpoints due there
    assert (cost.setpoints, cost.late, cost.early, cost.missed, cost.held_ticks) == (
        993, 1, 0, 2, 2)
    assert cost.on_time == 990
    first, second = cost.runs
    assert (first.first_tick, first.setpoints, first.missed, first.late) == (300, 1, 1, 0)
    assert (second.first_tick, second.setpoints, second.missed, second.late,
            second.worst_ticks) == (600, 2, 1, 1, 1)


def test_the_following_error_difference_is_the_bump_and_goes_to_its_run(cfg, tmp_path):
    cost, res = run(cfg, tmp_path)
    # the replay is BUMP counts ahead on drive ticks 600..639: rows k = 512 and 528
    assert cost.diff_max == pytest.approx(BUMP * res, rel=1e-9)
    assert cost.diff_max_t_s == pytest.approx(512 * T)
    # elsewhere equal: to the mm <-> m round trip of the trace file
    assert cost.runs[0].fe_diff == pytest.approx(0.0, abs=1e-15)
    assert cost.runs[1].fe_diff == pytest.approx(BUMP * res)
    assert cost.clean_diff == pytest.approx(0.0, abs=1e-15)
    assert cost.fe_max_lockstep == pytest.approx(FE, abs=res)


def test_the_tolerance_follows_from_the_transport_delay_and_jitter(cfg, tmp_path):
    one_way = np.full(N_DRIVE, 20_000)
    one_way[500] = 80_000
    cost, res = run(cfg, tmp_path, one_way)
    t = cost.tolerance
    assert (t.delay_s, t.jitter_s, t.controller_lateness_s, t.emulator_lateness_s) == \
        pytest.approx((20e-6, 60e-6, 30e-6, 0.0))
    assert t.late_ticks == 1  # 110 µs < T
    assert t.v_max == pytest.approx(V) and t.a_max == pytest.approx(0.0, abs=1e-6)
    assert t.value == pytest.approx(LOOP_PEAK * V * T + 2 * res)
    assert cost.within  # 1 µm of bump against 25 µm
    one_way[500] = 300_000  # 330 µs with the controller's lateness: three ticks
    t = run(cfg, tmp_path, one_way)[0].tolerance
    assert t.late_ticks == math.ceil(330e-6 / T) == 3
    assert t.value == pytest.approx(LOOP_PEAK * V * 3 * T + 2 * res)
    # a drive tick 1 ms late in the program (drive tick 1000): 1.33 ms, eleven ticks
    t = run(cfg, tmp_path, one_way, emulator_late_ns=1_000_000)[0].tolerance
    assert t.emulator_lateness_s == pytest.approx(1e-3) and t.late_ticks == 11


def test_ticks_without_a_row_say_nothing_about_their_setpoints(cfg, tmp_path):
    cost, _ = run(cfg, tmp_path, lost=range(800, 810))
    assert (cost.setpoints, cost.on_time, cost.late, cost.missed) == (983, 980, 1, 2)
