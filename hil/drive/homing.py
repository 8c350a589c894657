"""Homing mode (CiA 402, 6060h = 6): find the machine's home position and set the position
actual value there to the home offset 607Ch.

Methods (6098h) offered, as CiA 402 draws them, for the plant's home switch
(:mod:`plant.effects.reference`: a *negative* home switch, on below its edge, the edge
half an index period above the start of the travel by default) and the encoder's index
mark (latched to its exact count):

======  ============================================================================
method  home position
======  ============================================================================
0       none: homing ends at once, the position actual value unchanged
5, 6    the first index mark above (5) or below (6) the switch's edge
21, 22  the edge itself, as it was met (5 and 6 without the index)
35, 37  the current position (37 is its newer number)
======  ============================================================================

The methods of a positive home switch (3, 4, 19, 20) are refused: the plant has none, and
with this switch they would search the wrong way into a limit switch.

A search runs in the homing speeds 6099h (:01 toward the switch, :02 over the edge and to
the index mark) at the homing acceleration 609Ah: if the axis starts on the home side of
the edge it first moves off the switch's edge the other way (at 6099h:01), reverses at the
edge, crosses it toward home (at 6099h:02), goes on to the next index mark, and stops
there (at 609Ah) -- the home position is where the edge or the mark was met, wherever the
axis comes to rest.  Then the position actual value reads 607Ch at the home position:
the drive's position offset (:attr:`Homing.shift_counts`, in increments) is set to
607Ch less the home position's encoder count.

Status (statusword bits 13, 12, 10): 0 0 1 not started or interrupted, 0 0 0 in progress,
0 1 0 home found and stopping, 0 1 1 attained (the axis stands and is held there),
1 0 x error (x: the speed is 0).  A rising edge of controlword bit 4 starts homing; its
falling edge and halt (bit 8) interrupt it (the axis stops at 609Ah).  A limit switch met
on the way is a homing error (the drive's monitoring faults it too, 8612h).
"""

from enum import IntEnum

from hil.cia402 import SW_HOMING_ATTAINED, SW_HOMING_ERROR, SW_TARGET_REACHED
from hil.drive.profile import ProfileGenerator

#: method -> (the side of the edge the home is on: +1 above, -1 below; index mark used);
#: the switch is on below its edge
SWITCH_METHODS = {5: (1, True), 6: (-1, True), 21: (1, False), 22: (-1, False)}
CURRENT_POSITION = (35, 37)
METHODS = frozenset((0, *SWITCH_METHODS, *CURRENT_POSITION))


class Phase(IntEnum):
    IDLE = 0       # not started, or interrupted
    LEAVE = 1      # moving off the switch's edge away from home
    APPROACH = 2   # moving toward home until the edge is crossed
    INDEX = 3      # on toward home until the next index mark
    STOP = 4       # home found: stopping
    ATTAINED = 5   # home found and standing
    ERROR = 6


class Homing:
    """One drive's homing (see the module docstring).

    Args:
        profile: the drive's profile generator (its demand position and speed).
        counts_per_mark: encoder counts between two index marks.

    Attributes:
        phase: where the search is.
        shift_counts: increments added to the encoder count to give the position actual
            value (0 until a homing ends; kept after).
    """

    def __init__(self, profile: ProfileGenerator, counts_per_mark: int):
        self.profile = profile
        self.counts_per_mark = counts_per_mark
        self.phase = Phase.IDLE
        self.shift_counts = 0.0
        self._method = (1, True)
        self._switch = 0.0
        self._mark = 0.0
        self._offset = 0.0

    def start(self, method: int, switch: float, counts: float, offset_counts: float) -> None:
        """Start ``method`` (6098h, one of :data:`METHODS`) with the home switch at
        ``switch`` (1.0 on), the encoder at ``counts`` and 607Ch = ``offset_counts``."""
        self._offset = offset_counts
        if method == 0:
            self.phase = Phase.ATTAINED
            return
        if method in CURRENT_POSITION:
            self._home(counts)
            self.phase = Phase.STOP
            return
        self._method = SWITCH_METHODS[method]
        home_side = self._method[0]
        side = -1 if switch > 0.0 else 1  # below the edge while the switch is on
        self.phase = Phase.APPROACH if side == -home_side else Phase.LEAVE
        self._switch = switch

    def reset(self) -> None:
        """The position reference is lost (an NMT reset node): no home, no offset."""
        self.phase = Phase.IDLE
        self.shift_counts = 0.0

    def interrupt(self) -> None:
        """Bit 4 fell or halt: stop where the axis is."""
        if self.phase in (Phase.LEAVE, Phase.APPROACH, Phase.INDEX):
            self.phase = Phase.IDLE

    def fail(self) -> None:
        """A limit switch or a fault ended the search."""
        if self.phase in (Phase.LEAVE, Phase.APPROACH, Phase.INDEX, Phase.STOP):
            self.phase = Phase.ERROR

    def _home(self, counts: float) -> None:
        self.shift_counts = self._offset - counts

    def speed(self, switch: float, marks: float, counts: float, speeds: tuple[float, float]
              ) -> float:
        """The speed the profile aims at this cycle (motor units/s), given the plant's
        home switch, index marks and encoder count and the homing speeds (6099h:01, :02);
        advances the search."""
        home_side, with_index = self._method
        moving = self.profile.v
        changed = switch != self._switch
        self._switch = switch
        if self.phase == Phase.LEAVE:
            if changed:
                self.phase = Phase.APPROACH
            return -home_side * speeds[0]
        if self.phase == Phase.APPROACH:
            if changed and moving * home_side > 0.0:
                if with_index:
                    self.phase, self._mark = Phase.INDEX, marks
                else:
                    self._home(counts)
                    self.phase = Phase.STOP
            return home_side * speeds[1]
        if self.phase == Phase.INDEX:
            if marks != self._mark and moving * home_side > 0.0:
                self._home(max(marks, self._mark) * self.counts_per_mark)
                self.phase = Phase.STOP
                return 0.0
            self._mark = marks
            return home_side * speeds[1]
        if self.phase == Phase.STOP and self.profile.stopped():
            self.phase = Phase.ATTAINED
        return 0.0

    def flags(self) -> int:
        """Statusword bits 13, 12, 10 of the phase."""
        phase = self.phase
        if phase == Phase.ERROR:
            return SW_HOMING_ERROR | (SW_TARGET_REACHED if self.profile.stopped() else 0)
        if phase == Phase.ATTAINED:
            return SW_HOMING_ATTAINED | SW_TARGET_REACHED
        if phase == Phase.STOP:
            return SW_HOMING_ATTAINED
        if phase == Phase.IDLE:
            return SW_TARGET_REACHED if self.profile.stopped() else 0
        return 0
