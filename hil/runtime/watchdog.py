"""The emulator's link watchdog: one meaning of "the master is lost" on every adapter.

Counted in ticks of the emulator's loop.  A tick *hears* the controller when the adapter
returned a new, valid setpoint in it: malformed, refused, repeated and stale frames do not
count, nor does a cycle the drive ran on its own (``can://`` without SYNC, or a SYNC with no
process data since the one before).  A setpoint may stand for longer than one tick: over
``can://`` the master's process data come once per communication cycle (1006h, SYNC) and
the drive runs several ticks on them; such an endpoint says for how long in
``heard_for_s`` (1.5 cycles), and the ticks within that time after a heard one are not
silent either.  ``silent`` is the number of ticks since then; before the first setpoint
the controller is absent.

* The drive answers (the emulator sends feedback) only while ``silent < limit``: nobody is
  listening otherwise, and a serial link would fill up.
* **Trip**: from the first tick with ``silent >= limit`` the watchdog cause
  (:attr:`~hil.drive.faults.Cause.WATCHDOG`, error code 8250h) is present on every drive;
  a drive whose power stage is on reacts as its abort connection option code 6007h says
  (:class:`~hil.cia402.AbortConnectionOption`; default 1: a fault, then the fault reaction
  of 605Eh: braking on the quick stop ramp, then torque off in FAULT).  The event is
  logged once, with the tick and the time.  A silent controller while no drive is enabled
  is no event: torque is already off.
* The link's own conditions (:meth:`io_adapters.base.Endpoint.link_conditions`: a lost
  heartbeat, NMT STOPPED, an NMT reset on ``can://``) are causes of the same kind
  (HEARTBEAT 8130h, NMT 8100h) with the same 6007h reaction, each logged when it starts
  and ends.
* **Recovery**: the first tick that hears the controller again ends the watchdog cause
  (event "recovered"); a drive that faulted *stays* in FAULT until the controller resets
  it: controlword bit 7 rising edge (e.g. 0x0000 then 0x0080: transition 15), then
  shutdown 0x0006 (2), switch on 0x0007 (3), enable operation 0x000F (4).
  :class:`hil.cia402.EnableSequencer`'s ``enable()`` sends exactly this.

On a machine of several axes one message carries every axis's setpoint, so the controller
is heard or silent for all of them at once; the link conditions are per axis (one CAN node
each).

Nothing here allocates per tick except the event record when something changes.
"""

import math
from dataclasses import asdict, dataclass

import numpy as np

from hil.drive import DriveSet, EmulatedDrive
from hil.drive.faults import ERROR_CODE, Cause
from io_adapters.base import LINK_HEARTBEAT_LOST, LINK_RESET, LINK_STOPPED

#: the drive's error code for a silent controller (CiA 301 8250h, RPDO timeout), carried in
#: Feedback.fault
FAULT_WATCHDOG = ERROR_CODE[Cause.WATCHDOG]
#: events kept in the report; later ones are counted only
MAX_EVENTS = 1000
#: the link conditions of an endpoint as drive causes
_LINK_CAUSES = ((LINK_HEARTBEAT_LOST, Cause.HEARTBEAT), (LINK_STOPPED, Cause.NMT),
                (LINK_RESET, Cause.NMT))
_LINK_EVENTS = {LINK_HEARTBEAT_LOST: "heartbeat lost", LINK_STOPPED: "NMT stopped",
                LINK_RESET: "NMT reset"}


@dataclass(frozen=True)
class WatchdogEvent:
    """One trip, recovery or link condition.

    Attributes:
        kind: "tripped", "recovered", or a link condition that started ("heartbeat lost",
            "NMT stopped", "NMT reset") or ended ("... ended").
        tick: the loop's deadline index of the tick it happened in.
        t_s: its deadline after the loop's start, s.
        silent_ticks: ticks without a setpoint up to this one (0 for the others).
        last_seq: the last setpoint's sequence number.
        axis: the axis index of a link condition (-1: every axis).
    """
    kind: str
    tick: int
    t_s: float
    silent_ticks: int
    last_seq: int
    axis: int = -1

    def message(self, period_s: float) -> str:
        """One log line."""
        if self.kind == "tripped":
            return (f"watchdog: no setpoint for {self.silent_ticks} cycles "
                    f"({self.silent_ticks * period_s * 1e3:.1f} ms) at t = {self.t_s:.4f} s "
                    f"(tick {self.tick}, last seq {self.last_seq}): cause "
                    f"{FAULT_WATCHDOG:04X}h, the drive reacts as 6007h says")
        if self.kind == "recovered":
            return (f"watchdog: setpoints again at t = {self.t_s:.4f} s (tick {self.tick}, "
                    f"seq {self.last_seq}); a faulted drive stays in FAULT until a fault "
                    f"reset (controlword bit 7) and re-enable")
        return f"link: {self.kind} on axis {self.axis} at t = {self.t_s:.4f} s (tick {self.tick})"


class Watchdog:
    """Counts silent ticks and sets every drive's link causes (see the module docstring).

    Args:
        limit: ticks without a setpoint that trip it (>= 1).
        period_s: the loop's period, for event times.
        log: receives each event's line when it happens.
    """

    def __init__(self, limit: int, period_s: float, log):
        if limit < 1:
            raise ValueError(f"watchdog limit {limit} must be at least 1 cycle")
        self.limit = limit
        self.period_s = period_s
        self.log = log
        self.silent = limit  # absent until the first setpoint
        self._covered = 0    # ticks after the last heard one that its setpoint stands for
        self.tripped = False
        self.events: list[WatchdogEvent] = []
        self.n_events = 0
        self._conditions: list[int] = []

    @property
    def answering(self) -> bool:
        """The controller was heard within the limit: feedback goes out."""
        return self.silent < self.limit

    def update(self, heard: bool, tick: int, seq: int, drive: EmulatedDrive | DriveSet,
               endpoint=None) -> None:
        """Call once per tick before the drives' cycle: ``heard`` a new setpoint (``seq``);
        ``drive`` one drive or every axis's (:class:`~hil.drive.DriveSet`); ``endpoint``
        the adapter whose link conditions and ``heard_for_s`` count too (None: none)."""
        drives = drive.drives if isinstance(drive, DriveSet) else (drive,)
        if len(self._conditions) != len(drives):
            self._conditions = [0] * len(drives)
        if heard:
            self.silent = 0
            self._covered = math.ceil(getattr(endpoint, "heard_for_s", 0.0) / self.period_s) - 1
            if self.tripped:
                self.tripped = False
                self._event("recovered", tick, seq)
        elif self._covered > 0:
            self._covered -= 1
        elif self.silent < self.limit:
            self.silent += 1
        silent = self.silent >= self.limit
        if silent and not self.tripped and any(d.sm.power_enabled for d in drives):
            self.tripped = True
            self._event("tripped", tick, seq)
        for axis, d in enumerate(drives):
            causes = Cause.WATCHDOG if silent else 0
            conditions = endpoint.link_conditions(axis) if endpoint is not None else 0
            for bit, cause in _LINK_CAUSES:
                if conditions & bit:
                    causes |= cause
            self._link_events(conditions, axis, tick, seq)
            d.link_causes = causes

    def steady_counts(self, counts: np.ndarray) -> bool:
        """Before the compiled steady loop (:mod:`hil.runtime.steady_tick`) runs ticks on
        a link without conditions or ``heard_for_s`` (UDP): the count into ``counts``
        (int64[3]: silent ticks, ticks a setpoint still covers, the limit); False when
        tripped (its ticks are the Python path's).  The compiled loop counts as
        :meth:`update` does while nothing but the count changes: a heard tick sets silent
        to 0 and covers nothing more; a silent tick adds one, and only while no setpoint
        covers it and it stays below the limit (the tick that would reach it is
        declined); with the controller absent (silent at the limit, not tripped: no
        drive's power stage is on) a silent tick changes nothing and a heard one is
        declined."""
        if self.tripped:
            return False
        counts[0], counts[1], counts[2] = self.silent, self._covered, self.limit
        return True

    def steady_causes(self) -> int:
        """The link cause a silent tick of the compiled loop leaves on every drive: the
        watchdog's while the controller is absent, else none (:meth:`update`)."""
        return Cause.WATCHDOG if self.silent >= self.limit else 0

    def steady_settle(self, counts: np.ndarray) -> None:
        """After the compiled loop: its count back (:meth:`steady_counts`)."""
        self.silent, self._covered = int(counts[0]), int(counts[1])

    def _link_events(self, conditions: int, axis: int, tick: int, seq: int) -> None:
        before = self._conditions[axis]
        self._conditions[axis] = conditions & ~LINK_RESET  # a reset is an event, not a state
        for bit, name in _LINK_EVENTS.items():
            if conditions & bit and not before & bit:
                self._event(name, tick, seq, axis)
            elif before & bit and not conditions & bit:
                self._event(f"{name} ended", tick, seq, axis)

    def _event(self, kind: str, tick: int, seq: int, axis: int = -1) -> None:
        event = WatchdogEvent(kind, tick, tick * self.period_s,
                              self.silent if kind == "tripped" else 0, seq, axis)
        self.n_events += 1
        if len(self.events) < MAX_EVENTS:
            self.events.append(event)
        self.log(event.message(self.period_s))

    def as_dict(self) -> dict:
        """Limit, state and events, JSON-ready."""
        return {"limit_cycles": self.limit, "limit_s": self.limit * self.period_s,
                "fault_code": FAULT_WATCHDOG, "tripped_at_end": self.tripped,
                "events": [asdict(e) for e in self.events], "events_total": self.n_events}
