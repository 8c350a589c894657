"""What kept a loop from its deadline: counters read only when a tick overran.

A real-time loop that falls behind is either not running (another thread or process had
its CPU: *involuntary context switches*; a wake-up the scheduler delayed while the loop
slept counts in no counter here, and the text says so), or running something it should
not (the
interpreter's *garbage collection*, numba *compiling* a kernel, *page faults* on memory
touched for the first time).  The kernel counts the first and the last per thread
(``getrusage(RUSAGE_THREAD)``); the interpreter's collector and numba's compiler report to
callbacks installed here, which cost nothing while nothing collects or compiles.  The
loop reads them at an overrun only (:meth:`Causes.since_last`: one system call), so a
loop on time pays nothing; what an overrun shows is the change since the previous
overrun (or the loop's start).  Over a steady run these counters stay at 0 on a loop that
keeps its time (memory locked and touched before the start, kernels warmed, no
allocation in the tick), so what moved is what happened.
"""

import gc
import resource
import time
from typing import NamedTuple

#: the collector's and the compiler's totals in this process, updated by their callbacks
_TOTALS = {"gc_collections": 0, "gc_ns": 0, "compile_ns": 0}


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
    """
    preempted: int
    page_faults: int
    major_faults: int
    gc_collections: int
    gc_ms: float
    compile_ms: float

    def text(self) -> str:
        """The suspects that moved, in words ("nothing the loop counts" when none did)."""
        parts = []
        if self.preempted:
            parts.append(f"{self.preempted} involuntary context switch(es): something else "
                         "had the loop's CPU")
        if self.page_faults:
            parts.append(f"{self.page_faults} page fault(s)"
                         + (f", {self.major_faults} from disk" if self.major_faults else ""))
        if self.gc_collections:
            parts.append(f"{self.gc_collections} garbage collection(s), {self.gc_ms:.2f} ms")
        if self.compile_ms:
            parts.append(f"numba compiling, {self.compile_ms:.1f} ms")
        # a wake-up the scheduler delayed (the CPU busy with other work or interrupts
        # while the loop slept) counts in none of them: the thread was not runnable yet
        return "; ".join(parts) or ("nothing the loop counts while it runs (no preemption, "
                                    "page fault, collection or compile): woken late, the "
                                    "CPU busy elsewhere, or a system call that blocked")

    def plus(self, other: "Cause") -> "Cause":
        """The two summed, field by field."""
        return Cause(self.preempted + other.preempted, self.page_faults + other.page_faults,
                     self.major_faults + other.major_faults,
                     self.gc_collections + other.gc_collections,
                     self.gc_ms + other.gc_ms, self.compile_ms + other.compile_ms)

    def as_dict(self) -> dict:
        return self._asdict()

    @classmethod
    def from_dict(cls, d: dict) -> "Cause":
        return cls(**d)


class Causes:
    """The counters of the calling thread (the loop's: build it there), read at each
    overrun with :meth:`since_last`."""

    def __init__(self):
        _install()
        self.last = self._read()

    @staticmethod
    def _read() -> tuple[int, int, int, int, int, int]:
        r = resource.getrusage(resource.RUSAGE_THREAD)
        return (r.ru_nivcsw, r.ru_minflt + r.ru_majflt, r.ru_majflt,
                _TOTALS["gc_collections"], _TOTALS["gc_ns"], _TOTALS["compile_ns"])

    def since_last(self) -> Cause:
        """What moved since the previous call (or since this was built)."""
        now, last = self._read(), self.last
        self.last = now
        return Cause(now[0] - last[0], now[1] - last[1], now[2] - last[2], now[3] - last[3],
                     (now[4] - last[4]) * 1e-6, (now[5] - last[5]) * 1e-6)
