"""What can fault the emulated drive: each cause with its CiA 402 error code, its text and
how it ends.

A cause is one bit of a mask, so the drive keeps every cause in one integer: the causes
*present* this cycle and the causes *latched* since the last fault reset.  The error code
603Fh (and the EMCY on CAN) is the code of the first cause latched.  A fault reset (the
rising edge of controlword bit 7) clears every latched cause that is no longer present; the
drive leaves FAULT (transition 15) once none is left.

Error codes are those of CiA 301 / CiA 402 (IEC 61800-7-201) where the standard has one,
and device-specific ``FFxxh`` codes for what only an emulator can have:

======  ============================  =========================================================
code    cause                         when it is present
======  ============================  =========================================================
8611h   following error               CSP: |607Ah - 6064h| beyond 6065h for longer than 6066h
8612h   software position limit       the position actual beyond 607Dh, moving outward
8612h   limit switch                  a limit switch (60FDh) active, moving outward
8400h   overspeed                     |606Ch| above 6080h by :data:`OVERSPEED_FACTOR`
2310h   continuous over-current       the I²t model above its trip level (until it cools)
2300h   peak current (voltage mode)   the sampled current above 6072h in voltage mode, where
                                      no current loop of the drive limits it (its trip)
8250h   setpoint timeout (watchdog)   no valid setpoint for the watchdog's cycles (RPDO timeout)
8130h   heartbeat lost                a heartbeat consumed (CAN 1016h) did not come in time
8100h   NMT stop or reset             the node was stopped or reset by NMT (CAN)
FF10h   setpoint refused              a setpoint with a non-finite value, a value beyond the
                                      drive's range or a mode it does not take
FF01h   plant state non-finite        the emulation's plant state became NaN or infinite
FF02h   plant state diverged          a plant state beyond its runaway bound
FF03h   drive loop non-finite         the drive's own speed/position loop gave a NaN
FF04h   braking reaction failed       a quick stop or fault reaction did not slow the axis
                                      down in time (:mod:`hil.drive.braking`): pulses
                                      inhibited, the holding brake closed
======  ============================  =========================================================

:class:`FaultLog` keeps a drive's latched causes, its 603Fh and the fault events.

The link causes (watchdog, heartbeat, NMT) act as the abort connection option code 6007h
says; the others take the fault reaction of 605Eh, except those in :data:`TORQUE_OFF`, for
which braking is impossible or unsafe (the state it would brake from is gone, or the
current that would brake is what tripped) and the drive removes torque at once.
"""

from dataclasses import asdict, dataclass
from enum import IntFlag


class Cause(IntFlag):
    """One reason for a drive fault (a bit of the drive's cause masks)."""
    FOLLOWING_ERROR = 1 << 0
    SOFTWARE_LIMIT = 1 << 1
    LIMIT_SWITCH = 1 << 2
    OVERSPEED = 1 << 3
    OVERCURRENT = 1 << 4
    WATCHDOG = 1 << 5
    HEARTBEAT = 1 << 6
    NMT = 1 << 7
    SETPOINT_REFUSED = 1 << 8
    PLANT_NONFINITE = 1 << 9
    PLANT_DIVERGED = 1 << 10
    LOOP_NONFINITE = 1 << 11
    PEAK_CURRENT = 1 << 12
    REACTION_FAILED = 1 << 13


#: 603Fh error code of each cause
ERROR_CODE = {
    Cause.FOLLOWING_ERROR: 0x8611, Cause.SOFTWARE_LIMIT: 0x8612, Cause.LIMIT_SWITCH: 0x8612,
    Cause.OVERSPEED: 0x8400, Cause.OVERCURRENT: 0x2310, Cause.WATCHDOG: 0x8250,
    Cause.HEARTBEAT: 0x8130, Cause.NMT: 0x8100, Cause.SETPOINT_REFUSED: 0xFF10,
    Cause.PLANT_NONFINITE: 0xFF01, Cause.PLANT_DIVERGED: 0xFF02, Cause.LOOP_NONFINITE: 0xFF03,
    Cause.PEAK_CURRENT: 0x2300, Cause.REACTION_FAILED: 0xFF04,
}
TEXT = {
    Cause.FOLLOWING_ERROR: "following error beyond 6065h for longer than 6066h",
    Cause.SOFTWARE_LIMIT: "position actual beyond the software position limit 607Dh",
    Cause.LIMIT_SWITCH: "limit switch reached (60FDh)",
    Cause.OVERSPEED: "speed actual above the maximum motor speed 6080h",
    Cause.OVERCURRENT: "continuous over-current (I2t)",
    Cause.WATCHDOG: "no valid setpoint within the watchdog time",
    Cause.HEARTBEAT: "the master's heartbeat was lost (1016h)",
    Cause.NMT: "NMT stop or reset (abort connection)",
    Cause.SETPOINT_REFUSED: "setpoint refused (non-finite, out of range or an unknown mode)",
    Cause.PLANT_NONFINITE: "plant state non-finite (the emulation restarted at rest)",
    Cause.PLANT_DIVERGED: "plant state diverged (the emulation restarted at rest)",
    Cause.LOOP_NONFINITE: "drive speed/position loop non-finite (loops reset)",
    Cause.PEAK_CURRENT: "current above 6072h in voltage mode (over-current trip)",
    Cause.REACTION_FAILED: "braking reaction did not stop the axis in time (pulses inhibited, "
                           "holding brake closed)",
}
#: causes whose reaction is always torque off, whatever 605Eh says
TORQUE_OFF = (Cause.PLANT_NONFINITE | Cause.PLANT_DIVERGED | Cause.LOOP_NONFINITE
              | Cause.OVERCURRENT | Cause.PEAK_CURRENT | Cause.REACTION_FAILED)
#: causes that come from the link to the master (their reaction is 6007h's)
LINK = Cause.WATCHDOG | Cause.HEARTBEAT | Cause.NMT
#: a speed above 6080h by this factor is an overspeed fault (the speed commands are limited
#: to 6080h itself; the margin keeps an overshoot of a limited command from tripping)
OVERSPEED_FACTOR = 1.1


def fault_text(code: int) -> str:
    """A drive's error code 603Fh in words (:data:`TEXT`)."""
    texts = [TEXT[cause] for cause, c in ERROR_CODE.items() if c == code]
    return " or ".join(texts) if texts else "a code this emulator does not use"


def first_cause(mask: int) -> Cause:
    """The lowest cause bit of a non-zero ``mask``."""
    return Cause(mask & -mask)


def causes_text(mask: int) -> str:
    """The causes of ``mask`` with their codes, one phrase each."""
    return "; ".join(f"{ERROR_CODE[c]:04X}h {TEXT[c]}" for c in Cause if mask & c)


#: fault events kept in :attr:`FaultLog.events`; later ones are counted only
MAX_EVENTS = 1000


@dataclass(frozen=True)
class FaultEvent:
    """A fault latched, or a fault reset taken.

    Attributes:
        kind: "fault" (causes latched) or "reset" (causes cleared by a fault reset).
        cycle: the drive cycle (PWM periods since the drive was built).
        causes: the causes (a :class:`~hil.drive.faults.Cause` mask).
        code: 603Fh after the event (0 after a complete reset).
        text: the causes in words, with their codes.
    """
    kind: str
    cycle: int
    causes: int
    code: int
    text: str


class FaultLog:
    """The drive's fault causes: latched since the last reset, and the events.

    Attributes:
        latched: causes latched and not yet reset (a Cause mask).
        code: 603Fh, the code of the first cause latched (0: none).
        events: the first :data:`MAX_EVENTS` events; ``n_events`` counts them all.
    """

    def __init__(self):
        self.latched = 0
        self.code = 0
        self.events: list[FaultEvent] = []
        self.n_events = 0

    def latch(self, causes: int, cycle: int) -> None:
        """Latch ``causes`` (those already latched are not events again)."""
        new = causes & ~self.latched
        if not new:
            return
        if not self.latched:
            self.code = ERROR_CODE[first_cause(new)]
        self.latched |= new
        self._event("fault", cycle, new)

    def reset(self, present: int, cycle: int) -> None:
        """A fault reset: clear the latched causes not in ``present``."""
        cleared = self.latched & ~present
        if not cleared:
            return
        self.latched &= present
        self.code = ERROR_CODE[first_cause(self.latched)] if self.latched else 0
        self._event("reset", cycle, cleared)

    def _event(self, kind: str, cycle: int, causes: int) -> None:
        self.n_events += 1
        if len(self.events) < MAX_EVENTS:
            self.events.append(FaultEvent(kind, cycle, causes, self.code, causes_text(causes)))

    def as_dict(self) -> dict:
        """JSON-ready: latched causes, 603Fh, events."""
        return {"latched": causes_text(self.latched), "error_code": self.code,
                "events": [asdict(e) for e in self.events], "events_total": self.n_events}
