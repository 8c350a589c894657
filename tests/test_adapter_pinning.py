"""Who may talk to a device: pinning and the handshake over real transports, the
controllers in separate processes (``python -c``), the device in this one.

A controller child sends a setpoint carrying its marker every few ms and reads the
feedback, says on stdout when a WELCOME refused it and when one let it in, and prints
its counters when its stdin closes.  The device here answers every setpoint it takes
and notes (marker, monotonic time) of each.  Waits are bounded by WAIT_S; every child is
reaped.  The takeover is checked by order (no setpoint of the new controller before
the old one died) and by a lower bound on the gap between the two controllers' records
(half of ``takeover_ms``: the other half is margin for the time between the device
hearing a record and its ``recv_setpoint`` returning on a loaded machine).
"""

import json
import os
import queue
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.serial_link import SerialEndpoint
from io_adapters.udp import UdpEndpoint
from tests.test_adapters import assert_counts_add_up

ROOT = Path(__file__).resolve().parent.parent
WAIT_S = 20.0
TAKEOVER_MS = 300.0
MARK_A, MARK_B = 1.0, 2.0

CONTROLLER = textwrap.dedent("""
    import json, select, sys
    from io_adapters import Feedback, Setpoint, open_endpoint
    url, marker = sys.argv[1], float(sys.argv[2])
    if sys.argv[3:] == ["wait"]:  # started, imported, waiting for the word
        sys.stdin.readline()
    with open_endpoint(url, "controller") as ep:
        port = ep.address[1] if url.startswith("udp:") else None
        print(json.dumps({"port": port, "session": ep.session}), flush=True)
        sp, fb, told, k = Setpoint(iq_ref_a=marker), Feedback(), set(), 0
        while not select.select([sys.stdin], [], [], 0)[0]:
            sp.seq, k = k, k + 1
            ep.send_setpoint(sp)
            ep.recv_feedback(fb, 0.005)
            event = "welcomed" if ep.welcomed else "refused" if ep.stats.handshakes else None
            if event and event not in told:
                told.add(event)
                print(json.dumps({"event": event}), flush=True)
        s = ep.stats
        print(json.dumps({"welcomed": ep.welcomed, "handshakes": s.handshakes,
                          "received": s.received}), flush=True)
""")


class Child:
    """A controller process; its stdout lines are read by a thread into a queue.  With
    ``wait`` it opens its endpoint only when :meth:`go` says so."""

    def __init__(self, url: str, marker: float, wait: bool = False):
        self.proc = subprocess.Popen(
            [sys.executable, "-c", CONTROLLER, url, str(marker)] + ["wait"] * wait,
            cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.lines = queue.Queue()
        self.events = set()
        threading.Thread(target=self._read, daemon=True).start()
        if not wait:
            self.go()

    def go(self) -> None:
        """(When started with ``wait``) open the endpoint now; note its port and session."""
        if self.proc.args[-1] == "wait":
            self.proc.stdin.write("go\n")
            self.proc.stdin.flush()
        self.hello = self.line()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(json.loads(line))
        self.lines.put(None)

    def line(self, timeout_s: float = WAIT_S) -> dict:
        got = self.lines.get(timeout=timeout_s)
        assert got is not None, f"controller exited with {self.proc.wait(WAIT_S)}"
        return got

    def poll_events(self) -> set:
        while not self.lines.empty():
            line = self.lines.get()
            if line is not None and "event" in line:
                self.events.add(line["event"])
        return self.events

    def stop(self) -> dict:
        """Close its stdin; its summary."""
        self.proc.stdin.close()
        while "welcomed" not in (line := self.line()):
            self.events.add(line["event"])
        assert self.proc.wait(WAIT_S) == 0
        return line

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait(WAIT_S)

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        if self.proc.poll() is None:
            self.kill()
        self.proc.stdin.close()
        self.proc.stdout.close()


def serve(device, taken: list, until, what: str) -> None:
    """Be the drive: take setpoints, answer each, note (marker, time) in ``taken``, until
    ``until()`` holds; fails after WAIT_S."""
    sp, fb = Setpoint(), Feedback()
    deadline = time.monotonic() + WAIT_S
    while not until():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        if device.recv_setpoint(sp, 0.01):
            taken.append((sp.iq_ref_a, time.monotonic_ns()))
            fb.seq = sp.seq
            device.send_feedback(fb)


def count(taken: list, marker: float) -> int:
    return sum(m == marker for m, _ in taken)


def served_longer_than_takeover(taken: list) -> bool:
    """The records span twice ``takeover_ms``: the pinned controller stays pinned by
    talking, not by the time of its first frame."""
    return len(taken) >= 20 and taken[-1][1] - taken[0][1] >= 2 * TAKEOVER_MS * 1e6


def test_a_second_local_sender_is_foreign_and_cannot_move_the_session():
    taken = []
    with UdpEndpoint("device", ("127.0.0.1", 0), takeover_ms=TAKEOVER_MS) as device:
        url = f"udp://127.0.0.1:{device.address[1]}"
        with Child(url, MARK_A) as a:
            serve(device, taken, lambda: served_longer_than_takeover(taken), "A's setpoints")
            with Child(url, MARK_B) as b:
                serve(device, taken, lambda: "refused" in b.poll_events()
                      and device.stats.foreign >= 20, "B to be refused")
                b_summary = b.stop()
            a_summary = a.stop()
        stats = device.stats
        assert device.peer[1] == a.hello["port"]
    assert count(taken, MARK_B) == 0
    assert b_summary["welcomed"] is False and b_summary["received"] == 0
    assert a_summary["welcomed"] is True
    assert (stats.peer_restarts, stats.stale_session) == (0, 0)
    assert stats.handshakes == 1  # A's HELLO; every one of B's was refused (foreign)
    assert_counts_add_up(stats)


def _global_ipv4() -> str | None:
    """This machine's first non-loopback IPv4 address, as ``ip -4 addr`` shows it."""
    try:
        out = subprocess.run(["ip", "-4", "-o", "addr", "show", "scope", "global"],
                             capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    for line in out.splitlines():
        return line.split()[3].partition("/")[0]
    return None


REMOTE_SENDER = textwrap.dedent("""
    import socket, sys
    from io_adapters import Setpoint, codec
    source, port = sys.argv[1], int(sys.argv[2])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((source, 0))
        sock.sendto(codec.encode_hello(5, 0), ("127.0.0.1", port))
        sock.sendto(codec.encode(Setpoint(iq_ref_a=9.0), 5, 0), ("127.0.0.1", port))
""")


def test_a_datagram_from_a_non_loopback_source_is_dropped():
    """Sent to 127.0.0.1 from this machine's own network address (a socket bound to it,
    in another process): the device bound to loopback without allow_remote drops it and
    stays free for a loopback controller."""
    source = _global_ipv4()
    if source is None:
        pytest.skip("this machine has no non-loopback IPv4 address to send from")
    with UdpEndpoint("device", ("127.0.0.1", 0)) as device:
        subprocess.run([sys.executable, "-c", REMOTE_SENDER, source, str(device.address[1])],
                       cwd=ROOT, check=True, timeout=60)
        sp = Setpoint()
        assert not device.recv_setpoint(sp, 0.2)
        assert (device.stats.foreign, device.stats.frames, device.peer) == (2, 2, None)
        assert not device.exposed
        with open_endpoint(f"udp://127.0.0.1:{device.address[1]}", "controller") as ctl:
            ctl.send_setpoint(Setpoint(iq_ref_a=1.0))
            assert device.recv_setpoint(sp, WAIT_S) and sp.iq_ref_a == 1.0
            assert device.peer == ctl.address
        assert_counts_add_up(device.stats, frames=4)


@pytest.fixture(params=["udp", "serial"])
def device_url(request):
    """(device endpoint, URL a controller opens) with takeover_ms=TAKEOVER_MS."""
    if request.param == "udp":
        with UdpEndpoint("device", ("127.0.0.1", 0), takeover_ms=TAKEOVER_MS) as device:
            yield device, f"udp://127.0.0.1:{device.address[1]}"
        return
    master, slave = os.openpty()  # slave kept open: the pty outlives each controller
    try:
        with SerialEndpoint("device", master, takeover_ms=TAKEOVER_MS) as device:
            yield device, f"serial://{os.ttyname(slave)}"
    finally:
        os.close(slave)


def test_a_restarted_controller_gets_back_in_after_takeover_ms(device_url):
    """A is pinned and dies; B (new process, new port, new session), started at once
    (imported beforehand, so that its HELLO comes well within takeover_ms; on serial
    never two controllers on the line), is refused, then accepted by a repeated HELLO
    once A has been silent for takeover_ms."""
    device, url = device_url
    taken = []
    with Child(url, MARK_A) as a, Child(url, MARK_B, wait=True) as b:
        serve(device, taken, lambda: count(taken, MARK_A) >= 20, "A's setpoints")
        a.kill()
        b.go()
        serve(device, taken, lambda: device.stats.foreign >= 1 or count(taken, MARK_B),
              "B's first HELLO")
        assert count(taken, MARK_B) == 0 and device.stats.peer_restarts == 0
        serve(device, taken, lambda: count(taken, MARK_B) >= 20, "B's setpoints")
        b_summary = b.stop()
    markers = [m for m, _ in taken]
    first_b = markers.index(MARK_B)
    assert set(markers[:first_b]) == {MARK_A} and set(markers[first_b:]) == {MARK_B}
    gap_ns = taken[first_b][1] - taken[first_b - 1][1]
    assert gap_ns >= TAKEOVER_MS * 1e6 / 2
    assert b_summary["welcomed"] is True and b_summary["received"] > 0
    stats = device.stats
    assert stats.peer_restarts == 1 and stats.handshakes >= 2
    assert (stats.foreign if url.startswith("udp:") else stats.stale_session) > 0
    assert_counts_add_up(stats)
