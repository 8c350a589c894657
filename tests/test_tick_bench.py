"""``hil bench tick`` (issue 12 part 6): the emulator's real tick (UDP on 127.0.0.1, a
controller process, the recording's ring) against the plant step alone.

No wall-clock figure is asserted; what is: the JSON's structure, that the controller
enabled the drives and its setpoints were heard, and that every tick that started in
OPERATION ENABLED took the compiled path but for the few where the controller's first
CSP setpoints changed the command (the compiled path declines a changed controlword or
mode, by design), with no fault cause, refusal or plant status among its exits.
"""

import json
import subprocess
import sys

from hil.bench import tick as bench_tick

PERCENTILES = {"p50", "p99", "p999", "max"}


def _check(row: dict, axes: int) -> None:
    assert row["axes"] == axes and row["rate_hz"] == 8000.0 and row["drive"] == "compiled"
    assert row["ticks"] == round(row["seconds"] * row["rate_hz"])
    assert set(row["tick_compute_us"]) == set(row["tick_cpu_us"]) == PERCENTILES
    assert set(row["plant_step_us"]) == {"p50", "p999"}
    assert row["ratio_p50"] == row["tick_compute_us"]["p50"] / row["plant_step_us"]["p50"]
    assert 0 < row["setpoints_heard"] <= row["ticks"]
    assert row["enabled_ticks"] > row["ticks"] // 2
    assert row["compiled_share_enabled"] > 0.99
    assert row["compiled_share"] >= row["compiled_share_enabled"] * row["enabled_ticks"] / \
        row["ticks"]
    assert row["exits"]["cause"] == row["exits"]["refused"] == 0
    assert row["exits"]["plant"] == row["exits"]["loop"] == 0
    # the compiled tick ran (a share that depends on how the two processes' clocks
    # line up on a loaded machine); its ticks are compiled drive cycles too
    assert 0.1 < row["steady_share"] <= row["compiled_share"]
    assert set(row["steady_declined"]) == {"frame", "sequence", "cycle"}
    # the compiled call is timed inside the tick that ran it
    call = row["compiled_call_us"]
    assert set(call) == PERCENTILES and 0.0 < call["p50"] <= call["max"]
    assert call["max"] <= row["tick_compute_us"]["max"]
    assert row["ratio_compiled_call_p50"] == call["p50"] / row["plant_step_us"]["p50"]
    assert row["overruns"] >= 0


def test_one_and_two_axes_take_the_compiled_path():
    rows = [bench_tick.bench(c, 1.0) for c in bench_tick.DEFAULT_CONFIGS]
    _check(rows[0], 1)
    _check(rows[1], 2)


def test_cli_prints_json():
    out = subprocess.run([sys.executable, "-m", "hil.cli", "bench", "tick", "--seconds", "0.3",
                          "--config", str(bench_tick.DEFAULT_CONFIGS[0]), "--json"],
                         capture_output=True, text=True, timeout=300, check=True)
    (row,) = json.loads(out.stdout)
    _check(row, 1)
    calls = row["socket_calls_us"]
    assert set(calls) == {"recvmsg", "poll", "sendto", "sum"}
    assert min(calls.values()) > 0.0
    assert calls["sum"] == calls["recvmsg"] + calls["poll"] + calls["sendto"]
    assert row["tick_without_socket_p50_us"] == row["tick_compute_us"]["p50"] - calls["sum"]
