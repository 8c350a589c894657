"""The hard-timed loop, its clocks, the scheduling requests and the cyclictest reference.

Timing behaviour is checked on a simulated clock, where a step consumes exactly the time
it is told to; runs on the real clock assert behaviour (tick counts, stop reasons, no
allocation growth, ordered and finite statistics), never how fast the machine was.
"""

import gc
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tracemalloc
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from hil.bench import loop as bench_loop
from hil.rt import scheduling
from hil.rt.clock import MAX_SPIN_FRACTION, MonotonicClock, SimulatedClock
from hil.rt.cyclictest import CyclictestError, parse_histogram, run_cyclictest
from hil.rt.loop import SKIPPED, OverrunPolicy, Percentiles, RealTimeLoop, Stall
from hil.rt.scheduling import SchedulingRequest, last_cpu, realtime_scheduling
from hil.runtime.common import shared_cpu
from tests.conftest import CONFIGS, ROOT
from tests.runtime_helpers import ENV, python_module

P = 100_000  # simulated period, ns


def simulated_loop(n_ticks, compute_ns=None, policy=None):
    """A loop on a simulated clock whose step at tick k consumes ``compute_ns.get(k, 0)``
    ns; returns (loop, clock, list of step indices called)."""
    clock = SimulatedClock(start_ns=1_000_000_000)
    called = []
    compute_ns = compute_ns or {}

    def step(k):
        called.append(k)
        clock.advance(compute_ns.get(k, 0))

    loop = RealTimeLoop(P, step, n_ticks=n_ticks, policy=policy or OverrunPolicy(), clock=clock)
    return loop, clock, called


# --- the loop on a simulated clock ------------------------------------------------------

def test_runs_exactly_n_ticks_with_indices_0_to_n_minus_1():
    loop, _, called = simulated_loop(50)
    stats = loop.run()
    assert called == list(range(50))
    assert (stats.ticks, stats.overruns, stats.skipped, stats.stopped_by) == (50, 0, 0, "completed")
    assert len(stats.lateness_ns) == len(stats.compute_ns) == 50


def test_duration_is_rounded_to_whole_periods():
    loop = RealTimeLoop(P, lambda k: None, duration_s=0.00105, clock=SimulatedClock())
    assert loop.n_ticks == 10


def test_deadlines_are_absolute_whatever_the_steps_take():
    """Tick k wakes at t0 + k*P (+ the wake-up latency): compute time does not drift it."""
    rng = np.random.default_rng(1)
    compute = {k: int(c) for k, c in enumerate(rng.integers(0, P // 2, 200))}
    clock = SimulatedClock(start_ns=7, wake_late_ns=3_000)
    wakes = []

    def step(k):
        wakes.append(clock.now_ns())
        clock.advance(compute[k])

    stats = RealTimeLoop(P, step, n_ticks=200, clock=clock).run()
    t0 = 7 + P
    assert wakes == [t0 + k * P + 3_000 for k in range(200)]
    assert np.all(stats.lateness_ns == 3_000)
    assert stats.compute_ns.tolist() == [compute[k] for k in range(200)]


def test_count_policy_counts_and_catches_up():
    """A step of 2.5 periods at tick 3 overruns; tick 4, woken 1.5 P late, overruns too;
    tick 5 is 0.5 P late and the loop is back on its deadlines from tick 6."""
    loop, _, called = simulated_loop(20, {3: 5 * P // 2}, OverrunPolicy("count"))
    stats = loop.run()
    assert called == list(range(20))
    assert (stats.overruns, stats.skipped, stats.ticks) == (2, 0, 20)
    assert stats.lateness_ns[3:7].tolist() == [0, 3 * P // 2, P // 2, 0]


def test_a_step_ending_exactly_on_the_next_deadline_is_not_an_overrun():
    loop, _, _ = simulated_loop(10, {2: P}, OverrunPolicy("count"))
    assert loop.run().overruns == 0


def test_skip_policy_drops_missed_deadlines_and_realigns():
    loop, _, called = simulated_loop(20, {3: 5 * P // 2}, OverrunPolicy("skip"))
    stats = loop.run()
    assert called == [0, 1, 2, 3] + list(range(6, 20))
    assert (stats.overruns, stats.skipped, stats.ticks) == (1, 2, 18)
    assert stats.lateness_ns[4] == stats.compute_ns[5] == SKIPPED
    assert stats.lateness_ns[6] == 0
    assert stats.lateness_us.max == 0.0 and stats.compute_us.max == 2.5 * P / 1e3


def test_skip_policy_at_the_end_counts_only_deadlines_within_the_run():
    loop, _, called = simulated_loop(10, {8: 10 * P}, OverrunPolicy("skip"))
    stats = loop.run()
    assert called == list(range(9))
    assert (stats.skipped, stats.ticks, stats.stopped_by) == (1, 9, "completed")


@pytest.mark.parametrize("action", ["count", "stop"])
def test_a_stall_resumes_at_the_present_deadline_whatever_the_policy(action):
    """A step of 10.5 periods at tick 3 misses 10 deadlines, at least resume_after = 5:
    a stall, logged; the loop goes on at tick 14 without running 4..13.  A step of 3.5
    periods at tick 20 misses 3, fewer: the count policy works them off late as before."""
    policy = OverrunPolicy(action, stop_after=10, resume_after=5)
    loop, _, called = simulated_loop(40, {3: 21 * P // 2, 20: 7 * P // 2}, policy)
    stats = loop.run()
    assert called == [0, 1, 2, 3] + list(range(14, 40))
    assert (stats.stalls, stats.skipped, stats.overruns) == (1, 10, 4)
    assert loop.stall_log == [Stall(3, 10, 19 * P // 2)]
    assert stats.lateness_ns[4] == SKIPPED and stats.lateness_ns[14] == 0
    assert stats.lateness_ns[21:25].tolist() == [5 * P // 2, 3 * P // 2, P // 2, 0]


def test_stop_policy_stops_after_n_overruns_outside_the_grace_period():
    """Overruns at ticks 1 and 3 fall in the grace period (5 ticks) and do not count
    towards stop_after=2 although there are two; those at 8 and 12 do."""
    slow = {k: 3 * P // 2 for k in (1, 3, 8, 12, 20)}
    loop, _, called = simulated_loop(30, slow, OverrunPolicy("stop", stop_after=2, grace_ticks=5))
    stats = loop.run()
    assert called == list(range(13))
    assert (stats.grace_overruns, stats.overruns, stats.stopped_by) == (2, 2, "overruns")


def test_count_policy_never_stops_and_counts_grace_apart():
    slow = {k: 3 * P // 2 for k in (1, 3, 8, 12, 20)}
    loop, _, called = simulated_loop(30, slow, OverrunPolicy("count", grace_ticks=5))
    stats = loop.run()
    assert called == list(range(30))
    assert (stats.grace_overruns, stats.overruns, stats.stopped_by) == (2, 3, "completed")


def test_stop_requested_before_the_run_runs_no_tick():
    loop, _, called = simulated_loop(10)
    loop.request_stop()
    stats = loop.run()
    assert (called, stats.ticks, stats.stopped_by) == ([], 0, "stop_flag")
    assert math.isnan(stats.lateness_us.p50)


def test_record_buffers_are_preallocated_and_reused():
    loop, _, _ = simulated_loop(100, {10: 2 * P})
    lateness, compute = loop.lateness_ns, loop.compute_ns
    for _ in range(2):
        stats = loop.run()
        assert loop.lateness_ns is lateness and loop.compute_ns is compute
        assert stats.lateness_ns.base is lateness and stats.compute_ns.base is compute
    assert lateness.dtype == compute.dtype == np.int64


@pytest.mark.parametrize("kwargs", [{"action": "drop"}, {"stop_after": 0},
                                    {"grace_ticks": -1}, {"resume_after": 0}])
def test_bad_overrun_policy_is_refused(kwargs):
    with pytest.raises(ValueError):
        OverrunPolicy(**kwargs)


@pytest.mark.parametrize("kwargs", [{}, {"n_ticks": 5, "duration_s": 1.0},
                                    {"n_ticks": 0}])
def test_loop_needs_exactly_one_positive_length(kwargs):
    with pytest.raises(ValueError):
        RealTimeLoop(P, lambda k: None, clock=SimulatedClock(), **kwargs)


def test_percentiles_are_nearest_rank():
    values = np.arange(1, 1001, dtype=np.int64) * 1000  # 1..1000 µs
    assert Percentiles.of_ns_in_us(values) == Percentiles(p50=500.0, p99=990.0, p999=999.0,
                                                          max=1000.0)


# --- the real clock ---------------------------------------------------------------------

def test_monotonic_clock_never_wakes_early():
    clock = MonotonicClock(spin_ns=20_000)
    deadline = clock.now_ns()
    for _ in range(200):
        deadline += 50_000
        assert clock.sleep_until(deadline) >= deadline


def test_spin_margin_is_capped_to_a_fraction_of_the_period():
    assert MonotonicClock.for_period(1_000_000).spin_ns == 50_000
    assert MonotonicClock.for_period(62_500).spin_ns == int(62_500 * MAX_SPIN_FRACTION)
    with pytest.raises(ValueError):
        MonotonicClock(spin_ns=-1)


def test_steady_loop_does_not_allocate_per_tick():
    """Traced memory at tick 1000 and at tick 3999 of a real-clock run: no growth."""
    traced = np.zeros(2, dtype=np.int64)

    def step(k):
        if k == 1000:
            traced[0] = tracemalloc.get_traced_memory()[0]
        elif k == 3999:
            traced[1] = tracemalloc.get_traced_memory()[0]

    loop = RealTimeLoop(50_000, step, n_ticks=4000, clock=MonotonicClock(spin_ns=20_000))
    tracemalloc.start()
    try:
        loop.run()
    finally:
        tracemalloc.stop()
    assert traced[0] > 0
    assert traced[1] - traced[0] < 512, f"grew {traced[1] - traced[0]} B over 2999 ticks"


def test_signal_handler_sets_the_stop_flag_and_the_loop_stops():
    called = []

    def step(k):
        called.append(k)
        if k == 100:
            os.kill(os.getpid(), signal.SIGUSR1)

    loop = RealTimeLoop(100_000, step, n_ticks=100_000)
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: loop.request_stop())
    try:
        stats = loop.run()
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert stats.stopped_by == "stop_flag"
    assert called == list(range(101)) and stats.ticks == 101


def test_short_real_run_gives_sane_statistics():
    loop = RealTimeLoop(250_000, lambda k: None, n_ticks=2000)
    with realtime_scheduling(SchedulingRequest(cpus=frozenset({last_cpu()}))):
        stats = loop.run()
    assert stats.ticks + stats.skipped == 2000 and stats.stopped_by == "completed"
    ran = stats.lateness_ns != SKIPPED
    assert np.all(stats.lateness_ns[ran] >= 0) and np.all(stats.compute_ns[ran] >= 0)
    for p in (stats.lateness_us, stats.compute_us):
        values = [p.p50, p.p99, p.p999, p.max]
        assert all(math.isfinite(v) and v >= 0 for v in values)
        assert values == sorted(values)
    assert math.isfinite(stats.cpu_fraction) and stats.cpu_fraction >= 0


# --- scheduling -------------------------------------------------------------------------

def _fds_to(path):
    links = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            links.append(os.readlink(f"/proc/self/fd/{fd}"))
        except OSError:
            continue
    return links.count(path)


def _timer_slack_ns():
    with open("/proc/self/timerslack_ns") as f:
        return int(f.read())


def _state():
    return (os.sched_getaffinity(0), os.sched_getscheduler(0), os.sched_getparam(0),
            gc.isenabled(), gc.get_freeze_count(), _timer_slack_ns(),
            _fds_to(scheduling.CPU_DMA_LATENCY_PATH))


def test_scheduling_reports_each_request_and_restores_everything():
    before = _state()
    cpu = last_cpu()
    with realtime_scheduling(SchedulingRequest(cpus=frozenset({cpu}))) as report:
        for name, grant in report.as_dict().items():
            assert isinstance(grant["granted"], bool) and grant["detail"], name
        if report.affinity.granted:
            assert os.sched_getaffinity(0) == {cpu}
        if report.fifo.granted:
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
            assert os.sched_getparam(0).sched_priority == 80
        if report.cpu_dma_latency.granted:
            assert _fds_to(scheduling.CPU_DMA_LATENCY_PATH) == before[-1] + 1
        if report.timer_slack.granted:  # Linux >= 6.7 gives SCHED_FIFO threads no slack
            assert _timer_slack_ns() <= 1
        assert report.gc_frozen.granted and not gc.isenabled()
        assert set(report.granted()) <= set(report.as_dict())
    assert _state() == before


def test_refused_requests_are_reported_not_raised(monkeypatch, tmp_path):
    monkeypatch.setattr(scheduling, "CPU_DMA_LATENCY_PATH", str(tmp_path / "no-such-device"))
    before = _state()
    request = SchedulingRequest(fifo_priority=1000, cpus=frozenset({100_000}), lock_memory=False,
                                cpu_dma_latency_us=0, timer_slack_ns=None, freeze_gc=False)
    with realtime_scheduling(request) as report:
        assert _state() == before
    assert not report.fifo.granted and "errno" in report.fifo.detail
    assert not report.affinity.granted and "errno" in report.affinity.detail
    assert not report.cpu_dma_latency.granted and "No such file" in report.cpu_dma_latency.detail
    assert report.mlockall == report.timer_slack == report.gc_frozen == report.kernel_threads
    assert report.mlockall.detail == "not requested"
    assert report.granted() == []
    assert _state() == before


def test_kdamond_is_kept_off_the_loops_cpu_and_given_back():
    """The kernel threads of KEPT_OFF_KERNEL_THREADS (DAMON's kdamond, docs/realtime.md)
    off the pinned loop's CPU while the block lasts, and allowed there again after it."""
    cpu = last_cpu()
    # a loop killed by SIGKILL earlier (several tests kill hil run) left them off its CPU
    for t in scheduling.kernel_threads():
        try:
            os.sched_setaffinity(t.pid, t.cpus | {cpu})
        except OSError:  # not permitted, or gone: the check below skips or takes the rest
            pass
    there = [t for t in scheduling.kernel_threads() if cpu in t.cpus and t.cpus - {cpu}]
    if not there:
        pytest.skip(f"no {', '.join(scheduling.KEPT_OFF_KERNEL_THREADS)} thread may run on "
                    f"CPU {cpu} and another here (DAMON off, one CPU, or a container, which "
                    f"sees no kernel thread)")
    with realtime_scheduling(SchedulingRequest(cpus=frozenset({cpu}))) as report:
        if not report.kernel_threads.granted:
            pytest.skip(f"moving kernel threads was refused: {report.kernel_threads.detail}")
        now = {t.pid: t for t in scheduling.kernel_threads()}
        moved = [t for t in there if t.pid in now]
        assert moved and all(cpu not in now[t.pid].cpus for t in moved), now
        assert all(t.name in report.kernel_threads.detail for t in moved)
    after = {t.pid: t.cpus for t in scheduling.kernel_threads()}
    assert all(cpu in after[t.pid] for t in moved if t.pid in after)


def test_scheduling_is_restored_when_the_block_raises():
    before = _state()
    request = SchedulingRequest(cpus=frozenset({last_cpu()}))
    with pytest.raises(RuntimeError, match="inside"), realtime_scheduling(request):
        raise RuntimeError("inside")
    assert _state() == before


# --- cyclictest -------------------------------------------------------------------------

#: cyclictest -q -m -p 80 -i 1000 -D 1 -h 10 --histfile=..., counts edited: 1000 samples,
#: 998 in the bins and 2 past the 10 µs range, the largest 250 µs.
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
# Histogram Overflow at cycle number:
# Thread 0: 00092 00262
"""


#: the name the process of _FIFO_CHILD gives itself (/proc/PID/comm), so a warning about it
#: can be told from one about another process on a shared machine
FIFO_CHILD_NAME = "fifo-neighbour"
#: a process that pins itself to a CPU under SCHED_FIFO (argv: the CPU, the priority), a
#: stand-in for another hil run or LinuxCNC's servo thread
_FIFO_CHILD = f"""
import ctypes, os, sys
ctypes.CDLL(None).prctl(15, b"{FIFO_CHILD_NAME}")  # PR_SET_NAME
os.sched_setaffinity(0, {{int(sys.argv[1])}})
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(sys.argv[2])))
except OSError as e:
    print("refused", e, flush=True)
else:
    print("ready", flush=True)
sys.stdin.read()
"""


@contextmanager
def fifo_neighbour(cpu: int, priority: int) -> Iterator[subprocess.Popen]:
    """A process of _FIFO_CHILD pinned to ``cpu`` at SCHED_FIFO ``priority`` for the block
    (the test is skipped where SCHED_FIFO is refused)."""
    child = subprocess.Popen([sys.executable, "-c", _FIFO_CHILD, str(cpu), str(priority)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        line = child.stdout.readline().strip()
        if line != "ready":
            pytest.skip(f"SCHED_FIFO is refused here: {line}")
        yield child
    finally:
        child.stdin.close()
        child.wait(timeout=10)
        child.stdout.close()


def test_a_real_time_thread_of_another_process_on_the_loops_cpu_is_named():
    """Another process pinned to the loop's CPU under SCHED_FIFO 10 is found there and on
    no other CPU, and by a loop not pinned; the warning hil run and hil controller print
    names it and says that a loop at 10 or below waits for it and one above preempts it,
    pinned or not; no warning without real time."""
    cpu = last_cpu()
    with fifo_neighbour(cpu, 10) as child:
        found = [n for n in scheduling.realtime_neighbours(cpu) if n.pid == child.pid]
        assert [(n.tid, n.policy, n.priority, n.cpus) for n in found] == [
            (child.pid, "SCHED_FIFO", 10, {cpu})]
        assert not any(n.pid == child.pid for c in os.sched_getaffinity(0) - {cpu}
                       for n in scheduling.realtime_neighbours(c))
        assert [n for n in scheduling.realtime_neighbours(None) if n.pid == child.pid] == found
        _, warning = shared_cpu(True, cpu, 10)
        assert f"CPU {cpu} is already held" in warning and f"pid {child.pid}" in warning
        assert "SCHED_FIFO 10 waits whenever" in warning and "--cpu N" in warning
        assert "SCHED_FIFO 11 preempts them" in shared_cpu(True, cpu, 11)[1]
        _, unpinned = shared_cpu(True, None, 10)
        assert "this loop is not pinned" in unpinned
        assert f"{FIFO_CHILD_NAME} (pid {child.pid}, thread {child.pid}, SCHED_FIFO 10, " \
               f"CPUs {cpu})" in unpinned
        assert shared_cpu(False, cpu, 10) == ([], None) == shared_cpu(False, None, 10)


def test_an_unpinned_hil_controller_warns_of_a_real_time_process_on_a_cpu_it_may_use(
        tmp_path):
    """hil controller in real time and not pinned (its default), beside a process pinned
    to the last CPU at SCHED_FIFO 10: its stderr names that process, pid and CPU before it
    waits for a drive (a port nobody answers: it then fails, exit 1)."""
    cpu = last_cpu()
    with fifo_neighbour(cpu, 10) as child, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))  # a port of our own that nothing answers on
        done = subprocess.run(python_module(
            "hil.cli", "controller", CONFIGS / "arrow500_x.toml", "--adapter",
            f"udp://127.0.0.1:{s.getsockname()[1]}", "--program",
            ROOT / "programs" / "demo_moves.nc", "--out", tmp_path / "ctl",
            "--connect-timeout", "1"), cwd=ROOT, env=ENV, capture_output=True, text=True,
            timeout=180, check=False)
    assert done.returncode == 1, done.stderr  # no drive answered: the run failed
    warnings = [line for line in done.stderr.splitlines() if "not pinned" in line]
    assert len(warnings) == 1, done.stderr
    assert warnings[0].startswith("hil controller: this loop is not pinned")
    assert (f"{FIFO_CHILD_NAME} (pid {child.pid}, thread {child.pid}, SCHED_FIFO 10, "
            f"CPUs {cpu})") in warnings[0]


def test_cyclictest_histogram_is_reduced_to_nearest_rank_percentiles():
    assert parse_histogram(HISTOGRAM) == Percentiles(p50=5.0, p99=6.0, p999=250.0, max=250.0)


def test_cyclictest_histogram_sums_the_threads_columns():
    two = HISTOGRAM.replace("000005 000500", "000005 000250 000250").replace(
        "000006 000490", "000006 000245 000245").replace("000009 000008", "000009 000004 000004")
    assert parse_histogram(two) == parse_histogram(HISTOGRAM)


def test_text_that_is_no_histogram_is_refused():
    with pytest.raises(CyclictestError, match="not a cyclictest histogram"):
        parse_histogram("T: 0 ( 1234) P:80 I:1000 C:   1000 Min: 5 Act: 6 Avg: 6 Max: 250\n")


def test_missing_cyclictest_gives_none(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))
    assert run_cyclictest(1000, 1) is None


def test_cyclictest_runs_when_installed():
    if shutil.which("cyclictest") is None:
        pytest.skip("cyclictest not installed (apt-get install rt-tests)")
    p = run_cyclictest(1000, 1, cpu=last_cpu())
    assert 0 <= p.p50 <= p.p99 <= p.p999 <= p.max


def test_bench_rows_have_the_documented_fields(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))
    notes = []
    rows = bench_loop.run([2000], 0.05, with_plant=False, note=notes.append)
    assert len(rows) == 1
    row = rows[0]
    assert {"rate_hz", "lateness_us", "overruns", "cyclictest_us"} <= set(row)
    assert set(row["lateness_us"]) == {"p50", "p99", "p999", "max"}
    assert (row["rate_hz"], row["period_us"], row["cyclictest_us"]) == (2000, 500, None)
    assert any("not installed" in n for n in notes)


def test_a_start_given_beforehand_is_tick_zeros_deadline_whenever_run_begins():
    """A controller aligned to its drive gives the loop tick 0's deadline: the ticks keep
    that phase exactly, however long the caller took to reach run() (before, the loop took
    one period after its own start, and the delay moved the phase: the serial loopback's
    setpoints then missed the drive's tick)."""
    from hil.rt.clock import SimulatedClock
    clock = SimulatedClock(start_ns=1_000_000_000)
    seen = []
    loop = RealTimeLoop(50_000, lambda k: seen.append(clock.now_ns()), n_ticks=3, clock=clock)
    loop.start_ns = 1_000_000_000 + 10_000_000 + 123
    clock.advance(7_654_321)  # what ran between the alignment and run()
    loop.run()
    assert seen == [loop.start_ns + k * 50_000 for k in range(3)]
