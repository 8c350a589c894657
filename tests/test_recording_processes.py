"""``hil run``'s recording with real processes: SIGKILL, a full disk, the run folder's
checks and its reserve, the events of a run, and what reads the recording (``hil
report``, also of a run cut short, ``hil identify``, ``hil export`` to MDF4 and CSV), and
a corrupt batch met by ``hil export`` and ``hil report``.

References: the feedback the test itself received (SIGKILL), the per-tick rows of the same
recording and report.json (events), the soak master's sine (identify), asammdf opening
the MDF4 file and the servo-trace reader opening the CSV, the recording's own values
(exports, the report of a run cut short), /proc (the reserve), pyarrow's message reader
(a corrupt batch's place).  No wall-clock duration is asserted; every wait is bounded;
children reaped.
"""

import csv
import json
import os
import resource
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from hil.cia402 import EnableSequencer, State, statusword_state
from hil.identify.record import load_record
from hil.report.latency import load_run
from hil.runtime.arrow import pa
from hil.runtime.record_reader import Recording
from hil.runtime.record_writer import RING_S
from hil.runtime.run_folder import EVENTS, RECORDING, REPORT, RESERVE_BYTES
from hil.runtime.soak_master import AMPLITUDE_M
from hil.runtime.watchdog import FAULT_WATCHDOG
from hil.trace_file import read_trace
from io_adapters import Feedback, Setpoint, open_endpoint
from plant import Plant, load_machine
from tests.runtime_helpers import (
    ARROW,
    ENV,
    EXIT_S,
    READY_S,
    SLOW_2KHZ,
    Children,
    batch_messages,
    machine_variant,
    python_module,
    reserve_held,
    terminate,
)

LIMIT = 200          # watchdog cycles: 0.1 s at 2 kHz
START_MM = 250.0     # mid travel
MASTER_S = 1.5       # the soak master's CSP sine
RESEND_S = 0.5       # a setpoint without an answer is sent again after this long


@pytest.fixture(scope="module")
def slow_config(tmp_path_factory) -> Path:
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


@pytest.fixture(scope="module")
def warm_cache():
    """The plant compiled in this process first, so that a child loads numba's cache and
    writes nothing big (the file-size limit below would refuse a cache file)."""
    Plant(load_machine(ARROW))


def _answer(ep, sp: Setpoint, fb: Feedback, n: int, seq: EnableSequencer | None = None) -> None:
    """``n`` feedbacks, each answered by a setpoint (controlword from ``seq``); a setpoint
    is sent again when no feedback comes within RESEND_S: a drive whose watchdog tripped
    while this process was held up by a loaded machine answers only once it hears again."""
    sp.seq += 1
    ep.send_setpoint(sp)
    for _ in range(n):
        for _ in range(int(EXIT_S / RESEND_S)):
            if ep.recv_feedback(fb, RESEND_S):
                break
            ep.send_setpoint(sp)
        else:
            raise AssertionError("the emulator stopped answering")
        sp.seq += 1
        if seq is not None:
            sp.controlword = seq.next_controlword(fb.statusword)
        ep.send_setpoint(sp)


def _run(tmp_path: Path, config: Path, *extra, **popen) -> subprocess.CompletedProcess:
    """``hil run`` to its end (bounded)."""
    return subprocess.run(python_module("hil.runtime.emulator", config, "--adapter",
                                        "udp://127.0.0.1:0", "--no-rt", *extra),
                          env=ENV, capture_output=True, text=True, timeout=READY_S, **popen)


# --- a run with events, a CSP stretch and a clean end: read by report, identify, export --

@pytest.fixture(scope="module")
def run_dir(slow_config, tmp_path_factory) -> Path:
    """The test enables the drive over UDP, falls silent (the watchdog trips, the drive
    faults), comes back until it sees FAULT; then the soak master resets the fault,
    enables and drives a CSP sine for MASTER_S and disables; then SIGTERM."""
    folder = tmp_path_factory.mktemp("events")
    run = folder / "run"
    sp, fb = Setpoint(), Feedback()
    with Children(folder) as children:
        proc, url = children.emulator(slow_config, "udp://127.0.0.1:0", run,
                                      "--watchdog-cycles", LIMIT, "--start", START_MM)
        with open_endpoint(url, "controller") as ep:
            seq = EnableSequencer(timeout_cycles=200)
            for _ in range(10):  # again if a loaded machine held this process too long
                seq.enable()
                _answer(ep, sp, fb, 200, seq)
                if statusword_state(fb.statusword) == State.OPERATION_ENABLED:
                    break
            assert statusword_state(fb.statusword) == State.OPERATION_ENABLED
            threading.Event().wait(1.0)  # silent: 2000 ticks at 2 kHz, the limit is 200
            _answer(ep, sp, fb, 1)  # heard again: the drive answers, in its fault reaction
            for _ in range(4000):
                if statusword_state(fb.statusword) == State.FAULT:
                    break
                _answer(ep, sp, fb, 1)
            assert statusword_state(fb.statusword) == State.FAULT
        master = children.start("master", python_module(
            "hil.runtime.soak_master", slow_config, "--adapter", url, "--rate", 2000,
            "--seconds", MASTER_S, "--out", folder / "master", "--no-rt"))
        assert master.wait(timeout=READY_S) == 0, children.log("master")
        assert terminate(proc) == 0, children.log("emulator")
    return run


def _events(run: Path) -> list[dict]:
    ev = Recording(run).events()
    return [{k: v[i] for k, v in ev.items()} for i in range(ev["tick"].size)]


def test_the_events_carry_their_tick_cycle_and_reason(run_dir):
    """Watchdog trip and recovery, the drive's fault (8250h, with its drive cycle) and its
    reset, the safe state with the cycle it was reached in, why the run stopped -- each
    as report.json has it, and the fault where the per-tick rows show it."""
    events = _events(run_dir)
    report = json.loads((run_dir / REPORT).read_text())
    kinds = [(e["source"], e["kind"]) for e in events]
    for want in [("watchdog", "tripped"), ("watchdog", "recovered"), ("drive", "fault"),
                 ("drive", "fault reset"), ("emulator", "safe state"), ("emulator", "stopped")]:
        assert want in kinds, (want, kinds)
    trip = next(e for e in events if e["kind"] == "tripped")
    fault = next(e for e in events if e["kind"] == "fault")
    first = report["faults"]["X"]["events"][0]
    assert (fault["code"], fault["cycle"]) == (FAULT_WATCHDOG, first["cycle"]) == (
        first["code"], first["cycle"])
    assert fault["tick"] == trip["tick"] >= 0 and "watchdog" in fault["reason"].lower()
    assert trip["t_s"] == pytest.approx(trip["tick"] * 1 / 2000)
    rows = Recording(run_dir).read(["tick", "fb_fault"])
    assert rows["fb_fault"][rows["tick"] == fault["tick"]][0] == FAULT_WATCHDOG
    assert rows["fb_fault"][rows["tick"] == fault["tick"] - 1][0] == 0
    safe = next(e for e in events if e["kind"] == "safe state")
    assert (safe["tick"], safe["cycle"]) == (-1, report["safe_state"]["cycle"])
    assert "SWITCH_ON_DISABLED" in safe["reason"]
    stopped = next(e for e in events if e["kind"] == "stopped")
    assert stopped["reason"].endswith("SIGTERM/SIGINT")
    assert report["recording"]["events"] == len(events)


def test_the_metadata_holds_the_machine_file_runtime_and_adapter(run_dir, slow_config):
    """The recording's metadata: the machine file's text, the runtime settings, the URL."""
    meta = Recording(run_dir).meta
    assert meta["machine_files"] == {str(slow_config): slow_config.read_text()}
    assert meta["runtime"]["watchdog_cycles"] == LIMIT
    assert meta["adapter"].startswith("udp://127.0.0.1:") and meta["period_ns"] == 500_000


def test_hil_report_reads_the_recording(run_dir):
    """hil report's reader: one slot per deadline, all of them ran (no skip policy)."""
    run = load_run(run_dir)
    report = json.loads((run_dir / REPORT).read_text())
    assert run.lateness_ns.size == report["loop"]["ticks"] == report["recording"]["rows"]


def test_hil_identify_reads_the_csp_stretch(run_dir):
    """hil identify's loader takes the longest CSP stretch with the drive enabled: the soak
    master's sine, whose position setpoint swings by its amplitude (reference:
    soak_master.AMPLITUDE_M) about where the axis stood, in SI on the run's grid."""
    rec = load_record(run_dir)
    assert rec.t.size >= 0.9 * MASTER_S * 2000
    assert np.diff(rec.t) == pytest.approx(1 / 2000)
    swing = (rec.pos_set.max() - rec.pos_set.min()) / 2
    assert swing == pytest.approx(AMPLITUDE_M, rel=0.02)
    assert abs(np.mean(rec.pos_set) - START_MM / 1000) < AMPLITUDE_M
    assert np.max(np.abs(rec.pos - rec.pos_set)) < 1e-3  # the drive's loops follow it


def test_the_mdf4_export_opens_with_asammdf_with_units_and_comments(run_dir, tmp_path):
    """hil export --to mdf4: asammdf opens it; every channel has the recording's values,
    unit and meaning, on the time tick * period; the statusword reads as its bits' names;
    the CSP target (the soak master's counts) has its twin in m, on the table's position
    while enabled, within the drive's following (reference: the plant's position); the events
    are a channel group; the machine file is attached."""
    from asammdf import MDF

    out = tmp_path / "run.mf4"
    done = subprocess.run(python_module("hil.cli", "export", run_dir, "--to", "mdf4", "--out",
                                        out), env=ENV, capture_output=True, text=True,
                          timeout=EXIT_S)
    assert done.returncode == 0, done.stderr
    rec = Recording(run_dir)
    rows = rec.read(["tick", "plant_table_pos", "lateness_ns", "fb_statusword", "sp_mode",
                     "drive_state"])
    with MDF(out) as mdf:
        pos = mdf.get("plant_table_pos")
        assert pos.unit == "m" and pos.comment == rec.docs["plant_table_pos"]
        np.testing.assert_array_equal(pos.samples, rows["plant_table_pos"])
        np.testing.assert_allclose(pos.timestamps, rows["tick"] * 5e-4)
        assert mdf.get("lateness_ns").unit == "ns"
        np.testing.assert_array_equal(mdf.get("fb_statusword", raw=True).samples,
                                      rows["fb_statusword"])
        assert any(b"Operation enabled" in w for w in mdf.get("fb_statusword").samples)
        csp = (rows["sp_mode"] == 8) & (rows["drive_state"] == State.OPERATION_ENABLED)
        target = mdf.get("sp_target_position")  # the soak master's counts, in m
        assert target.unit == "m" and csp.sum() > 1000
        np.testing.assert_allclose(target.samples[csp], rows["plant_table_pos"][csp],
                                   atol=1e-3)
        reasons = mdf.get("reason").samples
        assert any(b"SIGTERM" in r for r in reasons)
        assert len(mdf.attachments) == 1


def test_the_csv_export_is_a_servo_trace(run_dir, tmp_path):
    """hil export --to csv: the servo-trace reader opens it (uniform time from 0 at the
    run's period); pos_mm is the linear scale (reference: the recording's scale counts
    times the machine file's resolution); every number is the shortest text that reads
    back to its value (Python's repr); the events are rows of events.csv beside it."""
    done = subprocess.run(python_module("hil.cli", "export", run_dir, "--to", "csv", "--out",
                                        tmp_path), env=ENV, capture_output=True, text=True,
                          timeout=EXIT_S)
    assert done.returncode == 0, done.stderr
    trace = read_trace(tmp_path / "trace.csv", require=("pos_mm", "iq_a", "pos_set_mm"))
    rows = Recording(run_dir).read(["plant_scale_counts", "sp_mode"])
    resolution = load_machine(ARROW).sensors.scale_resolution_m
    assert trace.sample_time_s == pytest.approx(5e-4)
    np.testing.assert_allclose(trace.data["pos_mm"], rows["plant_scale_counts"] * resolution
                               * 1e3)
    csp = rows["sp_mode"] == 8
    assert np.isfinite(trace.data["pos_set_mm"][csp]).all()
    assert np.isnan(trace.data["pos_set_mm"][~csp]).all()
    assert trace.metadata["events"] == "events.csv beside this file"
    with open(tmp_path / "events.csv", newline="") as f:
        events = list(csv.DictReader(f))
    assert any(e["source"] == "watchdog" and e["kind"] == "tripped" for e in events), events
    lines = (tmp_path / "trace.csv").read_text().splitlines()
    rows_text = [line for line in lines if line and line[0] not in "#t"][:200]
    for token in ",".join(rows_text).split(","):
        assert repr(float(token)) == token, token


# --- SIGKILL, a full disk ----------------------------------------------------------------

def _killed_mid_run(slow_config, tmp_path, group: bool) -> tuple[Path, int, int]:
    """A run killed by SIGKILL while a controller exchanges with the drive: the emulator
    alone, or its whole process group (the emulator and its writer process, as the OOM
    killer or ``kill -9 -PGID`` would); returns the run folder, the drive's stamp of the
    last feedback the controller received, and the bytes of the run folder's reserve the
    emulator held just before (tests.runtime_helpers.reserve_held)."""
    run = tmp_path / "run"
    sp, fb = Setpoint(), Feedback()
    with Children(tmp_path) as children:
        proc, url = children.emulator(slow_config, "udp://127.0.0.1:0", run, group=group)
        with open_endpoint(url, "controller") as ep:
            _answer(ep, sp, fb, 4000)  # about 2 s at 2 kHz
            held = reserve_held(proc.pid)
            if group:
                os.killpg(proc.pid, signal.SIGKILL)
            else:
                proc.send_signal(signal.SIGKILL)
            assert proc.wait(timeout=EXIT_S) == -signal.SIGKILL
    return run, fb.t_ns, held


@pytest.fixture(scope="module")
def killed_group(slow_config, tmp_path_factory) -> tuple[Path, int, int]:
    """The emulator and its writer process killed by SIGKILL mid-run (_killed_mid_run)."""
    return _killed_mid_run(slow_config, tmp_path_factory.mktemp("killed"), group=True)


def test_sigkill_of_the_emulator_loses_nothing_its_writer_held(slow_config, tmp_path):
    """SIGKILL of the emulator: its writer process sees its pipe close, writes what the
    ring held and ends both streams: the recording closes cleanly (within a bounded wait)
    and holds every tick up to the one before the last feedback the controller received
    (the drive's stamps; the killed tick may have sent its feedback and not finished its
    row); no report.json (the emulator did not finish)."""
    run, last_fb_ns, _ = _killed_mid_run(slow_config, tmp_path, group=False)
    deadline = time.monotonic() + EXIT_S
    while not Recording(run).closed_cleanly() and time.monotonic() < deadline:
        time.sleep(0.05)
    rec = Recording(run)
    rows = rec.read(["tick", "tick_start_ns"])
    assert rec.closed_cleanly() and not (run / REPORT).exists()
    assert rows["tick"].tolist() == list(range(rows["tick"].size))
    assert rows["tick_start_ns"].max() >= last_fb_ns - 500_000  # one period at 2 kHz


def test_sigkill_of_the_process_group_leaves_the_recording_up_to_its_last_flush(killed_group):
    """SIGKILL of the emulator and its writer at once: the recording opens (no end
    marker) and holds the ticks up to at least the last feedback the controller received
    minus the flush bound RING_S (both stamps of the drive's clock); the events read."""
    run, last_fb_ns, _ = killed_group
    rec = Recording(run)
    rows = rec.read(["tick", "tick_start_ns"])
    assert not rec.closed_cleanly() and not (run / REPORT).exists()
    assert rows["tick"].tolist() == list(range(rows["tick"].size))
    assert rows["tick_start_ns"].max() >= last_fb_ns - RING_S * 1e9
    rec.events()  # the events stream, cut anywhere, still reads (RecordingError if not)


def test_the_reserve_is_held_under_no_name_and_goes_with_a_killed_run(killed_group):
    """While the run went on, the emulator held the run folder's 1 MB reserve allocated
    (its blocks counted through /proc/PID/fd) under no name; once the process group was
    killed by SIGKILL, nothing of it is left in the folder (the kernel closed its
    descriptor and gave its blocks back)."""
    run, _, held = killed_group
    assert held >= RESERVE_BYTES
    assert not os.path.lexists(run / ".hil-run-reserve")


def test_hil_report_reports_a_run_cut_short(killed_group):
    """hil report on the killed run (no report.json, no end marker): the page says it was
    cut short (and, where the kill fell inside a write, that the stream was cut off), and
    its figures are those of the recording's rows (reference: the rows read back, numpy's
    nearest-rank percentile, the loop's overrun definition lateness + compute > period
    after the first 0.1 s); the verdict fails it for that (exit 1)."""
    run, _, _ = killed_group
    done = subprocess.run(python_module("hil.cli", "report", run), env=ENV,
                          capture_output=True, text=True, timeout=READY_S)
    assert done.returncode == 1, done.stderr
    assert done.stdout.strip().splitlines()[-1] == (
        "FAIL: the emulator did not end normally (no report.json): the run was cut short")
    assert "> Cut short: no report.json (the emulator did not end normally)" in done.stdout
    report = json.loads((run / "report_latency.json").read_text())
    rec = Recording(run)
    rows = rec.read(["tick", "lateness_ns", "compute_ns"])
    assert ("the stream was cut off" in done.stdout) == rec.truncated
    assert report["ticks"] == rows["tick"].size > 0
    assert report["lateness_us"]["p50"] == pytest.approx(
        np.percentile(rows["lateness_ns"], 50, method="inverted_cdf") / 1e3)
    late = (rows["lateness_ns"] + rows["compute_ns"] > 500_000) & (rows["tick"] >= 200)
    assert report["overruns"] == np.count_nonzero(late)
    assert report["corrupt"] is None and report["scheduling"] == {}


@pytest.fixture
def corrupt_run(run_dir, tmp_path) -> tuple[Path, int, int, int]:
    """A copy of the events run with 64 bytes flipped in the middle of the body of its
    recording's middle batch; returns the folder, that batch's index and first byte, and
    the rows before it (references: pyarrow's message reader, the clean recording)."""
    copy = tmp_path / "run"
    copy.mkdir()
    for name in (RECORDING, EVENTS, REPORT):
        (copy / name).write_bytes((run_dir / name).read_bytes())
    messages = batch_messages(run_dir / RECORDING)
    index = len(messages) // 2
    start, body, end = messages[index]
    data = bytearray((copy / RECORDING).read_bytes())
    for i in range((body + end) // 2 - 32, (body + end) // 2 + 32):
        data[i] ^= 0xFF
    (copy / RECORDING).write_bytes(bytes(data))
    reader = pa.ipc.open_stream(pa.OSFile(str(run_dir / RECORDING)))
    return copy, index, start, sum(reader.read_next_batch().num_rows for _ in range(index))


def test_hil_export_stops_at_a_corrupt_batch_and_names_it(corrupt_run, tmp_path):
    """hil export --to csv of the recording with a corrupt batch: exit 1, stderr names
    the file, the batch and its first byte; the trace holds exactly the rows before it."""
    run, index, start, before = corrupt_run
    done = subprocess.run(python_module("hil.cli", "export", run, "--to", "csv", "--out",
                                        tmp_path / "csv"), env=ENV, capture_output=True,
                          text=True, timeout=EXIT_S)
    assert done.returncode == 1, done.stderr
    assert (f"{run / RECORDING}: batch {index} (at byte {start}) is corrupt: " in done.stderr
            and f"the {before} rows before it (ticks up to {before - 1}," in done.stderr)
    assert "exported what precedes it" in done.stderr and "Traceback" not in done.stderr
    trace = read_trace(tmp_path / "csv" / "trace.csv", require=("pos_mm",))
    assert trace.data["pos_mm"].size == before


def test_hil_report_stops_at_a_corrupt_batch_and_names_it(corrupt_run):
    """hil report of the recording with a corrupt batch: exit 1, stderr names the batch;
    the page says so, and its figures are of the ticks before it."""
    run, index, start, before = corrupt_run
    done = subprocess.run(python_module("hil.cli", "report", run), env=ENV,
                          capture_output=True, text=True, timeout=READY_S)
    assert done.returncode == 1, done.stderr
    assert f"batch {index} (at byte {start}) is corrupt: " in done.stderr
    assert "> Corrupt: " in done.stdout and "Traceback" not in done.stderr
    report = json.loads((run / "report_latency.json").read_text())
    assert report["ticks"] == before and f"batch {index} " in report["corrupt"]


def test_a_ring_that_cannot_be_made_is_refused_before_ready(tmp_path, warm_cache):
    """RLIMIT_FSIZE of 100 kB, below the ring's 2.9 MB at 8 kHz: exit 2 before ``ready:``
    with one line saying what could not be made and its size; nothing recorded."""
    run = tmp_path / "run"
    done = _run(tmp_path, ARROW, "--record", run, preexec_fn=_limit_file_size(100_000))
    assert done.returncode == 2 and "ready:" not in done.stdout
    assert "cannot make the recording's ring of 8000 rows (" in done.stderr
    assert "MB of shared memory): File too large" in done.stderr
    assert "Traceback" not in done.stderr and not (run / RECORDING).exists()


def _limit_file_size(limit: int):
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return preexec


def test_a_file_size_limit_stops_the_run_cleanly_with_a_readable_recording(slow_config,
                                                                          tmp_path, warm_cache):
    """RLIMIT_FSIZE of 1 MB (EFBIG once the recording reaches it; the ring's 0.7 MB of
    shared memory at 2 kHz is a file too and fits): exit 1 with one clear line, the axis
    in its safe state, the recording cut back to its last complete batch and closed with
    the end marker, report.json and the events complete and saying why."""
    limit = 1_000_000
    run = tmp_path / "run"
    done = _run(tmp_path, slow_config, "--record", run, preexec_fn=_limit_file_size(limit))
    assert done.returncode == 1, done.stderr
    assert f"writing {run / RECORDING} failed: File too large" in done.stderr
    assert "the axes were brought to their safe state" in done.stderr
    report = json.loads((run / REPORT).read_text())
    rec = Recording(run)
    rows = rec.read(["tick"])["tick"]
    assert rec.closed_cleanly() and (run / RECORDING).stat().st_size <= limit
    assert rows.size == report["recording"]["rows"] > 0
    assert report["recording"]["failed"].startswith(f"writing {run / RECORDING} failed")
    assert report["safe_state"]["state"] == "SWITCH_ON_DISABLED"
    assert report["loop"]["stopped_by"] == "stop_flag"
    stopped = [e for e in _events(run) if e["kind"] == "stopped"]
    assert len(stopped) == 1 and "the recording failed" in stopped[0]["reason"]


@pytest.fixture
def small_tmpfs(tmp_path):
    """An 8 MB tmpfs (root only)."""
    mount = tmp_path / "tmpfs"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (root only): {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=True)


def test_a_full_disk_stops_the_run_cleanly_with_a_readable_recording(small_tmpfs, tmp_path):
    """The disk fills up while the loop runs (a filler file takes the rest of the tmpfs
    after ``ready:``): ENOSPC stops the run with one clear line, the reserve makes room
    for the recording's end, the events and report.json, the recording reads to its end
    marker and the axis is in its safe state."""
    run = small_tmpfs / "run"
    with Children(tmp_path) as children:
        proc, _ = children.emulator(ARROW, "udp://127.0.0.1:0", run, "--duration", "20",
                                    "--rate", "2000", "--no-rt")
        for _ in range(int(EXIT_S / 0.1)):  # some flushes on disk first
            if (run / RECORDING).stat().st_size > 50_000:
                break
            threading.Event().wait(0.1)
        with open(small_tmpfs / "filler", "wb") as filler:
            try:
                while True:
                    filler.write(b"\0" * 65536)
                    filler.flush()
            except OSError as e:
                assert e.errno == 28  # ENOSPC
        assert proc.wait(timeout=EXIT_S) == 1
        log = children.log("emulator")
    assert "No space left on device" in log and "safe state" in log
    report = json.loads((run / REPORT).read_text())
    rec = Recording(run)
    assert rec.closed_cleanly()
    assert rec.read(["tick"])["tick"].size == report["recording"]["rows"] > 0
    assert report["safe_state"]["state"] == "SWITCH_ON_DISABLED"
    assert any(e["kind"] == "stopped" for e in _events(run))


# --- the run folder, checked before ready: --------------------------------------------------

def test_a_run_folder_without_room_for_the_duration_is_refused_with_the_figures(tmp_path):
    """--duration of 1e9 s: refused before ready with the free space, the need and how it
    was reckoned (reference: the recording's row of one axis, summed from its schema)."""
    done = _run(tmp_path, ARROW, "--record", tmp_path / "run", "--duration", "1e9")
    assert done.returncode == 2 and "ready:" not in done.stdout
    line = next(ln for ln in done.stderr.splitlines() if "recording needs about" in ln)
    assert f"--record {tmp_path / 'run'}: " in line and " free, the recording needs" in line
    assert "(1e+09 s at 8000 Hz, 1 axis(es): " in line


def test_an_existing_run_is_kept_and_a_planted_symlink_is_not_followed(tmp_path, warm_cache):
    """A folder holding a run is refused before ready without --force (its files kept
    byte for byte); with --force, symlinks planted under the run's names are replaced by
    the new files and their targets keep their bytes."""
    run = tmp_path / "run"
    first = _run(tmp_path, ARROW, "--record", run, "--duration", "0.2")
    assert first.returncode == 0, first.stderr
    before = {name: (run / name).read_bytes() for name in (RECORDING, EVENTS, REPORT)}
    again = _run(tmp_path, ARROW, "--record", run, "--duration", "0.2")
    assert again.returncode == 2 and "ready:" not in again.stdout
    assert "holds a run (recording.arrows, events.arrows, report.json); give --force" in (
        again.stderr)
    assert {name: (run / name).read_bytes() for name in before} == before
    targets = {}
    for name in (RECORDING, EVENTS, REPORT):
        target = tmp_path / f"target-{name}"
        target.write_bytes(b"not yours")
        (run / name).unlink()
        os.symlink(target, run / name)
        targets[name] = target
    forced = _run(tmp_path, ARROW, "--record", run, "--duration", "0.2", "--force")
    assert forced.returncode == 0, forced.stderr
    for name, target in targets.items():
        assert target.read_bytes() == b"not yours"
        assert not (run / name).is_symlink() and (run / name).stat().st_size > 0
    assert Recording(run).closed_cleanly()


def test_a_file_or_a_read_only_folder_is_refused_before_ready(tmp_path):
    """A file where the run folder should be; a read-only file system (a read-only tmpfs,
    root only): each refused with exit 2, naming the path and why, before ready."""
    (tmp_path / "file").write_text("x")
    done = _run(tmp_path, ARROW, "--record", tmp_path / "file")
    assert done.returncode == 2 and "ready:" not in done.stdout
    assert f"--record {tmp_path / 'file'}: exists and is not a folder" in done.stderr
    ro = tmp_path / "ro"
    ro.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(ro)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here (root only): {mounted.stderr}")
    try:
        done = _run(tmp_path, ARROW, "--record", ro)
    finally:
        subprocess.run(["umount", str(ro)], check=True)
    assert done.returncode == 2 and "ready:" not in done.stdout
    assert f"--record {ro}: the run folder is not writable: Read-only file system" in (
        done.stderr)
