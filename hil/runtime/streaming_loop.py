"""The emulator's hard-timed loop for runs of any length: no per-tick arrays.

:class:`hil.rt.loop.RealTimeLoop` keeps every tick's lateness and compute time in two
int64 arrays sized for the whole run, allocated up front: 11 GB for 24 h at 8 kHz.
:class:`StreamingLoop` has the same tick discipline -- tick k due at ``t0 + k *
period_ns``, ``t0`` one period after :meth:`StreamingLoop.run` starts, the same
:class:`~hil.rt.loop.OverrunPolicy` and grace period, :meth:`StreamingLoop.request_stop`
a flag checked before every tick -- but hands each tick's measurements to a *sink*
(``sink.end_tick(k, lateness_ns, compute_ns)``: the emulator's
:class:`~hil.runtime.recording.Recorder`, whose writer keeps the run's percentiles) and
may run until stopped (``n_ticks`` None).

The returned :class:`~hil.rt.loop.LoopStats` has empty arrays and NaN percentiles: the
sink has the samples (:meth:`hil.runtime.record_writer.RecordingWriter.loop_percentiles`).
"""

import sys
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from hil.rt.clock import Clock, MonotonicClock
from hil.rt.loop import LoopStats, OverrunPolicy, Percentiles, StopReason


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
        self._stop_requested = False

    def request_stop(self) -> None:
        """Stop before the next tick (safe from a signal handler or another thread)."""
        self._stop_requested = True

    def run(self) -> LoopStats:
        """Run the ticks (until done, stopped by the policy, or asked to stop)."""
        step, end_tick = self.step, self.sink.end_tick
        now_ns, sleep_until = self.clock.now_ns, self.clock.sleep_until
        period = self.period_ns
        n = sys.maxsize if self.n_ticks is None else self.n_ticks
        skip = self.policy.action == "skip"
        stop_after = self.policy.stop_after if self.policy.action == "stop" else 0
        grace = self.policy.grace_ticks
        ticks = overruns = grace_overruns = skipped = 0
        stopped_by: StopReason = "completed"

        wall0, cpu0 = time.monotonic_ns(), time.process_time_ns()
        t0 = now_ns() + period
        k = 0
        while k < n:
            if self._stop_requested:
                stopped_by = "stop_flag"
                break
            deadline = t0 + k * period
            wake = sleep_until(deadline)
            step(k)
            end = now_ns()
            end_tick(k, wake - deadline, end - wake)
            ticks += 1
            if end <= deadline + period:
                k += 1
                continue
            if k < grace:
                grace_overruns += 1
            else:
                overruns += 1
                if overruns == stop_after:
                    stopped_by = "overruns"
                    break
            k_next = min((end - t0) // period + 1, n) if skip else k + 1
            skipped += k_next - k - 1
            k = k_next
        wall_ns, cpu_ns = time.monotonic_ns() - wall0, time.process_time_ns() - cpu0
        none = Percentiles.of_ns_in_us(np.empty(0, dtype=np.int64))
        empty = np.empty(0, dtype=np.int64)
        return LoopStats(period_ns=period, lateness_ns=empty, compute_ns=empty, ticks=ticks,
                         overruns=overruns, grace_overruns=grace_overruns, skipped=skipped,
                         stopped_by=stopped_by, wall_s=wall_ns * 1e-9, cpu_s=cpu_ns * 1e-9,
                         lateness_us=none, compute_us=none)
