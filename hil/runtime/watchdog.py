"""The emulator's controller watchdog: a silent controller leaves the axis torque-free.

Counted in ticks of the emulator's loop.  A tick *hears* the controller when the adapter
returned a new, well-formed setpoint in it (malformed, repeated and stale frames do not
count).  ``silent`` is the number of ticks since the last one that heard it; before the
first setpoint the controller is absent.

* The drive answers (the emulator sends feedback) only while ``silent < limit``: nobody is
  listening otherwise, and a serial link would fill up.
* **Trip**: at the first tick with ``silent >= limit`` while the drive's power stage is
  enabled (OPERATION ENABLED or QUICK STOP ACTIVE), the watchdog sets the drive's fault
  input to :data:`FAULT_WATCHDOG`.  In that same tick's cycle the CiA 402 state machine
  takes transition 13 to FAULT REACTION ACTIVE, which removes torque (plant enable 0, the
  safe state; fault reaction option code 0: the axis coasts), and transition 14 to FAULT
  in the next.  The event is logged once, with the tick and the time.
  A silent controller while the drive is not enabled is no event: torque is already off.
* **Recovery**: the first tick that hears the controller again releases the fault input
  (event "recovered"; feedback ``fault`` reads 0 again) -- the drive *stays* in FAULT
  (statusword 0x0218 pattern x0xx 1000) until the controller resets it.  The controller
  resumes as after any CiA 402 fault: controlword bit 7 rising edge (e.g. 0x0000 then
  0x0080: transition 15 to SWITCH ON DISABLED), then shutdown 0x0006 (2), switch on 0x0007
  (3) and enable operation 0x000F (4).  :class:`hil.cia402.EnableSequencer`'s
  ``enable()`` sends exactly this.  Setpoints are followed again from OPERATION ENABLED on.

On a machine of several axes one message carries every axis's setpoint, so the controller
is heard or silent for all of them at once; the trip faults every drive whose power stage
is enabled (each its own CiA 402 FAULT), and the recovery releases each of those.

Nothing here allocates per tick except the event record when a trip or recovery happens.
"""

from dataclasses import asdict, dataclass

from hil.drive import DriveSet, EmulatedDrive

#: the drive's fault code for a lost controller: CiA 301 emergency error code 8130h
#: (life guard or heartbeat error), carried in Feedback.fault
FAULT_WATCHDOG = 0x8130
#: events kept in the report; later ones are counted only
MAX_EVENTS = 1000


@dataclass(frozen=True)
class WatchdogEvent:
    """One trip or recovery.

    Attributes:
        kind: "tripped" or "recovered".
        tick: the loop's deadline index of the tick it happened in.
        t_s: its deadline after the loop's start, s.
        silent_ticks: ticks without a setpoint up to this one (0 for a recovery).
        last_seq: the last setpoint's sequence number.
    """
    kind: str
    tick: int
    t_s: float
    silent_ticks: int
    last_seq: int

    def message(self, period_s: float) -> str:
        """One log line."""
        if self.kind == "tripped":
            return (f"watchdog: no setpoint for {self.silent_ticks} cycles "
                    f"({self.silent_ticks * period_s * 1e3:.1f} ms) at t = {self.t_s:.4f} s "
                    f"(tick {self.tick}, last seq {self.last_seq}): drive FAULT "
                    f"0x{FAULT_WATCHDOG:04X}, torque off")
        return (f"watchdog: setpoints again at t = {self.t_s:.4f} s (tick {self.tick}, seq "
                f"{self.last_seq}): fault input released; the drive stays in FAULT until a "
                f"fault reset (controlword bit 7) and re-enable")


class Watchdog:
    """Counts silent ticks and faults the drive (see the module docstring).

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
        self.tripped = False
        self.events: list[WatchdogEvent] = []
        self.n_events = 0

    @property
    def answering(self) -> bool:
        """The controller was heard within the limit: feedback goes out."""
        return self.silent < self.limit

    def update(self, heard: bool, tick: int, seq: int,
               drive: EmulatedDrive | DriveSet) -> None:
        """Call once per tick before the drives' cycle: ``heard`` a new setpoint (``seq``);
        ``drive`` one drive or every axis's (:class:`~hil.drive.DriveSet`)."""
        drives = drive.drives if isinstance(drive, DriveSet) else (drive,)
        if heard:
            self.silent = 0
            if self.tripped:
                self.tripped = False
                for d in drives:
                    if d.fault == FAULT_WATCHDOG:
                        d.fault = 0
                self._event("recovered", tick, seq)
            return
        if self.silent < self.limit:
            self.silent += 1
        if self.silent >= self.limit and not self.tripped and any(
                d.sm.power_enabled for d in drives):
            self.tripped = True
            for d in drives:
                if d.sm.power_enabled:
                    d.fault = FAULT_WATCHDOG
            self._event("tripped", tick, seq)

    def _event(self, kind: str, tick: int, seq: int) -> None:
        event = WatchdogEvent(kind, tick, tick * self.period_s,
                              self.silent if kind == "tripped" else 0, seq)
        self.n_events += 1
        if len(self.events) < MAX_EVENTS:
            self.events.append(event)
        self.log(event.message(self.period_s))

    def as_dict(self) -> dict:
        """Limit, state and events, JSON-ready."""
        return {"limit_cycles": self.limit, "limit_s": self.limit * self.period_s,
                "fault_code": FAULT_WATCHDOG, "tripped_at_end": self.tripped,
                "events": [asdict(e) for e in self.events], "events_total": self.n_events}
