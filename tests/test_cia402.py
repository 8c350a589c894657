"""The CiA 402 drive state machine and the master's enable sequence.

References: the standard's tables (CiA 402-2 / IEC 61800-7-201), hand-typed below: the
statusword bit patterns of the eight states, the controlword of each device control command
and the transitions 0-16 of the state diagram; the cycle counts of the enable sequence are
counted by hand from those tables; and canopen's independent implementation
(``canopen.profiles.p402.State402``: ``SW_MASK``, ``TRANSITIONTABLE``, ``OperationMode``).
"""

import itertools
import tracemalloc

import pytest
from canopen.profiles.p402 import OperationMode, State402
from hypothesis import given
from hypothesis import strategies as st

from hil import cia402
from hil.cia402 import (
    Cia402Error,
    DriveStateMachine,
    EnableSequencer,
    ModeOfOperation,
    QuickStopOption,
    State,
    statusword_state,
)

# The standard's statusword table, bit 15 left, "x" = not relevant for the state.
STANDARD_STATUSWORD = {
    "NOT_READY_TO_SWITCH_ON": "xxxx xxxx x0xx 0000",
    "SWITCH_ON_DISABLED": "xxxx xxxx x1xx 0000",
    "READY_TO_SWITCH_ON": "xxxx xxxx x01x 0001",
    "SWITCHED_ON": "xxxx xxxx x01x 0011",
    "OPERATION_ENABLED": "xxxx xxxx x01x 0111",
    "QUICK_STOP_ACTIVE": "xxxx xxxx x00x 0111",
    "FAULT_REACTION_ACTIVE": "xxxx xxxx x0xx 1111",
    "FAULT": "xxxx xxxx x0xx 1000",
}

# Controlwords of the standard's command table (bits 7 3 2 1 0, "x" taken as 0).
DISABLE_VOLTAGE, QUICK_STOP, SHUTDOWN, SWITCH_ON = 0x00, 0x02, 0x06, 0x07
ENABLE_OPERATION, DISABLE_OPERATION, FAULT_RESET = 0x0F, 0x07, 0x80

NR, SOD = "NOT_READY_TO_SWITCH_ON", "SWITCH_ON_DISABLED"
RTSO, SO = "READY_TO_SWITCH_ON", "SWITCHED_ON"
OE, QSA = "OPERATION_ENABLED", "QUICK_STOP_ACTIVE"
FRA, FLT = "FAULT_REACTION_ACTIVE", "FAULT"

# From power-up, the (controlword, fault) cycles that reach each state, by the standard's table.
PATHS = {
    NR: [],
    SOD: [(0x00, False)],
    RTSO: [(0x00, False), (SHUTDOWN, False)],
    SO: [(0x00, False), (SHUTDOWN, False), (SWITCH_ON, False)],
    OE: [(0x00, False), (SHUTDOWN, False), (SWITCH_ON, False), (ENABLE_OPERATION, False)],
    QSA: [(0x00, False), (SHUTDOWN, False), (SWITCH_ON, False), (ENABLE_OPERATION, False),
          (QUICK_STOP, False)],
    FRA: [(0x00, True)],
    FLT: [(0x00, True), (0x00, True)],
}

# Transitions by controlword: (number, source, controlword, target, quick stop option).
COMMAND_TRANSITIONS = [
    (2, SOD, SHUTDOWN, RTSO, 2),
    (3, RTSO, SWITCH_ON, SO, 2),
    (3, RTSO, ENABLE_OPERATION, SO, 2),   # "switch on + enable operation": 3, then 4
    (4, SO, ENABLE_OPERATION, OE, 2),
    (5, OE, DISABLE_OPERATION, SO, 2),
    (6, SO, SHUTDOWN, RTSO, 2),
    (7, RTSO, DISABLE_VOLTAGE, SOD, 2),
    (7, RTSO, QUICK_STOP, SOD, 2),
    (8, OE, SHUTDOWN, RTSO, 2),
    (9, OE, DISABLE_VOLTAGE, SOD, 2),
    (10, SO, DISABLE_VOLTAGE, SOD, 2),
    (10, SO, QUICK_STOP, SOD, 2),
    (11, OE, QUICK_STOP, QSA, 2),
    (12, QSA, DISABLE_VOLTAGE, SOD, 2),
    (12, QSA, DISABLE_VOLTAGE, SOD, 6),
    (16, QSA, ENABLE_OPERATION, OE, 6),
]


def pattern(text: str) -> tuple[int, int]:
    """(mask, value) of a bit string written most significant bit first."""
    bits = text.replace(" ", "")[::-1]
    mask = sum(1 << i for i, c in enumerate(bits) if c != "x")
    value = sum(1 << i for i, c in enumerate(bits) if c == "1")
    return mask, value


def in_state(statusword: int, name: str) -> bool:
    mask, value = pattern(STANDARD_STATUSWORD[name])
    return statusword & mask == value


def drive_in(name: str, quick_stop_option: int = 2) -> DriveStateMachine:
    drive = DriveStateMachine(quick_stop_option)
    for controlword, fault in PATHS[name]:
        drive.update(controlword, fault)
    assert drive.state == State[name] and in_state(drive.statusword, name)
    return drive


def assert_took(drive: DriveStateMachine, statusword: int, number: int, target: str):
    assert drive.state == State[target], f"transition {number}: {drive.state.name}"
    assert in_state(statusword, target), f"transition {number}: 0x{statusword:04X}"
    assert drive.log.recent()[-1] == number


def test_power_up_is_transition_0_then_1_automatic():
    """0: start -> NOT READY TO SWITCH ON; 1: -> SWITCH ON DISABLED with no command."""
    drive = DriveStateMachine(init_cycles=2)
    assert drive.log.recent() == (0,) and in_state(drive.statusword, NR)
    assert in_state(drive.update(0x00, False), NR)
    assert in_state(drive.update(0x00, False), NR)
    assert_took(drive, drive.update(0x00, False), 1, SOD)


@pytest.mark.parametrize("number,source,controlword,target,option", COMMAND_TRANSITIONS)
def test_command_transition(number, source, controlword, target, option):
    """Each transition from its source state with the standard's controlword."""
    drive = drive_in(source, option)
    assert_took(drive, drive.update(controlword, False), number, target)


@pytest.mark.parametrize("option", [1, 2, 3, 4])
def test_quick_stop_completes_with_12_when_the_axis_stops(option):
    """Option codes 1-4: QUICK STOP ACTIVE until the axis is at rest, then 12."""
    drive = drive_in(QSA, option)
    assert in_state(drive.update(QUICK_STOP, False), QSA) and drive.quick_stop_active
    assert_took(drive, drive.update(QUICK_STOP, False, stopped=True), 12, SOD)


@pytest.mark.parametrize("option", [5, 6, 7, 8])
def test_quick_stop_stays_active_after_stop(option):
    """Option codes 5-8: the drive stays in QUICK STOP ACTIVE at rest; 16 leaves it."""
    drive = drive_in(QSA, option)
    assert in_state(drive.update(QUICK_STOP, False, stopped=True), QSA)
    assert_took(drive, drive.update(ENABLE_OPERATION, False, stopped=True), 16, OE)


def test_16_is_refused_with_option_2():
    """Transition 16 is possible only with quick stop option codes 5-8."""
    drive = drive_in(QSA, 2)
    assert in_state(drive.update(ENABLE_OPERATION, False), QSA)


@pytest.mark.parametrize("source", [NR, SOD, RTSO, SO, OE, QSA])
def test_fault_in_every_state_takes_13_then_14(source):
    """13: a fault -> FAULT REACTION ACTIVE (the drive function stays enabled for a braking
    reaction); 14: reaction complete -> FAULT, not before."""
    drive = drive_in(source)
    held = PATHS[source][-1][0] if PATHS[source] else 0x00
    assert_took(drive, drive.update(held, True), 13, FRA)
    assert drive.power_enabled
    assert in_state(drive.update(held, True, reaction_done=False), FRA)
    assert_took(drive, drive.update(held, True), 14, FLT)
    assert in_state(drive.update(held, True), FLT)
    assert drive.log.recent()[-2:] == (13, 14)


def test_fault_reset_is_15_on_a_rising_edge_without_fault():
    """15 needs a 0 -> 1 edge of bit 7 while no fault is active: an edge during the fault
    and a held bit 7 after it do nothing."""
    drive = drive_in(FLT)
    assert in_state(drive.update(FAULT_RESET, True), FLT)       # edge, fault still active
    assert in_state(drive.update(FAULT_RESET, False), FLT)      # fault gone, bit 7 held
    assert in_state(drive.update(0x8F, False), FLT)             # still held
    assert in_state(drive.update(0x00, False), FLT)             # low
    assert_took(drive, drive.update(FAULT_RESET, False), 15, SOD)
    assert drive.log.count(15) == 1


# Every (state, command) pair the standard defines; every other pair leaves the state as is.
VALID = {
    (SOD, SHUTDOWN): RTSO,
    (RTSO, SWITCH_ON): SO, (RTSO, ENABLE_OPERATION): SO,
    (RTSO, DISABLE_VOLTAGE): SOD, (RTSO, QUICK_STOP): SOD,
    (SO, ENABLE_OPERATION): OE, (SO, SHUTDOWN): RTSO,
    (SO, DISABLE_VOLTAGE): SOD, (SO, QUICK_STOP): SOD,
    (OE, SWITCH_ON): SO, (OE, SHUTDOWN): RTSO, (OE, DISABLE_VOLTAGE): SOD, (OE, QUICK_STOP): QSA,
    (QSA, DISABLE_VOLTAGE): SOD,
}
WORDS = [DISABLE_VOLTAGE, QUICK_STOP, SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, 0x8F, 0x86, 0x81]


@pytest.mark.parametrize("source", [SOD, RTSO, SO, OE, QSA, FLT])
@pytest.mark.parametrize("word", WORDS)
def test_commands_not_valid_in_a_state_leave_it(source, word):
    """Only the standard's (state, command) pairs change the state; bit 7 set is no command."""
    drive = drive_in(source)
    statusword = drive.update(word, False)
    expected = VALID.get((source, word), source)
    if source == FLT and word & 0x80:
        expected = SOD                                            # a rising edge: 15
    assert drive.state == State[expected] and in_state(statusword, expected)


@given(st.sampled_from([SOD, RTSO, SO, OE, QSA]), st.integers(0, 0xFFFF))
def test_controlword_bits_8_to_15_are_ignored(source, word):
    """The state machine reads bits 0-3 and 7 only (4-6, 8-15 are mode or vendor bits)."""
    a, b = drive_in(source), drive_in(source)
    a.update(word, False)
    b.update(word & 0x008F, False)
    assert a.state == b.state


@pytest.mark.parametrize("name", list(STANDARD_STATUSWORD))
def test_statusword_extra_bits_and_decoding(name):
    """Bit 9 remote always; bit 4 voltage enabled after initialisation; bits 7, 10, 11 clear
    unless reported; the decoder inverts the table."""
    statusword = drive_in(name).statusword
    assert statusword & 0x0200 and bool(statusword & 0x0010) == (name != NR)
    assert statusword & 0x0C80 == 0
    assert statusword_state(statusword) == State[name]


@pytest.mark.parametrize("name,held", [(OE, ENABLE_OPERATION), (FLT, 0x00)])
def test_statusword_flags_follow_the_inputs(name, held):
    """Bits 7 (warning), 10 (target reached), 11 (internal limit), 12 and 13 copy the
    drive's flags; other bits of the flags never reach the statusword."""
    drive = drive_in(name)
    for bit in (0x0080, 0x0400, 0x0800, 0x1000, 0x2000):
        assert drive.update(held, name == FLT, flags=bit) & 0x3C80 == bit
    assert drive.update(held, name == FLT, flags=0x006F) == drive.update(held, name == FLT)
    assert in_state(drive.statusword, name)


def test_published_patterns_are_the_standards():
    """STATUS_PATTERNS, which other code may match against, is the standard's table."""
    for name, text in STANDARD_STATUSWORD.items():
        published = cia402.STATUS_PATTERNS[State[name]]
        assert (published.mask, published.value) == pattern(text), name


def test_decoding_agrees_with_the_standard_and_canopen_for_every_statusword():
    """All 65536 statuswords: our decoder, the hand-typed table and canopen's SW_MASK name
    the same state, or all three none."""
    for statusword in range(0x10000):
        names = [n for n in STANDARD_STATUSWORD if in_state(statusword, n)]
        assert len(names) <= 1
        expected = names[0] if names else "UNKNOWN"
        assert canopen_state(statusword) == expected, f"0x{statusword:04X}"
        try:
            ours = statusword_state(statusword).name
        except Cia402Error:
            ours = "UNKNOWN"
        assert ours == expected, f"0x{statusword:04X}"


def test_undefined_statusword_is_refused():
    """Bits 0-3 = 0101 are no state of the table."""
    with pytest.raises(Cia402Error, match="0x0005"):
        statusword_state(0x0005)


def test_power_and_quick_stop_flags():
    """The drive function is enabled in OPERATION ENABLED, QUICK STOP ACTIVE and FAULT
    REACTION ACTIVE only (the last two to brake)."""
    for name in STANDARD_STATUSWORD:
        drive = drive_in(name)
        assert drive.power_enabled == (name in (OE, QSA, FRA)), name
        assert drive.quick_stop_active == (name == QSA), name


def test_option_code_0_and_9_are_refused():
    """605Ah codes outside 1-8 are not offered."""
    for code in (0, 9):
        with pytest.raises(Cia402Error, match=str(code)):
            DriveStateMachine(code)
    assert DriveStateMachine(QuickStopOption.CURRENT_LIMIT_STAY).quick_stop_option == 7


def test_log_ring_keeps_the_last_transitions_and_counts_all():
    """A ring of 3 keeps the last 3 numbers; the counts keep everything."""
    drive = DriveStateMachine(log_length=3)
    for controlword, _ in PATHS[OE]:
        drive.update(controlword, False)
    assert drive.log.recent() == (2, 3, 4)
    assert [drive.log.count(n) for n in range(6)] == [1, 1, 1, 1, 1, 0]


def test_no_memory_retained_while_nothing_changes():
    """Holding OPERATION ENABLED for 2000 cycles: no line of hil/cia402.py holds more memory
    than after the first cycle, and the log is untouched."""
    drive = drive_in(OE)
    drive.update(ENABLE_OPERATION, False)
    only_module = [tracemalloc.Filter(True, cia402.__file__)]
    tracemalloc.start()
    before = tracemalloc.take_snapshot().filter_traces(only_module)
    for _ in itertools.repeat(None, 2000):
        drive.update(ENABLE_OPERATION, False)
    after = tracemalloc.take_snapshot().filter_traces(only_module)
    tracemalloc.stop()
    grown = [d for d in after.compare_to(before, "lineno") if d.size_diff > 0]
    assert grown == []
    assert drive.log.recent()[-1] == 4 and drive.log.count(4) == 1


def test_modes_of_operation():
    """6060h values of the standard, and canopen's."""
    assert [ModeOfOperation.PP, ModeOfOperation.PV, ModeOfOperation.CSP, ModeOfOperation.CSV,
            ModeOfOperation.CST] == [1, 3, 8, 9, 10]
    assert ModeOfOperation.CSP == OperationMode.CYCLIC_SYNCHRONOUS_POSITION
    assert ModeOfOperation.CST == OperationMode.CYCLIC_SYNCHRONOUS_TORQUE


# -- cross-check with canopen ----------------------------------------------------------------

def canopen_state(statusword: int) -> str:
    for name, (mask, value) in State402.SW_MASK.items():
        if statusword & mask == value:
            return name.replace(" ", "_")
    return "UNKNOWN"


@pytest.mark.parametrize("name", list(STANDARD_STATUSWORD))
def test_canopen_decodes_our_statusword(name):
    """canopen's SW_MASK table reads our statusword as the same state."""
    assert canopen_state(drive_in(name).statusword) == name


@pytest.mark.parametrize("pair", [p for p in State402.TRANSITIONTABLE if p[0] != "START"])
def test_canopen_transition_table(pair):
    """Every (from, to): controlword of canopen's table takes our drive there
    (16 needs an option code 5-8)."""
    source, target = (s.replace(" ", "_") for s in pair)
    drive = drive_in(source, 6 if (source, target) == (QSA, OE) else 2)
    drive.update(State402.TRANSITIONTABLE[pair], False)
    assert drive.state == State[target]


# -- the master's enable sequence ------------------------------------------------------------

def run(sequencer: EnableSequencer, drive: DriveStateMachine, faults: list[bool], n: int):
    """n cycles: the sequencer reads the last statusword, the drive the new controlword."""
    words = []
    for k in range(n):
        words.append(sequencer.next_controlword(drive.statusword))
        if sequencer.done or sequencer.failed:
            break
        drive.update(words[-1], faults[k] if k < len(faults) else False)
    return words


def test_sequencer_enables_from_power_up_in_5_cycles():
    """1, 2, 3, 4 take one cycle each; the 5th call sees OPERATION ENABLED."""
    drive, seq = DriveStateMachine(), EnableSequencer(timeout_cycles=20)
    seq.enable()
    words = run(seq, drive, [], 50)
    assert seq.done and not seq.failed
    assert words == [0x00, SHUTDOWN, SWITCH_ON, ENABLE_OPERATION, ENABLE_OPERATION]
    assert drive.log.recent() == (0, 1, 2, 3, 4)


def test_sequencer_resets_a_fault_with_a_bit_7_edge():
    """Fault for the first 3 cycles: 13, 14, a reset pulse refused while the fault is on,
    bit 7 low, high again (15), then 2, 3, 4: done on the 9th call."""
    drive, seq = DriveStateMachine(), EnableSequencer(timeout_cycles=20)
    seq.enable()
    words = run(seq, drive, [True, True, True], 50)
    assert seq.done
    assert words == [0x00, 0x00, FAULT_RESET, 0x00, FAULT_RESET, SHUTDOWN, SWITCH_ON,
                     ENABLE_OPERATION, ENABLE_OPERATION]
    assert drive.log.recent() == (0, 13, 14, 15, 2, 3, 4)


def test_sequencer_times_out_on_a_lasting_fault():
    """A fault that never clears: failed after timeout_cycles, naming the state and word."""
    drive, seq = DriveStateMachine(), EnableSequencer(timeout_cycles=10)
    seq.enable()
    words = run(seq, drive, [True] * 50, 50)
    assert seq.failed and not seq.done and len(words) == 11
    assert "FAULT" in seq.reason and "0x0218" in seq.reason and "10 cycles" in seq.reason
    assert seq.next_controlword(drive.statusword) == DISABLE_VOLTAGE


def test_sequencer_fails_when_the_drive_leaves_operation_enabled():
    """After done, a fault (13) is a failure, not a silent re-enable."""
    drive, seq = DriveStateMachine(), EnableSequencer(timeout_cycles=20)
    seq.enable()
    run(seq, drive, [], 50)
    drive.update(seq.next_controlword(drive.statusword), True)
    assert seq.next_controlword(drive.statusword) == DISABLE_VOLTAGE
    assert seq.failed and "left OPERATION_ENABLED for FAULT_REACTION_ACTIVE" in seq.reason


def test_sequencer_leaves_quick_stop_through_switch_on_disabled():
    """From QUICK STOP ACTIVE (option 2): disable voltage (12), then 2, 3, 4."""
    drive, seq = drive_in(QSA), EnableSequencer(timeout_cycles=20)
    seq.enable()
    words = run(seq, drive, [], 50)
    assert seq.done and words[0] == DISABLE_VOLTAGE
    assert drive.log.recent()[-4:] == (12, 2, 3, 4)


def test_sequencer_disables():
    """Disable from OPERATION ENABLED: disable voltage (9), done on the next call."""
    drive, seq = drive_in(OE), EnableSequencer(timeout_cycles=5)
    words = run(seq, drive, [], 10)
    assert seq.done and words == [DISABLE_VOLTAGE, DISABLE_VOLTAGE]
    assert drive.log.recent()[-1] == 9


def test_sequencer_refuses_an_undefined_statusword():
    """A statusword that matches no state fails the request at once."""
    seq = EnableSequencer(timeout_cycles=5)
    seq.enable()
    assert seq.next_controlword(0x0005) == DISABLE_VOLTAGE
    assert seq.failed and "0x0005" in seq.reason
