"""A hard-timed loop: one step per period on absolute deadlines, every tick measured.

::

    loop = RealTimeLoop(period_ns=125_000, step=plant_step, duration_s=10.0,
                        policy=OverrunPolicy("stop", stop_after=3, grace_ticks=100))
    signal.signal(signal.SIGINT, lambda *_: loop.request_stop())
    stats = loop.run()

Tick ``k`` is due at ``t0 + k * period_ns`` (``t0`` one period after :meth:`RealTimeLoop.run`
starts); the clock wakes the loop at that deadline, ``step(k)`` runs, and the loop writes

* ``lateness_ns[k]`` = wake-up time - deadline,
* ``compute_ns[k]`` = end of the step - wake-up time

into int64 arrays allocated when the loop is built and written through before the clock
starts (no page faults later).  A tick keeps nothing allocated: CPython's integers for the
timestamps are freed as they go, and traced memory does not grow over a run.  A tick
*overruns* when its step ends after the next deadline.  What follows is the
:class:`OverrunPolicy`'s choice, after Simulink Real-Time's and dSPACE's overload options:

* ``"count"``: keep going; the following ticks run late until the loop has caught up;
* ``"skip"``: drop the deadlines already missed and wait for the next future one; the
  dropped ticks are counted and their slots hold :data:`SKIPPED`;
* ``"stop"``: like ``"count"``, but stop once ``stop_after`` overruns have happened.

A *stall* -- a tick that ends ``resume_after`` or more deadlines late: the process was
stopped (SIGSTOP, a debugger) or the machine paused -- is no backlog to work off: whatever
the action, the loop resumes at the present deadline as ``"skip"`` does (the missed ticks
are counted in ``skipped``), counts it in ``stalls`` and logs it in the loop's
``stall_log`` (:class:`Stall`; the first :data:`MAX_STALLS_LOGGED`).  Replaying the missed
ticks back to back would run them on inputs that stopped arriving with the stall: a
drive's setpoint watchdog would count them as the controller's silence.  It is an overrun
too.

Every overrun after the grace period reads what kept the loop from its deadline
(:mod:`hil.rt.causes`: preemption, page faults, garbage collection, numba compiling,
counted since the previous run of overruns; read at the first overrun of a run only, so
the ticks that catch up after it cost nothing more, and nothing is read while the loop
keeps its time):
``overrun_causes`` sums them over the run and ``worst_overrun`` names the latest tick's
(where it ran: ``"compiled"`` in a burst, ``"python"`` in ``step``).

Overruns in the first ``grace_ticks`` ticks (start-up: caches, first page touches) are
counted apart and never stop the loop.  :meth:`RealTimeLoop.request_stop` only sets a
flag, checked before every tick: it is what a signal handler should call.
"""

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np

from hil.rt.causes import Cause, Causes
from hil.rt.clock import Clock, MonotonicClock

#: the value of a dropped tick's slot in ``lateness_ns`` and ``compute_ns``
SKIPPED = np.iinfo(np.int64).min
#: stalls kept in a loop's ``stall_log``; later ones are counted only
MAX_STALLS_LOGGED = 1000

StopReason = Literal["completed", "overruns", "stop_flag"]


@dataclass(frozen=True)
class OverrunPolicy:
    """What an overrun does (see the module docstring).

    Attributes:
        action: ``"count"``, ``"skip"`` or ``"stop"``.
        stop_after: with ``"stop"``, the overrun (after the grace period) that stops the loop.
        grace_ticks: the first ticks, whose overruns are counted apart and never stop it.
        resume_after: deadlines missed by one tick that make it a stall, after which the
            loop resumes at the present deadline (None: never; ``"skip"`` always does).
    """
    action: Literal["count", "skip", "stop"] = "count"
    stop_after: int = 1
    grace_ticks: int = 0
    resume_after: int | None = None

    def __post_init__(self):
        if self.action not in ("count", "skip", "stop"):
            raise ValueError(f"overrun action must be count, skip or stop, got {self.action!r}")
        if self.stop_after < 1:
            raise ValueError(f"stop_after must be >= 1, got {self.stop_after}")
        if self.grace_ticks < 0:
            raise ValueError(f"grace_ticks must be >= 0, got {self.grace_ticks}")
        if self.resume_after is not None and self.resume_after < 1:
            raise ValueError(f"resume_after must be >= 1, got {self.resume_after}")


@dataclass(frozen=True)
class Stall:
    """A tick that ended ``missed`` deadlines late (module docstring).

    Attributes:
        tick: its deadline index.
        missed: the deadlines after it that had passed when it ended, dropped.
        behind_ns: how long after the next deadline it ended, ns.
    """
    tick: int
    missed: int
    behind_ns: int


def nearest_rank(permille: int, n: int) -> int:
    """The 1-based rank in ``n`` sorted samples of the smallest one with at least
    ``permille`` / 1000 of them at or below it (exact integer arithmetic)."""
    return max(1, -(-permille * n // 1000))


@dataclass(frozen=True)
class Percentiles:
    """p50, p99, p99.9 and maximum of a sample, in the unit named by the field that holds
    them (nearest rank: the smallest value with at least that fraction at or below it;
    NaN for an empty sample)."""
    p50: float
    p99: float
    p999: float
    max: float

    @classmethod
    def of_ns_in_us(cls, values_ns: np.ndarray) -> "Percentiles":
        """The percentiles of ``values_ns`` (ns), in µs."""
        n = values_ns.size
        if n == 0:
            return cls(*([float("nan")] * 4))
        ordered = np.sort(values_ns)
        p50, p99, p999 = (float(ordered[nearest_rank(q, n) - 1]) / 1e3 for q in (500, 990, 999))
        return cls(p50=p50, p99=p99, p999=p999, max=float(ordered[-1]) / 1e3)

    def as_dict(self) -> dict:
        return {"p50": self.p50, "p99": self.p99, "p999": self.p999, "max": self.max}


@dataclass(frozen=True)
class LoopStats:
    """What one :meth:`RealTimeLoop.run` measured.

    Attributes:
        period_ns: the period.
        lateness_ns, compute_ns: views of the loop's buffers over the deadlines the run
            covered (``SKIPPED`` where a tick was dropped); the next run overwrites them.
        ticks: steps run.
        overruns: overruns after the grace period.
        grace_overruns: overruns within the grace period.
        skipped: ticks dropped by the ``"skip"`` policy or after a stall.
        stalls: ticks that ended ``resume_after`` or more deadlines late.
        stopped_by: ``"completed"``, ``"overruns"`` (the ``"stop"`` policy) or ``"stop_flag"``.
        wall_s, cpu_s: elapsed real time and the process's CPU time over the run (s).
        overrun_causes: what the overruns after the grace period found, summed
            (:class:`~hil.rt.causes.Cause` as a dict; None: there were none).
        worst_overrun: the one that ended latest: ``tick``, ``behind_us`` (after the
            next deadline), ``deadline_ns`` (its deadline on the loop's clock: the
            machine's monotonic clock, which another process's loop shares), ``where``
            ("compiled" or "python") and ``cause`` (what moved since the overrun before
            it); None: none.
        lateness_us, compute_us: percentiles over the ticks run.
    """
    period_ns: int
    lateness_ns: np.ndarray
    compute_ns: np.ndarray
    ticks: int
    overruns: int
    grace_overruns: int
    skipped: int
    stalls: int
    stopped_by: StopReason
    wall_s: float
    cpu_s: float
    overrun_causes: dict | None
    worst_overrun: dict | None
    lateness_us: Percentiles
    compute_us: Percentiles

    @property
    def cpu_fraction(self) -> float:
        """CPU time over elapsed time: the share of one core the run used."""
        return self.cpu_s / self.wall_s if self.wall_s > 0 else 0.0

    def as_dict(self) -> dict:
        """The scalar figures (no arrays), JSON-ready."""
        return {"period_ns": self.period_ns, "ticks": self.ticks, "overruns": self.overruns,
                "grace_overruns": self.grace_overruns, "skipped": self.skipped,
                "stalls": self.stalls, "stopped_by": self.stopped_by, "wall_s": self.wall_s,
                "cpu_s": self.cpu_s, "cpu_fraction": self.cpu_fraction,
                "overrun_causes": self.overrun_causes, "worst_overrun": self.worst_overrun,
                "lateness_us": self.lateness_us.as_dict(),
                "compute_us": self.compute_us.as_dict()}


@dataclass(frozen=True)
class TickCounts:
    """What :func:`run_ticks` counted (see :class:`LoopStats` for the fields)."""
    ticks: int
    overruns: int
    grace_overruns: int
    skipped: int
    stalls: int
    stopped_by: StopReason
    wall_s: float
    cpu_s: float
    overrun_causes: dict | None
    worst_overrun: dict | None


def run_ticks(loop, end_tick: Callable[[int, int, int], None], n: int) -> TickCounts:
    """The tick discipline of :class:`RealTimeLoop` and
    :class:`hil.runtime.streaming_loop.StreamingLoop` (module docstring): ``loop.step(k)``
    at ``t0 + k * loop.period_ns`` for k < ``n``, ``end_tick(k, lateness_ns,
    compute_ns)`` after each, ``loop.policy`` on an overrun, ``loop.stop_requested``
    checked before every tick, waits on ``loop.clock``, logs stalls in
    ``loop.stall_log``.

    A loop with a ``burst`` (not None) may run ticks in compiled code:
    ``loop.burst(k, t0, n)`` runs ticks from k on, each waited for, run and ended as
    here, up to the first that overran, and returns (ticks run, the last one's end, and
    the wake-up of the tick after them when that one was woken but is this loop's to run:
    :meth:`hil.runtime.steady_tick.SteadyTick.burst`); the policy here judges the last
    one as it judges a tick run here."""
    step, now_ns, sleep_until = loop.step, loop.clock.now_ns, loop.clock.sleep_until
    burst = getattr(loop, "burst", None)
    period = loop.period_ns
    skip = loop.policy.action == "skip"
    stop_after = loop.policy.stop_after if loop.policy.action == "stop" else 0
    grace = loop.policy.grace_ticks
    resume_after = loop.policy.resume_after or n + 1
    stall_log = loop.stall_log
    ticks = overruns = grace_overruns = skipped = stalls = 0
    stopped_by: StopReason = "completed"
    causes = Causes()
    total: Cause | None = None
    worst: dict | None = None
    episode: Cause | None = None  # what the first overrun of the present run of them read
    on_time = True  # the tick before ended in time

    wall0, cpu0 = time.monotonic_ns(), time.process_time_ns()
    # a phase given beforehand is kept exactly: taken from the clock here, it would move
    # by whatever ran between the caller's wake-up and this line
    t0 = loop.start_ns if loop.start_ns is not None else now_ns() + period
    k = 0
    woke = None  # the wake-up of tick k, woken in a burst but this loop's to run
    while k < n:
        if loop.stop_requested:
            stopped_by = "stop_flag"
            break
        ran = 0
        if burst is not None and woke is None:
            ran, end, woke = burst(k, t0, n)
        if ran:
            ticks += ran
            k += ran - 1  # the last tick run; the ones before it ended on time
            deadline = t0 + k * period
            on_time = on_time or ran > 1
        else:
            deadline = t0 + k * period
            wake = woke if woke is not None else sleep_until(deadline)
            woke = None
            step(k)
            end = now_ns()
            end_tick(k, wake - deadline, end - wake)
            ticks += 1
        if end <= deadline + period:
            k += 1
            on_time = True
            continue
        if k < grace:
            grace_overruns += 1
        else:
            overruns += 1
            if on_time or episode is None:  # ticks catching up inherit its cause
                episode = causes.since_last()
                total = episode if total is None else total.plus(episode)
            behind = end - deadline - period
            if worst is None or behind > worst["behind_ns"]:
                worst = {"tick": k, "behind_ns": behind, "deadline_ns": deadline,
                         "where": "compiled" if ran else "python", "cause": episode}
            if overruns == stop_after:
                stopped_by = "overruns"
                break
        on_time = False
        missed = (end - t0) // period - k
        if missed >= resume_after:
            stalls += 1
            if len(stall_log) < MAX_STALLS_LOGGED:
                stall_log.append(Stall(k, missed, end - deadline - period))
        k_next = min(k + missed + 1, n) if skip or missed >= resume_after else k + 1
        skipped += k_next - k - 1
        k = k_next
    if worst is not None:
        worst = {"tick": worst["tick"], "behind_us": worst["behind_ns"] * 1e-3,
                 "deadline_ns": worst["deadline_ns"], "where": worst["where"],
                 "cause": worst["cause"].as_dict()}
    return TickCounts(ticks, overruns, grace_overruns, skipped, stalls, stopped_by,
                      (time.monotonic_ns() - wall0) * 1e-9,
                      (time.process_time_ns() - cpu0) * 1e-9,
                      None if total is None else total.as_dict(), worst)


class RealTimeLoop:
    """Call ``step(k)`` at ``t0 + k * period_ns`` for k = 0 .. n_ticks - 1.

    Args:
        period_ns: the period (ns), e.g. 125_000 for 8 kHz.
        step: the work of one tick, given the tick index; it must not block.
        n_ticks: how many deadlines to run; or
        duration_s: how long to run (rounded to whole periods).
        policy: what an overrun does.
        clock: what to wait on; by default ``MonotonicClock.for_period(period_ns)``.
    """

    def __init__(self, period_ns: int, step: Callable[[int], None], n_ticks: int | None = None,
                 duration_s: float | None = None, policy: OverrunPolicy = OverrunPolicy(),
                 clock: Clock | None = None):
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns}")
        if (n_ticks is None) == (duration_s is None):
            raise ValueError("give exactly one of n_ticks and duration_s")
        if n_ticks is None:
            n_ticks = round(duration_s * 1e9 / period_ns)
        if n_ticks < 1:
            raise ValueError(f"the loop needs at least one tick, got {n_ticks} "
                             f"(period {period_ns} ns, duration {duration_s} s)")
        self.period_ns = int(period_ns)
        self.step = step
        self.n_ticks = int(n_ticks)
        self.policy = policy
        self.clock = clock if clock is not None else MonotonicClock.for_period(self.period_ns)
        self.lateness_ns = np.full(self.n_ticks, SKIPPED, dtype=np.int64)
        self.compute_ns = np.full(self.n_ticks, SKIPPED, dtype=np.int64)
        self.stop_requested = False
        #: the same request for compiled code that runs ticks (a ``burst``), read every tick
        self.stop_word = np.zeros(1, np.int64)
        self.stall_log: list[Stall] = []
        #: runs ticks in compiled code where it may, writing their ``lateness_ns`` and
        #: ``compute_ns`` itself (:func:`run_ticks`); None: every tick is ``step``'s
        self.burst = None
        #: tick 0's deadline on ``clock`` (ns), where the ticks must keep a phase found
        #: before the run (a controller aligned to its drive); None: one period after
        #: :meth:`run` starts
        self.start_ns: int | None = None

    def request_stop(self) -> None:
        """Stop before the next tick (safe to call from a signal handler).  The request
        stays: a later :meth:`run` returns at once."""
        self.stop_requested = True
        self.stop_word[0] = 1

    def run(self) -> LoopStats:
        """Run the ticks (until done, stopped by the policy, or asked to stop)."""
        lateness, compute = self.lateness_ns, self.compute_ns
        lateness.fill(SKIPPED)
        compute.fill(SKIPPED)

        def end_tick(k: int, late_ns: int, compute_ns: int) -> None:
            lateness[k] = late_ns
            compute[k] = compute_ns

        c = run_ticks(self, end_tick, self.n_ticks)
        done = slice(0, c.ticks + c.skipped)
        ran = lateness[done] != SKIPPED
        return LoopStats(
            period_ns=self.period_ns, lateness_ns=lateness[done], compute_ns=compute[done],
            **asdict(c), lateness_us=Percentiles.of_ns_in_us(lateness[done][ran]),
            compute_us=Percentiles.of_ns_in_us(compute[done][ran]))
