"""What kept a loop from its deadline (hil/rt/causes.py): each counter moves with the
thing it counts, done on purpose here, and a loop's worst overrun names it.  The time
comes from a simulated clock, so which tick overruns is exact."""

import gc
import mmap
import os
import subprocess
import sys
import time

import numba
import pytest

from hil.rt.causes import CLOCK_TICKS_S, Cause, Causes, steal_ticks
from hil.rt.clock import SimulatedClock
from hil.rt.loop import RealTimeLoop
from hil.runtime.timing_quality import TimingQuality

P = 125_000


def test_each_counter_moves_with_what_it_counts():
    """A collection, fresh pages touched and a kernel compiled each show in their own
    counter; a second read with nothing done in between reads zero."""
    causes = Causes()
    causes.since_last()
    gc.collect()
    assert causes.since_last().gc_collections >= 1
    # 32 MB the process never touched (a fresh mapping: the allocator's own free memory
    # may have been touched before), written page by page: a fault per 4 kB page, or per
    # 2 MB one where the kernel maps transparent huge pages
    size = 32 << 20
    with mmap.mmap(-1, size) as fresh:
        for offset in range(0, size, mmap.PAGESIZE):
            fresh[offset] = 1
        assert causes.since_last().page_faults >= size // (2 << 20) // 2

    @numba.njit
    def add_one(x):
        return x + 1

    add_one(1)
    assert causes.since_last().compile_ms > 0
    quiet = causes.since_last()
    assert (quiet.page_faults, quiet.gc_collections, quiet.compile_ms) == (0, 0, 0.0)


def test_the_worst_overrun_names_the_tick_how_late_and_what_ran():
    """Tick 30 collects garbage and takes 3 periods, tick 60 one and a half: three
    overruns (30, 31 that starts 2 periods late, 60); the worst is 30, 2 periods behind
    the next deadline, in a Python tick, with the collection; the total has both
    collections; TimingQuality's text says it in words."""
    clock = SimulatedClock(start_ns=1_000_000_000)

    def step(k: int) -> None:
        if k in (30, 60):
            gc.collect()
            clock.advance(3 * P if k == 30 else 3 * P // 2)

    stats = RealTimeLoop(P, step, n_ticks=100, clock=clock).run()
    assert stats.overruns == 3
    worst = stats.worst_overrun
    assert (worst["tick"], worst["behind_us"], worst["where"]) == (30, 2 * P / 1e3, "python")
    assert worst["cause"]["gc_collections"] >= 1
    assert stats.overrun_causes["gc_collections"] >= 2
    loop = stats.as_dict()
    quality = TimingQuality.of_controller({"loop": loop, "feedback": {
        "lag_ticks": {"2+": 0}, "ticks_without_new": 0}})
    text = quality.worst_text()
    assert text.startswith("controller's worst overrun: tick 30 (t = 0.0037 s), 250.0 µs "
                           "after the next deadline, in a python tick; since the overrun "
                           "before it: "), text
    assert "garbage collection(s)" in text


def test_a_loop_on_time_has_no_worst_overrun_and_an_empty_cause_says_so():
    stats = RealTimeLoop(P, lambda k: None, n_ticks=50, clock=SimulatedClock()).run()
    assert stats.worst_overrun is None and stats.overrun_causes is None
    assert Cause(0, 0, 0, 0, 0.0, 0.0).text().startswith("nothing the loop counts")


@pytest.mark.skipif(not os.path.exists("/proc/thread-self/schedstat"),
                    reason="this kernel keeps no scheduler statistics per thread "
                           "(/proc/thread-self/schedstat)")
def test_a_cpu_shared_with_a_busy_process_shows_as_waiting_for_it():
    """This thread and a busy child on one CPU, both at normal priority: the scheduler
    shares it, so the thread spends much of 0.4 s of its own busy work runnable but
    waiting; the text names the wait and its interval."""
    cpu = min(os.sched_getaffinity(0))
    before = os.sched_getaffinity(0)
    busy = subprocess.Popen([sys.executable, "-c", f"import os; os.sched_setaffinity(0, "
                             f"{{{cpu}}}); print(flush=True)\nwhile True: pass"],
                            stdout=subprocess.PIPE)
    try:
        busy.stdout.readline()  # pinned and spinning from here
        os.sched_setaffinity(0, {cpu})
        causes = Causes()
        end = time.monotonic() + 0.4
        while time.monotonic() < end:
            pass
        cause = causes.since_last()
    finally:
        os.sched_setaffinity(0, before)
        busy.kill()
        busy.wait()
    assert cause.runqueue_ms > 50.0 and cause.interval_s >= 0.4, cause
    assert "ms for its CPU in 0.4" in cause.text()


def test_steal_is_read_from_the_cpus_line_of_proc_stat():
    """/proc/stat's eighth number after the name is steal, in clock ticks: CPU 1's line,
    the sum line for a thread on several CPUs; the text names steal first."""
    stat = (b"cpu  4433588 541129 591785 5079609 4928 0 15240 1588 0 0\n"
            b"cpu0 1873107 274211 247295 2925582 1337 0 6816 793 0 0\n"
            b"cpu1 2560481 266918 344490 2154026 3590 0 8423 795 0 0\n")
    assert (steal_ticks(stat, 1), steal_ticks(stat, None), steal_ticks(stat, 7)) == (795, 1588, 0)
    text = Cause(0, 0, 0, 0, 0.0, 0.0, steal_ms=1000.0 / CLOCK_TICKS_S).text()
    assert text.startswith("the hypervisor ran something else on the loop's virtual CPU for 10 ms")


def test_worst_overruns_of_both_loops_at_one_moment_name_the_machine():
    """The emulator's worst overrun (8 kHz, 7 ms behind) and the controller's (1 ms
    behind) overlap on the shared monotonic clock: the line says the machine stopped both;
    2 ms apart after the emulator's ended they do not; a report without deadlines (an
    earlier version's) gives no line."""
    from hil.runtime.timing_quality import TimingQuality, same_moment

    def side(name: str, deadline_ns: int | None, behind_us: float) -> TimingQuality:
        worst = {"tick": 10, "behind_us": behind_us, "where": "python",
                 "cause": Cause(0, 0, 0, 0, 0.0, 0.0).as_dict()}
        if deadline_ns is not None:
            worst["deadline_ns"] = deadline_ns
        return TimingQuality(name, 1000, 1, behind_us, 0, 0, "setpoints", 0, 0, worst,
                             125e-6)

    emulator = side("emulator", 5_000_000_000, 7000.0)  # its tick ends at +7.125 ms
    assert same_moment(emulator, side("controller", 5_006_000_000, 1000.0)).startswith(
        "both loops' worst overruns happened at the same moment (emulator 7000.0 µs, "
        "controller 1000.0 µs behind, 6000 µs apart)")
    assert same_moment(emulator, side("controller", 5_009_200_000, 1000.0)) == ""
    assert same_moment(emulator, side("controller", None, 1000.0)) == ""
