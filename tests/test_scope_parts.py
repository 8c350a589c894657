"""``hil scope``'s parts without a browser: following a recording as it grows
(hil/runtime/record_follow.py), min/max per pixel (hil/scope/envelope.py), the trigger
(hil/scope/trigger.py), the status panel's figures (RunStatus with traces) and the page's
view of a run (hil/scope/view.py), each against values computed here from the rows written.
"""

import json
import os
import subprocess

import numpy as np
import pyarrow as pa
import pytest

from hil.cia402 import SW_OPERATION_ENABLED, ModeOfOperation, State
from hil.runtime.record_follow import Follower
from hil.runtime.record_reader import CorruptBatchError, Recording
from hil.runtime.record_trace import axis_trace
from hil.runtime.run_events import EVENT_COLUMNS
from hil.runtime.run_status import RunStatus
from hil.runtime.stream_file import END_OF_STREAM, FORMAT, ArrowStream, schema_of
from hil.scope.envelope import Envelope
from hil.scope.trigger import Trigger
from hil.scope.view import KEEP_S, STOPPED_AFTER_S, KeptRows, ScopeView
from tests.runtime_helpers import ENV, EXIT_S, python_module

PERIOD_NS = 1_000_000
#: table metres per encoder count of the synthetic axis
PER_COUNT = 1e-6
ROWS_PER_BATCH = 250


def _columns(n: int, start: int = 0) -> dict[str, np.ndarray]:
    """``n`` ticks of one CSP axis from tick ``start``: the position a sine of 10 mm, the
    target 0.1 mm ahead of it, a setpoint every tick but each 50th (and sequence numbers
    that skip one there), the statusword with Operation enabled."""
    tick = np.arange(start, start + n, dtype=np.int64)
    pos = 0.01 * np.sin(tick * 1e-3)
    sp_new = (tick % 50 != 49).astype(np.uint8)
    return {"tick": tick, "lateness_ns": np.full(n, 10_000, np.int64),
            "compute_ns": np.full(n, 100_000, np.int64), "sp_new": sp_new,
            "sp_seq": tick.astype(np.uint32), "sp_mode": np.full(n, 8, np.int8),
            "fb_statusword": np.full(n, 0x1237, np.uint16), "fb_fault": np.zeros(n, np.uint16),
            "drive_state": np.full(n, int(State.OPERATION_ENABLED), np.uint8),
            "sp_target_position_counts": (pos + 1e-4) / PER_COUNT,
            "sp_target_velocity_counts_s": np.zeros(n), "sp_velocity_offset_counts_s":
                np.zeros(n), "sp_iq_ref_a": np.zeros(n), "plant_encoder_counts": pos / PER_COUNT,
            "plant_scale_counts": np.zeros(n), "plant_table_pos": pos,
            "plant_table_vel": np.zeros(n), "plant_iq_meas_a": np.cos(tick * 1e-3)}


UNITS = {"plant_table_pos": "m", "plant_table_vel": "m/s", "plant_iq_meas_a": "A",
         "sp_target_position_counts": "counts", "plant_encoder_counts": "counts"}


def _stream(folder, n_batches: int) -> tuple[ArrowStream, pa.Schema]:
    """recording.arrows in ``folder`` as the writer makes it, ``n_batches`` written, the
    stream left open (a run going on); events.arrows beside it, without events."""
    meta = json.dumps({"format": FORMAT, "period_ns": PERIOD_NS, "axes": [
        {"name": "X", "prefix": "", "kind": "screw", "table_per_count": PER_COUNT,
         "scale_resolution_m": 0.0}]}).encode()
    cols = _columns(1)
    schema = schema_of([(k, v.dtype.name, UNITS.get(k, "-"), "") for k, v in cols.items()],
                       meta)
    path = folder / "recording.arrows"
    stream = ArrowStream(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), str(path),
                         schema)
    for i in range(n_batches):
        _write(stream, schema, i)
    events = folder / "events.arrows"
    ArrowStream(os.open(events, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), str(events),
                schema_of([(k, *v) for k, v in EVENT_COLUMNS.items()], meta)).close()
    return stream, schema


def _write(stream: ArrowStream, schema: pa.Schema, i: int) -> None:
    cols = _columns(ROWS_PER_BATCH, i * ROWS_PER_BATCH)
    stream.write(pa.RecordBatch.from_arrays([pa.array(v) for v in cols.values()],
                                            schema=schema))


def test_the_follower_reads_each_flushed_batch_once_and_waits_for_a_partial_one(tmp_path):
    """Polls between writes return exactly the new rows; a batch whose bytes are not all
    on disk yet is left for a later poll; the end marker ends the stream; ``read`` gives
    the rows of chosen spans again."""
    stream, schema = _stream(tmp_path, 3)
    follow = Follower(Recording(tmp_path))
    rows = follow.poll(["tick"])
    assert rows["tick"].tolist() == list(range(3 * ROWS_PER_BATCH))
    assert follow.poll(["tick"]) is None and not follow.ended
    _write(stream, schema, 3)
    path = tmp_path / "recording.arrows"
    whole = path.read_bytes()
    cut = tmp_path / "cut"
    cut.mkdir()
    # the same stream with its last batch half written: not read until it is whole
    (cut / "recording.arrows").write_bytes(whole[:len(whole) - 100])
    partial = Follower(Recording(cut))
    assert partial.poll(["tick"])["tick"].size == 3 * ROWS_PER_BATCH
    assert partial.poll(["tick"]) is None
    (cut / "recording.arrows").write_bytes(whole)
    assert partial.poll(["tick"])["tick"][0] == 3 * ROWS_PER_BATCH
    assert follow.poll(["tick"], max_batches=1)["tick"].size == ROWS_PER_BATCH
    stream.close()
    assert path.read_bytes().endswith(END_OF_STREAM)
    assert follow.poll(["tick"]) is None and follow.ended
    again = [r["tick"] for r in follow.read(follow.spans_between(260, 510), ["tick"])]
    assert [a[0] for a in again] == [250, 500]


def test_the_follower_stops_at_a_corrupt_batch(tmp_path):
    """A flipped byte in a batch not read yet: the poll raises the error the reader
    raises for the whole file."""
    stream, _ = _stream(tmp_path, 2)
    stream.close()
    follow = Follower(Recording(tmp_path))
    follow.poll(["tick"], max_batches=1)
    second = Follower(Recording(tmp_path))
    second.poll(["tick"])
    data = bytearray((tmp_path / "recording.arrows").read_bytes())
    # a byte in the middle of the second (last) batch, before the end marker
    data[(second.spans[1].offset + len(data) - len(END_OF_STREAM)) // 2] ^= 0xFF
    (tmp_path / "recording.arrows").write_bytes(bytes(data))
    with pytest.raises(CorruptBatchError) as read:
        Recording(tmp_path).read(["tick"])
    with pytest.raises(CorruptBatchError) as followed:
        follow.poll(["tick"])
    assert str(followed.value) == str(read.value)  # the reader's words: batch, rows before


def test_the_envelope_keeps_a_one_sample_spike_and_each_pixels_extremes():
    """Against min and max computed per bin by hand: a spike one sample wide in 10^6
    samples reaches its full height at 1000 pixels."""
    t = np.arange(1_000_000) * 1e-5
    y = np.sin(t)
    y[123_457] = 50.0
    env = Envelope(0.0, 10.0, 1000, ["y"])
    for start in range(0, t.size, 4096):  # batch by batch, as a recording is read
        env.add(t[start:start + 4096], {"y": y[start:start + 4096]})
    times, kept, values = env.curve()
    assert kept.size == 1000 and times.size == values["y"].size == 2000
    assert values["y"].max() == 50.0
    bins = y.reshape(1000, 1000)
    assert np.array_equal(values["y"][0::2], bins.min(axis=1))
    assert np.array_equal(values["y"][1::2], bins.max(axis=1))
    with pytest.raises(ValueError, match="t1_s > t0_s"):
        Envelope(1.0, 1.0, 10, ["y"])


def test_the_trigger_fires_on_the_first_crossing_after_it_was_armed():
    t = np.arange(10) * 0.1
    y = np.array([0, 0, 1, 1, 0, 0, 1, 1, 0, 0], float)
    assert Trigger("y", 0.5).first(t, y, after_s=-1.0) == pytest.approx(0.2)
    assert Trigger("y", 0.5).first(t, y, after_s=0.2) == pytest.approx(0.6)
    assert Trigger("y", 0.5, slope="falling").first(t, y, -1.0) == pytest.approx(0.4)
    assert Trigger("y", 0.5, slope="either").first(t, y, 0.4) == pytest.approx(0.6)
    assert Trigger("y", 2.0).first(t, y, -1.0) is None
    assert Trigger("y", 0.5, pre=0.25).window(1.0, 2.0) == (0.5, 2.5)
    for bad in ({"slope": "up"}, {"mode": "auto"}, {"pre": 1.5}, {"level": float("nan")}):
        with pytest.raises(ValueError):
            Trigger(**{"channel": "y", "level": 0.5, **bad})


def test_the_panel_counts_following_error_statusword_and_setpoints_never_applied(tmp_path):
    """The following error is the CSP target less the encoder position (0.1 mm here), in
    the trace's mm; each 50th tick's setpoint is missing, its sequence number skipped."""
    stream, _ = _stream(tmp_path, 1)
    stream.close()
    rec = Recording(tmp_path)
    status = RunStatus(PERIOD_NS, rec.units, traces={"": axis_trace(rec, "X")})
    cols = _columns(1000)
    cols["sp_seq"] = np.cumsum(cols["sp_new"]).astype(np.uint32) + np.arange(1000) // 50
    status.add({k: cols[k] for k in status.columns()})
    panel = status.panel()
    now, position, unit = panel["axes"]["axis"]
    assert now.following_error == pytest.approx(0.1, abs=1e-6)
    assert now.following_error_max == pytest.approx(0.1, abs=1e-6)
    assert now.statusword & SW_OPERATION_ENABLED and now.mode == ModeOfOperation.CSP
    assert (position, unit) == (pytest.approx(cols["plant_table_pos"][-1] * 1e3), "mm")
    # ticks 49, 99, ..., 999 had none; the numbers skipped after each but the last
    assert panel["link"]["ticks_without"] == 20 and not panel["link"]["silent"]
    assert panel["link"]["skipped_setpoints"] == 19


def test_kept_rows_hold_what_concatenating_and_cutting_holds():
    """KeptRows appends in place and drops the rows that age out by an index; after every
    batch it holds exactly what joining the batches and cutting before the keep limit
    gives (the plain way it replaced), through growth, moves to the front and batches
    longer than the kept span."""
    rng = np.random.default_rng(7)
    kept = KeptRows({"tick": np.empty(0, np.int64), "x": np.empty(0)})
    plain = {"tick": np.empty(0, np.int64), "x": np.empty(0)}
    tick, moves = 0, 0
    for _ in range(400):
        n = int(rng.integers(1, 300))
        rows = {"tick": np.arange(tick, tick + n), "x": rng.normal(size=n)}
        tick += n
        keep_from = tick - int(rng.integers(50, 500))
        before = kept._data["tick"]
        kept.extend(rows, keep_from)
        moves += kept._data["tick"] is before and kept._lo == 0
        plain = {k: np.concatenate([plain[k], rows[k]]) for k in plain}
        start = np.searchsorted(plain["tick"], keep_from)
        plain = {k: v[start:] for k, v in plain.items()}
        for k in plain:
            assert np.array_equal(kept[k], plain[k]) and kept[k].dtype == plain[k].dtype
    assert moves > 0  # the kept rows did move to the front in place
    assert kept._data["tick"].size <= 2 * (500 + 300)


def test_the_view_keeps_a_bounded_buffer_and_draws_the_same_curve_from_it_or_the_file(
        tmp_path):
    """The buffer holds at most KEEP_S of the chosen channels however long the run; a span
    the buffer holds draws the same curve as when it is read back from the recording;
    the whole run reaches from its first row to its last."""
    n_batches = int(1.5 * KEEP_S / (ROWS_PER_BATCH * PERIOD_NS * 1e-9))
    stream, _ = _stream(tmp_path, n_batches)
    stream.close()
    view = ScopeView(tmp_path, pixels=500)
    both = ["plant_table_pos", "plant_iq_meas_a"]
    view.choose(both, None)
    view.update()
    assert view.samples.full  # more batches wait: a channel dropped and added meanwhile
    view.choose(["plant_table_pos"], None)
    assert set(view.buffer) == {"tick", "plant_table_pos"} and view.update()
    view.choose(both, None)  # read back from the recording
    assert set(view.buffer) == {"tick", *both}
    assert view.buffer["plant_iq_meas_a"].size == view.buffer["tick"].size
    while view.update():
        pass
    assert view.state() == "ended"
    kept_s = (view.buffer["tick"][-1] - view.buffer["tick"][0]) * 1e-3
    assert kept_s <= KEEP_S
    end = view.end_s
    from_buffer = view.curve(end - 10.0, end)
    view.buffer = {"tick": np.empty(0, np.int64)}  # now only the file has the rows
    from_file = view.curve(end - 10.0, end)
    for name in from_buffer.values:
        assert np.array_equal(from_buffer.values[name], from_file.values[name])
    whole = view.whole()
    pixel_s = (end + 1e-3) / 500
    assert whole.t_s.min() < pixel_s and whole.t_s.max() > end - pixel_s


def test_a_run_cut_short_reads_up_to_its_last_whole_batch_and_shows_as_stopped(tmp_path):
    """A recording without its end marker whose last batch is half written (SIGKILL): the
    view reads the whole batches, says live while the file may still grow, and stopped
    once it has not grown for STOPPED_AFTER_S (a clock of the test's)."""
    stream, schema = _stream(tmp_path, 3)
    _write(stream, schema, 3)
    path = tmp_path / "recording.arrows"
    path.write_bytes(path.read_bytes()[:-100])  # the 4th batch cut, no end marker
    now = [0.0]
    view = ScopeView(tmp_path, pixels=100, clock=lambda: now[0])
    view.choose(["plant_table_pos"], None)
    while view.update():
        pass
    assert view.state() == "live"
    now[0] = STOPPED_AFTER_S + 0.5
    view.update()
    assert view.state() == "stopped"
    assert view.status.last_tick == 3 * ROWS_PER_BATCH - 1
    end_s = view.end_s
    pixel_s = (end_s + 1e-3) / 100
    assert view.whole().t_s.max() > end_s - pixel_s  # the last whole batch's rows drawn


def test_hil_scope_refuses_a_folder_without_a_recording(tmp_path):
    """Bad input: exit status 2 and a line naming the folder, before any server starts."""
    done = subprocess.run(python_module("hil.cli", "scope", tmp_path), env=ENV,
                          capture_output=True, text=True, timeout=EXIT_S)
    assert done.returncode == 2, done.stderr
    assert f"{tmp_path}: no recording.arrows" in done.stderr


def test_the_scope_bench_lists_each_segments_p999_in_the_order_they_ran():
    """hil bench scope's per-segment figures follow the segments' order (closed, open,
    closed, open), whatever the grouping by page state, and its text shows them."""
    import numpy as np

    from hil.bench.scope import _in_turn, text
    bounds = [(False, 0, 1), (True, 1, 2), (False, 2, 3), (True, 3, 4)]
    groups = {False: [np.array([1]), np.array([3])], True: [np.array([2]), np.array([4])]}
    assert [int(a[0]) for a in _in_turn(groups, bounds)] == [1, 2, 3, 4]
    q = {"p50": 0.0, "p99": 0.0, "p999": 1.0, "max": 1.0}
    r = {"config": "c", "rate_hz": 8000, "segments": 2, "seconds": 10.0, "closed": {
        "ticks": 1, "lateness_us": q}, "open": {"ticks": 1, "lateness_us": q},
        "ratio_p999": 1.0, "ok": True, "scope_cpu_s": 1.0, "page_updates": 1,
        "each_segment": [{"page": "closed", "lateness_p999_us": 587.7},
                         {"page": "open", "lateness_p999_us": 2386.6}]}
    assert text(r).endswith("p99.9 per segment, in turn, µs: 587.7 (closed), 2386.6 (open)")
