"""What kept a loop from its deadline: counters read only when a tick overran.

A real-time loop that falls behind is either not running or running something it should
not.  Not running: another thread or process had its CPU (*involuntary context
switches*), it was runnable but *waited for its CPU* (a wake-up the scheduler delayed:
the kernel's run-queue wait of the thread), or the hypervisor ran another guest on the
virtual CPU (the CPU's *steal time*).  Running what it should not: the interpreter's
*garbage collection*, numba *compiling* a kernel, *page faults* on memory touched for the
first time.  The kernel counts switches and faults per thread
(``getrusage(RUSAGE_THREAD)``), the run-queue wait per thread (``/proc/thread-self/
schedstat``, ns) and steal per CPU (``/proc/stat``, in clock ticks of 10 ms); the
interpreter's collector and numba's compiler report to callbacks installed here, which
cost nothing while nothing collects or compiles.  The loop reads them at an overrun only
(:meth:`Causes.since_last`: a system call and two small reads of /proc), so a loop on
time pays nothing; what an overrun shows is the change since the previous overrun (or
the loop's start).  Over a steady run these counters stay at 0 on a loop that keeps its
time (memory locked and touched before the start, kernels warmed, no allocation in the
tick), so what moved is what happened.
"""

import gc
import os
import resource
import time
from typing import NamedTuple

#: the collector's and the compiler's totals in this process, updated by their callbacks
_TOTALS = {"gc_collections": 0, "gc_ns": 0, "compile_ns": 0}
#: the thread's scheduler statistics: time on the CPU, time runnable waiting for it (ns)
SCHEDSTAT = "/proc/thread-self/schedstat"
#: a run-queue wait the text names: at least this share of the time since the previous
#: read (a SCHED_FIFO loop at 8 kHz on a CPU of its own waits about 0.06 % of the time,
#: 0.08 µs a wake-up, measured on the 2-vCPU VM) ...
RUNQUEUE_NOTED_SHARE = 0.001
#: ... and at least this long, ms
RUNQUEUE_NOTED_MS = 0.5
#: the kernel's clock ticks per second in /proc/stat (USER_HZ)
CLOCK_TICKS_S = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _read_proc(path: str, size: int) -> bytes:
    """Up to ``size`` bytes of a /proc file (b"" where it cannot be read).  Plain system
    calls: a file object would leave the io machinery's caches behind, memory a loop's
    overrun should not keep."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return b""
    try:
        return os.read(fd, size)
    except OSError:
        return b""
    finally:
        os.close(fd)


def runqueue_wait_ns(path: str = SCHEDSTAT) -> int:
    """The calling thread's time runnable but not running since it started, ns (0 where
    the kernel does not say)."""
    fields = _read_proc(path, 256).split()
    return int(fields[1]) if len(fields) > 1 else 0


def steal_ticks(stat: bytes, cpu: int | None) -> int:
    """Steal time of CPU ``cpu`` (None: all CPUs together) in ``/proc/stat``'s content
    ``stat``, clock ticks (0 where the line or its eighth field is missing)."""
    name = b"cpu" if cpu is None else b"cpu%d" % cpu
    for line in stat.splitlines():
        fields = line.split()
        if fields and fields[0] == name:
            return int(fields[8]) if len(fields) > 8 else 0
    return 0


def _steal_now() -> int:
    """Steal of the CPU the calling thread is pinned to (all CPUs where it has several),
    clock ticks (the CPU lines come first in /proc/stat: 64 kB hold a few hundred)."""
    cpus = os.sched_getaffinity(0)
    return steal_ticks(_read_proc("/proc/stat", 65536),
                       next(iter(cpus)) if len(cpus) == 1 else None)


def _on_gc(phase: str, info: dict, started: list[int] = [0]) -> None:  # noqa: B006
    # the default list keeps the start time between the "start" and "stop" calls
    if phase == "start":
        started[0] = time.perf_counter_ns()
    else:
        _TOTALS["gc_collections"] += 1
        _TOTALS["gc_ns"] += time.perf_counter_ns() - started[0]


def _install() -> None:
    """The callbacks, once per process (numba is imported here, not with this module: a
    process that never runs a loop need not load it)."""
    if _on_gc in gc.callbacks:
        return
    gc.callbacks.append(_on_gc)
    from numba.core import event

    class CompileTime(event.Listener):
        """numba's compile events: the time between the outermost start and its end."""

        def __init__(self):
            self.depth = 0
            self.t0 = 0

        def on_start(self, ev) -> None:
            if self.depth == 0:
                self.t0 = time.perf_counter_ns()
            self.depth += 1

        def on_end(self, ev) -> None:
            self.depth -= 1
            if self.depth == 0:
                _TOTALS["compile_ns"] += time.perf_counter_ns() - self.t0

    event.register("numba:compile", CompileTime())


class Cause(NamedTuple):
    """What changed between two reads of the counters (see the module docstring).

    Attributes:
        preempted: involuntary context switches of the loop's thread.
        page_faults: its minor and major page faults.
        major_faults: those that read a page from disk.
        gc_collections: the interpreter's collections (any thread of the process).
        gc_ms: their time, ms.
        compile_ms: numba's compile time, ms.
        runqueue_ms: the loop's thread runnable, waiting for its CPU, ms.
        steal_ms: the hypervisor's steal of the loop's CPU, ms (10 ms steps).
        interval_s: the time these counts cover, s.
    """
    preempted: int
    page_faults: int
    major_faults: int
    gc_collections: int
    gc_ms: float
    compile_ms: float
    runqueue_ms: float = 0.0
    steal_ms: float = 0.0
    interval_s: float = 0.0

    def text(self) -> str:
        """The suspects that moved, in words ("nothing the loop counts" when none did)."""
        parts = []
        if self.steal_ms:
            parts.append(f"the hypervisor ran something else on the loop's virtual CPU for "
                         f"{self.steal_ms:.0f} ms (steal time)")
        if self.preempted:
            parts.append(f"{self.preempted} involuntary context switch(es): something else "
                         "had the loop's CPU")
        if (self.runqueue_ms >= RUNQUEUE_NOTED_MS
                and self.runqueue_ms >= RUNQUEUE_NOTED_SHARE * self.interval_s * 1e3):
            parts.append(f"runnable but waiting {self.runqueue_ms:.2f} ms for its CPU in "
                         f"{self.interval_s:.3g} s (woken late: the CPU busy with another "
                         "task)")
        if self.page_faults:
            parts.append(f"{self.page_faults} page fault(s)"
                         + (f", {self.major_faults} from disk" if self.major_faults else ""))
        if self.gc_collections:
            parts.append(f"{self.gc_collections} garbage collection(s), {self.gc_ms:.2f} ms")
        if self.compile_ms:
            parts.append(f"numba compiling, {self.compile_ms:.1f} ms")
        return "; ".join(parts) or ("nothing the loop counts (no preemption, wait for the "
                                    "CPU, steal, page fault, collection or compile): "
                                    "interrupts on the loop's CPU, or a system call that "
                                    "blocked")

    def plus(self, other: "Cause") -> "Cause":
        """The two summed, field by field."""
        return Cause(self.preempted + other.preempted, self.page_faults + other.page_faults,
                     self.major_faults + other.major_faults,
                     self.gc_collections + other.gc_collections,
                     self.gc_ms + other.gc_ms, self.compile_ms + other.compile_ms,
                     self.runqueue_ms + other.runqueue_ms, self.steal_ms + other.steal_ms,
                     self.interval_s + other.interval_s)

    def as_dict(self) -> dict:
        return self._asdict()

    @classmethod
    def from_dict(cls, d: dict) -> "Cause":
        """The cause a report's dict holds (keys this version does not know are left
        out, missing ones 0: a report of another version reads too)."""
        return cls(**{k: d[k] for k in cls._fields if k in d})


class Causes:
    """The counters of the calling thread (the loop's: build it there), read at each
    overrun with :meth:`since_last`."""

    def __init__(self):
        _install()
        self.last = self._read()

    @staticmethod
    def _read() -> tuple[int, ...]:
        r = resource.getrusage(resource.RUSAGE_THREAD)
        return (r.ru_nivcsw, r.ru_minflt + r.ru_majflt, r.ru_majflt,
                _TOTALS["gc_collections"], _TOTALS["gc_ns"], _TOTALS["compile_ns"],
                runqueue_wait_ns(), _steal_now(), time.monotonic_ns())

    def since_last(self) -> Cause:
        """What moved since the previous call (or since this was built)."""
        now, last = self._read(), self.last
        self.last = now
        d = [a - b for a, b in zip(now, last)]
        return Cause(d[0], d[1], d[2], d[3], d[4] * 1e-6, d[5] * 1e-6, d[6] * 1e-6,
                     d[7] * 1e3 / CLOCK_TICKS_S, d[8] * 1e-9)
