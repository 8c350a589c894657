"""Clocks a real-time loop waits on: ``now_ns()`` and ``sleep_until(deadline_ns)``.

:class:`MonotonicClock` sleeps for the bulk of the wait and spins on
``time.monotonic_ns`` for the last ``spin_ns``, so it wakes within a clock read of the
deadline unless the sleep itself overshoots the margin.  The standard library has no
``clock_nanosleep`` (``time`` lacks it on the Python 3.11 this was written on), so the
bulk is a relative ``time.sleep`` (resumed after a signal, PEP 475); the spin ends on the
absolute deadline, so relative sleeps cannot accumulate drift.  The sleep wakes late by
the thread's timer slack (50 µs by default): request a slack of 1 ns with
:func:`hil.rt.scheduling.realtime_scheduling` before a run.  Sleeping for most of the
period matters under SCHED_FIFO: a thread that busy-waits through whole periods runs into
the kernel's real-time throttling and is stopped for tens of milliseconds.

:class:`SimulatedClock` jumps to each deadline; a step can :meth:`~SimulatedClock.advance`
it to model its compute time, which makes overruns deterministic in tests.
"""

import time
from typing import Protocol

#: default spin margin: covers the usual wake-up latency of a sleep with 1 ns timer slack
#: under SCHED_FIFO with /dev/cpu_dma_latency at 0 (p99 about 30-40 µs on a 2-vCPU VM).
DEFAULT_SPIN_NS = 50_000
#: the most of a period :meth:`MonotonicClock.for_period` spins: the thread must sleep
#: for most of every period or real-time throttling stops it.
MAX_SPIN_FRACTION = 0.4


class Clock(Protocol):
    """What :class:`hil.rt.loop.RealTimeLoop` needs from a clock (times in ns)."""

    def now_ns(self) -> int:
        """Current time on a monotonic clock."""

    def sleep_until(self, deadline_ns: int) -> int:
        """Return at or after ``deadline_ns``; returns the time of waking."""


class MonotonicClock:
    """``CLOCK_MONOTONIC``: sleep until ``spin_ns`` before the deadline, then spin.

    Args:
        spin_ns: how long before the deadline the sleep ends and the spin starts (ns).
            Larger tolerates later wake-ups at the cost of CPU time.
    """

    def __init__(self, spin_ns: int = DEFAULT_SPIN_NS):
        if spin_ns < 0:
            raise ValueError(f"spin_ns must be >= 0, got {spin_ns}")
        self.spin_ns = int(spin_ns)

    @classmethod
    def for_period(cls, period_ns: int, spin_ns: int = DEFAULT_SPIN_NS) -> "MonotonicClock":
        """A clock for a loop of ``period_ns``: ``spin_ns``, but at most
        ``MAX_SPIN_FRACTION`` of the period (25 µs at 16 kHz, 50 µs at 8 kHz and below)."""
        return cls(min(spin_ns, int(period_ns * MAX_SPIN_FRACTION)))

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, deadline_ns: int) -> int:
        now_ns = time.monotonic_ns
        sleep_ns = deadline_ns - self.spin_ns - now_ns()
        if sleep_ns > 0:
            time.sleep(sleep_ns * 1e-9)
        t_ns = now_ns()
        while t_ns < deadline_ns:
            t_ns = now_ns()
        return t_ns


class SimulatedClock:
    """A clock that only moves when told: deterministic time for tests.

    ``sleep_until`` jumps to the deadline (or stays, when already past it) and then adds
    ``wake_late_ns``, a fixed wake-up latency.

    Args:
        start_ns: the time the clock starts at.
        wake_late_ns: how late every ``sleep_until`` wakes (ns, >= 0).
    """

    def __init__(self, start_ns: int = 0, wake_late_ns: int = 0):
        if wake_late_ns < 0:
            raise ValueError(f"wake_late_ns must be >= 0, got {wake_late_ns}")
        self.t_ns = int(start_ns)
        self.wake_late_ns = int(wake_late_ns)

    def now_ns(self) -> int:
        return self.t_ns

    def sleep_until(self, deadline_ns: int) -> int:
        self.t_ns = max(self.t_ns, deadline_ns) + self.wake_late_ns
        return self.t_ns

    def advance(self, duration_ns: int) -> None:
        """Let ``duration_ns`` pass (a step's compute time)."""
        self.t_ns += int(duration_ns)
