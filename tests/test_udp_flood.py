"""A UDP device under a flood of datagrams (issue 27 item 6): the receive budget, the
socket filter that holds a flood off while the pinned controller talks, and the one
stranger's datagram a call decodes; real sockets on the loopback, no mocks.

Counts only: how many datagrams a call read (``stats.frames``), how many the kernel
dropped (``stats.rx_dropped``), what the device took and answered.  The filter is Linux's
(SO_ATTACH_FILTER); elsewhere these tests are skipped.
"""

import select
import socket
import sys
import time

import pytest

from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.codec import encode_hello
from io_adapters.udp import DATAGRAM_COST_NS, MIN_RX_BUDGET, UdpEndpoint, rx_budget_for
from io_adapters.udp_flood import attach, kernel_drops, peer_program
from tests.test_adapters import assert_counts_add_up

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="socket filters are Linux's")

BUDGET = 5
WAIT_S = 5.0
#: not a msgpack array of 4 (a HELLO's start): counted foreign on its first byte
JUNK = b"\x01" + bytes(59)


def _settle(sock: socket.socket) -> None:
    """Loopback delivers within the send unless the kernel defers it: wait until the
    datagrams sent are queued at ``sock``."""
    deadline = time.monotonic() + WAIT_S
    while not _queued(sock):
        assert time.monotonic() < deadline, "the datagrams did not arrive"
        time.sleep(0.001)


def _queued(sock: socket.socket) -> bool:
    return bool(select.select((sock,), (), (), 0.0)[0])


class Bench:
    """A device with a receive budget, its pinned controller, and a stranger's socket on
    the same loopback address (``family``)."""

    def __init__(self, host: str = "127.0.0.1", **options):
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.device = UdpEndpoint("device", (host, 0), **options)
        self.device.drain = True
        self.device.rx_budget = BUDGET
        port = self.device.address[1]
        url = f"udp://[{host}]:{port}" if family == socket.AF_INET6 else f"udp://{host}:{port}"
        self.ctl = open_endpoint(url, "controller")
        self.stranger = socket.socket(family, socket.SOCK_DGRAM)
        self.stranger.bind((host, 0))
        self.to = self.device.address
        self.sp, self.fb = Setpoint(), Feedback()
        self.tick()  # the HELLO: the controller is pinned
        assert self.device.peer == self.ctl.address

    def tick(self) -> bool:
        """One setpoint of the controller, one receive of the device (as a tick)."""
        self.sp.seq += 1
        self.ctl.send_setpoint(self.sp)
        _settle(self.device._sock)
        got = Setpoint()
        taken = self.device.recv_setpoint(got, 0.0)
        return taken and got.seq == self.sp.seq

    def junk(self, n: int, payload: bytes = JUNK) -> None:
        for _ in range(n):
            self.stranger.sendto(payload, self.to)

    def close(self) -> None:
        self.device.close()
        self.ctl.close()
        self.stranger.close()


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def test_the_budget_follows_the_share_of_the_period():
    """A quarter of an 8 kHz period in 3 µs datagrams: 10; never below two."""
    assert rx_budget_for(0.25, 125_000) == 125_000 // 4 // DATAGRAM_COST_NS == 10
    assert rx_budget_for(0.25, 1_000_000) == 83
    assert rx_budget_for(0.01, 62_500) == MIN_RX_BUDGET


def test_a_flood_is_read_within_the_budget_then_held_off_by_the_kernel(bench):
    """Junk queued ahead of the controller's setpoint: a call reads exactly its budget and
    leaves the rest queued (counted, a notice), and since strangers' datagrams were among
    them while the controller talks, the socket's filter comes on.  The junk already
    queued is read a budget a call; what the stranger sends afterwards never reaches the
    endpoint (the kernel's drops are counted as ``rx_dropped``), and the controller's
    setpoints are taken tick after tick."""
    dev, st = bench.device, bench.device.stats
    bench.junk(3 * BUDGET)
    frames = st.frames
    assert not bench.tick(), "the setpoint waits behind a budget's worth of junk"
    assert (st.frames - frames, st.rx_limited, st.foreign) == (BUDGET, 1, BUDGET)
    assert [kind for kind, _ in dev.notices] == ["receive budget met", "flood filter on"]
    assert dev._flood.filtering == bench.ctl.address
    bench.junk(1000)  # dropped in the kernel from now on
    reads = []
    for _ in range(4):
        frames = st.frames
        bench.tick()
        reads.append(st.frames - frames)
        assert st.frames - frames <= BUDGET
    assert bench.tick(), "the controller's setpoint is taken"
    # 2 budgets of old junk, then the 4 setpoints queued behind it, then one a tick
    assert sum(reads) == 2 * BUDGET + 5 and st.foreign == 3 * BUDGET
    dev.close()  # the episode ends: the last drops counted
    assert st.rx_dropped == 1000
    assert [kind for kind, _ in dev.notices][-1] == "receive within budget again"
    assert_counts_add_up(st)


def test_the_filter_comes_off_when_the_controller_falls_silent():
    """While the filter is on a stranger's HELLO cannot get in: once the pinned
    controller has been silent for takeover_ms the filter comes off, and a new
    controller's HELLO takes the device over."""
    b = Bench(takeover_ms=200.0)
    try:
        b.junk(3 * BUDGET)
        b.tick()
        assert b.device._flood.filtering is not None
        b.ctl.close()
        time.sleep(0.3)
        b.device.recv_setpoint(Setpoint(), 0.0)  # a tick: the filter comes off
        assert b.device._flood.filtering is None
        assert b.device.notices[-1][0] == "flood filter off"
        with open_endpoint(f"udp://127.0.0.1:{b.to[1]}", "controller") as new:
            deadline = time.monotonic() + WAIT_S
            while b.device.peer != new.address:
                assert time.monotonic() < deadline, "the new controller did not get in"
                new.send_setpoint(Setpoint())  # its HELLO again every 100 ms
                b.device.recv_setpoint(Setpoint(), 0.01)
    finally:
        b.stranger.close()
        b.device.close()


def test_one_strangers_datagram_a_call_is_decoded(bench):
    """Two strangers' HELLOs in one call: the first is decoded and refused with a
    WELCOME (the controller talks), the second is foreign on its address alone and not
    answered; junk is foreign on its first byte.  The next call decodes one again."""
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))
    other.settimeout(0.2)
    try:
        hello = encode_hello(99, 0)
        bench.stranger.sendto(hello, bench.to)
        other.sendto(hello, bench.to)
        bench.junk(1)
        st = bench.device.stats
        foreign = st.foreign
        assert bench.tick()
        assert (st.foreign - foreign, st.handshakes, st.rx_limited) == (3, 1, 0)
        bench.stranger.settimeout(0.2)
        assert bench.stranger.recv(100), "the first HELLO was answered"
        with pytest.raises(TimeoutError):
            other.recv(100)
        other.sendto(hello, bench.to)
        assert bench.tick()
        assert other.recv(100), "a HELLO in the next call is answered"
    finally:
        other.close()


@pytest.mark.parametrize("host", ["127.0.0.1", "::1"])
def test_the_filter_admits_the_controller_and_drops_every_other_sender(host):
    """The kernel program on its own, IPv4 and IPv6: a device socket with the filter for
    one peer queues that peer's datagrams and drops another socket's on the same
    address, and counts them."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        dev, peer, other = (socket.socket(family, socket.SOCK_DGRAM) for _ in range(3))
    except OSError as e:
        pytest.skip(f"no {host}: {e}")
    with dev, peer, other:
        try:
            for s in (dev, peer, other):
                s.bind((host, 0))
        except OSError as e:
            pytest.skip(f"cannot bind {host}: {e}")
        attach(dev, peer_program(peer.getsockname()))
        before = kernel_drops(dev)
        for k in range(5):
            other.sendto(b"x%d" % k, dev.getsockname())
            peer.sendto(b"p%d" % k, dev.getsockname())
        dev.settimeout(1.0)
        got = [dev.recvfrom(100)[0] for _ in range(5)]
        assert got == [b"p%d" % k for k in range(5)]
        assert kernel_drops(dev) - before == 5
