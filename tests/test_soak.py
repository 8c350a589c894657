"""``hil soak`` in CI: a short soak asserts that memory stays flat, not timing.

Emulator and soak master as separate processes at 4 kHz for 15 s (``--no-rt``: the CI
machine is shared), RSS sampled every half second.  The reference for "flat": the recording
held in memory, as ``hil run`` did before, grew by one row (``row_bytes(1)``, about 300
bytes) per tick; after the warm-up each process must grow by less than an eighth of that
per tick, averaged by least squares over the samples.  The lateness figures are
reported, not asserted.
"""

import json
import subprocess

from hil.runtime.record_reader import Recording
from hil.runtime.recording import row_bytes
from hil.runtime.soak import warmup_s
from tests.runtime_helpers import ENV, EXIT_S, READY_S, python_module

RATE_HZ = 4000
MINUTES = 0.25
#: the most a process may grow per tick after the warm-up, bytes
MAX_BYTES_PER_TICK = row_bytes(1) / 8


def test_a_short_soak_keeps_both_processes_memory_flat(tmp_path):
    """Both processes end cleanly; per process the RSS slope after the warm-up stays
    under MAX_BYTES_PER_TICK; the emulator's recording holds every tick it ran (but those
    its report counts as not recorded); the JSON has a row per minute and process, and
    the plot is written."""
    done = subprocess.run(python_module("hil.cli", "soak", "--minutes", MINUTES, "--rate",
                                        RATE_HZ, "--no-rt", "--rss-every", "0.5", "--out",
                                        tmp_path), env=ENV, capture_output=True, text=True,
                          timeout=READY_S + MINUTES * 60 + 3 * EXIT_S)
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads((tmp_path / "soak.json").read_text())
    assert result["exit"] == {"emulator": 0, "master": 0}
    run_s = MINUTES * 60
    for name, proc in result["processes"].items():
        memory = proc["memory"]
        assert memory["samples"] >= 0.5 * (run_s - warmup_s(run_s)), (name, memory)
        per_tick = memory["slope_mb_per_min"] * 1e6 / (60 * RATE_HZ)
        assert per_tick < MAX_BYTES_PER_TICK, (name, memory)
        minutes = [m["minute"] for m in proc["minutes"]]
        assert minutes == [0], name  # one row per started minute
    report = json.loads((tmp_path / "emulator" / "report.json").read_text())
    ticks = Recording(tmp_path / "emulator").read(["tick"])["tick"]
    recording = report["recording"]
    assert ticks.size == recording["rows"] == report["loop"]["ticks"] - recording[
        "ticks_not_recorded"]
    assert (tmp_path / "soak.png").stat().st_size > 0
    assert "RSS growth goal" in done.stdout
