"""Clocks a real-time loop waits on: ``now_ns()`` and ``sleep_until(deadline_ns)``.

:class:`MonotonicClock` sleeps for the bulk of the wait and spins on the clock for the
last ``spin_ns``, so it wakes within a clock read of the deadline unless the sleep itself
overshoots the margin.  Both are :func:`sleep_until_ns`, compiled: ``clock_nanosleep``
on ``CLOCK_MONOTONIC`` to the absolute time ``deadline - spin`` (resumed after a signal),
then ``clock_gettime`` until the deadline, so no wait accumulates drift.  The emulator's
compiled steady loop (:mod:`hil.runtime.steady_tick`) waits with the same function, so
both paths keep one discipline.  The sleep wakes late by the thread's timer slack (50 µs
by default): request a slack of 1 ns with :func:`hil.rt.scheduling.realtime_scheduling`
before a run.  Sleeping for most of the period matters under SCHED_FIFO: a thread that
busy-waits through whole periods runs into the kernel's real-time throttling and is
stopped for tens of milliseconds.

:class:`SimulatedClock` jumps to each deadline; a step can :meth:`~SimulatedClock.advance`
it to model its compute time, which makes overruns deterministic in tests.
"""

import errno
import time
from typing import Protocol

import numpy as np
from numba import njit, types

#: default spin margin: covers the usual wake-up latency of a sleep with 1 ns timer slack
#: under SCHED_FIFO with /dev/cpu_dma_latency at 0 (p99 about 30-40 µs on a 2-vCPU VM).
DEFAULT_SPIN_NS = 50_000
#: the most of a period :meth:`MonotonicClock.for_period` spins: the thread must sleep
#: for most of every period or real-time throttling stops it.
MAX_SPIN_FRACTION = 0.4


_clock_gettime = types.ExternalFunction("clock_gettime",
                                        types.int32(types.int32, types.voidptr))
_clock_nanosleep = types.ExternalFunction(
    "clock_nanosleep", types.int32(types.int32, types.int32, types.voidptr, types.voidptr))
_CLOCK_MONOTONIC, _TIMER_ABSTIME, _EINTR = time.CLOCK_MONOTONIC, 1, errno.EINTR


@njit(cache=True, inline="always")
def now_ns(timespec):
    """``CLOCK_MONOTONIC`` (``time.monotonic_ns``'s clock), ns; ``timespec``: int64[2]
    of room."""
    _clock_gettime(_CLOCK_MONOTONIC, timespec.ctypes)
    return timespec[0] * 1_000_000_000 + timespec[1]


@njit(cache=True, nogil=True)
def sleep_until_ns(deadline_ns, spin_ns, timespec):
    """Sleep until ``spin_ns`` before ``deadline_ns`` (``CLOCK_MONOTONIC``, absolute),
    then spin until it: (the time woken, the time the sleep ended), ns; the second less
    ``deadline_ns - spin_ns`` is the wake-up latency cyclictest measures (the time the
    call came, when that was later).  ``timespec``: int64[2] of room."""
    start = deadline_ns - spin_ns
    if start > now_ns(timespec):
        timespec[0] = start // 1_000_000_000
        timespec[1] = start % 1_000_000_000
        while _clock_nanosleep(_CLOCK_MONOTONIC, _TIMER_ABSTIME, timespec.ctypes,
                               timespec.ctypes) == _EINTR:
            timespec[0] = start // 1_000_000_000
            timespec[1] = start % 1_000_000_000
    slept = t_ns = now_ns(timespec)
    while t_ns < deadline_ns:
        t_ns = now_ns(timespec)
    return t_ns, slept


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
        self._timespec = np.zeros(2, np.int64)
        # compiled (or loaded from numba's cache) now, not at the loop's first deadline
        sleep_until_ns(0, 0, self._timespec)

    @classmethod
    def for_period(cls, period_ns: int, spin_ns: int = DEFAULT_SPIN_NS) -> "MonotonicClock":
        """A clock for a loop of ``period_ns``: ``spin_ns``, but at most
        ``MAX_SPIN_FRACTION`` of the period (25 µs at 16 kHz, 50 µs at 8 kHz and below)."""
        return cls(min(spin_ns, int(period_ns * MAX_SPIN_FRACTION)))

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, deadline_ns: int) -> int:
        return sleep_until_ns(deadline_ns, self.spin_ns, self._timespec)[0]


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
