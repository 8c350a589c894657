"""Ask the operating system for real-time treatment, report what it granted, undo it all.

::

    with realtime_scheduling(SchedulingRequest(cpus=frozenset({last_cpu()}))) as report:
        stats = loop.run()
    report.as_dict()["fifo"]    # {'granted': True, 'detail': 'SCHED_FIFO priority 80'}

Each request is made in turn and never raises: a refusal (no privilege, no such device,
not Linux) is a :class:`Grant` with ``granted=False`` and the reason.  On leaving the
``with`` block everything that was changed is restored in reverse order.

The policy, the affinity and the timer slack belong to the *calling thread*: enter the
block in the thread that runs the loop.  Threads it starts afterwards inherit them, so a
helper thread (a ``multiprocessing.Queue`` feeder, for one) competes with the loop on its
CPU at the same priority and may never run: set up IPC before entering, or give helpers
normal priority.  ``mlockall``, ``/dev/cpu_dma_latency`` and the GC are process-wide;
the kernel threads' CPUs are the whole system's (given back on leaving; a process killed by
SIGKILL leaves them off its CPU).
"""

import ctypes
import functools
import gc
import os
import struct
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass, fields

#: the PM QoS device: while an fd that wrote a value stays open, CPU idle states with a
#: longer exit latency (µs) are not used.
CPU_DMA_LATENCY_PATH = "/dev/cpu_dma_latency"

_MCL_CURRENT, _MCL_FUTURE = 1, 2
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30


@dataclass(frozen=True)
class SchedulingRequest:
    """What to ask for; ``None`` (or ``False``) leaves that setting alone.

    Attributes:
        fifo_priority: SCHED_FIFO priority, 1..99 (cyclictest's usual 80 by default).
        cpus: CPUs to pin the calling thread to (see :func:`last_cpu`).
        lock_memory: ``mlockall(MCL_CURRENT | MCL_FUTURE)``: no page faults later.
        cpu_dma_latency_us: hold ``/dev/cpu_dma_latency`` at this many µs.
        timer_slack_ns: the calling thread's timer slack (the kernel default is 50 µs;
            Linux 6.7 and later give SCHED_FIFO threads none, earlier kernels do not).
        freeze_gc: collect, ``gc.freeze()`` and ``gc.disable()``: no collector pauses.
        kernel_threads_off: keep the kernel threads of :data:`KEPT_OFF_KERNEL_THREADS` off
            ``cpus`` while the block lasts; needs ``cpus``.
    """
    fifo_priority: int | None = 80
    cpus: frozenset[int] | None = None
    lock_memory: bool = True
    cpu_dma_latency_us: int | None = 0
    timer_slack_ns: int | None = 1
    freeze_gc: bool = True
    kernel_threads_off: bool = True


@dataclass(frozen=True)
class Grant:
    """The outcome of one request: granted or not, and what was set or why not."""
    granted: bool
    detail: str


@dataclass(frozen=True)
class SchedulingReport:
    """One :class:`Grant` per request of a :class:`SchedulingRequest`."""
    fifo: Grant
    affinity: Grant
    mlockall: Grant
    cpu_dma_latency: Grant
    timer_slack: Grant
    gc_frozen: Grant
    kernel_threads: Grant

    def as_dict(self) -> dict:
        """``{name: {"granted": bool, "detail": str}}`` (JSON-ready)."""
        return asdict(self)

    def granted(self) -> list[str]:
        """Names of the requests that were granted."""
        return [f.name for f in fields(self) if getattr(self, f.name).granted]


_NOT_REQUESTED = Grant(False, "not requested")


def last_cpu() -> int:
    """The highest-numbered CPU this process may run on (CPU 0 usually takes most
    interrupts and housekeeping)."""
    return max(os.sched_getaffinity(0))


@dataclass(frozen=True)
class RealtimeNeighbour:
    """A thread of another process under a real-time policy, on CPUs a loop may use.

    Attributes:
        pid, tid: its process and thread ids.
        command: the process's name (``/proc/PID/comm``).
        policy: ``"SCHED_FIFO"`` or ``"SCHED_RR"``.
        priority: its real-time priority, 1..99.
        cpus: the CPUs it may run on (its affinity).
    """
    pid: int
    tid: int
    command: str
    policy: str
    priority: int
    cpus: frozenset[int]

    def describe(self) -> str:
        return (f"{self.command} (pid {self.pid}, thread {self.tid}, {self.policy} "
                f"{self.priority}, CPUs {cpu_list(self.cpus)})")


def cpu_list(cpus: frozenset[int] | set[int]) -> str:
    """CPUs as the kernel's lists write them: ``0-3,6``."""
    runs: list[list[int]] = []
    for c in sorted(cpus):
        if runs and c == runs[-1][1] + 1:
            runs[-1][1] = c
        else:
            runs.append([c, c])
    return ",".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


#: /proc/PID/stat: the kernel-thread flag (PF_KTHREAD), the flag of a thread whose CPUs
#: may not be changed (PF_NO_SETAFFINITY: per-CPU workers, bound interrupt threads), and the
#: policies by number
_PF_KTHREAD = 0x00200000
_PF_NO_SETAFFINITY = 0x04000000
_RT_POLICIES = {1: "SCHED_FIFO", 2: "SCHED_RR"}


def realtime_neighbours(cpu: int | None) -> list[RealtimeNeighbour]:
    """Threads of other processes under SCHED_FIFO or SCHED_RR, by pid and tid, that a
    loop can share a CPU with: pinned to ``cpu`` alone, or -- ``cpu`` None, a loop not
    pinned -- allowed on any CPU this process may run on.  A loop on a CPU with one of them
    waits whenever one at its priority or above runs (the kernel's own per-CPU threads are
    left out: every CPU has them).  Empty off Linux or where ``/proc`` cannot be read; a
    thread gone meanwhile is skipped."""
    own = os.getpid()
    mine = os.sched_getaffinity(0)
    found = []
    try:
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit() and int(p) != own]
    except OSError:
        return []
    for pid in pids:
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue
        for tid in tids:
            try:
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    stat = f.read()
                # the fields after the command's closing parenthesis start at field 3
                rest = stat[stat.rindex(")") + 2:].split()
                flags, priority, policy = int(rest[6]), int(rest[37]), int(rest[38])
                if flags & _PF_KTHREAD or policy not in _RT_POLICIES:
                    continue
                cpus = os.sched_getaffinity(tid)
                shares = bool(cpus & mine) if cpu is None else cpus == {cpu}
                if not shares:
                    continue
                command = stat[stat.index("(") + 1:stat.rindex(")")]
            except (OSError, ValueError, IndexError):
                continue
            found.append(RealtimeNeighbour(pid, tid, command, _RT_POLICIES[policy], priority,
                                           frozenset(cpus)))
    return found


#: kernel threads kept off a pinned loop's CPU, by name up to its first ``.`` (``kdamond.0``):
#: DAMON's monitor holds its CPU without preemption for up to 0.7 ms every half second
#: (traced on this project's VM, docs/realtime.md) and the scheduler sends it to the loop's
#: CPU whenever the other CPUs are busy (a browser on the scope's page).  Moving every
#: movable kernel thread instead (RCU's, kthreadd, kswapd, ...) made the loop's lateness
#: p99.9 worse there (7 µs -> 75 and 135 µs, 16 s runs; why was not traced).
KEPT_OFF_KERNEL_THREADS = ("kdamond",)


@dataclass(frozen=True)
class KernelThread:
    """A kernel thread whose CPUs may be changed: its pid, name and allowed CPUs."""
    pid: int
    name: str
    cpus: frozenset[int]


def kernel_threads(names: tuple[str, ...] = KEPT_OFF_KERNEL_THREADS) -> list[KernelThread]:
    """The kernel's threads named ``names`` (a name up to its first ``.``) whose CPUs may be
    changed (the per-CPU ones left out).  Empty off Linux, where ``/proc`` cannot be read,
    or inside a PID namespace (a container sees no kernel thread)."""
    found = []
    try:
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                stat = f.read()
            name = stat[stat.index("(") + 1:stat.rindex(")")]
            flags = int(stat[stat.rindex(")") + 2:].split()[6])
            if (name.split(".")[0] not in names or not flags & _PF_KTHREAD
                    or flags & _PF_NO_SETAFFINITY):
                continue
            found.append(KernelThread(pid, name, frozenset(os.sched_getaffinity(pid))))
        except (OSError, ValueError, IndexError):  # gone meanwhile
            continue
    return found


@functools.cache
def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def _refused(err: OSError) -> Grant:
    return Grant(False, f"refused: {err.strerror or err} (errno {err.errno})")


def _libc_call(name: str, *args) -> int:
    """Call a libc function that returns -1 on error; raise OSError with its errno."""
    result = getattr(_libc(), name)(*args)
    if result == -1:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))
    return result


def _request_affinity(cpus: frozenset[int] | None, undo: ExitStack) -> Grant:
    if cpus is None:
        return _NOT_REQUESTED
    try:
        original = os.sched_getaffinity(0)
        os.sched_setaffinity(0, cpus)
    except OSError as err:
        return _refused(err)
    undo.callback(os.sched_setaffinity, 0, original)
    return Grant(True, f"CPUs {sorted(cpus)}")


def _give_back(pid: int, cpus: frozenset[int]) -> None:
    """Allow kernel thread ``pid`` on ``cpus`` again.  Adding back what was taken, not
    setting what was found, leaves it right when two loops overlap: the second found it
    already moved and took nothing."""
    try:
        os.sched_setaffinity(pid, os.sched_getaffinity(pid) | cpus)
    except OSError:  # gone meanwhile
        pass


def _request_kernel_threads_off(cpus: frozenset[int] | None, keep_off: bool,
                                undo: ExitStack) -> Grant:
    if not keep_off or cpus is None:
        return _NOT_REQUESTED
    moved, refused = [], None
    for thread in kernel_threads():
        if not thread.cpus & cpus or thread.cpus <= cpus:  # not there, or nowhere else
            continue
        try:
            os.sched_setaffinity(thread.pid, thread.cpus - cpus)
        except OSError as err:
            refused = err
            continue
        moved.append(thread.name)
        undo.callback(_give_back, thread.pid, thread.cpus & cpus)
    if refused is not None and not moved:
        return _refused(refused)
    where = f"CPU {cpu_list(cpus)}"
    if not moved:
        return Grant(True, f"none of {', '.join(KEPT_OFF_KERNEL_THREADS)} may run on {where} "
                           f"(none visible, or kept off already)")
    return Grant(True, f"{len(moved)} kept off {where} until the end: {', '.join(moved)}")


def _request_mlockall(lock: bool, undo: ExitStack) -> Grant:
    if not lock:
        return _NOT_REQUESTED
    try:
        _libc_call("mlockall", _MCL_CURRENT | _MCL_FUTURE)
    except OSError as err:
        return _refused(err)
    undo.callback(_libc().munlockall)
    return Grant(True, "MCL_CURRENT | MCL_FUTURE")


def _request_cpu_dma_latency(latency_us: int | None, undo: ExitStack) -> Grant:
    if latency_us is None:
        return _NOT_REQUESTED
    try:
        fd = os.open(CPU_DMA_LATENCY_PATH, os.O_WRONLY | os.O_CLOEXEC)
    except OSError as err:
        return _refused(err)
    try:
        os.write(fd, struct.pack("i", latency_us))
    except OSError as err:
        os.close(fd)
        return _refused(err)
    undo.callback(os.close, fd)
    return Grant(True, f"{latency_us} µs, fd {fd} held open")


def _request_timer_slack(slack_ns: int | None, undo: ExitStack) -> Grant:
    if slack_ns is None:
        return _NOT_REQUESTED
    ulong = ctypes.c_ulong
    try:
        original = _libc_call("prctl", _PR_GET_TIMERSLACK, ulong(0), ulong(0), ulong(0), ulong(0))
        _libc_call("prctl", _PR_SET_TIMERSLACK, ulong(slack_ns), ulong(0), ulong(0), ulong(0))
    except OSError as err:
        return _refused(err)
    undo.callback(_libc().prctl, _PR_SET_TIMERSLACK, ulong(original), ulong(0), ulong(0), ulong(0))
    return Grant(True, f"{slack_ns} ns (was {original} ns)")


def _request_fifo(priority: int | None, undo: ExitStack) -> Grant:
    if priority is None:
        return _NOT_REQUESTED
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as err:
        return _refused(err)
    undo.callback(os.sched_setscheduler, 0, policy, param)
    return Grant(True, f"SCHED_FIFO priority {priority}")


def _request_gc_freeze(freeze: bool, undo: ExitStack) -> Grant:
    if not freeze:
        return _NOT_REQUESTED
    was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    if was_enabled:
        undo.callback(gc.enable)
    undo.callback(gc.unfreeze)
    return Grant(True, f"{gc.get_freeze_count()} objects frozen, collector disabled")


@contextmanager
def realtime_scheduling(
        request: SchedulingRequest = SchedulingRequest()) -> Iterator[SchedulingReport]:
    """Apply ``request`` for the ``with`` block; yields the :class:`SchedulingReport`.

    Order: affinity, the kernel threads kept off, memory lock, idle-state latency, timer
    slack, FIFO (so the set-up runs at normal priority), GC freeze (last, so it freezes
    the set-up's objects);
    restored in the reverse order, also when the block raises.  Off Linux nothing is
    requested and every entry says so.
    """
    if not sys.platform.startswith("linux"):
        off = Grant(False, f"needs Linux, running on {sys.platform}")
        yield SchedulingReport(off, off, off, off, off, off, off)
        return
    with ExitStack() as undo:
        affinity = _request_affinity(request.cpus, undo)
        # a loop that could not be pinned has no CPU to keep free
        kernel_threads = _request_kernel_threads_off(
            request.cpus if affinity.granted else None, request.kernel_threads_off, undo)
        mlockall = _request_mlockall(request.lock_memory, undo)
        dma = _request_cpu_dma_latency(request.cpu_dma_latency_us, undo)
        slack = _request_timer_slack(request.timer_slack_ns, undo)
        fifo = _request_fifo(request.fifo_priority, undo)
        gc_frozen = _request_gc_freeze(request.freeze_gc, undo)
        yield SchedulingReport(fifo=fifo, affinity=affinity, mlockall=mlockall,
                               cpu_dma_latency=dma, timer_slack=slack, gc_frozen=gc_frozen,
                               kernel_threads=kernel_threads)


def helper_threads_realtime(cpu: int, priority: int) -> dict[str, str]:
    """Give every thread of this process but the loop's and the main one -- an adapter's
    receive thread (canopen's on ``can://``), the recording's event and answer threads
    (:mod:`hil.runtime.record_writer`) -- SCHED_FIFO ``priority`` on ``cpu``; returns
    thread name -> what was done.  At normal priority such a thread, preempted while it
    holds the GIL, stalls the loop waiting behind it for milliseconds (priority
    inversion; measured on ``can://udp_multicast`` at 2 kHz: the emulator's lateness
    p99.9 2.4-3.4 ms, 50-100 µs with this).  One below the loop on the loop's CPU, it
    runs while the loop sleeps; it never spins (it blocks in its receive), so it cannot
    starve the loop."""
    done = {}
    for t in threading.enumerate():
        if t in (threading.main_thread(), threading.current_thread()) or t.native_id is None:
            continue
        try:
            os.sched_setaffinity(t.native_id, {cpu})
            os.sched_setscheduler(t.native_id, os.SCHED_FIFO, os.sched_param(priority))
            done[t.name] = f"SCHED_FIFO {priority} on CPU {cpu}"
        except OSError as e:
            done[t.name] = f"left as it was: {e}"
    return done
