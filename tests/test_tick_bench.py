"""``hil bench tick`` (issues 12 part 6 and 29): ``hil run``'s loop (UDP on 127.0.0.1, a
controller process, the recording's ring taken by a thread) with each compiled tick's
phases stamped, against the plant step alone.

No wall-clock figure is asserted; what is: the JSON's structure, that the controller's
setpoints were heard and the compiled loop ran the run's ticks, many a call, with no
fault cause, refusal or plant status among the drives' exits, that every row reached the
drain, and that the parts of a tick add up as the stamps make them (each part of each tick
no longer than the tick, so no percentile of a part above the tick's).
"""

import json
import subprocess
import sys

from hil.bench import tick as bench_tick
from hil.runtime.steady_tick import BURST_S

#: calls the enable sequence and the start may take besides those the test explains
ENABLE_CALLS = 20

PERCENTILES = {"p50", "p99", "p999", "max"}
PARTS = ("socket_calls_us", "compiled_work_us", "glue_us")


def _check(row: dict, axes: int) -> None:
    assert row["axes"] == axes and row["rate_hz"] == 8000.0 and row["drive"] == "compiled"
    planned = round(row["seconds"] * row["rate_hz"])
    assert 0.9 * planned <= row["ticks"] <= planned
    for key in ("tick_compute_us", "lateness_us", "compiled_tick_us", *PARTS):
        assert set(row[key]) == PERCENTILES, key
    assert set(row["plant_step_us"]) == {"p50", "p999"}
    assert row["ratio_p50"] == row["tick_compute_us"]["p50"] / row["plant_step_us"]["p50"]
    assert row["ratio_compiled_work_p50"] == (row["compiled_work_us"]["p50"]
                                              / row["plant_step_us"]["p50"])
    assert 0 < row["setpoints_heard"] <= row["ticks"]
    assert row["ticks_lost_to_the_ring"] == 0
    assert row["exits"]["cause"] == row["exits"]["refused"] == 0
    assert row["exits"]["plant"] == row["exits"]["loop"] == 0
    # the drives idle, enable and hold compiled; the loop returns to Python only for what
    # hil.runtime.steady_tick lists: an overrun (many on a loaded machine), a declined
    # tick, BURST_S of ticks run, and the few Python ticks of the enable sequence
    loop = row["compiled_loop"]
    assert row["compiled_share"] > 0.9
    explained = (row["overruns"] + row["grace_overruns"] + sum(loop["declined"].values())
                 + loop["ticks"] / (BURST_S * row["rate_hz"]) + ENABLE_CALLS)
    assert loop["calls"] <= explained, (loop, row["overruns"])
    assert row["compiled_share"] == loop["ticks"] / row["ticks"]
    tick = row["compiled_tick_us"]
    for part in ("socket_calls_us", "compiled_work_us"):
        assert 0.0 < row[part]["p50"] <= tick["p50"] and row[part]["max"] <= tick["max"]
    assert row["glue_us"]["p50"] >= 0.0 and row["python_per_call_us"] > 0.0
    assert row["overruns"] >= 0


def test_one_and_two_axes_take_the_compiled_loop():
    rows = [bench_tick.bench(c, 1.0) for c in bench_tick.DEFAULT_CONFIGS]
    _check(rows[0], 1)
    _check(rows[1], 2)


def test_cli_prints_json():
    out = subprocess.run([sys.executable, "-m", "hil.cli", "bench", "tick", "--seconds", "0.5",
                          "--config", str(bench_tick.DEFAULT_CONFIGS[0]), "--json"],
                         capture_output=True, text=True, timeout=300, check=True)
    (row,) = json.loads(out.stdout)
    _check(row, 1)
