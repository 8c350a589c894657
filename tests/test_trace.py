"""The triggered trace recorder (hil.measure.trace) against hand-built signals whose
trigger sample and kept samples are worked out by hand, and the servo-trace CSV file
(hil.trace_file) against the format of docs/trace-format.md: exact round trips and
errors that name the file, the line and the column."""

import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.measure.trace import (
    TraceConfigError,
    TraceNotDoneError,
    TraceRecorder,
    Trigger,
)
from hil.trace_file import IDENTIFICATION, TraceFormatError, read_trace, write_trace

DT_S = 0.001


def feed(recorder: TraceRecorder, rows) -> None:
    """Feed rows through one preallocated array, as a controller cycle would."""
    values = np.zeros(len(recorder.names))
    for row in rows:
        values[:] = row
        recorder.record(values)


def ramp_rows(n: int):
    """Signal a = 0, 1, 2, ... and b = 100 - a."""
    return [(float(k), 100.0 - k) for k in range(n)]


# --- recorder -----------------------------------------------------------------------

def test_level_rising_keeps_the_samples_before_the_crossing():
    """a = 0 .. 9, rising through 4.5: first sample >= 4.5 after one below is a = 5, so
    with 3 pre-trigger samples and depth 6 the recording is a = 2, 3, 4 | 5, 6, 7."""
    rec = TraceRecorder(("a", "b"), depth=6, pre_trigger=3,
                        trigger=Trigger.level("a", 4.5), dt_s=DT_S)
    feed(rec, ramp_rows(10))
    out = rec.result()
    assert out.data["a"].tolist() == [2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    assert out.data["b"].tolist() == [98.0, 97.0, 96.0, 95.0, 94.0, 93.0]
    assert out.trigger_index == 3 and out.data["a"][out.trigger_index] == 5.0
    assert out.t_s.tolist() == [k * DT_S for k in range(6)]
    assert out.trigger_time_s == pytest.approx(3 * DT_S)


def test_level_threshold_reached_exactly_triggers_and_falling_direction():
    """Rising: previous < threshold <= this, so reaching 5.0 exactly triggers at a = 5;
    falling through 96.5 on b = 100 - a triggers at b = 96 (a = 4)."""
    rising = TraceRecorder(("a", "b"), 3, 1, Trigger.level("a", 5.0), DT_S)
    falling = TraceRecorder(("a", "b"), 3, 1, Trigger.level("b", 96.5, "falling"), DT_S)
    for rec in (rising, falling):
        feed(rec, ramp_rows(20))
    assert rising.result().data["a"].tolist() == [4.0, 5.0, 6.0]
    assert falling.result().data["a"].tolist() == [3.0, 4.0, 5.0]


def test_level_either_direction_and_wrong_direction_ignored():
    """x = 0, 2, 0, -2, 0: a falling trigger at 1 fires at x = 0 (third sample), not on
    the rising crossing; 'either' fires on the rising one at x = 2."""
    rows = [(0.0,), (2.0,), (0.0,), (-2.0,), (0.0,), (5.0,)]
    falling = TraceRecorder(("x",), 2, 1, Trigger.level("x", 1.0, "falling"), DT_S)
    either = TraceRecorder(("x",), 2, 1, Trigger.level("x", 1.0, "either"), DT_S)
    feed(falling, rows)
    feed(either, rows)
    assert falling.result().data["x"].tolist() == [2.0, 0.0]
    assert either.result().data["x"].tolist() == [0.0, 2.0]


def test_trigger_waits_until_the_pre_trigger_samples_are_in():
    """A crossing at sample 1 comes before 3 pre-trigger samples exist: it is ignored and
    the next crossing (sample 5) triggers."""
    rows = [(0.0,), (1.0,), (0.0,), (0.0,), (0.0,), (1.0,), (1.0,), (0.0,)]
    rec = TraceRecorder(("x",), 5, 3, Trigger.level("x", 0.5), DT_S)
    feed(rec, rows)
    assert rec.result().data["x"].tolist() == [0.0, 0.0, 0.0, 1.0, 1.0]


def test_edge_trigger_on_a_control_bit_change():
    """A status word 0x0237 whose bit 3 (fault, 0x0008) sets at sample 4: an edge trigger
    on it with 2 pre-trigger samples keeps samples 2..5; an unchanged signal never
    triggers."""
    words = [0x0237] * 4 + [0x023F] * 6
    rows = [(float(w), float(k)) for k, w in enumerate(words)]
    rec = TraceRecorder(("status", "k"), 4, 2, Trigger.edge("status"), DT_S)
    feed(rec, rows)
    assert rec.result().data["k"].tolist() == [2.0, 3.0, 4.0, 5.0]
    quiet = TraceRecorder(("status", "k"), 4, 2, Trigger.edge("status"), DT_S)
    feed(quiet, [(float(0x0237), float(k)) for k in range(50)])
    assert not quiet.triggered and not quiet.done


def test_immediate_trigger_records_the_first_depth_samples():
    """Immediate: the recording is samples 0 .. depth-1, trigger index = pre_trigger; the
    recorder is done exactly at sample depth-1 and ignores later samples."""
    rec = TraceRecorder(("a", "b"), 5, 2, Trigger(), DT_S)
    feed(rec, ramp_rows(4))
    assert rec.triggered and not rec.done
    feed(rec, ramp_rows(5)[4:])
    assert rec.done
    feed(rec, [(99.0, 99.0)] * 3)
    out = rec.result()
    assert out.data["a"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0] and out.trigger_index == 2


def test_reset_rearms_the_recorder():
    """After reset the recorder waits for a new crossing: a = 20.. (above 10.5, no
    crossing), then a = 0, 1, ... crosses at 11: recording 11, 12, 13."""
    rec = TraceRecorder(("a", "b"), 3, 0, Trigger.level("a", 10.5), DT_S)
    feed(rec, ramp_rows(20))
    rec.reset()
    assert not rec.triggered and not rec.done
    feed(rec, [(20.0 + k, 0.0) for k in range(5)] + ramp_rows(15))
    assert rec.result().data["a"].tolist() == [11.0, 12.0, 13.0]


@settings(max_examples=60, deadline=None)
@given(depth=st.integers(1, 40), data=st.data())
def test_recording_equals_the_fed_values(depth, data):
    """Property: for random signals, depth and pre-trigger, the recording is the fed
    values around the first armed rising crossing of 0.5 (found by a plain search)."""
    pre = data.draw(st.integers(0, depth - 1))
    n = data.draw(st.integers(depth, 3 * depth + 5))
    x = np.array(data.draw(st.lists(st.sampled_from([0.0, 1.0, 0.25, 0.75]), min_size=n,
                                    max_size=n)))
    rec = TraceRecorder(("x", "y"), depth, pre, Trigger.level("x", 0.5), DT_S)
    feed(rec, zip(x, -x))
    start = [k for k in range(max(pre, 1), n) if x[k - 1] < 0.5 <= x[k]]
    if start and start[0] + depth - pre <= n:
        k = start[0]
        out = rec.result()
        assert np.array_equal(out.data["x"], x[k - pre:k - pre + depth])
        assert np.array_equal(out.data["y"], -x[k - pre:k - pre + depth])
    else:
        assert not rec.done


def test_record_allocates_no_array():
    """record() keeps writing into the one buffer allocated at construction."""
    rec = TraceRecorder(("a", "b"), 64, 8, Trigger.level("a", 1e9), DT_S)
    buffer = rec._buffer
    feed(rec, ramp_rows(300))
    assert rec._buffer is buffer and buffer.shape == (64, 2) and buffer.dtype == np.float64


@pytest.mark.parametrize("make", [
    lambda: Trigger("window"),
    lambda: Trigger.level("a", 1.0, "up"),
    lambda: Trigger("level"),
    lambda: Trigger.level("a", math.nan),
    lambda: TraceRecorder(("a",), 4, 4, Trigger(), DT_S),
    lambda: TraceRecorder(("a", "a"), 4, 0, Trigger(), DT_S),
    lambda: TraceRecorder(("t_s",), 4, 0, Trigger(), DT_S),
    lambda: TraceRecorder(("a",), 4, 0, Trigger.edge("b"), DT_S),
    lambda: TraceRecorder(("a",), 4, 0, Trigger(), 0.0),
])
def test_impossible_configurations_refused(make):
    """Unknown kind or direction, a level trigger without a signal, a NaN threshold,
    pre_trigger = depth, repeated names, t_s as a signal, a trigger signal that is not
    recorded, zero sample time."""
    with pytest.raises(TraceConfigError):
        make()


def test_result_before_done_refused():
    """result() before the recording is complete raises (a RuntimeError)."""
    rec = TraceRecorder(("a",), 4, 0, Trigger(), DT_S)
    with pytest.raises(TraceNotDoneError, match="not finished"):
        rec.result()


# --- trace file ---------------------------------------------------------------------

def identification_columns(n: int = 50, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {"t_s": np.arange(n) * 0.000125, "pos_set_mm": rng.normal(size=n) * 1e3,
            "pos_mm": rng.normal(size=n) / 3.0, "iq_a": rng.normal(size=n) * 1e-7,
            "vel_mm_min": rng.normal(size=n) * 500.0}


def test_round_trip_is_exact_and_keeps_metadata_and_comments(tmp_path):
    """write → read gives every value bit for bit (repr printing), the metadata with
    sample_time_s added, and the comment lines outside the data."""
    cols = identification_columns()
    path = write_trace(tmp_path / "x.csv", cols, {"axis": "X", "source": "test run 1"},
                       comments=("recorded by the test", "second comment"))
    trace = read_trace(path, require=IDENTIFICATION)
    assert trace.names == tuple(cols)
    for name, values in cols.items():
        assert np.array_equal(trace.column(name), values), name
    assert trace.metadata == {"sample_time_s": "0.000125", "axis": "X", "source": "test run 1"}
    assert trace.comments == ("recorded by the test", "second comment")
    assert trace.sample_time_s == 0.000125 and trace.n_samples == 50


def test_recording_round_trip(tmp_path):
    """A recorder's result written and read back: same columns, t_s and sample time."""
    rec = TraceRecorder(("pos_set_mm", "pos_mm", "iq_a"), 20, 5,
                        Trigger.level("pos_set_mm", 1.05), 0.003)
    feed(rec, [(0.1 * k, 0.09 * k, math.sin(k)) for k in range(40)])
    out = rec.result()
    trace = read_trace(write_trace(tmp_path / "r.csv", out), require=IDENTIFICATION)
    assert np.array_equal(trace.t_s, out.t_s) and trace.sample_time_s == 0.003
    for name in out.names:
        assert np.array_equal(trace.column(name), out.data[name])


def read_text(folder, text: str, **kwargs):
    """Write ``text`` as a trace file in ``folder`` and read it."""
    path = folder / "trace.csv"
    path.write_text(text)
    return read_trace(path, **kwargs)


def test_si_accessors(tmp_path):
    """Hand-computed: 1500 mm = 1.5 m, 60000 mm/min = 1 m/s, 180 deg = π rad,
    10800 deg/min = 180 deg/s = π rad/s, A unchanged."""
    text = ("# sample_time_s: 0.5\nt_s,pos_mm,vel_mm_min,pos_deg,vel_deg_min,iq_a\n"
            "0.0,1500.0,60000.0,180.0,10800.0,2.5\n")
    trace = read_text(tmp_path, text)
    assert trace.si("pos_mm")[0] == pytest.approx(1.5)
    assert trace.si("vel_mm_min")[0] == pytest.approx(1.0)
    assert trace.si("pos_deg")[0] == pytest.approx(math.pi)
    assert trace.si("vel_deg_min")[0] == pytest.approx(math.pi)
    assert trace.si("iq_a")[0] == 2.5 and trace.si("t_s")[0] == 0.0


def test_missing_required_column_named_with_file_and_line(tmp_path):
    """No iq_a (nor force_n): the error names the column, the file and the header line
    (line 2, after one metadata line); without require= the same file reads."""
    path = tmp_path / "no_iq.csv"
    path.write_text("# axis: X\nt_s,pos_set_mm,pos_mm\n0.0,0.0,0.0\n0.001,0.0,0.0\n")
    with pytest.raises(TraceFormatError) as err:
        read_trace(path, require=IDENTIFICATION)
    assert "'iq_a'" in str(err.value) and f"{path}:2:" in str(err.value)
    assert read_trace(path).names == ("t_s", "pos_set_mm", "pos_mm")


def test_non_uniform_time_named_with_line(tmp_path):
    """A dropped sample (t jumps from 0.002 to 0.004) is reported at its line (header on
    line 2, so sample 3 is line 6)."""
    path = tmp_path / "gap.csv"
    path.write_text("# sample_time_s: 0.001\nt_s,x_mm\n0.0,1\n0.001,2\n0.002,3\n0.004,4\n")
    expected = re.escape(f"{path}:6: t_s steps from 0.002 to 0.004")
    with pytest.raises(TraceFormatError, match=expected):
        read_trace(path)


def test_metadata_sample_time_must_match_t_s(tmp_path):
    """sample_time_s 0.002 against steps of 0.001: refused at the first step."""
    path = tmp_path / "dt.csv"
    path.write_text("# sample_time_s: 0.002\nt_s,x_mm\n0.0,1\n0.001,2\n0.002,3\n")
    with pytest.raises(TraceFormatError, match=r":4: .*sample_time_s"):
        read_trace(path)
    path.write_text("# sample_time_s: 0.002\nt_s,x_mm\n0.0,1\n0.0020000001,2\n0.004,3\n")
    assert read_trace(path).sample_time_s == 0.002


@pytest.mark.parametrize("body, message", [
    ("t_s,x_mm\n0.0,1\n0.001,1,5\n", ":3: 3 values, the header has 2"),
    ("t_s,x_mm\n0.0,1\n0.001,\"2\"\n", ":3: column 'x_mm': bad value '\"2\"'"),
    ("t_s,x_mm\n0.0,1\n0.001;2\n", ":3: 1 values"),
    ("t_s,x_mm,x_mm\n0.0,1,1\n", ":1: column 'x_mm' appears twice"),
    ("t_s,x_mm\n", "no data rows"),
    ("# only: comments\n", "no header row"),
    ("t_s,x_mm\n0.5,1\n0.501,1\n", ":2: t_s starts at 0.5"),
    ("t_s,x_mm\n0.0,1\n0.001,1\n0.002,1\n0.0035,1\n", ":5: t_s steps from 0.002 to 0.0035"),
    ("t_s,x_mm\n0.0,1\n0.001,1\nnan,1\n0.003,1\n", ":4: t_s is nan"),
    ("# sample_time_s: fast\nt_s,x_mm\n0.0,1\n", "sample_time_s 'fast'"),
    ("x_mm,y_mm\n0.0,1\n", "required column 't_s' missing"),
])
def test_bad_files_refused_with_line_and_value(tmp_path, body, message):
    """Each broken file gives a TraceFormatError naming the file and the line, value or
    column (line numbers counted by hand from the text)."""
    path = tmp_path / "bad.csv"
    path.write_text(body)
    with pytest.raises(TraceFormatError) as err:
        read_trace(path)
    assert str(path) in str(err.value) and message in str(err.value), str(err.value)


def test_extra_columns_kept(tmp_path):
    """Columns outside the format (temperature_c, ctrl_word) are read and kept."""
    text = ("t_s,pos_set_mm,pos_mm,iq_a,temperature_c,ctrl_word\n"
            "0.0,0,0,0,21.5,6\n0.1,0,0,0,21.6,7\n")
    trace = read_text(tmp_path, text, require=IDENTIFICATION)
    assert trace.column("temperature_c").tolist() == [21.5, 21.6]
    assert trace.column("ctrl_word").tolist() == [6.0, 7.0]
    with pytest.raises(TraceFormatError, match="'ctrl_word' has no unit suffix"):
        trace.si("ctrl_word")


def test_rotary_axis_deg_columns_accepted(tmp_path):
    """pos_set_deg and pos_deg stand in for pos_set_mm and pos_mm (rotary axes)."""
    text = "t_s,pos_set_deg,pos_deg,iq_a\n0.0,90,90,1\n0.1,91,90.5,1\n"
    trace = read_text(tmp_path, text, require=IDENTIFICATION)
    assert trace.resolve("pos_mm") == "pos_deg"
    assert trace.si(trace.resolve("pos_set_mm")).tolist() == pytest.approx(
        [math.pi / 2.0, math.radians(91.0)])


def test_linear_motor_force_in_place_of_current(tmp_path):
    """force_n satisfies the iq_a requirement (linear motors); iq_a itself is absent."""
    text = "t_s,pos_set_mm,pos_mm,force_n\n0.0,0,0,120\n0.1,0,0,121\n"
    trace = read_text(tmp_path, text, require=IDENTIFICATION)
    assert trace.resolve("iq_a") == "force_n" and trace.si("force_n").tolist() == [120.0, 121.0]
    with pytest.raises(KeyError, match="no column 'iq_a'"):
        trace.column("iq_a")


@pytest.mark.parametrize("metadata, comments", [
    ({"bad key": 1}, ()), ({"k": "two\nlines"}, ()), ({}, ("looks: like metadata",)),
])
def test_writer_refuses_what_would_not_read_back(tmp_path, metadata, comments):
    """A key with a space, a two-line value, a comment that reads as metadata."""
    with pytest.raises(TraceFormatError):
        write_trace(tmp_path / "w.csv", identification_columns(3), metadata, comments)


def test_writer_refuses_unequal_columns_and_missing_time(tmp_path):
    """Columns of different lengths, or no t_s column: refused."""
    with pytest.raises(TraceFormatError, match="shape"):
        write_trace(tmp_path / "w.csv", {"t_s": [0.0, 1.0], "x_mm": [1.0]})
    with pytest.raises(TraceFormatError, match="'t_s'"):
        write_trace(tmp_path / "w.csv", {"x_mm": [1.0]})
