"""The NC's alarms, numbered and worded as in the SINUMERIK alarm list.

An axis raises an alarm with its number, the axis name, the alarm text (SINUMERIK's
``Axis %1 ...`` with the axis name for %1), what was measured (``detail``, in the CNC's
units: mm or deg) and the tick and time it was raised.  Every alarm but the software limit
switch's stops the axes (:mod:`hil.controller.nc`: rapid stop, then the drives disabled,
follow-up); 10720 and 10620 keep the axis inside its software limits instead
(:mod:`hil.controller.limits`: the program ends before the block, the speed is limited).

=======  ===========================================  ========================================
number   text                                         raised when
=======  ===========================================  ========================================
25000    Axis %1 hardware fault active encoder        a feedback value is NaN or infinite
25040    Axis %1 standstill monitoring                the following error at rest beyond
                                                      MD36030 after MD36040
25050    Axis %1 contour monitoring                   the actual position off the loop
                                                      model's by more than MD36400
25201    Axis %1 drive fault                          the enabled drive left OPERATION
                                                      ENABLED (CiA 402 FAULT: its 603Fh code)
26000    Axis %1 clamping monitoring                  a clamped axis moved beyond MD36050
10720    Axis %1 software limit switch                a block's end point (or a setpoint)
                                                      beyond MD36100/MD36110, found before
                                                      it moves: the program ends before it
10620    Axis %1 reaches software limit switch        a test mode's speed limited so the
                                                      axis stops on the limit
1000     System error                                 the NC's own loop state became NaN or
                                                      infinite (an internal error)
=======  ===========================================  ========================================

An :class:`AlarmList` keeps the first raise of each number with its tick and time and
counts the raises after it (an alarm shown once in the NC's list, however often its
cause recurs).
"""

import math
from dataclasses import asdict, dataclass
from enum import IntEnum

from hil.cia402 import Cia402Error, statusword_state


class AlarmNumber(IntEnum):
    """The alarms this NC raises (SINUMERIK alarm numbers)."""
    SYSTEM_ERROR = 1000
    SOFTWARE_LIMIT_REACHED = 10620
    SOFTWARE_LIMIT = 10720
    ENCODER_HW_FAULT = 25000
    STANDSTILL = 25040
    CONTOUR = 25050
    DRIVE_FAULT = 25201
    CLAMPING = 26000


#: the feedback values the NC reads (:class:`~io_adapters.messages.Feedback` fields)
FEEDBACK_VALUES = ("encoder_counts", "scale_counts", "velocity_counts_s", "iq_a", "id_a")

#: SINUMERIK's alarm text, %1 the axis name
TEXT = {
    AlarmNumber.SYSTEM_ERROR: "System error",
    AlarmNumber.SOFTWARE_LIMIT_REACHED: "Axis %1 reaches software limit switch",
    AlarmNumber.SOFTWARE_LIMIT: "Axis %1 software limit switch",
    AlarmNumber.ENCODER_HW_FAULT: "Axis %1 hardware fault active encoder",
    AlarmNumber.STANDSTILL: "Axis %1 standstill monitoring",
    AlarmNumber.CONTOUR: "Axis %1 contour monitoring",
    AlarmNumber.DRIVE_FAULT: "Axis %1 drive fault",
    AlarmNumber.CLAMPING: "Axis %1 clamping monitoring",
}


@dataclass(frozen=True)
class Alarm:
    """One alarm as raised.

    Attributes:
        number: the alarm number (:class:`AlarmNumber`).
        axis: the axis name (letter).
        text: the alarm text with the axis name in place of %1.
        detail: what was measured, in the CNC's units (mm or deg), e.g.
            "deviation 2.31 mm > 1 mm".
        tick: the controller's basic-clock tick (counted from its start) it was raised in.
        t_s: the controller time of that tick, s: from the start of the program or test
            mode (the servo trace's time), 0 before one started.
    """
    number: int
    axis: str
    text: str
    detail: str
    tick: int
    t_s: float

    def message(self) -> str:
        """One line: ``alarm 25050 axis X contour monitoring at t = 1.234 s (detail)``."""
        what = TEXT[AlarmNumber(self.number)].replace("Axis %1 ", "").lower()
        return (f"alarm {self.number} axis {self.axis} {what} at t = {self.t_s:.3f} s "
                f"({self.detail})")


class AlarmList:
    """The alarms of one axis: the first raise of each number, and how often each was
    raised in all.

    Attributes:
        alarms: the first raise of each number, in the order raised.
    """

    def __init__(self, axis: str):
        self.axis = axis
        self.alarms: list[Alarm] = []
        self._raised: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self.alarms)

    def __bool__(self) -> bool:
        return bool(self.alarms)

    def raise_alarm(self, number: AlarmNumber, detail: str, tick: int, t_s: float) -> bool:
        """Raise ``number``; True when it is the first raise of that number."""
        seen = self._raised.get(number, 0)
        self._raised[number] = seen + 1
        if seen:
            return False
        text = TEXT[number].replace("%1", self.axis)
        self.alarms.append(Alarm(int(number), self.axis, text, detail, tick, t_s))
        return True

    def count(self, number: int) -> int:
        """How often ``number`` was raised."""
        return self._raised.get(number, 0)

    def as_dicts(self) -> list[dict]:
        """JSON-ready: each alarm's fields, its ``count`` and its ``message``."""
        return [{**asdict(a), "count": self.count(a.number), "message": a.message()}
                for a in self.alarms]

    def clear(self) -> None:
        """Empty the list (the NC's RESET)."""
        self.alarms.clear()
        self._raised.clear()


def feedback_detail(fb) -> str:
    """Alarm 25000's detail: the feedback's non-finite values."""
    return ", ".join(f"{n} = {getattr(fb, n)}" for n in FEEDBACK_VALUES
                     if not math.isfinite(getattr(fb, n)))


def drive_fault_detail(fb) -> str:
    """Alarm 25201's detail: the drive's error code 603Fh (hex), its state, statusword."""
    try:
        state = statusword_state(fb.statusword).name
    except Cia402Error:
        state = "no CiA 402 state"
    return f"603Fh = 0x{fb.fault:04X}, drive in {state}, statusword 0x{fb.statusword:04X}"
