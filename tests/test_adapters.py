"""One behaviour suite over every adapter (python-can style), then the registry and a
round trip with a device in another process.

Links: ``udp`` — two sockets on 127.0.0.1, ephemeral ports; ``serial`` — a real
``os.openpty`` pair, the device on the master (``serial://fd/N``), the controller on
the slave opened by path with pyserial.  Each link can also hand the device raw
messages as the controller, one transport frame each (a datagram from the controller's
own socket, or a frame with a good CRC on the controller's line), so malformed and
out-of-sequence messages reach the codec from the peer the device has pinned; a link
opened with ``controller=False`` has a raw peer only, which the device pins when its
first good message arrives.  Timing: a receive that should succeed waits up to WAIT_S
and returns as soon as the message is there; only "returned False" is asserted for one
that should not.  Every test that counts frames also checks that the counters add up
(:func:`assert_counts_add_up`, the identity of the AdapterStats docstring).
"""

import gc
import io
import json
import os
import select
import socket
import subprocess
import sys
import textwrap
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import EntryPoint
from pathlib import Path

import msgpack
import pytest

from io_adapters import (
    MODE_VOLTAGE,
    AdapterClosed,
    AdapterConfigError,
    AdapterError,
    Endpoint,
    Feedback,
    Setpoint,
    codec,
    known_schemes,
    open_endpoint,
    register,
    registry,
    udp,
)
from io_adapters.msgpack_endpoint import MAX_DROPOUT, MAX_MISORDER
from io_adapters.serial_link import frame

ROOT = Path(__file__).resolve().parent.parent
WAIT_S = 5.0
QUIET_S = 0.02
SP_WIRE = codec.SCHEMAS[Setpoint].names
FB_WIRE = codec.SCHEMAS[Feedback].names


@dataclass
class Link:
    """A device and a controller endpoint joined by one transport (controller None: a raw
    peer only)."""
    device: Endpoint
    controller: Endpoint | None
    inject: Callable[[list[bytes]], None]  # raw messages to the device, one frame each
    close: Callable[[], None]

    @property
    def session(self) -> int:
        """The session of the peer that ``inject`` speaks for."""
        return RAW_SESSION if self.controller is None else self.controller.session


RAW_SESSION = 7


def udp_link(query: str = "", controller: bool = True) -> Link:
    device = open_endpoint(f"udp://127.0.0.1:0{query}", "device")
    ctl = (open_endpoint(f"udp://127.0.0.1:{device.address[1]}{query}", "controller")
           if controller else None)
    if ctl is None:
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        raw.bind(("127.0.0.1", 0))
    else:  # the controller's own socket: its address, which the device pins
        raw = socket.socket(fileno=os.dup(ctl.fileno()))

    def inject(messages):
        for m in messages:
            raw.sendto(m, device.address)

    def close():
        device.close()
        if ctl is not None:
            ctl.close()
        raw.close()
    return Link(device, ctl, inject, close)


def serial_link(query: str = "", controller: bool = True) -> Link:
    master, slave = os.openpty()
    device = open_endpoint(f"serial://fd/{master}{query}", "device")
    ctl = (open_endpoint(f"serial://{os.ttyname(slave)}{query}", "controller")
           if controller else None)

    def inject(messages):  # one write: the pty hands it over in one piece
        os.write(slave, b"".join(frame(m) for m in messages))

    def close():
        device.close()
        if ctl is not None:
            ctl.close()
        os.close(slave)
    return Link(device, ctl, inject, close)


LINKS = {"udp": udp_link, "serial": serial_link}


@pytest.fixture(params=sorted(LINKS))
def make_link(request):
    made = []

    def make(query="", controller=True):
        made.append(LINKS[request.param](query, controller))
        return made[-1]
    yield make
    for link in made:
        link.close()


@pytest.fixture
def link(make_link):
    return make_link()


def setpoint_msg(session=RAW_SESSION, frame_no=0, **values) -> bytes:
    return codec.encode(Setpoint(**values), session, frame_no)


def assert_same_wire_fields(a, b, names):
    for name in names:  # repr: exact floats, the sign of -0.0, int vs float
        assert repr(getattr(a, name)) == repr(getattr(b, name)), name


COUNTED = ("received", "malformed", "refused_nonfinite", "refused_mode", "refused_range",
           "duplicates", "out_of_order", "foreign", "stale_session", "handshakes")


def assert_counts_add_up(stats, frames=None):
    """Every frame in exactly one counter (the AdapterStats docstring); ``frames``: the
    number the test knows reached the endpoint."""
    assert stats.frames == sum(getattr(stats, name) for name in COUNTED), stats
    if frames is not None:
        assert stats.frames == frames, stats


# -- the behaviour suite --------------------------------------------------------------

def test_setpoint_and_feedback_round_trip_exactly(link):
    sp = Setpoint(seq=0xFFFFFFFF, controlword=0x001F, mode=MODE_VOLTAGE, iq_ref_a=1.2345678901234567,
                  id_ref_a=-0.0, ud_v=5e-324, uq_v=-1.7976931348623157e308)
    got_sp = Setpoint()
    assert link.controller.send_setpoint(sp)
    assert link.device.recv_setpoint(got_sp, WAIT_S)
    assert_same_wire_fields(got_sp, sp, SP_WIRE)
    assert 0 < sp.t_ns <= got_sp.rx_ns  # one machine, one monotonic clock

    fb = Feedback(seq=got_sp.seq, statusword=0x0637, time_s=12.5, encoder_counts=-123456789.0,
                  scale_counts=float(2**53), iq_a=-3.25, id_a=-5e-324, fault=-3)
    got_fb = Feedback()
    assert not link.controller.welcomed
    assert link.device.send_feedback(fb)
    assert link.controller.recv_feedback(got_fb, WAIT_S)
    assert_same_wire_fields(got_fb, fb, FB_WIRE)
    assert (got_fb.sp_t_ns, got_fb.sp_rx_ns) == (sp.t_ns, got_sp.rx_ns)
    assert got_fb.round_trip_ns() == (got_fb.rx_ns - sp.t_ns) - (fb.t_ns - got_sp.rx_ns) >= 0
    assert link.controller.welcomed  # the device answered the HELLO sent when it opened
    for ep in (link.device, link.controller):
        s = ep.stats  # one HELLO and its WELCOME, one record each way
        assert (s.sent, s.received, s.malformed, s.handshakes) == (1, 1, 0, 1)
        assert_counts_add_up(s, frames=2)


def test_frames_in_order_and_counted(link):
    """Many setpoints and answers in lock step: nothing lost, duplicated or reordered."""
    sp, fb, got_sp, got_fb = Setpoint(), Feedback(), Setpoint(), Feedback()
    for k in range(50):
        sp.seq, sp.iq_ref_a = k, k / 8
        link.controller.send_setpoint(sp)
        assert link.device.recv_setpoint(got_sp, WAIT_S), k
        fb.seq, fb.iq_a = got_sp.seq, got_sp.iq_ref_a
        link.device.send_feedback(fb)
        assert link.controller.recv_feedback(got_fb, WAIT_S), k
        assert (got_fb.seq, got_fb.iq_a) == (k, k / 8)
    for ep in (link.device, link.controller):
        s = ep.stats
        assert (s.received, s.lost, s.duplicates, s.out_of_order) == (50, 0, 0, 0)
        assert_counts_add_up(s, frames=51)  # and the handshake


def test_duplicate_older_and_missing_frames_are_counted(link):
    """As the controller, after its HELLO (which carried frame 0 without using it up)."""
    link.inject([setpoint_msg(link.session, f, iq_ref_a=v) for f, v in
                 [(0, 1.0), (0, 2.0), (codec.U32, 3.0), (3, 4.0), (4, 5.0)]])
    got, sp = [], Setpoint()
    while link.device.recv_setpoint(sp, WAIT_S if not got else QUIET_S):
        got.append(sp.iq_ref_a)
    s = link.device.stats
    assert got == [1.0, 4.0, 5.0]
    assert (s.duplicates, s.out_of_order, s.lost, s.received) == (1, 1, 2, 3)
    link.inject([setpoint_msg(link.session ^ 1, 5, iq_ref_a=6.0)])  # not the pinned session
    assert not link.device.recv_setpoint(sp, QUIET_S) and sp.iq_ref_a == 5.0
    assert (s.stale_session, s.peer_restarts) == (1, 0)
    assert_counts_add_up(s, frames=7)


def test_frame_counter_wraps(make_link):
    link = make_link(controller=False)  # the raw peer is pinned by its first frame
    link.inject([setpoint_msg(frame_no=0xFFFFFFFF, seq=1), setpoint_msg(frame_no=0, seq=2)])
    sp = Setpoint()
    assert link.device.recv_setpoint(sp, WAIT_S) and sp.seq == 1
    assert link.device.recv_setpoint(sp, WAIT_S) and sp.seq == 2
    assert (link.device.stats.lost, link.device.stats.out_of_order) == (0, 0)


def _taken(link, frames_values) -> list[float]:
    """Inject setpoints (frame number, iq_ref_a) from the peer as the controller; the
    values the device took, in order."""
    link.inject([setpoint_msg(link.session, f & codec.U32, iq_ref_a=v)
                 for f, v in frames_values])
    got, sp = [], Setpoint()
    while link.device.recv_setpoint(sp, WAIT_S if not got else QUIET_S):
        got.append(sp.iq_ref_a)
    return got


def test_one_frame_far_ahead_costs_the_peer_nothing(link):
    """A frame of the peer's session 100 000 ahead (forged from its address, or a stray
    of an old run) is dropped, and the peer's own next frames are taken: one frame is
    no reason to follow a jump (issue 27 item 8)."""
    got = _taken(link, [(0, 1.0), (100_000, 9.0), (1, 2.0), (2, 3.0), (3, 4.0)])
    s = link.device.stats
    assert got == [1.0, 2.0, 3.0, 4.0]
    assert (s.out_of_order, s.resyncs, s.lost, s.received) == (1, 0, 0, 4)
    assert link.device.notices == []
    assert_counts_add_up(s, frames=6)


def test_two_frames_in_sequence_after_a_jump_resynchronise(link):
    """A peer whose count jumped (frames lost beyond MAX_DROPOUT, or forward or back)
    loses the first frame after the jump; the second continues it, and the check
    follows: the frames after it are taken, a notice says so.  The peer's own count
    coming back is a jump too, followed the same way."""
    far = MAX_DROPOUT + 1
    got = _taken(link, [(0, 1.0), (far, 9.0), (far + 1, 2.0), (far + 2, 3.0),
                        (1, 8.0), (2, 4.0), (3, 5.0), (-50, 7.0), (-49, 6.0)])
    s = link.device.stats
    assert got == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert (s.out_of_order, s.resyncs, s.lost, s.received) == (3, 3, 0, 6)
    assert [kind for kind, _ in link.device.notices] == ["frames resynchronised"]  # 1/s
    assert_counts_add_up(s, frames=10)


def test_late_frames_within_the_window_stay_dropped(link):
    """Frames up to MAX_MISORDER behind are late, dropped without resynchronising even
    when two follow each other; a gap up to MAX_DROPOUT ahead is frames lost."""
    got = _taken(link, [(0, 1.0), (-MAX_MISORDER, 9.0), (1 - MAX_MISORDER, 9.0),
                        (1, 2.0), (1 + MAX_DROPOUT, 3.0)])
    s = link.device.stats
    assert got == [1.0, 2.0, 3.0]
    assert (s.out_of_order, s.resyncs, s.lost) == (2, 0, MAX_DROPOUT - 1)


def _replace(message: bytes, index: int, value) -> bytes:
    values = list(msgpack.unpackb(message))
    values[index] = value
    return msgpack.packb(values)


GOOD = setpoint_msg(controlword=6)
MALFORMED = {
    "random bytes": bytes.fromhex("9c01c3ff00a5d4e17b3f2288c0de51") * 3,
    "wrong version": _replace(GOOD, 0, 2),
    "feedback to the device": codec.encode(Feedback(), 7, 0),
    "truncated": GOOD[:-3],
    "extra element": msgpack.packb(list(msgpack.unpackb(GOOD)) + [0]),
    "float in an int field": _replace(GOOD, 5, 6.0),
    "int in a float field": _replace(GOOD, 7, 1),
    "controlword out of range": _replace(GOOD, 5, 0x10000),
    "not an array": msgpack.packb({"controlword": 6}),
}


@pytest.mark.parametrize("bad", sorted(MALFORMED))
def test_malformed_frame_is_counted_and_dropped(link, bad):
    sp = Setpoint(iq_ref_a=99.0)
    link.inject([MALFORMED[bad]])
    assert not link.device.recv_setpoint(sp, QUIET_S)
    assert sp == Setpoint(iq_ref_a=99.0)  # untouched
    assert (link.device.stats.malformed, link.device.stats.timeouts) == (1, 1)
    link.controller.send_setpoint(Setpoint(controlword=6, iq_ref_a=1.5))
    assert link.device.recv_setpoint(sp, WAIT_S)
    assert (sp.controlword, sp.iq_ref_a) == (6, 1.5)
    assert_counts_add_up(link.device.stats, frames=3)  # the HELLO, the bad one, the good one


def test_timeouts_return_false(link):
    sp, fb = Setpoint(), Feedback()
    assert not link.device.recv_setpoint(sp, QUIET_S)
    assert not link.device.recv_setpoint(sp, 0.0)
    assert not link.controller.recv_feedback(fb, 0.0)
    assert (link.device.stats.timeouts, link.controller.stats.timeouts) == (2, 1)


def test_drain_keeps_the_newest(make_link):
    link = make_link("?drain=1")
    link.inject([setpoint_msg(link.session, k, seq=k) for k in range(3)])
    sp = Setpoint()
    assert link.device.recv_setpoint(sp, WAIT_S)
    assert sp.seq == 2
    assert (link.device.stats.received, link.device.stats.drained) == (3, 2)


def test_close_is_idempotent_and_final(link):
    for ep in (link.device, link.controller):
        with ep:
            pass
        assert ep.closed
        ep.close()
        with pytest.raises(AdapterClosed):
            ep.fileno()
    with pytest.raises(AdapterClosed):
        link.controller.send_setpoint(Setpoint())
    with pytest.raises(ConnectionError):  # AdapterClosed is one
        link.device.recv_setpoint(Setpoint(), 0.0)


def test_each_side_has_its_own_methods(link):
    with pytest.raises(AdapterError, match="controller side"):
        link.device.send_setpoint(Setpoint())
    with pytest.raises(AdapterError, match="device side"):
        link.controller.recv_setpoint(Setpoint(), 0.0)


def test_fileno_becomes_readable(link):
    link.controller.send_setpoint(Setpoint())
    assert select.select([link.device.fileno()], [], [], WAIT_S)[0]


def test_bad_record_is_refused_when_sent(link):
    with pytest.raises(ValueError, match="controlword=70000"):  # FrameError is one
        link.controller.send_setpoint(Setpoint(controlword=70000))
    assert link.controller.stats.sent == 0


def _open_fds() -> int:
    gc.collect()
    return len(os.listdir("/proc/self/fd"))


@pytest.mark.parametrize("name", sorted(LINKS))
def test_no_descriptor_leaks(name):
    before = _open_fds()
    links = [LINKS[name]() for _ in range(3)]
    for link in links:
        link.controller.send_setpoint(Setpoint())
        assert link.device.recv_setpoint(Setpoint(), WAIT_S)
        link.close()
    assert _open_fds() == before  # with the closed endpoints still referenced


# -- UDP addressing -------------------------------------------------------------------

def test_udp_device_answers_nobody_before_a_setpoint():
    with open_endpoint("udp://127.0.0.1:0", "device") as device:
        assert device.peer is None
        assert not device.send_feedback(Feedback())
        assert device.stats.sent == 0


def test_udp_fixed_peer_and_foreign_datagrams():
    with open_endpoint("udp://127.0.0.1:0", "device") as a, \
            open_endpoint(f"udp://127.0.0.1:{a.address[1]}", "controller") as ctl, \
            open_endpoint(f"udp://127.0.0.1:0?peer=127.0.0.1:{ctl.address[1]}", "device") as b:
        assert b.send_feedback(Feedback(seq=3))  # fixed peer: no setpoint needed
        assert not ctl.recv_feedback(Feedback(), QUIET_S)  # b is not ctl's device
        assert (ctl.stats.foreign, ctl.stats.malformed) == (1, 0)


def test_udp_second_device_on_a_port_is_refused():
    with open_endpoint("udp://127.0.0.1:0", "device") as first, \
            pytest.raises(AdapterError, match="cannot bind"):
        open_endpoint(f"udp://127.0.0.1:{first.address[1]}", "device")


@pytest.mark.parametrize("url, role, match", [
    ("udp://0.0.0.0:0", "device", "allow_remote"),
    ("udp://192.0.2.1:5005", "controller", "allow_remote"),
    ("udp://127.0.0.1", "device", "HOST:PORT"),
    ("udp://127.0.0.1:99999", "device", "HOST:PORT"),
    ("udp://127.0.0.1:0?bogus=1", "device", "unknown option 'bogus'"),
    ("udp://127.0.0.1:0?drain=maybe", "device", "drain"),
    ("udp://127.0.0.1:0?drain=1&drain=0", "device", "twice"),
    ("udp://127.0.0.1:0?bind=127.0.0.1:0", "device", "controller side"),
    ("udp://127.0.0.1:5005?peer=127.0.0.1:1", "controller", "device side"),
    ("udp://127.0.0.1:0", "controller", "not 0"),
])
def test_udp_bad_urls_are_refused(url, role, match):
    with pytest.raises(AdapterConfigError, match=match):
        open_endpoint(url, role)


def test_udp_remote_needs_the_flag():
    with open_endpoint("udp://0.0.0.0:0?allow_remote=1", "device") as ep:
        assert ep.address[0] == "0.0.0.0"


# -- UDP arrival stamps ---------------------------------------------------------------

def test_udp_arrival_is_the_kernels_receive_stamp():
    """rx_ns is when the datagram reached the socket, not when recv returned it: before the
    receiver even asked, after the sender's send stamp less the documented bound (the
    realtime-to-monotonic conversion is never late and at most ``window_ns`` early)."""
    link = udp_link()
    try:
        assert link.device.kernel_stamps and link.controller.kernel_stamps
        sp, got_sp, fb, got_fb = Setpoint(), Setpoint(), Feedback(), Feedback()
        assert link.controller.send_setpoint(sp)
        time.sleep(QUIET_S)  # it waits in the socket
        before = time.monotonic_ns()
        assert link.device.recv_setpoint(got_sp, WAIT_S)
        after = time.monotonic_ns()
        assert sp.t_ns - link.device.clock.window_ns <= got_sp.rx_ns <= before <= after
        assert link.device.send_feedback(fb)
        time.sleep(QUIET_S)
        before = time.monotonic_ns()
        assert link.controller.recv_feedback(got_fb, WAIT_S)
        after = time.monotonic_ns()
        assert fb.t_ns - link.controller.clock.window_ns <= got_fb.rx_ns <= before <= after
        assert got_fb.sp_rx_ns == got_sp.rx_ns  # the echo carries the kernel's stamp
    finally:
        link.close()


def test_udp_draining_keeps_the_newest_records_arrival():
    link = udp_link("?drain=1")
    try:
        link.inject([setpoint_msg(link.session, 0, seq=0)])
        time.sleep(QUIET_S)
        newest_sent = time.monotonic_ns()
        link.inject([setpoint_msg(link.session, 1, seq=1)])
        sp = Setpoint()
        assert link.device.recv_setpoint(sp, WAIT_S) and sp.seq == 1
        assert newest_sent - link.device.clock.window_ns <= sp.rx_ns <= time.monotonic_ns()
    finally:
        link.close()


@pytest.mark.parametrize("option", [None, 0x7FFF], ids=["unknown", "refused"])
def test_udp_without_kernel_stamps_stamps_in_user_space(monkeypatch, option):
    """No SO_TIMESTAMPNS on the platform (None), or the kernel refuses the option: rx_ns
    is the time recv returned the record, as on serial."""
    monkeypatch.setattr(udp, "SO_TIMESTAMPNS", option)
    link = udp_link()
    try:
        assert not link.device.kernel_stamps and link.device.clock is None
        sp, got = Setpoint(), Setpoint()
        assert link.controller.send_setpoint(sp)
        time.sleep(QUIET_S)
        before = time.monotonic_ns()
        assert link.device.recv_setpoint(got, WAIT_S)
        assert sp.t_ns < before <= got.rx_ns <= time.monotonic_ns()
    finally:
        link.close()


def test_realtime_offset_is_measured_when_opened_and_again_a_second_on(monkeypatch):
    clock = udp.RealtimeToMonotonic()
    m0 = time.monotonic_ns()
    now = time.clock_gettime_ns(time.CLOCK_REALTIME)
    m1 = time.monotonic_ns()
    assert m0 - clock.window_ns <= clock.monotonic_ns(now) <= m1  # never late
    measured = []
    monkeypatch.setattr(clock, "measure", lambda: measured.append(True))
    clock.monotonic_ns(now + udp.OFFSET_REFRESH_NS // 2)
    assert not measured
    clock.monotonic_ns(now + 2 * udp.OFFSET_REFRESH_NS)
    assert measured == [True]


# -- a record-level endpoint: the contract without bytes (as a CAN adapter will be) -----

class MemoryEndpoint(Endpoint):
    """Passes records between two objects in one process; ``memory://`` in tests."""

    def __init__(self, role, drain=False):
        super().__init__(role, drain=drain)
        self.inbox = deque()
        self.peer = None

    @classmethod
    def from_url(cls, url, role):
        return cls(role)

    def _write(self, record):
        if self.peer is None:
            return False
        self.peer.inbox.append({n: getattr(record, n) for n in type(record).__slots__})
        return True

    def _read(self, into, timeout_s):
        if not self.inbox:
            return False
        for name, value in self.inbox.popleft().items():
            setattr(into, name, value)
        self.stats.received += 1
        return True

    def _close(self):
        self.inbox.clear()


def test_a_record_level_endpoint_gets_the_same_bookkeeping():
    device, controller = MemoryEndpoint("device", drain=True), MemoryEndpoint("controller")
    assert not device.send_feedback(Feedback())  # nobody to send to yet
    device.peer, controller.peer = controller, device
    for k in range(3):
        controller.send_setpoint(Setpoint(seq=k))
    sp, fb = Setpoint(), Feedback()
    assert device.recv_setpoint(sp, 0.0) and sp.seq == 2 and device.stats.drained == 2
    device.send_feedback(Feedback(seq=sp.seq))
    assert controller.recv_feedback(fb, 0.0)
    assert fb.seq == 2 and fb.sp_t_ns == sp.t_ns and fb.round_trip_ns() >= 0
    assert not controller.recv_feedback(fb, 0.0) and controller.stats.timeouts == 1
    with pytest.raises(io.UnsupportedOperation, match="no file descriptor"):
        controller.fileno()
    controller.close()
    controller.close()
    with pytest.raises(AdapterClosed):
        controller.send_setpoint(sp)


# -- registry -------------------------------------------------------------------------

def test_transports_are_imported_only_when_opened():
    script = textwrap.dedent("""
        import sys
        import io_adapters
        lazy = ("io_adapters.udp", "io_adapters.serial_link", "serial",
                "io_adapters.can_cia402", "can", "canopen")
        assert not [m for m in lazy if m in sys.modules], sys.modules.keys()
        assert io_adapters.known_schemes() == ["can", "serial", "udp"]
        with io_adapters.open_endpoint("udp://127.0.0.1:0", "device"):
            pass
        assert "io_adapters.udp" in sys.modules
        assert "io_adapters.serial_link" not in sys.modules and "serial" not in sys.modules
    """)
    subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=True, timeout=60)


@pytest.mark.parametrize("url", ["canbus://vcan0", "UDP-ish://x", "127.0.0.1:5005"])
def test_unknown_scheme_lists_the_known_ones(url):
    with pytest.raises(AdapterConfigError, match="can, serial, udp"):
        open_endpoint(url, "device")


def test_bad_role_is_refused():
    with pytest.raises(AdapterConfigError, match="'drive'"):
        open_endpoint("udp://127.0.0.1:0", "drive")


@pytest.fixture
def clean_registry(monkeypatch):
    monkeypatch.setattr(registry, "_registered", {})


def test_register_adds_a_scheme(clean_registry):
    register("memory", f"{__name__}:MemoryEndpoint")
    assert "memory" in known_schemes()
    with open_endpoint("memory://", "controller") as ep:
        assert isinstance(ep, MemoryEndpoint)


@pytest.mark.parametrize("scheme, target, match", [
    ("udp", f"{__name__}:MemoryEndpoint", "already registered"),
    ("Mem", f"{__name__}:MemoryEndpoint", "lower-case"),
    ("mem", "MemoryEndpoint", "module:Class"),
])
def test_register_refuses(clean_registry, scheme, target, match):
    with pytest.raises(AdapterConfigError, match=match):
        register(scheme, target)


@pytest.mark.parametrize("target, match", [
    ("no_such_module_xyz:Thing", "cannot be loaded"),
    (f"{__name__}:NoSuchClass", "cannot be loaded"),
    (f"{__name__}:Link", "not an Endpoint"),
])
def test_broken_registrations_fail_when_opened(clean_registry, target, match):
    register("broken", target)
    with pytest.raises(AdapterConfigError, match=match):
        open_endpoint("broken://", "device")


def test_entry_points_add_schemes(monkeypatch):
    plug = EntryPoint("plug", f"{__name__}:MemoryEndpoint", registry.ENTRY_POINT_GROUP)
    monkeypatch.setattr(registry, "entry_points",
                        lambda group: [plug] if group == registry.ENTRY_POINT_GROUP else [])
    assert known_schemes() == ["can", "plug", "serial", "udp"]
    with open_endpoint("plug://", "device") as ep:
        assert isinstance(ep, MemoryEndpoint)


# -- a device in another process --------------------------------------------------------

ECHO_DEVICE = textwrap.dedent("""
    import json, sys
    from io_adapters import Feedback, Setpoint, open_endpoint
    n = int(sys.argv[1])
    with open_endpoint("udp://127.0.0.1:0", "device") as ep:
        print(ep.address[1], flush=True)
        sp, fb, answered = Setpoint(), Feedback(), 0
        while answered < n and ep.recv_setpoint(sp, 10.0):
            fb.seq, fb.encoder_counts = sp.seq, 2.0 * sp.iq_ref_a
            ep.send_feedback(fb)
            answered += 1
        s = ep.stats
        print(json.dumps({"answered": answered, "malformed": s.malformed, "lost": s.lost}))
""")


def test_device_in_another_process_answers_every_setpoint():
    n = 200
    with subprocess.Popen([sys.executable, "-c", ECHO_DEVICE, str(n)], cwd=ROOT,
                          stdout=subprocess.PIPE, text=True) as child:
        try:
            port = int(child.stdout.readline())
            with open_endpoint(f"udp://127.0.0.1:{port}", "controller") as ctl:
                sp, fb = Setpoint(), Feedback()
                for k in range(n):
                    sp.seq, sp.iq_ref_a = k, k / 4
                    assert ctl.send_setpoint(sp)
                    assert ctl.recv_feedback(fb, WAIT_S), f"no answer to setpoint {k}"
                    assert (fb.seq, fb.encoder_counts) == (k, k / 2), k
                s = ctl.stats
                assert (s.received, s.lost, s.duplicates, s.out_of_order) == (n, 0, 0, 0)
            summary = json.loads(child.stdout.readline())
            assert child.wait(timeout=30) == 0
        finally:
            if child.poll() is None:
                child.kill()
    assert summary == {"answered": n, "malformed": 0, "lost": 0}
