"""The events of a run -- faults, watchdog and link events, overruns, the safe state --
each with its tick and reason, gathered for the recording's event stream.

The real-time path only appends what it already kept: a drive's
:class:`~hil.drive.faults.FaultLog` its events (with the drive cycle), the
:class:`~hil.runtime.watchdog.Watchdog` its events (with the tick), the
:class:`~hil.runtime.recording.Recorder` a mark per tick a fault log grew and its count of
ticks it could not record, the loop its stalls (:class:`~hil.rt.loop.Stall`), the
emulator the adapter's notices (:meth:`EventCollector.note`: a flood held off, frame
numbers resynchronised).  :class:`EventCollector`, called each flush by the recording's
event thread in the emulator's process, turns those into :class:`RunEvent` rows, sent to
the writer process; overruns the writer process finds in the rows themselves
(:class:`Overruns`: a tick whose lateness plus compute time passes the period ended after
the next deadline, the loop's own definition), one event per run of consecutive late
ticks.

``tick`` is the loop's deadline index (``t_s = tick * period``); -1 for what happens
outside the loop (the safe state after it).  A fault logged in the safe state has its
drive cycle (PWM periods since the drive was built) and tick -1.
"""

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the writer process imports this module without the drives
    from hil.drive import DriveSet
    from hil.drive.faults import FaultLog
    from hil.rt.loop import Stall
    from hil.runtime.recording import Recorder
    from hil.runtime.watchdog import Watchdog

#: overrun events written; later ones are counted in report.json only
MAX_OVERRUN_EVENTS = 10_000
#: event columns: name -> (Arrow type name, unit, meaning)
EVENT_COLUMNS = {
    "tick": ("int64", "1", "deadline index of the tick (-1: outside the loop)"),
    "t_s": ("float64", "s", "tick * period (NaN outside the loop)"),
    "axis": ("string", "-", "axis letter (empty: every axis)"),
    "source": ("string", "-", "drive, watchdog, link, loop, recording, inject or emulator"),
    "kind": ("string", "-", "what happened"),
    "code": ("int32", "603Fh", "the drive's error code where there is one, else 0"),
    "cycle": ("int64", "1", "drive cycle (PWM periods since the drive was built; -1: none)"),
    "count": ("int64", "1", "how many (overrun ticks, ticks not recorded or missed)"),
    "reason": ("string", "-", "why, in words"),
}


@dataclass(frozen=True)
class RunEvent:
    """One event of a run (the columns of :data:`EVENT_COLUMNS` but ``t_s``)."""
    tick: int
    axis: str
    source: str
    kind: str
    reason: str
    code: int = 0
    cycle: int = -1
    count: int = 1


class Overruns:
    """Runs of consecutive late rows, carried across batches (the writer process scans
    each batch it writes)."""

    def __init__(self, period_ns: int):
        self.period_ns = period_ns
        self.open: list[int] | None = None  # [first tick, count, worst excess ns]
        self.events = 0
        self.dropped = 0

    def scan(self, tick: np.ndarray, lateness: np.ndarray, compute: np.ndarray,
             out: list[RunEvent]) -> None:
        """Append to ``out`` the runs that end in these rows (ns columns)."""
        excess = lateness + compute - self.period_ns
        rows = np.flatnonzero(excess > 0)
        if rows.size == 0 or rows[0] != 0:
            self.close(out)
        if rows.size == 0:
            return
        breaks = np.flatnonzero(np.diff(rows) > 1)
        for first, last in zip(rows[np.r_[0, breaks + 1]], rows[np.r_[breaks, rows.size - 1]]):
            if self.open is None:
                self.open = [int(tick[first]), 0, 0]
            self.open[1] += int(last - first + 1)
            self.open[2] = max(self.open[2], int(excess[first:last + 1].max()))
            if last < tick.size - 1:
                self.close(out)

    def close(self, out: list[RunEvent]) -> None:
        """Append the run still open, if any (the rows have ended)."""
        if self.open is None:
            return
        first, count, worst = self.open
        self.open = None
        if self.events >= MAX_OVERRUN_EVENTS:
            self.dropped += 1
            return
        self.events += 1
        out.append(RunEvent(first, "", "loop", "overrun",
                            f"{count} tick(s) from here ended after the next deadline, the "
                            f"latest by {worst / 1e3:.1f} µs", count=count))

    def finish(self) -> list[RunEvent]:
        """The run still open and the count of runs not listed, once the rows have ended."""
        out: list[RunEvent] = []
        self.close(out)
        if self.dropped:
            out.append(RunEvent(-1, "", "loop", "overruns not listed",
                                f"{self.dropped} more runs of overruns after the first "
                                f"{MAX_OVERRUN_EVENTS} (report.json counts them)",
                                count=self.dropped))
        return out


class EventCollector:
    """Turns what the drives, the watchdog and the recorder logged into events, in the
    emulator's process (overruns are found by the writer process in the rows,
    :class:`Overruns`).

    Args:
        names: the axis letters, in the drives' order.
        drives: every axis's drive.
        watchdog: the emulator's watchdog.
        recorder: the ring (fault marks, ticks not recorded).
        injectors: every axis's fault injector (:class:`~hil.inject.Injector`): what it
            injected, reached or refused.
        stall_log: the loop's stalls (:attr:`hil.runtime.streaming_loop.StreamingLoop.
            stall_log`), appended by the loop.
    """

    def __init__(self, names: tuple[str, ...], drives: "DriveSet", watchdog: "Watchdog",
                 recorder: "Recorder", injectors: tuple = (),
                 stall_log: "list[Stall] | tuple" = ()):
        self.names, self.drives = names, drives
        self.watchdog, self.recorder = watchdog, recorder
        self.injectors = injectors
        self.stall_log = stall_log
        self._injected_done = [0] * len(injectors)
        self._faults_done = [0] * len(names)
        self._watchdog_done = 0
        self._stalls_done = 0
        self._lost_done = 0
        self._noted: deque[RunEvent] = deque()

    def note(self, event: RunEvent) -> None:
        """An event the emulator's loop met (the adapter's notices), for the next
        :meth:`collect` (safe from the loop's thread while another collects)."""
        self._noted.append(event)

    def collect(self) -> list[RunEvent]:
        """The events logged since the last call."""
        out: list[RunEvent] = []
        marks = self.recorder.fault_marks
        while marks:
            tick, axis, n = marks.popleft()
            self._faults(axis, n, tick, out)
        events = self.watchdog.events
        while self._watchdog_done < len(events):
            e = events[self._watchdog_done]
            self._watchdog_done += 1
            link = e.kind not in ("tripped", "recovered")
            out.append(RunEvent(e.tick, self.names[e.axis] if e.axis >= 0 else "",
                                "link" if link else "watchdog", e.kind,
                                e.message(self.watchdog.period_s)))
        self._stalls(out)
        noted = self._noted
        while noted:
            out.append(noted.popleft())
        self._lost(out)
        self._injected(out)
        return out

    def _stalls(self, out: list[RunEvent]) -> None:
        log, period_s = self.stall_log, self.watchdog.period_s
        while self._stalls_done < len(log):
            s = log[self._stalls_done]
            self._stalls_done += 1
            out.append(RunEvent(
                s.tick, "", "loop", "stall",
                f"the tick ended {s.behind_ns * 1e-6:.1f} ms after the next deadline: "
                f"{s.missed} ticks ({s.missed * period_s * 1e3:.1f} ms) missed, at least the "
                f"watchdog's {self.watchdog.limit}: the loop resumed at the present deadline "
                f"without running them (neither the drives' time nor the watchdog counts "
                f"them)", count=s.missed))

    def _injected(self, out: list[RunEvent]) -> None:
        period_s = self.watchdog.period_s
        for axis, inj in enumerate(self.injectors):
            events = inj.events
            while self._injected_done[axis] < len(events):
                e = events[self._injected_done[axis]]
                self._injected_done[axis] += 1
                tick = round(e.t_s / period_s) if e.t_s >= 0.0 else -1
                out.append(RunEvent(tick, self.names[axis], "inject", e.kind, e.reason))

    def finish(self) -> list[RunEvent]:
        """What remains once the loop has stopped: ticks not recorded, faults logged in
        the safe state (tick -1), and what was only counted."""
        out: list[RunEvent] = self.collect()
        for axis, d in enumerate(self.drives.drives):
            self._faults(axis, d.faults.n_events, -1, out)
            kept = len(d.faults.events)
            if d.faults.n_events > kept:
                more = d.faults.n_events - kept
                out.append(RunEvent(-1, self.names[axis], "drive", "faults not listed",
                                    f"{more} fault events after the first {kept} were "
                                    "counted only (the drive keeps that many)", count=more))
        kept = len(self.watchdog.events)
        if self.watchdog.n_events > kept:
            more = self.watchdog.n_events - kept
            out.append(RunEvent(-1, "", "watchdog", "events not listed",
                                f"{more} watchdog and link events after the first {kept} "
                                "were counted only", count=more))
        return out

    def _faults(self, axis: int, n: int, tick: int, out: list[RunEvent]) -> None:
        log: "FaultLog" = self.drives.drives[axis].faults
        kept = log.events
        for e in kept[self._faults_done[axis]:min(n, len(kept))]:
            kind = "fault" if e.kind == "fault" else "fault reset"
            out.append(RunEvent(tick, self.names[axis], "drive", kind, e.text, code=e.code,
                                cycle=e.cycle))
        self._faults_done[axis] = max(self._faults_done[axis], n)

    def _lost(self, out: list[RunEvent]) -> None:
        rec = self.recorder
        lost = rec.lost - self._lost_done
        if lost <= 0:
            return
        self._lost_done += lost
        last = rec.last_lost_tick
        out.append(RunEvent(last, "", "recording", "ticks not recorded",
                            f"{lost} ticks up to this one not recorded: the writer fell "
                            "behind and the ring was full", count=lost))
