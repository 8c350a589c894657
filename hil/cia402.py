"""The CiA 402 (IEC 61800-7-201) drive state machine, table-driven: device and master side.

The device side, :class:`DriveStateMachine`, is what the emulated drive runs once per cycle:
it reads the controlword (object 6040h) and the drive's fault input, takes at most one
transition of the standard's table and answers the statusword (6041h).  The master side,
:class:`EnableSequencer`, is what the controller runs at start-up: from each statusword it
computes the next controlword that leads the drive to OPERATION ENABLED (or disables it),
resetting a fault on the way.

Transition numbers are those of the standard's state diagram (CiA 402-2, figure "Finite
state automaton"; IEC 61800-7-201 § 6.3).  Options this drive implements:

* quick stop option code (605Ah): any of 1-8, default 2 (slow down on the quick stop ramp,
  then SWITCH ON DISABLED).  The state machine does not ramp; the drive's speed controller
  does while :attr:`DriveStateMachine.quick_stop_active` and reports ``stopped=True``.
  Codes 1-4 take transition 12 on that report; codes 5-8 stay in QUICK STOP ACTIVE, from
  where enable operation (16) or disable voltage (12) leave it.  Code 0 (coast at once) is
  not offered: the plant would lose torque while the state still claims a controlled stop.
* fault reaction option code (605Eh, :class:`FaultReactionOption`): the state machine does
  not brake either; the drive runs its reaction in FAULT REACTION ACTIVE (torque on while it
  brakes, :attr:`DriveStateMachine.power_enabled`) and reports its end, after which
  transition 14 leads to FAULT (torque off).  A caller that does not say (``reaction_done``
  left True) gets code 0's behaviour: 14 follows 13 on the next cycle.

Nothing here imports canopen; the tests compare against it as an independent reading.
"""

from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType
from typing import NamedTuple

from io_adapters.messages import MODE_VOLTAGE


class Cia402Error(ValueError):
    """A statusword that matches no state, or a drive option this module does not offer."""


class State(IntEnum):
    """The eight states of the CiA 402 power drive system (PDS) finite state automaton."""
    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class ModeOfOperation(IntEnum):
    """Values of modes of operation (6060h) and its display (6061h) that the drive knows."""
    PP = 1    # profile position
    PV = 3    # profile velocity
    HOMING = 6
    CSP = 8   # cyclic synchronous position
    CSV = 9   # cyclic synchronous velocity
    CST = 10  # cyclic synchronous torque
    VOLTAGE = MODE_VOLTAGE  # manufacturer-specific (a negative value): d-q voltage setpoints


def mode_name(mode: int) -> str:
    """The name of mode of operation ``mode`` (``"CSP"``), or its number as text when it is
    none this drive knows."""
    try:
        return ModeOfOperation(mode).name
    except ValueError:
        return str(mode)


class FaultReactionOption(IntEnum):
    """Fault reaction option codes (605Eh): how the drive stops before it enters FAULT."""
    DISABLE_DRIVE = 0          # torque off at once, the motor coasts
    SLOW_DOWN_RAMP = 1         # brake on the slow down ramp (6084h), then torque off
    QUICK_STOP_RAMP = 2        # brake on the quick stop ramp (6085h), then torque off
    CURRENT_LIMIT = 3          # brake at the current limit, then torque off
    VOLTAGE_LIMIT = 4          # brake at the voltage limit (this drive: its current limit)


class AbortConnectionOption(IntEnum):
    """Abort connection option codes (6007h): what a lost master (setpoint watchdog,
    heartbeat, NMT stop or reset) does to a drive whose power stage is on."""
    NO_ACTION = 0
    FAULT = 1                  # a fault (then 605Eh's reaction)
    DISABLE_VOLTAGE = 2        # as the disable voltage command: torque off
    QUICK_STOP = 3             # as the quick stop command (then 605Ah's reaction)


class QuickStopOption(IntEnum):
    """Quick stop option codes (605Ah) 1-8: how to stop, and whether to disable afterwards."""
    SLOW_DOWN_RAMP_DISABLE = 1
    QUICK_STOP_RAMP_DISABLE = 2
    CURRENT_LIMIT_DISABLE = 3
    VOLTAGE_LIMIT_DISABLE = 4
    SLOW_DOWN_RAMP_STAY = 5
    QUICK_STOP_RAMP_STAY = 6
    CURRENT_LIMIT_STAY = 7
    VOLTAGE_LIMIT_STAY = 8

    @property
    def disables_after_stop(self) -> bool:
        """Codes 1-4 end the quick stop in SWITCH ON DISABLED (12); 5-8 stay (16 allowed)."""
        return self <= QuickStopOption.VOLTAGE_LIMIT_DISABLE


# Statusword (6041h) bits.
SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5          # 0 = the drive reacts to a quick stop request
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9              # the controlword is processed
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT_ACTIVE = 1 << 11
SW_FOLLOWS_COMMAND = 1 << 12    # CSP/CSV/CST: the drive follows the command value
SW_SET_POINT_ACK = 1 << 12      # PP: a new set-point was taken (bit 12 by mode)
SW_SPEED_ZERO = 1 << 12         # PV: the speed is zero
SW_HOMING_ATTAINED = 1 << 12    # homing: the home position was found
SW_FOLLOWING_ERROR = 1 << 13    # CSP, PP: the following error is beyond its window (6065h)
SW_HOMING_ERROR = 1 << 13       # homing: it failed
#: each statusword bit's name as CiA 402-2 gives it (6041h); bits 12 and 13 mean what the
#: mode of operation makes them, so their names list the meaning in each mode
STATUSWORD_BITS = MappingProxyType({
    SW_READY_TO_SWITCH_ON: "Ready to switch on",
    SW_SWITCHED_ON: "Switched on",
    SW_OPERATION_ENABLED: "Operation enabled",
    SW_FAULT: "Fault",
    SW_VOLTAGE_ENABLED: "Voltage enabled",
    SW_QUICK_STOP: "Quick stop",
    SW_SWITCH_ON_DISABLED: "Switch on disabled",
    SW_WARNING: "Warning",
    SW_REMOTE: "Remote",
    SW_TARGET_REACHED: "Target reached",
    SW_INTERNAL_LIMIT_ACTIVE: "Internal limit active",
    SW_FOLLOWS_COMMAND: "Drive follows the command value (CSP/CSV/CST), set-point "
                        "acknowledge (PP), speed 0 (PV), homing attained (homing)",
    SW_FOLLOWING_ERROR: "Following error (CSP/PP), homing error (homing)",
})
#: the statusword bits a caller of DriveStateMachine.update may set
SW_CALLER_BITS = (SW_WARNING | SW_TARGET_REACHED | SW_INTERNAL_LIMIT_ACTIVE
                  | SW_FOLLOWS_COMMAND | SW_FOLLOWING_ERROR)

CW_FAULT_RESET = 1 << 7  # controlword (6040h) bit 7: fault reset, acts on its 0 -> 1 edge
# controlword bits of the profile modes (CiA 402-2 §12, §14, §16)
CW_NEW_SET_POINT = 1 << 4            # PP: new set-point (its rising edge); homing: start
CW_CHANGE_SET_IMMEDIATELY = 1 << 5   # PP: the new set-point replaces the one under way
CW_RELATIVE = 1 << 6                 # PP: the target is relative to the previous one
CW_HALT = 1 << 8                     # PP, PV, homing: stop (6084h, 609Ah)


@dataclass(frozen=True)
class BitPattern:
    """``word & mask == value``: a state's statusword pattern or a controlword command.

    For a command, ``value`` is also the controlword a master sends to give it.
    """
    mask: int
    value: int

    def matches(self, word: int) -> bool:
        return word & self.mask == self.value


#: statusword patterns of the standard's table, bits 0-3, 5 and 6
STATUS_PATTERNS = MappingProxyType({
    State.NOT_READY_TO_SWITCH_ON: BitPattern(0x004F, 0x0000),  # x0xx 0000
    State.SWITCH_ON_DISABLED: BitPattern(0x004F, 0x0040),      # x1xx 0000
    State.READY_TO_SWITCH_ON: BitPattern(0x006F, 0x0021),      # x01x 0001
    State.SWITCHED_ON: BitPattern(0x006F, 0x0023),             # x01x 0011
    State.OPERATION_ENABLED: BitPattern(0x006F, 0x0027),       # x01x 0111
    State.QUICK_STOP_ACTIVE: BitPattern(0x006F, 0x0007),       # x00x 0111
    State.FAULT_REACTION_ACTIVE: BitPattern(0x004F, 0x000F),   # x0xx 1111
    State.FAULT: BitPattern(0x004F, 0x0008),                   # x0xx 1000
})

# Device control commands, controlword bits 7, 3, 2, 1, 0 of the standard's command table.
SHUTDOWN = BitPattern(0x0087, 0x0006)            # 0 x 1 1 0 -> 2, 6, 8
SWITCH_ON = BitPattern(0x008F, 0x0007)           # 0 0 1 1 1 -> 3
DISABLE_VOLTAGE = BitPattern(0x0082, 0x0000)     # 0 x x 0 x -> 7, 9, 10, 12
QUICK_STOP = BitPattern(0x0086, 0x0002)          # 0 x 0 1 x -> 7, 10, 11
DISABLE_OPERATION = BitPattern(0x008F, 0x0007)   # 0 0 1 1 1 -> 5
ENABLE_OPERATION = BitPattern(0x008F, 0x000F)    # 0 1 1 1 1 -> 4, 16
FAULT_RESET = BitPattern(0x0080, 0x0080)         # 0 -> 1 x x x x -> 15, on the edge only
# "Switch on + enable operation" (0 1 1 1 1) also takes 3 in READY TO SWITCH ON; 4 follows
# on the next cycle while the word is held.
_SWITCH_ON_ANY = BitPattern(0x0087, 0x0007)
_ANY = BitPattern(0x0000, 0x0000)


class _Cond(IntEnum):
    """What besides the controlword a row needs this cycle."""
    COMMAND = 0     # the controlword alone
    FAULT = 1       # the fault input is set
    INIT_DONE = 2   # initialisation after power-up is over
    REACTION_DONE = 3  # the fault reaction is complete (605Eh)
    RESET = 4       # rising edge of controlword bit 7 and no fault
    STOPPED = 5     # the caller reports the axis stopped


class _Row(NamedTuple):
    number: int
    source: State
    condition: _Cond
    command: BitPattern
    target: State


_S = State
# 13: fault in any state outside the fault box -> FAULT REACTION ACTIVE (listed first: wins).
_FAULT_ROWS = tuple(_Row(13, s, _Cond.FAULT, _ANY, _S.FAULT_REACTION_ACTIVE)
                    for s in State if s not in (_S.FAULT_REACTION_ACTIVE, _S.FAULT))
_TABLE = _FAULT_ROWS + (
    # 0: start -> NOT READY TO SWITCH ON is the power-up itself (DriveStateMachine.power_up)
    _Row(1, _S.NOT_READY_TO_SWITCH_ON, _Cond.INIT_DONE, _ANY, _S.SWITCH_ON_DISABLED),
    _Row(2, _S.SWITCH_ON_DISABLED, _Cond.COMMAND, SHUTDOWN, _S.READY_TO_SWITCH_ON),
    _Row(3, _S.READY_TO_SWITCH_ON, _Cond.COMMAND, _SWITCH_ON_ANY, _S.SWITCHED_ON),
    _Row(7, _S.READY_TO_SWITCH_ON, _Cond.COMMAND, DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    _Row(7, _S.READY_TO_SWITCH_ON, _Cond.COMMAND, QUICK_STOP, _S.SWITCH_ON_DISABLED),
    _Row(4, _S.SWITCHED_ON, _Cond.COMMAND, ENABLE_OPERATION, _S.OPERATION_ENABLED),
    _Row(6, _S.SWITCHED_ON, _Cond.COMMAND, SHUTDOWN, _S.READY_TO_SWITCH_ON),
    _Row(10, _S.SWITCHED_ON, _Cond.COMMAND, DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    _Row(10, _S.SWITCHED_ON, _Cond.COMMAND, QUICK_STOP, _S.SWITCH_ON_DISABLED),
    _Row(5, _S.OPERATION_ENABLED, _Cond.COMMAND, DISABLE_OPERATION, _S.SWITCHED_ON),
    _Row(8, _S.OPERATION_ENABLED, _Cond.COMMAND, SHUTDOWN, _S.READY_TO_SWITCH_ON),
    _Row(9, _S.OPERATION_ENABLED, _Cond.COMMAND, DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    _Row(11, _S.OPERATION_ENABLED, _Cond.COMMAND, QUICK_STOP, _S.QUICK_STOP_ACTIVE),
    _Row(12, _S.QUICK_STOP_ACTIVE, _Cond.COMMAND, DISABLE_VOLTAGE, _S.SWITCH_ON_DISABLED),
    _Row(14, _S.FAULT_REACTION_ACTIVE, _Cond.REACTION_DONE, _ANY, _S.FAULT),
    _Row(15, _S.FAULT, _Cond.RESET, _ANY, _S.SWITCH_ON_DISABLED),
)
# 12: quick stop complete -> SWITCH ON DISABLED, option codes 1-4 only.
_DISABLE_AFTER_STOP_ROWS = (
    _Row(12, _S.QUICK_STOP_ACTIVE, _Cond.STOPPED, _ANY, _S.SWITCH_ON_DISABLED),)
# 16: enable operation from QUICK STOP ACTIVE, option codes 5-8 only.
_STAY_AFTER_STOP_ROWS = (
    _Row(16, _S.QUICK_STOP_ACTIVE, _Cond.COMMAND, ENABLE_OPERATION, _S.OPERATION_ENABLED),)

# Statusword of each state without the per-cycle flags: the state pattern, bit 5 set exactly
# where the table requires it, voltage enabled once initialised (the emulated DC link is
# always charged), remote always (the drive follows the controlword).
_BASE_STATUSWORD = tuple(
    STATUS_PATTERNS[s].value | SW_REMOTE
    | (0 if s == _S.NOT_READY_TO_SWITCH_ON else SW_VOLTAGE_ENABLED)
    for s in State)

N_TRANSITIONS = 17  # transition numbers 0 .. 16


def base_statusword(state: State) -> int:
    """The statusword of ``state`` without a cycle's flags (:data:`SW_CALLER_BITS`)."""
    return _BASE_STATUSWORD[state]


def statusword_state(statusword: int) -> State:
    """The state a statusword reports.

    Raises:
        Cia402Error: bits 0-3, 5 and 6 match no state of the standard's table.
    """
    state = _decode(statusword)
    if state is None:
        raise Cia402Error(f"statusword 0x{statusword:04X} matches no CiA 402 state")
    return state


def _decode(statusword: int) -> State | None:
    for state, pattern in STATUS_PATTERNS.items():
        if pattern.matches(statusword):
            return state
    return None


class TransitionLog:
    """The transitions a drive took: a count per number and a ring of the last ones.

    Preallocated; :meth:`record` allocates nothing.
    """

    def __init__(self, length: int):
        if length < 1:
            raise Cia402Error(f"transition log length {length} must be at least 1")
        self._ring = [0] * length
        self._next = 0
        self._stored = 0
        self._counts = [0] * N_TRANSITIONS

    def record(self, number: int) -> None:
        """Note that transition ``number`` (0-16) was taken."""
        self._ring[self._next] = number
        self._next = (self._next + 1) % len(self._ring)
        self._stored = min(self._stored + 1, len(self._ring))
        self._counts[number] += 1

    def count(self, number: int) -> int:
        """How often transition ``number`` was taken since the log was created."""
        return self._counts[number]

    def recent(self) -> tuple[int, ...]:
        """The last transitions taken (at most the log length), oldest first."""
        n = len(self._ring)
        start = (self._next - self._stored) % n
        return tuple(self._ring[(start + i) % n] for i in range(self._stored))


class DriveStateMachine:
    """The device side: the emulated drive's CiA 402 state machine, one :meth:`update` a cycle.

    Args:
        quick_stop_option: 605Ah, 1-8 (see the module docstring).
        init_cycles: updates spent in NOT READY TO SWITCH ON after power-up before the
            automatic transition 1 (0: the first update takes it).
        log_length: how many of the last transitions :attr:`log` keeps.

    Attributes:
        quick_stop_option: the 605Ah code in force.
        log: the transitions taken, power-up (0) included.
    """

    def __init__(self, quick_stop_option: int = QuickStopOption.QUICK_STOP_RAMP_DISABLE,
                 init_cycles: int = 0, log_length: int = 64):
        if init_cycles < 0:
            raise Cia402Error(f"init_cycles {init_cycles} must be >= 0")
        self.set_quick_stop_option(quick_stop_option)
        self._init_cycles = init_cycles
        self._cond = [False] * len(_Cond)
        self._cond[_Cond.COMMAND] = True
        self.log = TransitionLog(log_length)
        self.power_up()

    def set_quick_stop_option(self, code: int) -> None:
        """Take 605Ah ``code`` (1-8) from the next :meth:`update` on."""
        try:
            option = QuickStopOption(code)
        except ValueError as e:
            raise Cia402Error(f"quick stop option code {code} not offered; "
                              "605Ah must be 1-8") from e
        extra = (_DISABLE_AFTER_STOP_ROWS if option.disables_after_stop
                 else _STAY_AFTER_STOP_ROWS)
        rows = _TABLE + extra
        self._rows = tuple(tuple(r for r in rows if r.source == s) for s in State)
        self.quick_stop_option = option

    def power_up(self) -> None:
        """Transition 0: power on (or reset) -> NOT READY TO SWITCH ON, initialisation starts."""
        self._state = State.NOT_READY_TO_SWITCH_ON
        self._init_left = self._init_cycles
        self._previous_controlword = 0
        self._statusword = _BASE_STATUSWORD[self._state]
        self.log.record(0)

    @property
    def state(self) -> State:
        """The current state."""
        return self._state

    def stays(self, controlword: int) -> bool:
        """Under ``controlword``, repeated, with no fault, the state takes no transition of
        its own: true only in SWITCH ON DISABLED, READY TO SWITCH ON and SWITCHED ON, whose
        rows all hang on the command (13, the fault, aside)."""
        rows = self._rows[self._state]
        return (self._state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                                State.SWITCHED_ON)
                and all(r.condition == _Cond.FAULT or (r.condition == _Cond.COMMAND
                                                       and not r.command.matches(controlword))
                        for r in rows))

    @property
    def statusword(self) -> int:
        """The statusword the last :meth:`update` returned (after power-up: NOT READY's)."""
        return self._statusword

    @property
    def power_enabled(self) -> bool:
        """The drive function is enabled: torque may be on (OPERATION ENABLED, QUICK STOP
        ACTIVE, FAULT REACTION ACTIVE).

        The standard keeps the drive function enabled in QUICK STOP ACTIVE so the axis can
        be braked on the quick stop ramp (605Ah codes 1-8), and in FAULT REACTION ACTIVE for
        a braking fault reaction (605Eh codes 1-4); the drive decides whether it brakes.
        """
        return self._state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE,
                               State.FAULT_REACTION_ACTIVE)

    @property
    def quick_stop_active(self) -> bool:
        """A quick stop is being executed: the speed setpoint follows the quick stop ramp."""
        return self._state == State.QUICK_STOP_ACTIVE

    def update(self, controlword: int, fault: bool, *, stopped: bool = False,
               reaction_done: bool = True, flags: int = 0) -> int:
        """One cycle: take at most one transition and return the statusword.

        Args:
            controlword: 6040h as received this cycle (16 bits).
            fault: the drive detects a fault this cycle (13 from any non-fault state; no
                fault reset while set).
            stopped: the axis has come to rest; completes a quick stop (12, codes 1-4).
            reaction_done: the fault reaction is complete (14).
            flags: statusword bits the drive sets this cycle, of :data:`SW_CALLER_BITS`
                (warning 7, target reached 10, internal limit active 11, 12, 13).

        Returns:
            The statusword 6041h (16 bits).
        """
        cond = self._cond
        cond[_Cond.FAULT] = fault
        cond[_Cond.INIT_DONE] = self._init_left == 0
        cond[_Cond.RESET] = (not fault and bool(controlword & CW_FAULT_RESET)
                             and not self._previous_controlword & CW_FAULT_RESET)
        cond[_Cond.STOPPED] = stopped
        cond[_Cond.REACTION_DONE] = reaction_done
        self._previous_controlword = controlword
        if self._init_left > 0 and self._state == State.NOT_READY_TO_SWITCH_ON:
            self._init_left -= 1
        for row in self._rows[self._state]:
            if cond[row.condition] and row.command.matches(controlword):
                self._state = row.target
                self.log.record(row.number)
                break
        statusword = _BASE_STATUSWORD[self._state]
        if flags:
            statusword |= flags & SW_CALLER_BITS
        self._statusword = statusword
        return statusword


# The master's command in each state on the way to OPERATION ENABLED (FAULT: reset pulse).
_ENABLE_WORD = MappingProxyType({
    State.NOT_READY_TO_SWITCH_ON: DISABLE_VOLTAGE.value,  # wait for 1
    State.SWITCH_ON_DISABLED: SHUTDOWN.value,              # 2
    State.READY_TO_SWITCH_ON: SWITCH_ON.value,             # 3
    State.SWITCHED_ON: ENABLE_OPERATION.value,             # 4
    State.OPERATION_ENABLED: ENABLE_OPERATION.value,       # hold
    State.QUICK_STOP_ACTIVE: DISABLE_VOLTAGE.value,        # 12, then start again
    State.FAULT_REACTION_ACTIVE: DISABLE_VOLTAGE.value,    # wait for 14
})


class EnableSequencer:
    """The master side: the controlword that brings a drive to OPERATION ENABLED, or disables it.

    Call :meth:`next_controlword` once a cycle with the latest statusword.  A new sequencer
    is disabling (target SWITCH ON DISABLED).  A fault met while enabling is reset with a
    pulse on controlword bit 7 (low, then high), repeated while the fault persists.  The
    request fails when its target is not reached within ``timeout_cycles`` calls, when the
    statusword matches no state, or when the drive leaves OPERATION ENABLED after reaching
    it; a failed sequencer sends disable voltage (0) until the next :meth:`enable` or
    :meth:`disable`.

    Args:
        timeout_cycles: calls allowed to reach the target, counted from the request.

    Attributes:
        target: the state requested (OPERATION_ENABLED or SWITCH_ON_DISABLED).
        cycles: calls since the request (stops counting once failed).
        done: the drive is in the target state (a faulted drive counts as disabled).
        failed: the request failed; ``reason`` says why, with the statusword and cycle.
    """

    def __init__(self, timeout_cycles: int):
        if timeout_cycles < 1:
            raise Cia402Error(f"timeout_cycles {timeout_cycles} must be at least 1")
        self.timeout_cycles = timeout_cycles
        self._last_word = DISABLE_VOLTAGE.value
        self.disable()

    def enable(self) -> None:
        """Request OPERATION ENABLED."""
        self._request(State.OPERATION_ENABLED)

    def disable(self) -> None:
        """Request SWITCH ON DISABLED (disable voltage: 7, 9, 10, 12); a faulted drive counts
        as disabled and is not reset."""
        self._request(State.SWITCH_ON_DISABLED)

    def _request(self, target: State) -> None:
        self.target = target
        self.cycles = 0
        self.done = False
        self.failed = False
        self.reason = ""

    def next_controlword(self, statusword: int) -> int:
        """The controlword to send this cycle, given the last statusword received."""
        state = _decode(statusword)
        if not self.failed:
            self.cycles += 1
            self._follow(state, statusword)
        word = DISABLE_VOLTAGE.value if self.failed else self._word_for(state)
        self._last_word = word
        return word

    def _follow(self, state: State | None, statusword: int) -> None:
        if state is None:
            self._fail(f"statusword 0x{statusword:04X} matches no state")
            return
        reached = state == self.target or (
            self.target == State.SWITCH_ON_DISABLED and state == State.FAULT)
        if self.done and not reached:
            self._fail(f"drive left {self.target.name} for {state.name} "
                       f"(statusword 0x{statusword:04X}) at cycle {self.cycles}")
        elif reached:
            self.done = True
        elif self.cycles > self.timeout_cycles:
            self._fail(f"{self.target.name} not reached in {self.timeout_cycles} cycles: "
                       f"drive in {state.name} (statusword 0x{statusword:04X})")

    def _fail(self, reason: str) -> None:
        self.done = False
        self.failed = True
        self.reason = reason

    def _word_for(self, state: State) -> int:
        if self.target != State.OPERATION_ENABLED:
            return DISABLE_VOLTAGE.value
        if state == State.FAULT:
            if self._last_word & CW_FAULT_RESET:
                return DISABLE_VOLTAGE.value       # bit 7 low ...
            return FAULT_RESET.value               # ... then high: 15
        return _ENABLE_WORD[state]
