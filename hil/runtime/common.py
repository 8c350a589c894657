"""What the runtime's processes share: exit codes, input errors, signals, JSON, scheduling.

Exit codes of ``hil run``, ``hil controller`` and ``hil demo``: :data:`EXIT_OK` (done, or
stopped by SIGTERM/SIGINT with every file written), :data:`EXIT_FAILED` (the run itself
failed: overruns under the ``stop`` policy, a drive that never answered or faulted, a child
process that failed), :data:`EXIT_BAD_INPUT` (a machine file, part program, URL or option
refused before anything started).
"""

import json
import math
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

from hil.controller.config import cnc_unit
from hil.rt.scheduling import (
    RealtimeNeighbour,
    SchedulingReport,
    SchedulingRequest,
    cpu_list,
    realtime_neighbours,
    realtime_scheduling,
)
from plant.machines import MachineSet

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


class RuntimeInputError(ValueError):
    """A runtime setting given on the command line is out of range; the message names the
    option, the value and the unit or range expected."""


def eprint(*args) -> None:
    """Print to stderr at once (the processes' log)."""
    print(*args, file=sys.stderr, flush=True)


def start_arg(text: str) -> float | dict[str, float]:
    """``--start``: one number (mm, or deg on rotary tables) for every axis, or
    ``X=10,Y=-5,C=90`` per axis (an axis not named starts at 0)."""
    text = text.strip()
    if "=" not in text:
        return float(text)
    starts = {}
    for item in text.split(","):
        name, sep, value = item.partition("=")
        name = name.strip().upper()
        if not sep or len(name) != 1 or not name.isalpha() or name in starts:
            raise ValueError(f"--start {text!r}: expected a number or AXIS=VALUE,AXIS=VALUE")
        starts[name] = float(value)
    return starts


def start_positions(machine: MachineSet, start: float | dict[str, float]) -> tuple[float, ...]:
    """Each axis's start in SI (m, rad) from ``--start`` in CNC units (:func:`start_arg`);
    refuses an axis letter the machine does not have."""
    if not isinstance(start, dict):
        return tuple(start / cnc_unit(a.config)[0] for a in machine.axes)
    unknown = set(start) - set(machine.names)
    if unknown:
        raise RuntimeInputError(f"--start names axes {', '.join(sorted(unknown))}; "
                                f"{machine.path} has {', '.join(machine.names)}")
    return tuple(start.get(a.name, 0.0) / cnc_unit(a.config)[0] for a in machine.axes)


def check_link(url: str, n_axes: int) -> str:
    """Refuse, before anything opens, a link that cannot carry ``n_axes`` axes per message
    (``serial://``: at most :data:`io_adapters.serial_link.MAX_AXES_BY_WIRE` of its wire,
    its frames hold 255 bytes); returns the URL to open.  On ``can://`` that is one CiA 402 node per axis:
    the URL with ``axes=N`` added (node-IDs ``node`` .. ``node + N - 1``), or refused
    when it names another number of axes."""
    if url.startswith("can://"):
        query = urlsplit(url).query
        given = [v for k, v in parse_qsl(query, keep_blank_values=True) if k == "axes"]
        if not given:
            return url if n_axes == 1 else f"{url}{'&' if query else '?'}axes={n_axes}"
        if given != [str(n_axes)]:
            raise RuntimeInputError(f"--adapter {url}: axes={','.join(given)}, but the "
                                    f"machine has {n_axes} (one CiA 402 node per axis; "
                                    "leave axes out to take the machine's)")
    if url.startswith("serial://"):
        from io_adapters.serial_link import MAX_AXES_BY_WIRE, MAX_PAYLOAD

        wires = [v for k, v in parse_qsl(urlsplit(url).query, keep_blank_values=True)
                 if k == "wire"]
        wire = wires[0] if wires else "msgpack"
        most = MAX_AXES_BY_WIRE.get(wire)  # an unknown wire: the endpoint refuses it
        if most is not None and n_axes > most:
            raise RuntimeInputError(f"--adapter {url}: serial frames hold {MAX_PAYLOAD} bytes, "
                                    f"{most} axes per message at most on the {wire} wire; "
                                    f"this machine has {n_axes} (use udp://)")
    return url


def period_ns_of(rate_hz: float) -> int:
    """The loop period in whole ns for a rate in Hz (the same integer in every process, so
    two loops at one rate on one machine keep their phase)."""
    return round(1e9 / rate_hz)


@contextmanager
def stop_on_signals(request_stop: Callable[[], None]) -> Iterator[None]:
    """SIGTERM and SIGINT call ``request_stop`` (which must only set a flag) for the
    ``with`` block; the previous handlers come back after it."""
    def handler(signum, frame) -> None:
        request_stop()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def scheduling(realtime: bool, cpu: int | None, priority: int):
    """A context manager yielding the :class:`SchedulingReport` of SCHED_FIFO ``priority``
    pinned to ``cpu`` (None: not pinned), memory locked, ``/dev/cpu_dma_latency`` at 0,
    1 ns timer slack and the GC frozen -- or, without ``realtime``, yielding None."""
    if not realtime:
        return nullcontext(None)
    cpus = None if cpu is None else frozenset({cpu})
    return realtime_scheduling(SchedulingRequest(fifo_priority=priority, cpus=cpus))


def shared_cpu(realtime: bool, cpu: int | None, priority: int
               ) -> tuple[list[RealtimeNeighbour], str | None]:
    """Other processes' real-time threads a loop about to run at SCHED_FIFO ``priority``
    can share a CPU with (:func:`hil.rt.scheduling.realtime_neighbours`): those pinned to
    its ``cpu``, or, the loop not pinned (``cpu`` None), those allowed on any CPU it may
    use; and a warning naming them (None: none, or the loop is not real-time).  Two loops
    on one CPU starve each other: the lower one waits while the other runs, and a spinning
    one at the same priority holds the CPU until it sleeps."""
    if not realtime:
        return [], None
    found = realtime_neighbours(cpu)
    if not found:
        return [], None
    above = [n for n in found if n.priority >= priority]
    where = (f"CPU {cpu} is already held by" if cpu is not None else
             f"this loop is not pinned: the CPUs it may run on "
             f"({cpu_list(os.sched_getaffinity(0))}) are open to")
    return found, (f"{where} real-time threads of other processes: "
                   f"{'; '.join(n.describe() for n in found)}. This loop at SCHED_FIFO "
                   f"{priority} " + (f"waits whenever {len(above)} of them at its priority "
                                     f"or above run" if above else "preempts them") +
                   " on its CPU; choose a free CPU with --cpu N")


def scheduling_dict(report: SchedulingReport | None) -> dict:
    """The report as JSON, or every request "not requested" when real time was off."""
    if report is not None:
        return report.as_dict()
    off = {"granted": False, "detail": "not requested (--no-rt)"}
    return {name: dict(off) for name in ("fifo", "affinity", "mlockall", "cpu_dma_latency",
                                         "timer_slack", "gc_frozen", "kernel_threads")}


def check_cpu(cpu: int | None, option: str = "--cpu") -> None:
    """Refuse a CPU this process may not run on."""
    if cpu is not None and cpu not in os.sched_getaffinity(0):
        raise RuntimeInputError(f"{option} {cpu}: not one of the CPUs this process may use "
                                f"{sorted(os.sched_getaffinity(0))}")


def _finite(value):
    """``value`` with every non-finite float replaced by None (strict JSON)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def write_json(path: Path, data: dict) -> Path:
    """Write ``data`` as strict JSON (NaN and inf become null) atomically: the file is
    complete or absent, never half written."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(_finite(data), indent=1, allow_nan=False) + "\n")
    os.replace(tmp, path)
    return path


def served_url(url: str, address: tuple | None) -> str:
    """``url`` with the port actually bound when it asked for port 0 (``udp://H:0``)."""
    scheme, sep, rest = url.partition("://")
    netloc, q, query = rest.partition("?")
    if scheme != "udp" or address is None or not netloc.endswith(":0"):
        return url
    return f"{scheme}{sep}{netloc[:-2]}:{address[1]}{q}{query}"


class StopFlag:
    """What a SIGTERM/SIGINT handler sets: a flag, passed on to the loop once it exists, so
    a signal during start-up still ends the run cleanly (the loop then runs no tick)."""

    def __init__(self):
        self.requested = False
        self._loop = None

    def request(self) -> None:
        """Set the flag (safe in a signal handler: no I/O, no allocation of note)."""
        self.requested = True
        if self._loop is not None:
            self._loop.request_stop()

    def attach(self, loop) -> None:
        """The :class:`~hil.rt.loop.RealTimeLoop` to stop; stopped at once if already asked."""
        self._loop = loop
        if self.requested:
            loop.request_stop()


def reap(children: list[subprocess.Popen]) -> None:
    """Kill what still runs of ``children`` and wait for each; close the first one's
    stdout (the emulator's, read for its ``ready:`` line).  For a ``finally`` block."""
    for child in children:
        if child.poll() is None:
            child.kill()
            child.wait()
    if children and children[0].stdout is not None:
        children[0].stdout.close()
