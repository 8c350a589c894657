"""The loop never waits for a peer: a peer that stops reading, on every transport.

Each test makes 10 000 sends to a peer that does not read and asserts that every call
returned, that the sends the transport had no room for were dropped and counted
(``send_dropped``), and, on the ptys, that the calls kept returning while the descriptor
could not take a byte (``select`` says it is not writable): a send that waited for room
(the old serial code, 0.1 s a send) would not have returned until the peer read.  No
duration is asserted.  On serial the stream must stay framed:
what the peer reads afterwards decodes to exactly the frames counted as sent, with no
bad frame and no skipped byte.

Transports: a real ``os.openpty`` pair (the device on the master descriptor), a socat pty
pair (the device opens one end by path, through pyserial; nobody reads the other end),
and UDP: on this machine's loopback a receiver whose buffer is full never makes a send
fail (the kernel drops the datagram at the receiving socket, which the controller later
counts as lost), so the full-buffer paths run in a private network namespace whose own
loopback has a 1 kbit/s token bucket (``unshare -n``, ``tc``): its queue holds the
datagrams and fills the socket's send buffer (BlockingIOError), or, with a short queue
and IP_RECVERR, refuses them (ENOBUFS).
"""

import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest

from io_adapters import AdapterStats, Feedback, Setpoint, open_endpoint
from io_adapters.serial_link import FrameReader
from io_adapters.udp import UdpEndpoint
from tests.test_adapters import assert_counts_add_up

ROOT = Path(__file__).resolve().parent.parent
SENDS = 10_000
WAIT_S = 10.0


def send_many(ep) -> int:
    """SENDS feedback records; how many went out."""
    fb, sent = Feedback(), 0
    for k in range(SENDS):
        fb.seq = k
        sent += ep.send_feedback(fb)
    return sent


def read_frames(reader: FrameReader, fd: int, expected: int) -> int:
    """Read ``fd`` (non-blocking) into ``reader`` until ``expected`` good frames came or
    WAIT_S passed; the number of good frames."""
    good = 0
    os.set_blocking(fd, False)
    deadline = time.monotonic() + WAIT_S
    while good < expected and time.monotonic() < deadline:
        try:
            reader.feed(os.read(fd, 65536))
        except BlockingIOError:
            time.sleep(0.001)
        while reader.next_payload() is not None:
            good += 1
    return good


def assert_never_waited_and_stayed_framed(ep, far_fd: int) -> None:
    sent = send_many(ep)
    s = ep.stats
    assert s.send_dropped > 0 and sent + s.send_dropped == SENDS == s.sent + s.send_dropped
    assert not select.select((), (ep.fileno(),), (), 0)[1], "full, and the sends returned"
    # the peer reads again: the frame left half written (if one was) is finished before
    # the next one is started
    far = AdapterStats()
    reader = FrameReader(far)
    good = read_frames(reader, far_fd, s.sent - 1)
    assert ep.send_feedback(Feedback())
    good += read_frames(reader, far_fd, s.sent - good)
    assert good == s.sent
    assert (far.malformed, far.bytes_skipped) == (0, 0)


def test_pty_whose_far_side_never_reads():
    master, slave = os.openpty()
    try:
        with open_endpoint(f"serial://fd/{master}", "device") as ep:
            assert_never_waited_and_stayed_framed(ep, slave)
    finally:
        os.close(slave)


def test_socat_pty_pair_whose_far_side_never_reads():
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (apt-get install socat)")
    with tempfile.TemporaryDirectory(prefix="stalled-") as tmp:
        a, b = Path(tmp) / "a", Path(tmp) / "b"
        socat = subprocess.Popen(["socat", f"pty,raw,echo=0,link={a}",
                                  f"pty,raw,echo=0,link={b}"],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + WAIT_S
            while not (a.exists() and b.exists()):
                assert socat.poll() is None and time.monotonic() < deadline, "no pty pair"
                time.sleep(0.01)
            far = os.open(b, os.O_RDWR | os.O_NOCTTY)  # held open, not read
            try:
                with open_endpoint(f"serial://{a}", "device") as ep:  # through pyserial
                    assert_never_waited_and_stayed_framed(ep, far)
            finally:
                os.close(far)
        finally:
            socat.terminate()
            socat.wait(WAIT_S)


def test_udp_receiver_with_a_full_buffer_on_loopback():
    """Linux loopback: every send succeeds and returns at once; the datagrams the full
    receiver could not take are dropped there, and it counts them as lost."""
    with UdpEndpoint("device", ("127.0.0.1", 0)) as device, \
            UdpEndpoint("controller", device.address[:2], rcvbuf=4096) as ctl:
        ctl.send_setpoint(Setpoint())
        assert device.recv_setpoint(Setpoint(), WAIT_S)  # pinned to ctl
        assert send_many(device) == SENDS
        assert device.stats.send_dropped == 0
        fb, got = Feedback(), 0
        while ctl.recv_feedback(fb, 0.05):
            got += 1
        assert 0 < got < SENDS
        assert device.send_feedback(fb)  # one more, behind the gap
        assert ctl.recv_feedback(fb, WAIT_S)
        assert ctl.stats.received + ctl.stats.lost == SENDS + 1
        assert_counts_add_up(ctl.stats)


NAMESPACE_DEVICE = textwrap.dedent("""
    import json, socket, sys
    from io_adapters import Feedback, Setpoint
    from io_adapters.udp import UdpEndpoint
    IP_RECVERR = 11  # linux/in.h; Python's socket module does not name it
    sends, recverr = int(sys.argv[1]), sys.argv[2] == "1"
    with UdpEndpoint("device", ("127.0.0.1", 0)) as device, \\
            UdpEndpoint("controller", device.address[:2]) as ctl:
        ctl.send_setpoint(Setpoint())
        assert device.recv_setpoint(Setpoint(), 10.0)
        if recverr:  # on the device's own socket, through its descriptor
            with socket.socket(fileno=os.dup(device.fileno())) as same:
                same.setsockopt(socket.IPPROTO_IP, IP_RECVERR, 1)
        fb, sent = Feedback(), 0
        for k in range(sends):
            sent += device.send_feedback(fb)
        print(json.dumps({"sent": sent, "dropped": device.stats.send_dropped,
                          "stats_sent": device.stats.sent}))
""").replace("import json, socket", "import json, os, socket")


def _in_namespace(queue_limit: str, recverr: bool) -> dict:
    """Run NAMESPACE_DEVICE in a new network namespace whose loopback sends at 1 kbit/s."""
    if shutil.which("unshare") is None or shutil.which("tc") is None:
        pytest.skip("needs unshare and tc to give a private loopback a slow queue")
    setup = (f"ip link set lo up && tc qdisc add dev lo root tbf rate 1kbit burst 1600 "
             f"{queue_limit} && exec {sys.executable} -c \"$0\" {SENDS} {int(recverr)}")
    for unshare in (["unshare", "-n"], ["unshare", "-rn"]):
        run = subprocess.run(unshare + ["sh", "-c", setup, NAMESPACE_DEVICE], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
        if run.returncode == 0:
            return json.loads(run.stdout)
        if "Traceback" in run.stderr:
            pytest.fail(run.stderr)
    pytest.skip(f"cannot make a network namespace with a slow loopback here: "
                f"{run.stderr.strip()}")


def test_udp_send_buffer_full_drops_and_counts():
    """The token bucket's long queue holds the datagrams, charged to the sending socket,
    until its send buffer is full: sendto raises BlockingIOError."""
    got = _in_namespace("limit 10000000", recverr=False)
    assert got["dropped"] > 0 and got["sent"] + got["dropped"] == SENDS
    assert got["stats_sent"] == got["sent"]


def test_udp_enobufs_drops_and_counts():
    """A short queue refuses the datagrams; with IP_RECVERR Linux says so (ENOBUFS)."""
    got = _in_namespace("latency 1s", recverr=True)
    assert got["dropped"] > 0 and got["sent"] + got["dropped"] == SENDS
    assert got["stats_sent"] == got["sent"]
