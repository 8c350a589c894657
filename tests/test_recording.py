"""The recording's parts in one process: the ring, the streams and their reader, the events
found in the rows, the percentile histogram, the run folder and the streaming loop, and
the checksums of the batches and the schema.

References: the values handed to the ring (read back exactly), brute-force runs of late
ticks, numpy's exact nearest-rank percentiles, the file system itself (a symlink's
target left untouched), pyarrow's message reader (where each batch lies in the file).  The processes (SIGKILL, a full disk, the exports of a real run)
are in ``test_recording_processes.py``.
"""

import argparse
import math
import os
from fractions import Fraction
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.drive import DriveSet, EmulatedDrive
from hil.rt.loop import Percentiles
from hil.runtime.emulator import Emulator, RuntimeConfig
from hil.runtime import export
from hil.runtime.export import export_csv
from hil.runtime.log_histogram import EXACT_NS, LogHistogram
from hil.runtime.record_reader import CorruptBatchError, Recording, RecordingError
from hil.runtime.record_trace import AxisTrace
from hil.runtime.record_writer import RING_S, RecordingWriter
from hil.runtime.recording import PLANT_DOCUMENTED, Recorder, column_specs, row_bytes
from hil.runtime.run_events import EventCollector, Overruns, RunEvent
from hil.runtime.run_folder import (
    EVENTS,
    RECORDING,
    REPORT,
    RESERVE_BYTES,
    RunFolder,
    RunFolderError,
)
from hil.runtime.stream_file import CRC_KEY, END_OF_STREAM
from hil.runtime.streaming_loop import StreamingLoop
from hil.runtime.watchdog import Watchdog
from hil.trace_file import read_trace
from io_adapters.messages import message_pair
from plant import OUTPUTS, Plant, load_machine
from tests.conftest import CONFIGS
from tests.runtime_helpers import batch_messages, reserve_held, write_unchecked_recording

ARROW = CONFIGS / "arrow500_x.toml"
PERIOD_NS = 125_000


@pytest.fixture(scope="module")
def plant() -> Plant:
    return Plant(load_machine(ARROW), table_pos=0.25)


class Rig:
    """A real drive, its ring and what each tick handed to it (the reference)."""

    def __init__(self, plant: Plant, slots: int):
        plant.reset(0.25)
        self.drives = DriveSet([EmulatedDrive(plant)])
        self.sp, self.fb = message_pair(1)
        self.recorder = Recorder(slots, ("screw",))
        self.times: dict[int, float] = {}

    def tick(self, k: int) -> None:
        self.sp.seq = k
        self.sp.iq_ref_a = 0.01 * k
        self.drives.cycle(self.sp, self.fb)
        self.recorder.record(k, k % 3 == 0, 1000 + k, self.sp, self.fb, self.drives)
        self.recorder.end_tick(k, 10 * k, 20 * k)
        self.times[k] = float(self.drives.drives[0].plant.out[OUTPUTS["time_s"]])


def test_the_ring_keeps_every_row_until_taken_and_counts_what_it_could_not_record(plant):
    """A ring of 4 rows, 6 ticks, nothing taken: rows 0-3 kept as they were handed over,
    ticks 4 and 5 counted as not recorded (never written over a row not yet taken); once
    the rows are taken the next tick goes into the first slot again."""
    rig = Rig(plant, slots=4)
    for k in range(6):
        rig.tick(k)
    rec = rig.recorder
    assert (rec.committed, rec.lost, rec.last_lost_tick) == (4, 2, 5)
    rows = rec.columns(0, 4)
    assert rows["tick"].tolist() == [0, 1, 2, 3]
    assert rows["sp_seq"].tolist() == [0, 1, 2, 3]
    assert rows["sp_new"].tolist() == [1, 0, 0, 1]
    assert rows["tick_start_ns"].tolist() == [1000, 0, 0, 1003]
    assert rows["lateness_ns"].tolist() == [0, 10, 20, 30]
    assert rows["plant_time_s"].tolist() == [rig.times[k] for k in range(4)]
    assert rows["sp_iq_ref_a"].tolist() == pytest.approx([0.0, 0.01, 0.02, 0.03])
    rec.release(4)
    rig.tick(6)
    assert rec.columns(4, 5)["tick"].tolist() == [6] and rec.common[0, 0] == 6


def test_every_plant_output_is_documented_with_a_unit():
    """Each plant output has a unit and a meaning in the recording (a new output must be
    added to hil.runtime.recording._PLANT), and the per-axis columns carry the axis letter."""
    assert set(PLANT_DOCUMENTED) == set(OUTPUTS)
    specs = column_specs(("screw", "rotary"), ("X", "C"))
    units = {c.name: c.unit for c in specs}
    assert units["X_plant_table_pos"] == "m" and units["C_plant_table_pos"] == "rad"
    assert all(c.unit and c.doc for c in specs)
    assert row_bytes(2) - row_bytes(1) == row_bytes(1) - row_bytes(0)


def _writer(folder: Path, rig: Rig, failures: list) -> RecordingWriter:
    watchdog = Watchdog(800, PERIOD_NS * 1e-9, lambda line: None)
    events = EventCollector(("X",), rig.drives, watchdog, rig.recorder)
    return RecordingWriter(RunFolder.open(folder), rig.recorder, events,
                           {"period_ns": PERIOD_NS, "axes": []}, PERIOD_NS, failures.append)


def test_the_streams_read_back_what_the_ring_held_in_whole_batches(plant, tmp_path):
    """Five flushes of rows of unequal length (the ring of 50 wrapping twice), then the
    end: the reader gives back every row exactly, in order, with its unit; the events
    stream holds the closing event; the file ends with the end-of-stream marker."""
    rig = Rig(plant, slots=50)
    failures: list = []
    writer = _writer(tmp_path, rig, failures)
    k = 0
    for n in (7, 50, 13, 44, 1):
        for _ in range(n):
            rig.tick(k)
            k += 1
        assert writer.flush()
    writer.stop([RunEvent(-1, "X", "emulator", "safe state", "test", cycle=123)])
    writer.folder.close()
    rec = Recording(tmp_path)
    rows = rec.read(["tick", "plant_time_s", "lateness_ns"])
    assert rows["tick"].tolist() == list(range(k))
    assert rows["plant_time_s"].tolist() == [rig.times[i] for i in range(k)]
    assert rows["lateness_ns"].tolist() == [10 * i for i in range(k)]
    assert rec.units["plant_time_s"] == "s" and rec.period_ns == PERIOD_NS
    assert rec.closed_cleanly() and not rec.truncated and failures == []
    ev = rec.events()
    assert (ev["kind"][-1], ev["cycle"][-1], ev["tick"][-1]) == ("safe state", 123, -1)
    assert writer.as_dict()["rows"] == k and writer.as_dict()["ticks_not_recorded"] == 0


@pytest.fixture(scope="module")
def written(plant, tmp_path_factory) -> tuple[Path, list[int], int]:
    """A recording of 6 flushes, one batch each (the ring never wraps), with the row count
    after each batch and the length of the schema message: the references."""
    folder = tmp_path_factory.mktemp("written")
    rig = Rig(plant, slots=256)
    writer = _writer(folder, rig, [])
    ends, k = [], 0
    for n in (5, 64, 3, 30, 17, 9):
        for _ in range(n):
            rig.tick(k)
            k += 1
        writer.flush()
        ends.append(k)
    writer.stop([])
    writer.folder.close()
    sink = pa.BufferOutputStream()
    pa.ipc.new_stream(sink, Recording(folder).schema).close()
    return folder / RECORDING, ends, sink.getvalue().size - len(END_OF_STREAM)


@settings(max_examples=40, deadline=None)
@given(share=st.floats(0.0, 1.0))
def test_a_cut_recording_reads_up_to_its_last_complete_batch(written, tmp_path_factory, share):
    """The file cut at any byte (as SIGKILL or a full disk leave it): past its schema it
    opens, and gives exactly the rows of the batches wholly before the cut -- never a
    partial batch, never garbage; it ends with the end-of-stream marker only uncut."""
    path, ends, schema_bytes = written
    data = path.read_bytes()
    folder = tmp_path_factory.mktemp("cut")
    cut = int(share * len(data))
    (folder / RECORDING).write_bytes(data[:cut])
    if cut < schema_bytes:
        with pytest.raises(RecordingError, match="cannot read the recording"):
            Recording(folder)
        return
    rec = Recording(folder)
    ticks = rec.read(["tick"])["tick"]
    assert ticks.size in [0, *ends]
    assert ticks.tolist() == list(range(ticks.size))
    assert rec.closed_cleanly() == (cut == len(data))


def _damaged(path: Path, folder: Path, edit) -> Path:
    """``path``'s run folder copied to ``folder``, its recording's bytes passed through
    ``edit`` (a bytearray changed in place)."""
    folder.mkdir()
    (folder / EVENTS).write_bytes((path.parent / EVENTS).read_bytes())
    data = bytearray(path.read_bytes())
    edit(data)
    (folder / RECORDING).write_bytes(bytes(data))
    return folder


def _flip(data: bytearray, first: int, n: int = 64) -> None:
    for i in range(first, first + n):
        data[i] ^= 0xFF


def test_every_batch_carries_a_crc_and_a_flipped_body_is_named_and_stopped_at(written,
                                                                              tmp_path):
    """The clean recording reads whole, every batch with its CRC-32.  64 bytes flipped in
    the middle of one batch's body (its values, compressed), for each batch in turn: the
    read stops there with the batch's index and first byte (reference: pyarrow's message
    reader) and the rows before it; asked to stop quietly, it gives exactly those rows
    and names the batch."""
    path, ends, _ = written
    messages = batch_messages(path)
    assert len(messages) == len(ends) + 1  # the empty batch after the schema, one per flush
    reader = pa.ipc.open_stream(pa.OSFile(str(path)))
    for _ in messages:
        assert CRC_KEY in reader.read_next_batch_with_custom_metadata().custom_metadata
    clean = Recording(path.parent)
    assert clean.checksums and clean.read(["tick"])["tick"].size == ends[-1]
    for index, (start, body, end) in enumerate(messages[1:], 1):
        folder = _damaged(path, tmp_path / f"batch{index}",
                          lambda data: _flip(data, (body + end) // 2 - 32))
        before = ends[index - 2] if index > 1 else 0
        with pytest.raises(CorruptBatchError, match=rf"{RECORDING}: batch {index} \(at byte "
                           rf"{start}\) is corrupt: .*; the {before} rows before it"):
            Recording(folder).read()
        rec = Recording(folder)
        assert rec.read(["tick"], stop_at_corrupt=True)["tick"].tolist() == list(range(before))
        error = rec.corrupt[RECORDING]
        assert (error.index, error.offset, error.rows_before) == (index, start, before)
        assert not rec.truncated


def test_a_corrupt_batch_is_told_from_a_cut_off_end(written, tmp_path):
    """A batch whose metadata length was raised past the end of a file closed with its end
    marker is corrupt, not cut off; in a file cut inside its last batch (no end marker) a
    batch before it with a flipped body is corrupt too, while the partial last batch
    alone reads as the cut-off end."""
    path, ends, _ = written
    messages = batch_messages(path)
    start, body, end = messages[3]

    def long_metadata(data: bytearray) -> None:
        data[start + 4:start + 8] = (2**31 - 8).to_bytes(4, "little")

    with pytest.raises(CorruptBatchError, match="batch 3 "):
        Recording(_damaged(path, tmp_path / "long", long_metadata)).read()
    last = messages[-1]
    cut = (last[1] + last[2]) // 2

    def flipped_and_cut(data: bytearray) -> None:
        _flip(data, (body + end) // 2 - 32)
        del data[cut:]

    with pytest.raises(CorruptBatchError, match="batch 3 "):
        Recording(_damaged(path, tmp_path / "flipped", flipped_and_cut)).read()
    rec = Recording(_damaged(path, tmp_path / "cut", lambda data: data.__delitem__(
        slice(cut, None))))
    assert rec.read(["tick"])["tick"].size == ends[-2] and rec.truncated


def test_a_changed_byte_in_the_schema_is_refused(written, tmp_path):
    """The run's metadata edited in place (its period, still valid JSON): refused as a
    corrupt schema, not read with the wrong period."""
    path, _, _ = written

    def edit(data: bytearray) -> None:
        at = data.index(b'"period_ns": 125000') + len(b'"period_ns": 12500')
        data[at] = ord("1")

    with pytest.raises(RecordingError, match=r"the schema .* is corrupt: CRC-32 [0-9a-f]{8} "
                                             r"stored, [0-9a-f]{8} computed"):
        Recording(_damaged(path, tmp_path / "schema", edit))


def test_a_recording_of_the_format_before_the_checksums_reads_unchecked(tmp_path, capsys):
    """A recording of format 'hil-recording 1' (no CRC anywhere, pyarrow's plain writer)
    reads whole, says it has no checksums, and hil export says so on stderr."""
    rec = Recording(write_unchecked_recording(tmp_path, rows=50))
    assert not rec.checksums and rec.read(["tick"])["tick"].tolist() == list(range(50))
    parser = argparse.ArgumentParser()
    export.add_arguments(parser)  # hil export's own options, whatever they become
    args = parser.parse_args([str(tmp_path), "--to", "mdf4", "--out", str(tmp_path / "r.mf4")])
    assert export.run_from_args(args) == 0
    assert "carries no checksums" in capsys.readouterr().err


def _late_runs(excess: np.ndarray) -> list[tuple[int, int]]:
    """(first row, count) of each run of consecutive rows with excess > 0, by a loop."""
    runs, start = [], None
    for i, e in enumerate(excess):
        if e > 0 and start is None:
            start = i
        if e <= 0 and start is not None:
            runs.append((start, i - start))
            start = None
    if start is not None:
        runs.append((start, len(excess) - start))
    return runs


@settings(max_examples=60, deadline=None)
@given(late=st.lists(st.booleans(), min_size=1, max_size=80),
       cuts=st.lists(st.integers(1, 79), max_size=6))
def test_overrun_events_are_the_runs_of_late_ticks_across_batches(late, cuts):
    """Ticks ending after the next deadline (lateness + compute > period), seen a batch at
    a time: one event per run of consecutive late ticks with its first tick and count,
    whatever the batch boundaries (reference: a loop over the whole run)."""
    n = len(late)
    lateness = np.where(late, PERIOD_NS, 0).astype(np.int64)
    compute = np.full(n, 1, dtype=np.int64)
    tick = np.arange(n, dtype=np.int64) + 100
    scanner, out = Overruns(PERIOD_NS), []
    bounds = [0, *sorted({c for c in cuts if c < n}), n]
    for a, b in zip(bounds, bounds[1:]):
        scanner.scan(tick[a:b], lateness[a:b], compute[a:b], out)
    scanner.close(out)
    want = _late_runs(lateness + compute - PERIOD_NS)
    assert [(e.tick - 100, e.count) for e in out] == want
    assert all(e.kind == "overrun" and e.source == "loop" for e in out)


@settings(max_examples=60, deadline=None)
@given(values=st.lists(st.one_of(st.integers(0, 3000), st.integers(0, 10 ** 10)), min_size=1,
                       max_size=400))
def test_the_histogram_percentiles_are_within_their_stated_precision(values):
    """p50/p99/p99.9 of the log histogram against numpy's exact nearest rank: exact below
    1024 ns, otherwise at most 1/512 below the exact value and never above; the maximum
    exact.  Added in two parts, as the writer adds batches."""
    v = np.array(values, dtype=np.int64)
    hist = LogHistogram()
    hist.add(v[: v.size // 2])
    hist.add(v[v.size // 2:])
    got, exact = hist.percentiles_us(), Percentiles.of_ns_in_us(v)
    assert got.max == exact.max
    for name in ("p50", "p99", "p999"):
        g, e = getattr(got, name) * 1e3, getattr(exact, name) * 1e3
        if e < EXACT_NS:
            assert g == pytest.approx(e, abs=1e-6)
        else:
            assert e * (1 - 1 / 512) - 1e-6 <= g <= e + 1e-6


# --- the run folder -----------------------------------------------------------------------

def test_a_symlink_planted_in_the_run_folder_is_never_written_through(tmp_path):
    """A symlink planted under a run file's name after the folder was checked: creating the
    file fails (O_EXCL | O_NOFOLLOW) and the symlink's target keeps its bytes; report.json
    written over a symlink replaces the link, not its target."""
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    folder = RunFolder.open(tmp_path / "run")
    try:
        os.symlink(target, tmp_path / "run" / RECORDING)
        with pytest.raises(FileExistsError):
            folder.create(RECORDING)
        os.symlink(target, tmp_path / "run" / REPORT)
        folder.write_json(REPORT, {"ok": 1})
    finally:
        folder.close()
    assert target.read_text() == "keep me"
    assert not (tmp_path / "run" / REPORT).is_symlink()
    assert (tmp_path / "run" / REPORT).read_text().strip().startswith("{")


def test_a_previous_run_is_kept_unless_forced_and_then_its_links_not_their_targets_go(tmp_path):
    """A folder holding a run file (here a symlink) is refused naming the file and --force;
    with force the entries go (the link itself) and the target stays."""
    target = tmp_path / "elsewhere.arrows"
    target.write_bytes(b"someone else's data")
    run = tmp_path / "run"
    run.mkdir()
    os.symlink(target, run / RECORDING)
    (run / EVENTS).write_bytes(b"old")
    with pytest.raises(RunFolderError, match=r"holds a run \(recording.arrows, events.arrows\); "
                                             "give --force"):
        RunFolder.open(run)
    RunFolder.open(run, force=True).close()
    assert not os.path.lexists(run / RECORDING) and not (run / EVENTS).exists()
    assert target.read_bytes() == b"someone else's data"


def test_the_run_folder_refuses_a_file_and_says_the_space_it_lacks(tmp_path):
    """A file where the folder should be, and a recording larger than the free space:
    each refused with the path and, for the space, both figures; the reserve is taken on
    the disk, held by its descriptor under no name (a reserve an older version left is
    removed), and given back at close."""
    (tmp_path / "file").write_text("x")
    with pytest.raises(RunFolderError, match="exists and is not a folder"):
        RunFolder.open(tmp_path / "file")
    reserve = tmp_path / "run" / ".hil-run-reserve"
    with RunFolder.open(tmp_path / "run") as folder:
        free = folder.free_bytes()
        with pytest.raises(RunFolderError, match=r"free, the recording needs about .* \(why\)"):
            folder.check_space(2 * free + 1e9, "why")
        reserve.write_bytes(b"left by a killed run of an older version")
        folder.hold_reserve()
        assert not os.path.lexists(reserve)
        assert reserve_held(os.getpid()) >= RESERVE_BYTES  # allocated, not sparse
    assert reserve_held(os.getpid()) == 0 and not os.path.lexists(reserve)


# --- the streaming loop -------------------------------------------------------------------

class Sink:
    def __init__(self):
        self.ticks: list[int] = []

    def end_tick(self, k: int, lateness_ns: int, compute_ns: int) -> None:
        assert lateness_ns >= 0 and compute_ns >= 0
        self.ticks.append(k)


def test_the_streaming_loop_runs_until_asked_to_stop_and_hands_every_tick_over():
    """Without a tick count it runs until a stop request (here from its own step at tick
    50): ticks 0..50 stepped and handed to the sink, in order, and nothing kept per tick."""
    sink = Sink()
    stepped: list[int] = []

    def step(k: int) -> None:
        stepped.append(k)
        if k == 50:
            loop.request_stop()

    loop = StreamingLoop(1_000_000, step, sink)
    stats = loop.run()
    assert stepped == sink.ticks == list(range(51))
    assert stats.ticks == 51 and stats.stopped_by == "stop_flag"
    assert stats.lateness_ns.size == 0 and stats.compute_ns.size == 0


def test_a_day_long_run_holds_no_more_in_memory_than_a_second_long_one(tmp_path):
    """--duration 86400 at 8 kHz (691 million ticks; the old in-memory buffers would have been
    205 GB): the emulator's ring and loop are those of a 1 s run (reference: the same
    emulator built for 1 s), about a second of rows."""
    def built(duration_s: float) -> Emulator:
        rc = RuntimeConfig(machine_file=ARROW, adapter_url="udp://127.0.0.1:0",
                           run_dir=tmp_path / "run", duration_s=duration_s, realtime=False)
        return Emulator(rc, load_machine(ARROW))

    day, second = built(86400.0), built(1.0)
    assert day.timing.n_ticks == 86400 * 8000 and day.loop.n_ticks == day.timing.n_ticks
    sizes = [sum(a.nbytes for a in (e.recorder.common, e.recorder.ints, e.recorder.floats))
             for e in (day, second)]
    assert sizes[0] == sizes[1] and day.recorder.slots == math.ceil(RING_S * 8000)
    assert not hasattr(day.loop, "lateness_ns")


def test_the_csv_export_keeps_a_uniform_time_base_across_missing_ticks(plant, tmp_path):
    """Ticks 10-14 without a row (as the skip overrun policy leaves them): the servo trace
    has a row of NaN for each, so the trace reader (which insists on a uniform time base
    from 0) opens it and finds the gap where it was."""
    rig = Rig(plant, slots=64)
    writer = _writer(tmp_path / "run", rig, [])
    for k in [*range(10), *range(15, 20)]:
        rig.tick(k)
    writer.stop([])
    writer.folder.close()
    trace = AxisTrace(name="X", prefix="", rotary=False, table_per_count=1e-9,
                      scale_resolution_m=1e-6, period_s=PERIOD_NS * 1e-9)
    out = export_csv(Recording(tmp_path / "run"), tmp_path / "trace.csv", trace)
    read = read_trace(out)
    assert read.sample_time_s == pytest.approx(PERIOD_NS * 1e-9)
    gap = np.isnan(read.data["iq_a"])
    assert np.flatnonzero(gap).tolist() == list(range(10, 15)) and read.data["t_s"].size == 20


def test_the_csv_export_prints_times_and_counts_as_their_exact_decimals(plant, tmp_path):
    """200 ticks of 125 us with the table at 123.4567 mm: each t_s is the exact decimal of
    tick * 125 us (tick 36 at 0.0045, not 36 * 0.000125 = 0.0045000000000000005 in
    floats), pos_mm the exact decimal of the 0.1 um scale's counts, and motor_pos_mm the
    float nearest the encoder's counts times 10 mm / 2**22 (reference: Python's exact
    fractions); the events' times likewise."""
    rig = Rig(plant, slots=256)
    plant.reset(0.1234567)
    writer = _writer(tmp_path / "run", rig, [])
    for k in range(200):
        rig.tick(k)
    writer.stop([])
    writer.folder.close()
    trace = AxisTrace(name="X", prefix="", rotary=False, table_per_count=0.01 / 2 ** 22,
                      scale_resolution_m=1e-7, period_s=PERIOD_NS * 1e-9)
    rec = Recording(tmp_path / "run")
    out = export_csv(rec, tmp_path / "trace.csv", trace)
    lines = [line.split(",") for line in out.read_text().splitlines() if line[0] not in "#t"]
    text = dict(zip(trace.names(), zip(*lines)))
    rows = rec.read(["tick", "plant_scale_counts", "plant_encoder_counts"])
    ticks = rows["tick"].tolist()
    assert ticks == list(range(200)) and "0.0045" in text["t_s"]
    assert [Fraction(t) for t in text["t_s"]] == [Fraction(k * PERIOD_NS, 10 ** 9)
                                                  for k in ticks]
    assert [Fraction(p) for p in text["pos_mm"]] == [
        Fraction(int(c), 10_000) for c in rows["plant_scale_counts"]]
    assert [float(p) for p in text["motor_pos_mm"]] == [
        float(Fraction(int(c) * 10, 2 ** 22)) for c in rows["plant_encoder_counts"]]
    events, _ = export.export_events_csv(rec, tmp_path / "events.csv")
    for row in events.read_text().splitlines()[1:]:
        t_s, tick = row.split(",")[:2]
        assert t_s == "" or Fraction(t_s) == Fraction(int(tick) * PERIOD_NS, 10 ** 9), row
