"""The latency report (hil.report) against figures worked out by hand, the run folder's
format, its pairing with a controller's folder, the host fingerprint on a machine missing
files, and the shape of the adapter benchmark's rows (no timing asserted).

Percentiles are nearest rank, as hil.rt computes them: the p-th percentile of n samples
is the ceil(p/100 * n)-th smallest.  The synthetic run has 1000 ticks that ran, with
lateness 10, 20, ..., 10000 ns, so p50 is the 500th (5000 ns), p99 the 990th (9900 ns),
p99.9 the 999th (9990 ns).
"""

import json
import multiprocessing
import os
from multiprocessing import resource_tracker

import numpy as np
import pyarrow as pa
import pytest

from hil.bench import adapters as bench_adapters
from hil.report import host
from hil.report.baseline import CyclictestBaseline
from hil.report.latency import (
    NO_VALUE,
    Pairing,
    ReportError,
    RoundTrip,
    RunData,
    build_report,
    load_run,
    report_run,
    write_report,
)
from hil.report.render import markdown
from hil.runtime.stream_file import FORMAT, ArrowStream, schema_of

PERIOD_NS = 100_000
N_RAN = 1000
SKIPPED_SLOT = 500                  # the loop dropped this deadline
COMPUTE_NS = 30_000
SLOW_COMPUTE_NS = 95_000            # the last tick's: it overruns by 5 µs
RT_SLOTS = np.arange(1, 1000, 10)   # 100 ticks that first used a new setpoint
TRANSPORT_NS = 50_000 + 100 * np.arange(RT_SLOTS.size)  # 50.0 .. 59.9 µs
WAIT_NS = 2_000
SEND_BEFORE_END_NS = 500            # the feedback leaves 0.5 µs before the step ends
CONTROLLER_CLOCK_OFFSET_NS = 123_456_789  # another machine's clock
SCHEDULING = {"fifo": {"granted": True, "detail": "SCHED_FIFO priority 80"},
              "cpu_dma_latency": {"granted": False, "detail": "refused: Permission denied"}}
ADAPTER_STATS = {"sent": 100, "received": 100, "lost": 0, "malformed": 0}

#: cyclictest -h 10 output, edited: 1000 wake-ups, 998 in bins 5, 6 and 9 µs, 2 past 10 µs
HISTOGRAM = """\
# Histogram
000000 000000
000001 000000
000002 000000
000003 000000
000004 000000
000005 000500
000006 000490
000007 000000
000008 000000
000009 000008
# Total: 000000998
# Min Latencies: 00005
# Avg Latencies: 00006
# Max Latencies: 00250
# Histogram Overflows: 00002
"""


def loop_arrays() -> tuple[np.ndarray, np.ndarray]:
    """lateness_ns and compute_ns with one dropped slot (1001 slots, 1000 ticks ran)."""
    lateness = np.insert(10 * np.arange(1, N_RAN + 1), SKIPPED_SLOT, NO_VALUE).astype(np.int64)
    compute = np.full(N_RAN + 1, COMPUTE_NS, dtype=np.int64)
    compute[SKIPPED_SLOT] = NO_VALUE
    compute[-1] = SLOW_COMPUTE_NS
    return lateness, compute


def stamps(lateness: np.ndarray, compute: np.ndarray) -> dict[str, np.ndarray]:
    """The five round-trip stamps of the module docstring, built from the parts."""
    keys = ("tick_start_ns", "sp_t_ns", "sp_rx_ns", "fb_t_ns", "fb_rx_ns")
    out = {k: np.zeros(lateness.size, dtype=np.int64) for k in keys}
    k = RT_SLOTS
    tick = 10**12 + k * PERIOD_NS + lateness[k]
    sp_rx = tick - WAIT_NS
    fb_t = tick + compute[k] - SEND_BEFORE_END_NS
    sp_t = sp_rx - TRANSPORT_NS // 2 + CONTROLLER_CLOCK_OFFSET_NS
    fb_rx = sp_t + TRANSPORT_NS + (fb_t - sp_rx)
    for key, values in zip(keys, (tick, sp_t, sp_rx, fb_t, fb_rx)):
        out[key][k] = values
    return out


def expected_round_trip(n_slots: int) -> RoundTrip:
    parts = {name: np.full(n_slots, NO_VALUE, dtype=np.int64) for name in
             ("total_ns", "transport_ns", "wait_ns", "compute_ns")}
    parts["transport_ns"][RT_SLOTS] = TRANSPORT_NS
    parts["wait_ns"][RT_SLOTS] = WAIT_NS
    parts["compute_ns"][RT_SLOTS] = COMPUTE_NS
    parts["total_ns"][RT_SLOTS] = TRANSPORT_NS + WAIT_NS + COMPUTE_NS - SEND_BEFORE_END_NS
    return RoundTrip(**parts)


def synthetic_run(**changes) -> RunData:
    lateness, compute = loop_arrays()
    fields = {"period_ns": PERIOD_NS, "lateness_ns": lateness, "compute_ns": compute,
              "overruns": 1, "skipped": 1, "scheduling": SCHEDULING,
              "adapter": "udp://127.0.0.1:5005", "adapter_stats": ADAPTER_STATS,
              "round_trip": expected_round_trip(lateness.size), "host": host.host_fingerprint()}
    return RunData(**{**fields, **changes})


def write_recording(folder, columns: dict, meta: dict | None = None) -> None:
    """recording.arrows as the daemon writes it (hil.runtime.stream_file.ArrowStream): an
    Arrow IPC stream of ``columns`` in a few batches, each with its CRC-32, the run's
    metadata (and ``meta``) and the schema's CRC-32 in its schema."""
    meta = json.dumps({"format": FORMAT, "period_ns": PERIOD_NS, **(meta or {})}).encode()
    schema = schema_of([(name, values.dtype.name, "", "") for name, values in columns.items()],
                       meta)
    path = folder / "recording.arrows"
    stream = ArrowStream(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), str(path), schema)
    n = len(next(iter(columns.values())))
    for start in range(0, n, 300):
        stream.write(pa.RecordBatch.from_arrays(
            [pa.array(values[start:start + 300]) for values in columns.values()], schema=schema))
    stream.close()


def write_run_folder(folder, with_stamps=True, recorded=None, recording_meta=None,
                     **meta_changes):
    """A run folder as the daemon writes it (the documented keys only): one row per tick
    that ran, the stamps of ``stamps()`` but the controller's fb_rx_ns (``recorded``:
    which of them, default all four), ``recording_meta`` added to the recording's
    metadata."""
    lateness, compute = loop_arrays()
    ran = np.flatnonzero(lateness != NO_VALUE)
    columns = {"tick": ran, "lateness_ns": lateness[ran], "compute_ns": compute[ran]}
    if with_stamps:
        all_stamps = stamps(lateness, compute)
        for key in recorded or ("tick_start_ns", "sp_t_ns", "sp_rx_ns", "fb_t_ns"):
            columns[key] = all_stamps[key][ran]
    write_recording(folder, columns, recording_meta)
    meta = {"loop": {"period_ns": PERIOD_NS, "ticks": N_RAN, "overruns": 1, "skipped": 1,
                     "stopped_by": "completed"},
            "scheduling": SCHEDULING,
            "adapter": {"name": "udp://127.0.0.1:5005", "stats": ADAPTER_STATS},
            "watchdog": [], **meta_changes}
    (folder / "report.json").write_text(json.dumps(meta))


# -- the figures -----------------------------------------------------------------------------

def test_tick_figures_are_nearest_rank_over_the_ticks_that_ran():
    r = build_report(synthetic_run())
    assert (r["period_us"], r["ticks"], r["overruns"], r["missed_ticks"]) == (100.0, 1000, 1, 1)
    assert r["lateness_us"] == {"min": 0.01, "p50": 5.0, "p99": 9.9, "p999": 9.99, "max": 10.0}
    assert r["compute_us"] == {"min": 30.0, "p50": 30.0, "p99": 30.0, "p999": 30.0, "max": 95.0}


def test_slack_is_period_minus_compute_minus_lateness():
    # the last tick: 100 - 95 - 10 = -5 µs; the others 70 µs - lateness 0.01 .. 9.99 µs,
    # so the k-th smallest slack (k >= 2) is 60.01 + 0.01 (k - 2) µs
    assert build_report(synthetic_run())["slack_us"] == {
        "min": -5.0, "p50": 64.99, "p99": 69.89, "p999": 69.98, "max": 69.99}


def test_round_trip_parts_by_hand():
    rt = build_report(synthetic_run())["round_trip"]
    assert (rt["adapter"], rt["samples"], rt["with_transport"]) == ("udp://127.0.0.1:5005", 100, 100)
    assert (rt["negative_waits"], rt["pairing"]) == (0, None)
    # 100 samples 50.0, 50.1, ..., 59.9 µs: p50 is the 50th, p99 the 99th, p99.9 the 100th
    assert rt["transport_us"] == {"min": 50.0, "p50": 54.9, "p99": 59.8, "p999": 59.9, "max": 59.9}
    assert rt["wait_us"] == dict.fromkeys(("min", "p50", "p99", "p999", "max"), 2.0)
    assert rt["compute_us"] == dict.fromkeys(("min", "p50", "p99", "p999", "max"), 30.0)
    assert rt["total_us"] == {"min": 81.5, "p50": 86.4, "p99": 91.3, "p999": 91.4, "max": 91.4}


def test_a_run_without_round_trips_or_samples_reports_nulls():
    lateness = np.array([NO_VALUE], dtype=np.int64)
    r = build_report(synthetic_run(lateness_ns=lateness, compute_ns=lateness.copy(),
                                   round_trip=None, adapter=None, adapter_stats=None))
    assert r["ticks"] == 0 and r["lateness_us"] is None and r["slack_us"] is None
    assert r["round_trip"] is None and r["adapter"] is None


def test_cyclictest_baseline_sits_beside_the_lateness():
    base = CyclictestBaseline.from_histogram(HISTOGRAM, interval_us=100)
    r = build_report(synthetic_run(), base)
    assert r["cyclictest"] == {"interval_us": 100, "samples": 1000, "overflows": 2, "latency_us": {
        "min": 5.0, "p50": 5.0, "p99": 6.0, "p999": 250.0, "max": 250.0}}
    assert r["host_source"] == "run"


def test_histogram_counts_each_quantity_on_both_sides():
    """The synthetic run at 100 µs spins 40 µs: its 900 ticks later than 1 µs after the
    spin have a known wake-up latency (40 µs + lateness, all above 40 µs), the other 100
    are hidden by the spin; cyclictest's 998 binned wake-ups (5, 6, 9 µs, all within the
    spin) imply a lateness after the spin of 0 (the first bin)."""
    r = build_report(synthetic_run(), CyclictestBaseline.from_histogram(HISTOGRAM, 100))
    hist = r["histogram"]
    edges = np.array(hist["edges_us"])
    for key in ("lateness_counts", "wakeup_counts", "cyclictest_wakeup_counts",
                "cyclictest_lateness_counts"):
        assert len(hist[key]) == edges.size - 1, key
    assert hist["spin_us"] == 40.0
    assert sum(hist["lateness_counts"]) == 1000
    assert (sum(hist["wakeup_counts"]), hist["wakeup_hidden"]) == (900, 100)
    assert sum(np.array(hist["wakeup_counts"])[edges[1:] <= 40.0]) == 0
    assert sum(hist["cyclictest_wakeup_counts"]) == 998
    assert hist["cyclictest_lateness_counts"][0] == 998


def _stair_labels(ax) -> list[str]:
    return [p.get_label() for p in ax.patches if type(p).__name__ == "StepPatch"]


def test_histogram_panels_set_like_beside_like():
    """Each panel of latency_hist.png holds one quantity, the loop's and cyclictest's: the
    top one the wake-up latency, the bottom one the lateness after the spin; each series'
    dashed line stands at the p99.9 of the matching row of the report's wakeup table and
    its legend quotes it (the old figure set the loop's lateness beside cyclictest's
    wake-up latency)."""
    from hil.report.render import histogram_figure

    r = build_report(synthetic_run(), CyclictestBaseline.from_histogram(HISTOGRAM, 100))
    w = r["wakeup"]
    top, bottom = histogram_figure(r).axes
    for ax, quantity, key in ((top, "wake-up latency, ", "wakeup_us"),
                              (bottom, "lateness after the spin, ", "lateness_us")):
        labels = _stair_labels(ax)
        assert len(labels) == 2 and all(label.startswith(quantity) for label in labels), labels
        rows = (w["loop"][key]["p999"], w["cyclictest"][key]["p999"])
        for label, side, p999 in zip(labels, ("loop", "cyclictest 100 µs"), rows):
            assert label.startswith(quantity + side) and f"p99.9 {p999:.3g} µs" in label, label
        dashed = sorted(line.get_xdata()[0] for line in ax.get_lines())
        assert dashed == sorted(rows)
    assert top.get_xscale() == "log" and top.get_yscale() == "log"


def test_histogram_without_cyclictest_shows_the_loop_alone():
    from hil.report.render import histogram_figure

    top, bottom = histogram_figure(build_report(synthetic_run())).axes
    assert [len(_stair_labels(ax)) for ax in (top, bottom)] == [1, 1]


def test_timeline_reads_microsecond_jitter_and_a_long_stall():
    """latency_time.png: one tick 150 ms late among ticks 0.05 µs late and one 3 µs late:
    symmetric-log axes whose range holds all of them (a linear axis to 150 000 µs made
    the µs invisible), and legend markers large enough to see (the plot's are 1.5 pt)."""
    from hil.report.render import timeline_figure

    lateness = np.full(1000, 50, dtype=np.int64)
    lateness[100], lateness[500] = 3_000, 150_000_000
    compute = np.full(1000, 20_000, dtype=np.int64)
    late_ax, compute_ax = timeline_figure(lateness, compute, PERIOD_NS).axes
    for ax, values in ((late_ax, lateness / 1e3), (compute_ax, (lateness + compute) / 1e3)):
        assert ax.get_yscale() == "symlog"
        low, high = ax.get_ylim()
        assert low <= values.min() and values.max() <= high
    markers = [h for h in compute_ax.get_legend().legend_handles if h.get_marker() == "o"]
    assert len(markers) == 2 and all(h.get_markersize() >= 5 for h in markers)


def test_host_is_taken_now_when_the_run_recorded_none():
    r = build_report(synthetic_run(host=None))
    assert r["host_source"] == "report" and set(r["host"]) == HOST_KEYS


# -- the files -------------------------------------------------------------------------------

def test_written_report_has_json_markdown_with_units_and_pngs(tmp_path):
    run = synthetic_run()
    report = build_report(run, CyclictestBaseline.from_histogram(HISTOGRAM, 100))
    paths = write_report(tmp_path, report, run)
    assert [p.name for p in paths] == ["report_latency.json", "report.md", "latency_hist.png",
                                       "latency_time.png"]
    assert json.loads(paths[0].read_text()) == report
    md = paths[1].read_text()
    for text in ("| 0.010 µs | 5.000 µs | 9.900 µs | 9.990 µs | 10.000 µs |",  # lateness
                 "| -5.000 µs | 64.990 µs | 69.890 µs | 69.980 µs | 69.990 µs |",  # slack
                 # wake-up latency: the loop's lateness + its 40 µs spin, cyclictest's own
                 "| wake-up latency, loop | 45.0 µs | 49.9 µs | 50.0 µs | 50.0 µs | 90.000 % |",
                 ("| wake-up latency, cyclictest 100 µs | 5.0 µs | 6.0 µs | 250.0 µs | 250.0 µs "
                 "| 0.200 % |"),
                 "| 50.000 µs | 54.900 µs | 59.800 µs | 59.900 µs | 59.900 µs |",  # transport
                 "Period 100.000 µs (10000 Hz); 1000 ticks run; 1 overruns; 1 missed ticks",
                 "| fifo | yes | SCHED_FIFO priority 80 |", "| lost | 0 |", "PREEMPT_RT",
                 ("![wake-up latency and lateness after the spin, beside cyclictest]"
                  "(latency_hist.png)"),
                 "![lateness and compute time over the run](latency_time.png)"):
        assert text in md, text
    for png in paths[2:]:
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_wake_up_latency_is_spin_plus_lateness_where_the_sleep_overshot():
    # 100 µs period: the clock spins the last 40 µs.  900 ticks woke on time after the spin
    # (0.2 µs late: a clock read), 100 slept past the margin by 1..100 µs
    lateness = np.r_[np.full(900, 200), 1000 * np.arange(1, 101)].astype(np.int64)
    w = build_report(synthetic_run(lateness_ns=lateness, compute_ns=np.full(1000, 30_000),
                                   round_trip=None))["wakeup"]
    assert w["spin_us"] == 40.0
    loop = w["loop"]
    assert loop["beyond_spin"] == 0.099  # the 1 µs one is within a clock read's allowance
    # p50 falls among the hidden ones; p99 is the 990th smallest: 90 µs past, + 40 µs spin
    assert loop["wakeup_us"] == {"p50": None, "p99": 130.0, "p999": 139.0, "max": 140.0}
    assert loop["lateness_us"] == {"p50": 0.2, "p99": 90.0, "p999": 99.0, "max": 100.0}


def test_cyclictest_lateness_after_the_spin_is_its_latency_less_the_spin():
    base = CyclictestBaseline.from_histogram(HISTOGRAM, interval_us=100)
    cyc = build_report(synthetic_run(), base)["wakeup"]["cyclictest"]
    assert cyc["wakeup_us"] == {"p50": 5.0, "p99": 6.0, "p999": 250.0, "max": 250.0}
    assert cyc["lateness_us"] == {"p50": 0.0, "p99": 0.0, "p999": 210.0, "max": 210.0}
    assert cyc["beyond_spin"] == 2 / 1000  # the two overflows; every bin is below 40 µs


def test_load_run_derives_the_parts_from_the_stamps(tmp_path):
    """One slot per deadline (the skipped one empty); without the controller's receive
    stamps only wait and compute are known."""
    write_run_folder(tmp_path)
    run = load_run(tmp_path)
    lateness, compute = loop_arrays()
    assert (run.period_ns, run.overruns, run.skipped) == (PERIOD_NS, 1, 1)
    np.testing.assert_array_equal(run.lateness_ns, lateness)
    np.testing.assert_array_equal(run.compute_ns, compute)
    assert run.scheduling == SCHEDULING and run.host is None
    assert (run.adapter, run.adapter_stats) == ("udp://127.0.0.1:5005", ADAPTER_STATS)
    want = expected_round_trip(lateness.size)
    for name in ("wait_ns", "compute_ns"):
        np.testing.assert_array_equal(getattr(run.round_trip, name), getattr(want, name), name)
    for name in ("total_ns", "transport_ns"):
        assert np.all(getattr(run.round_trip, name) == NO_VALUE), name
    rt = build_report(run)["round_trip"]
    assert (rt["samples"], rt["with_transport"], rt["total_us"], rt["transport_us"]) == (
        100, 0, None, None)
    assert rt["wait_us"]["p50"] == 2.0


def test_negative_waits_are_counted_and_explained():
    rt = expected_round_trip(N_RAN + 1)
    rt.wait_ns[RT_SLOTS[:3]] = -1_000  # three setpoints arrived 1 µs after their tick began
    report = build_report(synthetic_run(round_trip=rt))
    assert report["round_trip"]["negative_waits"] == 3
    assert "3 of 100 waits are negative." in markdown(report, "run", "h.png")
    assert "negative" not in markdown(build_report(synthetic_run()), "run", "h.png")


# -- pairing with the controller's folder ----------------------------------------------------

#: run ticks the controller recorded no row for (before its recording started)
BEFORE_RECORDING = RT_SLOTS[:10]
#: a tick whose own feedback the controller never read: it read the next tick's, which
#: echoes the same setpoint (same sp_t_ns, fb_t_ns one period later)
SUPERSEDED = RT_SLOTS[10]


def write_pair(folder):
    """An emulator run folder in folder/emulator and the controller's controller.npz in
    folder/controller: one row per controller tick, a tick without new feedback (all three
    stamps 0) after each one with."""
    run, ctl = folder / "emulator", folder / "controller"
    run.mkdir()
    ctl.mkdir()
    write_run_folder(run)
    all_stamps = stamps(*loop_arrays())
    sp_t, fb_t, fb_rx = (all_stamps[k][RT_SLOTS].copy() for k in ("sp_t_ns", "fb_t_ns",
                                                                   "fb_rx_ns"))
    i = int(np.flatnonzero(RT_SLOTS == SUPERSEDED)[0])
    fb_t[i] += PERIOD_NS
    fb_rx[i] += PERIOD_NS
    read = ~np.isin(RT_SLOTS, BEFORE_RECORDING)
    rows = np.stack([sp_t[read], fb_t[read], fb_rx[read]], axis=1)
    rows = np.insert(rows, np.arange(1, len(rows) + 1), 0, axis=0)  # the ticks without
    np.savez(ctl / "controller.npz", k=np.arange(len(rows)), fb_new=(rows[:, 0] != 0) * 1,
             fb_sp_t_ns=rows[:, 0], fb_t_ns=rows[:, 1], fb_rx_ns=rows[:, 2])
    return run, ctl


def test_pairing_fills_total_and_transport_of_the_matched_ticks(tmp_path):
    run_dir, ctl_dir = write_pair(tmp_path)
    run = load_run(run_dir, controller=ctl_dir)
    assert run.pairing == Pairing(controller=str(ctl_dir), rows=90, matched=89,
                                  unmatched_ticks=11, unmatched_rows=1)
    want = expected_round_trip(N_RAN + 1)
    unmatched = np.r_[BEFORE_RECORDING, SUPERSEDED]
    for name in ("total_ns", "transport_ns"):
        getattr(want, name)[unmatched] = NO_VALUE
    for name in ("total_ns", "transport_ns", "wait_ns", "compute_ns"):
        np.testing.assert_array_equal(getattr(run.round_trip, name), getattr(want, name), name)
    rt = build_report(run)["round_trip"]
    assert (rt["samples"], rt["with_transport"]) == (100, 89)
    assert rt["pairing"] == {"controller": str(ctl_dir), "rows": 90, "matched": 89,
                             "unmatched_ticks": 11, "unmatched_rows": 1}
    # the 89 transports left: 51.1 .. 59.9 µs in 0.1 µs steps; p50 is the 45th
    # (ceil 44.5), p99 the 89th (ceil 88.11)
    assert rt["transport_us"] == {"min": 51.1, "p50": 55.5, "p99": 59.9, "p999": 59.9,
                                  "max": 59.9}


def test_report_run_with_the_controller_reports_the_pairing(tmp_path):
    run_dir, ctl_dir = write_pair(tmp_path)
    report = report_run(run_dir, controller=ctl_dir)
    md = (run_dir / "report.md").read_text()
    assert report["round_trip"]["with_transport"] == 89
    assert "89 matched; 11 setpoints without a controller row" in md
    assert "--controller DIR" in (write_report(tmp_path, build_report(load_run(run_dir)))[1]
                                  .read_text())


@pytest.mark.parametrize("damage, match", [
    (lambda run, ctl: (ctl / "controller.npz").unlink(), "controller.npz: cannot read"),
    (lambda run, ctl: np.savez(ctl / "controller.npz", k=np.arange(3)),
     r"controller.npz: no \['fb_sp_t_ns', 'fb_t_ns', 'fb_rx_ns'\]"),
    (lambda run, ctl: np.savez(ctl / "controller.npz", fb_sp_t_ns=np.zeros(3, int),
                               fb_t_ns=np.zeros(2, int), fb_rx_ns=np.zeros(3, int)),
     "'fb_t_ns' has 2 slots"),
    (lambda run, ctl: write_run_folder(run, with_stamps=False), "no round-trip stamps to pair"),
])
def test_a_bad_pairing_is_refused_naming_file_and_key(tmp_path, damage, match):
    run_dir, ctl_dir = write_pair(tmp_path)
    damage(run_dir, ctl_dir)
    with pytest.raises(ReportError, match=match):
        load_run(run_dir, controller=ctl_dir)


def test_a_run_without_stamps_or_adapter_loads(tmp_path):
    write_run_folder(tmp_path, with_stamps=False, adapter=None)
    run = load_run(tmp_path)
    assert run.round_trip is None and run.adapter is None and run.adapter_stats is None


@pytest.mark.parametrize("damage, match", [
    (lambda d: (d / "recording.arrows").unlink(), "recording.arrows: cannot read"),
    (lambda d: (d / "recording.arrows").write_bytes(b"PAR1"), "recording.arrows: cannot read"),
    (lambda d: (d / "report.json").write_text("{"), "report.json: cannot read"),
    (lambda d: write_run_folder(d, loop={"period_ns": PERIOD_NS, "ticks": N_RAN + 1,
                                         "overruns": 0, "skipped": 1}),
     "rows for 1000 of 1001 deadlines, but .* says 1001 ticks"),
    (lambda d: write_run_folder(d, recording={"ticks_not_recorded": 1}),
     "and .*report.json 1 ticks not recorded"),
    (lambda d: write_run_folder(d, loop={"period_ns": 0, "ticks": N_RAN, "overruns": 0,
                                         "skipped": 1}), "'period_ns' must be an integer >= 1"),
    (lambda d: write_run_folder(d, scheduling=None), "needs the objects 'loop'"),
    (lambda d: write_run_folder(d, recorded=("tick_start_ns", "sp_t_ns")), "need all of"),
])
def test_a_bad_run_folder_is_refused_naming_file_and_key(tmp_path, damage, match):
    write_run_folder(tmp_path)
    damage(tmp_path)
    with pytest.raises(ReportError, match=match):
        load_run(tmp_path)


def test_a_run_cut_short_is_reported_from_its_recording(tmp_path):
    """No report.json (the emulator was killed): the report is made of the recording --
    its 1000 ticks, the one overrun its rows show (the last tick: 10 µs late + 95 µs of
    compute > the 100 µs period, past the first 0.1 s = 1000 ticks), the dropped slot
    counted as skipped only under the skip policy -- and says it was cut short; what only
    report.json holds (scheduling, the adapter's counters) is said to be unknown."""
    write_run_folder(tmp_path, recording_meta={"adapter": "udp://127.0.0.1:5005"})
    (tmp_path / "report.json").unlink()
    run = load_run(tmp_path)
    assert (run.overruns, run.skipped, run.scheduling, run.adapter_stats) == (1, 0, {}, None)
    report = build_report(run)
    assert report["ticks"] == N_RAN and report["corrupt"] is None
    assert report["notes"][0].startswith("Cut short: no report.json (the emulator did not "
                                         "end normally).")
    page = markdown(report, title="run", histogram_png="h.png")
    assert page.count("Not known: the run wrote no report.json.") == 2
    assert page.index("> Cut short") < page.index("Period 100.000 µs")
    write_run_folder(tmp_path, recording_meta={"runtime": {"overrun": "skip"}})
    (tmp_path / "report.json").unlink()
    assert load_run(tmp_path).skipped == 1


def test_report_run_writes_the_files_and_says_why_there_is_no_baseline(tmp_path, monkeypatch):
    write_run_folder(tmp_path)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    notes = []
    report = report_run(tmp_path, cyclictest_s=1, note=notes.append)
    assert report["cyclictest"] is None and any("not installed" in n for n in notes)
    assert {"report_latency.json", "report.md", "latency_hist.png"} <= {
        p.name for p in tmp_path.iterdir()}


# -- the host fingerprint --------------------------------------------------------------------

HOST_KEYS = {"kernel_release", "kernel_version", "machine", "preempt_rt", "preempt_rt_source",
             "preemption", "cpu_model", "cpu_count", "governors", "virtualization", "python",
             "numba"}


def test_host_fingerprint_on_this_machine_has_every_key():
    h = host.host_fingerprint()
    assert set(h) == HOST_KEYS
    assert isinstance(h["preempt_rt"], bool) and h["cpu_count"] >= 1
    assert json.loads(json.dumps(h)) == h


def test_host_fingerprint_never_raises_when_files_are_missing(tmp_path, monkeypatch):
    monkeypatch.setattr(host, "REALTIME_PATH", tmp_path / "no" / "realtime")
    monkeypatch.setattr(host, "CPUINFO_PATH", tmp_path / "no" / "cpuinfo")
    monkeypatch.setattr(host, "CPU_SYSFS", tmp_path / "no" / "cpu")
    monkeypatch.setenv("PATH", str(tmp_path / "no"))
    h = host.host_fingerprint()
    assert set(h) == HOST_KEYS
    assert h["preempt_rt_source"] == "uname -v" and h["virtualization"] == "unavailable"
    assert h["cpu_count"] == os.cpu_count()
    assert set(h["governors"].values()) == {"unavailable"} and len(h["governors"]) == os.cpu_count()


def test_host_fingerprint_reads_a_fake_tree(tmp_path, monkeypatch):
    (tmp_path / "realtime").write_text("1\n")
    (tmp_path / "cpuinfo").write_text(
        "processor\t: 0\nmodel name\t: Test CPU 3000\nflags\t\t: fpu hypervisor sse\n\n"
        "processor\t: 1\nmodel name\t: Test CPU 3000\nflags\t\t: fpu hypervisor sse\n")
    (tmp_path / "cpu" / "cpu0" / "cpufreq").mkdir(parents=True)
    (tmp_path / "cpu" / "cpu0" / "cpufreq" / "scaling_governor").write_text("performance\n")
    (tmp_path / "cpu" / "cpu1").mkdir()
    (tmp_path / "cpu" / "cpufreq").mkdir()  # not a CPU
    monkeypatch.setattr(host, "REALTIME_PATH", tmp_path / "realtime")
    monkeypatch.setattr(host, "CPUINFO_PATH", tmp_path / "cpuinfo")
    monkeypatch.setattr(host, "CPU_SYSFS", tmp_path / "cpu")
    monkeypatch.setenv("PATH", str(tmp_path / "no"))
    h = host.host_fingerprint()
    assert (h["preempt_rt"], h["preempt_rt_source"]) == (True, str(tmp_path / "realtime"))
    assert (h["cpu_model"], h["cpu_count"]) == ("Test CPU 3000", 2)
    assert h["governors"] == {"cpu0": "performance", "cpu1": "unavailable"}
    assert h["virtualization"].startswith("hypervisor flag set")


# -- the adapter benchmark -------------------------------------------------------------------

def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_adapter_bench_rows_have_the_documented_shape_and_leave_nothing_behind():
    resource_tracker.ensure_running()  # spawn starts it once per process and keeps its pipe
    before = _open_fds()
    notes = []
    rows = bench_adapters.run(5, ["udp", "serial"], note=notes.append)
    assert [r["adapter"] for r in rows] == ["udp", "serial"] and len(notes) == 2
    for row in rows:
        assert set(row) == {"adapter", "transport", "n", "setpoint_bytes", "feedback_bytes",
                            "round_trip_us", "raw_echo_us", "overhead_p50_us", "ratio_p50",
                            "cpu_dma_latency_held"}
        assert row["n"] == 5 and row["feedback_bytes"] > row["setpoint_bytes"] > 0
        for key in ("round_trip_us", "raw_echo_us"):
            p = row[key]
            assert set(p) == {"p50", "p99", "p999", "max"}
            assert 0 < p["p50"] <= p["p99"] <= p["p999"] <= p["max"]
        assert row["overhead_p50_us"] == row["round_trip_us"]["p50"] - row["raw_echo_us"]["p50"]
    assert multiprocessing.active_children() == []
    assert _open_fds() == before


def test_adapter_bench_refuses_unknown_adapters():
    with pytest.raises(ValueError, match="among"):
        bench_adapters.run(5, ["can"])
