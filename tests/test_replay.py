"""``hil replay``: a real ``hil run`` process against a real ``hil controller`` process over
UDP loopback, replayed offline, must reproduce every drive word and plant output of the
recording to 1e-9 relative (the reference is the recording itself: the replay shares no
state with the run but the recorded setpoints and the machine files' text in its
metadata); a recording with one plant value changed must be reported as not matching, at
that channel and tick.

Setup: the Arrow 500 X at 2 kHz PWM (``runtime_helpers.SLOW_2KHZ``), a short program (a
20 mm rapid and back, about 0.4 s).  The second run stops the controller (SIGSTOP) once the
drive is enabled, so the emulator's watchdog trips and the drive's fault reaction brakes
the axis -- the replay must reproduce those decisions too -- and continues it (SIGCONT):
``hil controller`` must then exit 1 naming the drive's watchdog fault.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hil.cia402 import State
from hil.replay import ReplayError, replay_run
from hil.runtime.arrow import pa
from hil.runtime.record_reader import Recording, RecordingError
from hil.runtime.stream_file import ArrowStream
from tests.conftest import ROOT
from tests.runtime_helpers import (
    ENV,
    EXIT_S,
    SLOW_2KHZ,
    Children,
    machine_variant,
    python_module,
    terminate,
)

PROGRAM = "N10 G90 G71\nN20 G0 X20\nN30 G0 X0\nN40 M30\n"
#: longest wait for the emulator's recording or log to show a state, s
STATE_S = 60.0


def wait_for(what: str, found, children: Children) -> None:
    """Poll ``found()`` (bounded by STATE_S)."""
    deadline = time.monotonic() + STATE_S
    while not found():
        assert time.monotonic() < deadline, f"no {what} within {STATE_S} s:\n" + \
            children.log("emulator")[-2000:]
        time.sleep(0.05)


def enabled_in_recording(run: Path) -> bool:
    """The recording so far has a tick in OPERATION ENABLED."""
    try:
        states = Recording(run).read(["drive_state"])["drive_state"]
        return bool((states == State.OPERATION_ENABLED).any())
    except RecordingError:  # the stream's schema not written yet
        return False


def loopback(folder: Path, config: Path, pause: bool) -> tuple[Path, int, str]:
    """One loopback run of PROGRAM; returns the emulator's run folder, the controller's
    exit status and log.  With ``pause`` the controller is stopped (SIGSTOP) once the drive
    is enabled, and continued (SIGCONT) once the emulator's watchdog has tripped."""
    program = folder / "short.nc"
    program.write_text(PROGRAM)
    run = folder / "emulator"
    cpus = sorted(os.sched_getaffinity(0))
    pin = ["--cpu", cpus[0]] if len(cpus) > 1 else []
    with Children(folder) as children:
        emulator, url = children.emulator(config, "udp://127.0.0.1:0", run, "--cpu", cpus[-1])
        ctl = children.start("controller", python_module(
            "hil.runtime.controller_proc", config, "--adapter", url, "--program", program,
            "--out", folder / "controller", *pin))
        if pause:
            wait_for("enabled drive", lambda: enabled_in_recording(run), children)
            ctl.send_signal(signal.SIGSTOP)
            wait_for("watchdog trip", lambda: "watchdog: no setpoint" in
                     children.log("emulator"), children)
            ctl.send_signal(signal.SIGCONT)
        status = ctl.wait(timeout=EXIT_S)
        assert terminate(emulator) == 0, children.log("emulator")
        return run, status, children.log("controller")


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


@pytest.fixture(scope="module")
def completed(config, tmp_path_factory) -> Path:
    run, status, log = loopback(tmp_path_factory.mktemp("completed"), config, pause=False)
    # an alarm (a contour deviation when the machine's other load delays ticks) ends the
    # program early, still a run to replay; anything else is a failure
    assert status == 0 or (status == 1 and "FAIL: alarm" in log), log
    return run


@pytest.fixture(scope="module")
def tripped(config, tmp_path_factory) -> tuple[Path, int, str]:
    return loopback(tmp_path_factory.mktemp("tripped"), config, pause=True)


def test_hil_replay_of_a_loopback_run_matches_its_recording(completed):
    out = subprocess.run([sys.executable, "-m", "hil.cli", "replay", completed, "--json"],
                         check=False, cwd=ROOT, env=ENV, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    rows = Recording(completed).read(["tick", "sp_new", "drive_state"])
    assert result["matches"] and result["worst"]["rel_diff"] <= 1e-9
    assert result["ticks"] == rows["tick"].size
    # the run moved the axis under a controller: enabled, with new setpoints
    assert (rows["drive_state"] == State.OPERATION_ENABLED).sum() > 100
    assert rows["sp_new"].sum() > 100


def test_the_watchdog_trip_and_fault_reaction_replay_too(tripped):
    run, _, _ = tripped
    result = replay_run(run)
    report = json.loads((run / "report.json").read_text())
    assert report["watchdog"]["events"][0]["kind"] == "tripped"
    faults = Recording(run).read(["fb_fault"])["fb_fault"]
    assert (faults == 0x8250).any()  # the watchdog's error code, latched in the run
    assert result.matches, result.line()


def test_the_controller_exits_1_and_says_the_watchdog_faulted_the_drive(tripped):
    _, status, log = tripped
    last = log.strip().splitlines()[-1]
    assert status == 1, log
    # paused mid-move, the NC may see its contour monitoring (25050) go first on resuming
    assert last.startswith("hil controller: FAIL: alarm 25") and "alarm 25201" in last, log
    assert "603Fh = 8250h (no valid setpoint within the watchdog time)" in last


def rewrite_recording(src: Path, dst: Path, column: str, row: int, factor: float) -> float:
    """``src``'s run folder copied to ``dst`` with ``column[row]`` multiplied by
    ``factor`` (written as hil run writes, each batch with its CRC-32: a changed value,
    not a corrupt file); returns the value written."""
    shutil.copytree(src, dst)
    path = dst / "recording.arrows"
    reader = pa.ipc.open_stream(pa.OSFile(str(src / "recording.arrows")))
    table = reader.read_all()
    values = table.column(column).to_numpy().copy()
    values[row] *= factor
    i = table.schema.get_field_index(column)
    table = table.set_column(i, table.schema.field(i), pa.array(values))
    stream = ArrowStream(os.open(path, os.O_WRONLY | os.O_TRUNC), str(path), table.schema)
    for batch in table.to_batches():
        stream.write(batch)
    stream.close()
    return float(values[row])


def test_a_recording_with_one_plant_value_changed_does_not_match(completed, tmp_path):
    rows = Recording(completed).read(["tick", "plant_table_pos"])
    row = int(np.argmax(np.abs(rows["plant_table_pos"])))  # mid-move, far from 0
    rewrite_recording(completed, tmp_path / "run", "plant_table_pos", row, 1.0 + 1e-8)
    result = replay_run(tmp_path / "run")
    assert not result.matches
    assert result.worst.channel == "plant_table_pos"
    assert result.worst.tick == int(rows["tick"][row])
    assert 0.5e-8 < result.worst.rel_diff < 2e-8


def test_a_recording_without_metadata_is_refused_naming_the_file(tmp_path):
    (tmp_path / "recording.arrows").write_bytes(b"not arrow")
    with pytest.raises(ReplayError, match="recording.arrows"):
        replay_run(tmp_path)
