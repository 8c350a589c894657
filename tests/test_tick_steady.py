"""The emulator's compiled loop (:mod:`hil.runtime.steady_tick`: one tick of it, as
:meth:`Emulator.step` calls it) against the emulator's Python tick, over real UDP sockets
on 127.0.0.1, bit for bit.

Two emulators of the Arrow 500 X, one with the compiled tick and one without
(``RuntimeConfig.steady_tick``), each behind its own UDP device endpoint, get the same
setpoints from two controller endpoints, tick by tick (:meth:`Emulator.step`, then the
ring's ``end_tick``, as the loop calls them).  The scenarios of
tests/test_tick_equivalence.py (enable, motion, a following-error fault, fault reset,
CSV, CST, software limits, refused setpoints, quick stop, parameters written) run over
the wire, on one axis and on machines of two and five, with traffic mixed in: what the compiled
tick takes itself (two or three setpoints queued in one tick, a silent tick, also after a
tick the Python path ran) and what it must hand to the Python path (a malformed
datagram, a repeated and an older frame, a stranger's datagram, a HELLO, a value out of
range; a setpoint followed by a malformed datagram or by a repeat of its frame, a value
out of range followed by a good setpoint, more setpoints queued than the compiled tick
takes).  Every tick the feedback each controller receives (all but the clock stamps and
the session) and the plants' arrays must be the same bits; at the end every recording
row (all but the clock stamps), the endpoints' counters, the watchdogs and the heard
counts; and that no numba function was compiled or loaded from the cache once the
emulators were open (a fault injection included: such a first call stalls the loop).  A
request waiting at the injection port (``hil run --inject-port``) is taken in the same tick
by both: the compiled tick hands that tick to the Python path.
Each scenario also checks that the compiled tick ran most ticks and
declined each kind of datagram it must, or the comparison would say nothing.
"""

import gc
import select
import socket
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import pytest
from numba.core.registry import CPUDispatcher

from hil.runtime import steady_tick as S
from hil.runtime.emulator import Emulator, RuntimeConfig
from io_adapters import open_endpoint
from io_adapters.codec import encode, encode_hello
from io_adapters.inject_port import InjectClient
from io_adapters.messages import (
    InjectRequest,
    Setpoint,
    SetpointGroup,
    axis_records,
    message_pair,
)
from io_adapters.udp_steady import MAX_QUEUED
from plant.machines import load_machine_set
from tests.conftest import CONFIGS
from tests.test_tick_equivalence import Script

ARROW_PATH = CONFIGS / "arrow500_x.toml"
XY_PATH = CONFIGS / "machines" / "arrow500_xy.toml"
FIVE_PATH = CONFIGS / "machines" / "geiss_5axis.toml"
#: the feedback's clock stamps: taken on each machine, compared for consistency only
STAMPS = ("t_ns", "sp_t_ns", "sp_rx_ns", "tick_ns", "rx_ns")
#: the traffic of several datagrams in one tick
MULTIPLE = ("garbage", "stranger", "hello", "inject", "queued", "queued3", "flood",
            "then_garbage", "then_repeat", "range_then_good", "junk_flood", "junk_more",
            "hellos", "forged_jump", "forged_pair")
#: a stranger's junk: not a msgpack array of 4, so foreign on its first byte
JUNK = b"\x01" + bytes(59)
#: how far ahead a forged frame of the controller's own session is (issue 27 item 8)
FORGED_AHEAD = 100_000
#: the recording's clock columns
CLOCK_COLUMNS = ("tick_start_ns", "sp_t_ns", "sp_rx_ns", "fb_t_ns")


@dataclass
class WireTwin:
    """An emulator of ``config`` behind a UDP device endpoint and the controller endpoint
    talking to it; :meth:`tick` is what tests/test_tick_equivalence.py's Script calls.

    ``extra`` maps a tick to the traffic sent before (or instead of) its setpoint."""
    steady: bool
    extra: dict
    config: Path = ARROW_PATH
    rate_hz: float | None = None
    watchdog_cycles: int | None = None
    emulator: Emulator = field(init=False)

    def __post_init__(self):
        machine = load_machine_set(self.config)
        rc = RuntimeConfig(self.config, "udp://127.0.0.1:0", realtime=False,
                           steady_tick=self.steady, rate_hz=self.rate_hz,
                           watchdog_cycles=self.watchdog_cycles, inject_port=0)
        self.emulator = Emulator(rc, machine, log=lambda message: None)
        self.emulator.open()
        self.emulator.open_inject_port()
        self.bench = InjectClient(self.emulator.inject_port.address)
        self.drives = self.emulator.drives
        port = self.emulator.endpoint.address[1]
        self.ctl = open_endpoint(f"udp://127.0.0.1:{port}", "controller")
        self.stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.stranger.bind(("127.0.0.1", 0))
        self.port = port
        self.fb = message_pair(len(machine.axes))[1]
        # the handshake first: a controller repeats its HELLO every 100 ms of wall time
        # until it is welcomed, which would make the twins' counts differ
        select.select((self.emulator.endpoint.fileno(),), (), (), 1.0)
        self.emulator.step(-1)
        assert not self.ctl.recv_feedback(self.fb, 0.2) and self.ctl.welcomed
        self.fb_t_ns: list[int] = []  # the stamps the controller received

    def close(self) -> None:
        self.ctl.close()
        self.stranger.close()
        self.bench.close()
        self.emulator.close_links()

    def _raw(self, payload: bytes) -> None:
        self.ctl._send_bytes(payload, None)

    def _send_shifted(self, sp: Setpoint | SetpointGroup, counts: float) -> None:
        """Send ``sp`` with the last axis's target ``counts`` further."""
        last = axis_records(sp)[-1]
        last.target_position_counts += counts
        self.ctl.send_setpoint(sp)
        last.target_position_counts -= counts

    def tick(self, k: int, sp: Setpoint | SetpointGroup) -> None:
        kind = self.extra.get(k)
        last = self.ctl._frame - 1  # the frame number of the last setpoint sent
        if kind in ("garbage", "garbage_only"):
            self._raw(b"\x93\x01\x02")
        elif kind == "stranger":
            self.stranger.sendto(encode(sp, 7, 0), ("127.0.0.1", self.port))
        elif kind == "hello":
            self._raw(encode_hello(self.ctl.session, self.ctl._frame))
        elif kind == "inject":  # a friction growth at once, before this tick's setpoint
            self.ctl.send_injection(InjectRequest(0, "friction_growth", {"growth_pct": 20.0}))
        elif kind == "bench":  # a torque constant loss through the injection port
            self.bench.send(InjectRequest(0, "torque_constant_loss", {"loss_pct": 5.0}))
            end = time.monotonic() + 1.0
            while not self.emulator.inject_port.requests and time.monotonic() < end:
                time.sleep(0.001)  # its receive thread has queued it: both twins alike
            assert self.emulator.inject_port.requests, f"tick {k}: the request not queued"
        elif kind == "skip":  # a frame lost on the way
            self.ctl._frame += 1
        elif kind in ("queued", "queued3", "flood"):  # older targets first, newest taken
            for i in range({"queued": 1, "queued3": 2, "flood": MAX_QUEUED}[kind]):
                self._send_shifted(sp, 1000.0 * (i + 1))
        elif kind in ("junk_flood", "junk_more"):  # 3 budgets' worth, then more
            for _ in range(3 * self.emulator.endpoint.rx_budget):
                self.stranger.sendto(JUNK, ("127.0.0.1", self.port))
        elif kind == "hellos":  # a stranger's HELLO twice in one tick: one is decoded
            for _ in range(2):
                self.stranger.sendto(encode_hello(7, 0), ("127.0.0.1", self.port))
        elif kind in ("forged_jump", "forged_pair"):  # from the controller's own socket
            shifted = axis_records(sp)[-1]
            shifted.target_position_counts += 500.0
            for i in range(1 if kind == "forged_jump" else 2):
                self._raw(encode(sp, self.ctl.session, self.ctl._frame + FORGED_AHEAD + i))
            shifted.target_position_counts -= 500.0
        if kind in ("repeat", "older"):  # instead of this tick's setpoint
            self._raw(encode(sp, self.ctl.session, last if kind == "repeat" else last - 1))
        elif kind in ("range", "range_then_good"):  # last axis's target beyond its bound
            last = axis_records(sp)[-1]
            good, last.target_position_counts = last.target_position_counts, 1e300
            self.ctl.send_setpoint(sp)
            last.target_position_counts = good
            if kind == "range_then_good":
                self.ctl.send_setpoint(sp)
        elif kind not in ("silent", "garbage_only"):
            self.ctl.send_setpoint(sp)
        if kind == "then_garbage":
            self._raw(b"\x93\x01\x02")
        elif kind == "then_repeat":
            self._raw(encode(sp, self.ctl.session, self.ctl._frame - 1))
        em = self.emulator
        if kind != "silent":  # loopback delivers within the send, unless the kernel is
            # busy and defers it: wait for the datagrams, as a tick on time would have
            select.select((em.endpoint.fileno(),), (), (), 1.0)
            if kind in MULTIPLE:
                time.sleep(0.002)
        frames = em.endpoint.stats.frames
        em.step(k)
        assert em.endpoint.stats.frames - frames <= em.endpoint.rx_budget, f"tick {k}"
        em.recorder.end_tick(k, 0, 0)
        if em.watchdog.answering:
            assert self.ctl.recv_feedback(self.fb, 1.0), f"tick {k}: no answer"
            self.fb_t_ns.append(self.fb.t_ns)
            for record in (self.fb, *axis_records(self.fb)):
                for name in STAMPS:
                    setattr(record, name, 0)


def _specialisations() -> dict:
    """Every numba function of this process -> its compiled signatures (by type():
    isinstance asks ``__class__``, which some objects' ``__getattr__`` answer with an
    error, as a canopen object left by another test does)."""
    return {f: len(f.signatures) for f in gc.get_objects()
            if issubclass(type(f), CPUDispatcher)}


def _compare(segments, extra: dict, config: Path = ARROW_PATH, rate_hz: float | None = None,
             watchdog_cycles: int | None = None) -> WireTwin:
    a, b = (WireTwin(steady, extra, config, rate_hz, watchdog_cycles)
            for steady in (False, True))
    try:
        opened = _specialisations()
        Script(segments, len(a.drives)).run(a, b)
        # nothing compiled (or loaded from numba's cache) once the emulators were open: a
        # kernel first called in the loop stalls it for the compile (seconds, cold cache)
        late = {f.py_func.__qualname__ for f, n in _specialisations().items()
                if n > opened.get(f, 0)}
        assert not late, f"compiled after open(): {sorted(late)}"
        ea, eb = a.emulator, b.emulator
        n = ea.recorder.committed
        assert n == eb.recorder.committed
        rows_a, rows_b = ea.recorder.columns(0, n), eb.recorder.columns(0, n)
        for name, col in rows_a.items():
            if name not in CLOCK_COLUMNS:
                assert col.tobytes() == rows_b[name].tobytes(), name
        # the compiled tick's row holds the stamp that went out on the wire
        sent = rows_b["fb_t_ns"][rows_b["fb_t_ns"] != 0]
        assert set(sent.tolist()) <= set(b.fb_t_ns)
        assert (rows_b["sp_rx_ns"] <= rows_b["fb_t_ns"]).all()
        for em in (ea, eb):  # a flood's episode ends: the kernel's last drops counted
            em.endpoint.close()
        assert ea.endpoint.stats == eb.endpoint.stats
        assert eb.endpoint.stats.lost == sum(kind == "skip" for kind in extra.values())
        assert ea.setpoints_heard == eb.setpoints_heard
        assert (ea.watchdog.silent, ea.watchdog.tripped, ea.watchdog.events) == (
            eb.watchdog.silent, eb.watchdog.tripped, eb.watchdog.events)
        for sa, sb in zip(axis_records(ea.sp), axis_records(eb.sp)):
            for name in (f.name for f in fields(Setpoint)):
                if name not in STAMPS:
                    assert np.array(getattr(sa, name)).tobytes() == np.array(
                        getattr(sb, name)).tobytes(), name
        assert ea.steady is None
    finally:
        a.close()
        b.close()
    return b


def test_scenario_with_every_kind_of_traffic():
    segments = [
        ("csp", 400, 0.0),          # enable, hold
        ("csp", 1500, 40.0),        # CSP ramp (malformed, stranger, HELLO, repeats inside)
        ("jump", 300, 3.0e7),       # the following-error fault
        ("cw", 5, 0x0000),
        ("cw", 5, 0x0080),          # fault reset
        ("csp", 600, 0.0),          # re-enable
        ("csv", 800, 3.0e5),        # CSV
        ("cst", 300, 0.5),          # CST
        ("csp", 400, -30.0),
        ("limit", 0, 2.0e4),        # 607Dh max just ahead
        ("csv", 800, 5.0e5),        # CSV runs into the software limit
        ("csv", 400, -5.0e5),
        ("nan", 20, 0.0),           # a refused setpoint (non-finite): fault
        ("cw", 5, 0x0000),
        ("cw", 5, 0x0080),
        ("csp", 400, 10.0),
        ("fe_window", 0, 0.5),      # 6065h written while running
        ("csp", 400, 10.0),
        ("cw", 200, 0x0002),        # quick stop
        ("csp", 600, 5.0),          # enable again
    ]
    extra = {700: "garbage_only", 701: "silent", 800: "stranger", 900: "hello", 1000: "repeat",
             1100: "older", 1200: "queued", 1250: "inject", 1270: "bench", 1300: "silent",
             1301: "silent",
             1400: "range", 1450: "skip", 4500: "garbage", 4501: "silent", 5000: "queued",
             5200: "repeat"}
    b = _compare(segments, extra)
    steady = b.emulator.steady
    assert steady.ticks > 5000
    declined = steady.declined
    assert declined[S.DECLINED_FRAME] >= 1      # the garbage alone
    assert declined[S.DECLINED_SEQUENCE] >= 2   # the repeat, the older frame
    assert declined[S.DECLINED_CYCLE] >= 2      # the following error, the range
    assert steady.silent == 4 and steady.queued == 2  # taken compiled
    assert b.emulator.injectors[0].levels["friction_growth"] == 20.0
    assert b.emulator.injectors[0].levels["torque_constant_loss"] == 5.0
    bench = [e for e in b.emulator.injectors[0].events if e.reason.endswith("(bench)")]
    assert [(e.kind, round(e.t_s / b.emulator.period_s)) for e in bench] == [("injected", 1270)]


@pytest.mark.parametrize("extra", [{}, {300 + 7 * i: kind for i, kind in enumerate(
    ["garbage", "repeat", "silent", "queued", "older", "hello", "stranger", "range",
     "garbage_only", "skip", "queued3", "then_garbage", "then_repeat",
     "range_then_good"] * 5)}])
def test_steady_motion(extra):
    """Plain CSP motion, quiet or with traffic every 7 ticks: the compiled tick runs every
    tick of the quiet one from the drive's second steady cycle on (a held controlword of
    the enable sequence too: its next command is a drive cycle's to take, in Python), and
    declines each kind of datagram it must in the other."""
    b = _compare([("csp", 200, 0.0), ("csp", 2000, 30.0)], extra)
    steady = b.emulator.steady
    if not extra:
        assert steady.ticks >= 2200 - 20
        assert steady.declined[S.DECLINED_FRAME] == steady.declined[S.DECLINED_SEQUENCE] == 0
        assert steady.declined[S.DECLINED_CYCLE] <= 3  # the enable sequence's commands
    else:
        # each value out of range faults the drive, and re-enabling takes ticks
        assert steady.ticks >= 1700
        assert min(steady.declined.values()) >= 3
        # taken compiled unless the drive was still re-enabling after a range fault
        assert steady.silent >= 3 and steady.queued >= 3


def test_two_axes():
    """A machine of two axes, one group message a tick: enable, CSP, CSV, a fault on both,
    re-enable, with traffic that goes to the Python path (a value out of range on the
    second axis declines the tick after the first axis ran: it is put back)."""
    extra = {500: "garbage_only", 501: "silent", 600: "repeat", 650: "silent",
             700: "queued", 710: "flood", 750: "then_garbage", 770: "garbage", 771: "silent",
             800: "range", 1500: "skip", 1600: "stranger"}
    b = _compare([("csp", 300, 0.0), ("csp", 800, 25.0), ("csv", 500, -2.0e5),
                  ("jump", 200, 3.0e7), ("cw", 3, 0), ("cw", 3, 0x80), ("csp", 400, 5.0)],
                 extra, XY_PATH)
    steady = b.emulator.steady
    assert steady.ticks > 1000
    assert min(steady.declined.values()) >= 1
    # the "queued" tick and the last of the flood's: its 65 setpoints take 7 ticks' budgets
    assert steady.silent == 3 and steady.queued == 2


def test_five_axes():
    """Seed 001's five-axis machine (three linear axes, two rotary), one group message a
    tick: enable, CSP, a fault on every axis, re-enable, with the traffic that goes to the
    Python path and the queued and silent ticks the compiled loop takes itself."""
    extra = {400: "garbage_only", 401: "silent", 450: "repeat", 500: "queued",
             550: "then_repeat", 600: "range", 900: "skip", 950: "stranger", 1000: "hello"}
    b = _compare([("csp", 300, 0.0), ("csp", 500, 20.0), ("jump", 150, 3.0e7), ("cw", 3, 0),
                  ("cw", 3, 0x80), ("csp", 400, 5.0)], extra, FIVE_PATH)
    steady = b.emulator.steady
    assert len(b.drives.drives) == 5
    assert steady.ticks > 500  # none while the value out of range's fault lasts
    assert min(steady.declined.values()) >= 1
    assert steady.silent == 1 and steady.queued == 1


@pytest.mark.parametrize("config", [ARROW_PATH, XY_PATH])
def test_several_drive_cycles_a_tick(config):
    """At 2 kHz a tick is four PWM periods of the Arrow's drives: the compiled tick runs
    them all, and a fault in the third puts the first two back (the Python tick runs the
    tick again)."""
    extra = {300: "garbage_only", 400: "repeat", 500: "range", 700: "skip"}
    b = _compare([("csp", 150, 0.0), ("csp", 500, 100.0), ("jump", 150, 3.0e7),
                  ("cw", 3, 0), ("cw", 3, 0x80), ("csp", 200, 5.0)], extra, config, 2000.0)
    steady = b.emulator.steady
    assert steady.cycles == 4
    assert steady.ticks > 500
    assert min(steady.declined.values()) >= 1


def test_a_flood_and_forged_frames_take_the_same_course_on_both_paths():
    """Issue 27 items 6 and 8 over the wire, compiled tick against Python tick: three
    budgets of a stranger's junk ahead of a setpoint (a tick reads one budget, never
    more, every tick of the run: see WireTwin.tick; the filter then keeps what the
    stranger sends next out of the socket), two strangers' HELLOs in one tick (one
    decoded), one frame of the controller's own session 100 000 ahead (dropped, its next
    frames taken), two such frames in sequence (followed, and the controller's own count
    followed back one frame later).  Both paths count, drop and take alike."""
    extra = {300: "forged_jump", 400: "forged_pair", 500: "hellos", 900: "junk_flood",
             905: "junk_more", 906: "junk_more"}
    b = _compare([("csp", 200, 0.0), ("csp", 1000, 30.0)], extra)
    em, steady = b.emulator, b.emulator.steady
    s = em.endpoint.stats
    budget = em.endpoint.rx_budget
    assert budget == 10  # 8 kHz, a quarter of the period (hil run's default)
    # the forged frame, then the forged pair's first and the controller's own frame
    # after it; followed twice: to the pair, back to the controller
    assert (s.out_of_order, s.resyncs, s.lost) == (3, 2, 0)
    assert s.foreign == 2 + 3 * budget  # the HELLOs and the junk read before the filter
    assert s.rx_dropped == 2 * 3 * budget  # the junk sent once the filter was on
    assert s.rx_limited == 3  # the three budgets of junk, a tick each
    assert steady.declined[S.DECLINED_SEQUENCE] >= 3 and steady.ticks > 1000


def test_silence_up_to_the_watchdog():
    """25 silent ticks against a watchdog of 20: the compiled tick runs the 19 that only
    count, the Python path the one that trips it (the drive faults, as 6007h says) and
    every one after."""
    silence = {300 + i: "silent" for i in range(25)}
    b = _compare([("csp", 200, 0.0), ("csp", 300, 20.0)], silence, watchdog_cycles=20)
    steady, watchdog = b.emulator.steady, b.emulator.watchdog
    assert steady.silent == 19
    assert [e.kind for e in watchdog.events] == ["tripped", "recovered"]
    assert watchdog.events[0].tick == 319
