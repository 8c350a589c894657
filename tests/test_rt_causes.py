"""What kept a loop from its deadline (hil/rt/causes.py): each counter moves with the
thing it counts, done on purpose here, and a loop's worst overrun names it.  The time
comes from a simulated clock, so which tick overruns is exact."""

import gc
import mmap

import numba

from hil.rt.causes import Cause, Causes
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
    assert "woken late, the CPU busy elsewhere" in Cause(0, 0, 0, 0, 0.0, 0.0).text()
