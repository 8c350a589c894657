"""The emulator's hard-timed loop for runs of any length: no per-tick arrays.

:class:`hil.rt.loop.RealTimeLoop` keeps every tick's lateness and compute time in two
int64 arrays sized for the whole run, allocated up front: 11 GB for 24 h at 8 kHz.
:class:`StreamingLoop` has the same tick discipline -- tick k due at ``t0 + k *
period_ns``, ``t0`` one period after :meth:`StreamingLoop.run` starts, the same
:class:`~hil.rt.loop.OverrunPolicy`, grace period and stalls (``stall_log``),
:meth:`StreamingLoop.request_stop` a flag checked before every tick -- but hands each tick's measurements to a *sink*
(``sink.end_tick(k, lateness_ns, compute_ns)``: the emulator's
:class:`~hil.runtime.recording.Recorder`, whose writer keeps the run's percentiles) and
may run until stopped (``n_ticks`` None).

The returned :class:`~hil.rt.loop.LoopStats` has empty arrays and NaN percentiles: the
sink has the samples (:meth:`hil.runtime.record_writer.RecordingWriter.loop_percentiles`).
"""

import sys
from collections.abc import Callable
from dataclasses import asdict
from typing import Protocol

import numpy as np

from hil.rt.clock import Clock, MonotonicClock
from hil.rt.loop import LoopStats, OverrunPolicy, Percentiles, Stall, run_ticks


class TickSink(Protocol):
    """Where the loop puts each tick's measurements."""

    def end_tick(self, k: int, lateness_ns: int, compute_ns: int) -> None:
        """Tick ``k`` woke ``lateness_ns`` after its deadline and its step took
        ``compute_ns`` (ns)."""


class StreamingLoop:
    """Call ``step(k)`` at ``t0 + k * period_ns`` for k = 0 .. n_ticks - 1 (or until
    stopped), then ``sink.end_tick(k, lateness, compute)``.

    Args:
        period_ns: the period (ns).
        step: the work of one tick, given the tick index; it must not block.
        sink: receives each tick's lateness and compute time.
        n_ticks: deadlines to run; None: until :meth:`request_stop` or the policy stops it.
        policy: what an overrun does (:class:`~hil.rt.loop.OverrunPolicy`).
        clock: what to wait on; by default ``MonotonicClock.for_period(period_ns)``.
    """

    def __init__(self, period_ns: int, step: Callable[[int], None], sink: TickSink,
                 n_ticks: int | None = None, policy: OverrunPolicy = OverrunPolicy(),
                 clock: Clock | None = None):
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        if n_ticks is not None and n_ticks < 1:
            raise ValueError(f"the loop needs at least one tick, got {n_ticks}")
        self.period_ns = int(period_ns)
        self.step = step
        self.sink = sink
        self.n_ticks = n_ticks
        self.policy = policy
        self.clock = clock if clock is not None else MonotonicClock.for_period(self.period_ns)
        self.stop_requested = False
        #: the same request for compiled code (hil.runtime.steady_tick reads it every tick)
        self.stop_word = np.zeros(1, np.int64)
        self.stall_log: list[Stall] = []  # appended by the loop's thread, read by others
        #: runs ticks in compiled code where it may (:func:`hil.rt.loop.run_ticks`); None:
        #: every tick is ``step``'s
        self.burst = None
        #: tick 0's deadline (ns) where a phase found before the run must be kept (the soak
        #: master aligned to its drive); None: one period after :meth:`run` starts
        self.start_ns: int | None = None

    def request_stop(self) -> None:
        """Stop before the next tick (safe from a signal handler or another thread)."""
        self.stop_requested = True
        self.stop_word[0] = 1

    def run(self) -> LoopStats:
        """Run the ticks (until done, stopped by the policy, or asked to stop)."""
        c = run_ticks(self, self.sink.end_tick,
                      sys.maxsize if self.n_ticks is None else self.n_ticks)
        none = Percentiles.of_ns_in_us(np.empty(0, dtype=np.int64))
        empty = np.empty(0, dtype=np.int64)
        return LoopStats(period_ns=self.period_ns, lateness_ns=empty, compute_ns=empty,
                         **asdict(c), lateness_us=none, compute_us=none)
