"""The compiled steady-state drive cycle (issue 12 part 6, :mod:`hil.drive.compiled`)
against the Python drive it stands for, bit for bit.

The same setpoint sequence goes through two drives on two identical plants: one every
cycle in Python (``compiled=False``), one taking the compiled path where it may.  Every
tick the feedback, the plant's state and outputs, and the recording row (each drive has
its own :class:`~hil.runtime.recording.Recorder`; the compiled one writes its rows
itself) must be the same bits; no tolerance.  The scenarios cross the boundary of the
steady state many times (enable, CSP motion, a following-error fault, fault reset,
re-enable, CSV, CST, mode changes, a software limit, refused setpoints, quick stop, a
parameter written while running, two axes), and hypothesis draws random ones.  Each
scenario also checks that the compiled path ran most of the enabled cycles, or the
comparison would say nothing.
"""

import math
from dataclasses import dataclass, field, fields

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.cia402 import EnableSequencer, State, statusword_state
from hil.drive import Cause, DriveSet, EmulatedDrive
from hil.drive import compiled as C
from hil.runtime.recording import Recorder
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    MODE_VOLTAGE,
    Feedback,
    axis_records,
    message_pair,
)
from plant import Plant
from plant import layout as L
from plant.config import load_machine
from tests.conftest import CONFIGS

ARROW = load_machine(CONFIGS / "arrow500_x.toml")
#: the Arrow with a holding brake on its motor (closing in 30 ms)
BRAKED = load_machine(CONFIGS / "arrow500_x.toml", {"brake": {"holding_torque_nm": 20.0}})
FB_FLOATS = tuple(f.name for f in fields(Feedback) if f.type in (float, "float"))
FB_INTS = tuple(f.name for f in fields(Feedback) if f.name not in FB_FLOATS)


@dataclass
class Twin:
    """One machine of ``n_axes`` Arrow 500 X axes (or ``machine``'s), Python or compiled,
    with its ring."""
    compiled: bool
    n_axes: int
    ticks: int
    machine: object = ARROW
    drives: DriveSet = field(init=False)
    recorder: Recorder = field(init=False)

    def __post_init__(self):
        self.drives = DriveSet([EmulatedDrive(Plant(self.machine, table_pos=0.25),
                                              compiled=self.compiled)
                                for _ in range(self.n_axes)])
        self.sp, self.fb = message_pair(self.n_axes)
        names = ("X", "Y")[:self.n_axes] if self.n_axes > 1 else None
        self.recorder = Recorder(self.ticks + 1, (ARROW.machine.kind,) * self.n_axes, names)
        self.recorder.attach(self.drives)

    def tick(self, k: int, sp) -> None:
        self.recorder.begin_tick()
        self.drives.cycle(sp, self.fb)
        self.recorder.record(k, True, k, sp, self.fb, self.drives)
        self.recorder.end_tick(k, 0, 0)


def _bits(values) -> bytes:
    return np.array(values, dtype=np.float64).tobytes()


def assert_same(a: Twin, b: Twin, k: int) -> None:
    for i, (fa, fb, da, db) in enumerate(zip(axis_records(a.fb), axis_records(b.fb),
                                             a.drives.drives, b.drives.drives)):
        where = f"tick {k}, axis {i}"
        assert [getattr(fa, n) for n in FB_INTS] == [getattr(fb, n) for n in FB_INTS], where
        assert _bits([getattr(fa, n) for n in FB_FLOATS]) == _bits(
            [getattr(fb, n) for n in FB_FLOATS]), where
        assert da.plant.state.tobytes() == db.plant.state.tobytes(), where
        assert da.plant.out.tobytes() == db.plant.out.tobytes(), where
        assert da.plant.inp.tobytes() == db.plant.inp.tobytes(), where
        assert (da.sm.state, da.tick, da.faults.latched) == (db.sm.state, db.tick,
                                                           db.faults.latched), where


def assert_same_rows(a: Twin, b: Twin) -> None:
    n = a.recorder.committed
    assert n == b.recorder.committed
    rows_a, rows_b = a.recorder.columns(0, n), b.recorder.columns(0, n)
    for name, col in rows_a.items():
        assert col.tobytes() == rows_b[name].tobytes(), name


def assert_same_state(a: EmulatedDrive, b: EmulatedDrive) -> None:
    """The objects' state once the compiled path has handed it back."""
    b.settle()
    for get in (lambda d: d.monitor.__dict__, lambda d: d.modes.interp.__dict__,
                lambda d: d.holding_brake.__dict__, lambda d: d.modes.profile.__dict__,
                lambda d: {k: v for k, v in d.modes.__dict__.items()
                           if isinstance(v, (int, float, tuple, type(None)))},
                lambda d: d.loops.speed.pi.__dict__, lambda d: d.loops.speed.notch.__dict__,
                lambda d: d.loops.pos.sym.__dict__):
        va, vb = get(a), get(b)
        assert {k: _bits(v) if isinstance(v, (float, tuple)) else v for k, v in va.items()
                if k != "params"} == {
            k: _bits(v) if isinstance(v, (float, tuple)) else v for k, v in vb.items()
            if k != "params"}


class Script:
    """Setpoints from a list of segments ``(kind, ticks, value)``: the controlword follows
    the CiA 402 enable sequence unless a segment gives it.

    kinds: "csp" (ramp, value in increments per tick), "jump" (one CSP step of value
    increments, then hold), "csv" (increments/s), "cst" (A), "volt" (voltage mode, u_q
    = value V, u_d = 0), "nan" (CSP with a NaN
    current feed-forward: refused), "cw" (this controlword, CSP hold), "limit" (607Dh max
    at the position plus ``value`` increments), "fe_window" (6065h to value rad),
    "settle" (the compiled drive's state handed back to its objects, as an SDO read does,
    and compared with the Python drive's).
    """

    def __init__(self, segments, n_axes: int):
        self.segments = segments
        self.n_axes = n_axes

    def run(self, a: Twin, b: Twin) -> None:
        enable = EnableSequencer(timeout_cycles=10_000)
        enable.enable()
        sp, _ = message_pair(self.n_axes)
        k = 0
        for kind, ticks, value in self.segments:
            if kind == "settle":  # as an SDO read does: the state back in the objects
                for da, db in zip(a.drives.drives, b.drives.drives):
                    assert_same_state(da, db)
                continue
            if kind in ("limit", "fe_window"):
                for d in (*a.drives.drives, *b.drives.drives):
                    if kind == "limit":
                        d.params.limit_max = (d.plant.out[L.O_ENCODER] + value) * d.rad_per_count
                    else:
                        d.params.fe_window = value
                continue
            for t in range(ticks):
                fbs = axis_records(a.fb)
                if kind == "cw":
                    sp.controlword = value
                else:
                    if enable.failed:  # the drive left OPERATION ENABLED: enable again
                        enable.enable()
                    sp.controlword = enable.next_controlword(fbs[0].statusword)
                sp.seq = k
                for s, f in zip(axis_records(sp), fbs):
                    s.seq = k
                    s.iq_ref_a = s.uq_v = 0.0
                    if kind in ("csp", "jump", "nan", "cw"):
                        if s.mode != MODE_CSP or statusword_state(
                                f.statusword) != State.OPERATION_ENABLED:
                            s.target_position_counts = f.encoder_counts  # hold where it is
                        s.mode = MODE_CSP
                        if kind == "csp" or kind == "jump" and t == 0:
                            s.target_position_counts += value
                        elif kind == "nan" and t == 0:
                            s.iq_ref_a = math.nan
                    elif kind == "csv":
                        s.mode, s.target_velocity_counts_s = MODE_CSV, value
                    elif kind == "volt":
                        s.mode, s.uq_v = MODE_VOLTAGE, value
                    else:
                        s.mode, s.iq_ref_a = MODE_CST, value
                a.tick(k, sp)
                b.tick(k, sp)
                assert_same(a, b, k)
                k += 1


def _compare(segments, n_axes: int = 1, machine=ARROW) -> Twin:
    ticks = sum(t for _, t, _ in segments)
    a, b = Twin(False, n_axes, ticks, machine), Twin(True, n_axes, ticks, machine)
    Script(segments, n_axes).run(a, b)
    assert_same_rows(a, b)
    for da, db in zip(a.drives.drives, b.drives.drives):
        assert_same_state(da, db)
    return b


def _compiled_share(twin: Twin, enabled_ticks: int) -> float:
    return min(d.compiled.cycles for d in twin.drives.drives) / enabled_ticks


@pytest.mark.parametrize("machine", [ARROW, BRAKED], ids=["arrow", "arrow_with_brake"])
def test_power_off_states(machine):
    """The power-off cycle (SWITCH ON DISABLED, READY TO SWITCH ON, SWITCHED ON under a
    held controlword): at rest, then coasting after disable voltage in motion (with a
    holding brake: it closes after its closing time, and stops the axis), between
    enables; the objects' state compared after each stretch."""
    segments = [
        ("cw", 300, 0x0000),        # SWITCH ON DISABLED
        ("settle", 0, 0.0),
        ("cw", 300, 0x0006),        # shutdown: READY TO SWITCH ON
        ("cw", 300, 0x0007),        # switch on: SWITCHED ON
        ("settle", 0, 0.0),
        ("csp", 600, 40.0),         # enable, CSP ramp
        ("cw", 800, 0x0000),        # disable voltage while moving: the axis coasts
        ("settle", 0, 0.0),
        ("csp", 400, 0.0),          # enable again, hold
        ("cw", 300, 0x0006),        # shutdown from OPERATION ENABLED: READY TO SWITCH ON
    ]
    b = _compare(segments, machine=machine)
    d = b.drives.drives[0].compiled
    # every held stretch but its first cycle (the transition's, in Python) and the one
    # that packs the state
    assert d.idle_cycles >= 300 + 300 + 300 + 800 + 300 - 5 * 3


def test_enable_motion_fault_reset_modes_limits_refusal_quick_stop():
    """One axis through every boundary of the steady state."""
    segments = [
        ("csp", 400, 0.0),          # enable, hold
        ("csp", 1500, 40.0),        # CSP ramp
        ("jump", 40, 3.0e7),        # a step far beyond 6065h, at the current limit
        ("settle", 0, 0.0),         # I²t heating, compared
        ("jump", 260, 0.0),         # then the following-error fault
        ("cw", 5, 0x0000),          # ...
        ("cw", 5, 0x0080),          # fault reset (rising edge of bit 7)
        ("csp", 600, 0.0),          # re-enable, hold
        ("csv", 800, 3.0e5),        # CSV
        ("cst", 300, 0.5),          # CST
        ("csp", 400, -30.0),        # back to CSP
        ("limit", 0, 2.0e4),        # 607Dh max just ahead
        ("csv", 800, 5.0e5),        # CSV runs into the software limit
        ("csv", 400, -5.0e5),       # and back in
        ("csp", 400, 10.0),
        ("nan", 20, 0.0),           # a refused setpoint: fault
        ("cw", 5, 0x0000),
        ("cw", 5, 0x0080),
        ("csp", 400, 10.0),         # re-enable
        ("fe_window", 0, 0.5),      # 6065h written while running
        ("csp", 400, 10.0),
        ("cw", 200, 0x0002),        # quick stop
        ("csp", 600, 5.0),          # enable again
    ]
    b = _compare(segments)
    d = b.drives[0]
    assert d.compiled.cycles > 5000
    # the compiled path declined the fault's first cycle and the refused setpoint itself
    assert d.compiled.exits[C.EXIT_CAUSE] >= 1 and d.compiled.exits[C.EXIT_REFUSED] >= 1
    assert [e.causes for e in d.faults.events if e.kind == "fault"] == [
        Cause.FOLLOWING_ERROR, Cause.SETPOINT_REFUSED]


def test_voltage_mode_runs_compiled_and_trips_at_the_current_limit():
    """Voltage mode runs compiled, the same bits as the Python drive, until the current
    passes 6072h: both drives trip (2300h) and take the torque off in the same cycle."""
    b = _compare([("csp", 300, 0.0), ("volt", 600, 2.0), ("volt", 400, -3.0),
                  ("volt", 200, 100.0), ("cw", 5, 0), ("cw", 5, 0x80), ("csp", 300, 0.0)])
    d = b.drives[0]
    assert d.compiled.cycles > 900
    assert d.compiled.exits[C.EXIT_CAUSE] >= 1
    # 100 V trips it at every enable the script retries
    assert {e.causes for e in d.faults.events if e.kind == "fault"} == {Cause.PEAK_CURRENT}
    assert d.sm.state == State.OPERATION_ENABLED  # reset and enabled again


def test_two_axes():
    """Two axes of one machine, one message: enable, CSP motion, CSV, a fault on both."""
    b = _compare([("csp", 300, 0.0), ("csp", 800, 25.0), ("csv", 500, -2.0e5),
                  ("jump", 200, 3.0e7), ("cw", 3, 0), ("cw", 3, 0x80), ("csp", 400, 5.0)],
                 n_axes=2)
    assert _compiled_share(b, 2200) > 0.5


_SEGMENT = st.one_of(
    st.tuples(st.just("csp"), st.integers(1, 300), st.floats(-80.0, 80.0)),
    st.tuples(st.just("jump"), st.integers(1, 100), st.sampled_from([1e3, -5e4, 3e7])),
    st.tuples(st.just("csv"), st.integers(1, 300), st.floats(-6e5, 6e5)),
    st.tuples(st.just("cst"), st.integers(1, 100), st.floats(-3.0, 3.0)),
    st.tuples(st.just("volt"), st.integers(1, 100), st.floats(-120.0, 120.0)),
    st.tuples(st.just("nan"), st.integers(1, 5), st.just(0.0)),
    st.tuples(st.just("cw"), st.integers(1, 20),
              st.sampled_from([0x00, 0x06, 0x07, 0x0F, 0x80, 0x02, 0x1F, 0x8F])),
    st.tuples(st.just("limit"), st.just(0), st.floats(-1e5, 1e5)),
    st.tuples(st.just("fe_window"), st.just(0), st.floats(1e-3, 2.0)),
    st.tuples(st.just("settle"), st.just(0), st.just(0.0)),
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_SEGMENT, min_size=3, max_size=12))
def test_random_sequences(segments):
    """Random segments after an enable (hypothesis): the same bits every tick."""
    _compare([("csp", 100, 0.0), *segments])


def test_steady_motion_runs_compiled():
    """Plain CSP motion after the enable: every cycle from the second in OPERATION
    ENABLED is compiled (the first is the transition's, in Python)."""
    b = _compare([("csp", 200, 0.0), ("csp", 2000, 30.0)])
    d = b.drives[0]
    assert d.sm.state == State.OPERATION_ENABLED
    assert d.compiled.exits == [0] * len(d.compiled.exits)
    assert d.compiled.cycles >= 2200 - 20
