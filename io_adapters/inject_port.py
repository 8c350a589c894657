"""A bench's injection port: a UDP socket on the loopback address, apart from the
controller's link, that takes INJECT messages (:mod:`io_adapters.codec`, kind 5) from the
bench's own software on this machine -- ``hil scope``'s injection panel, or a script.

A real HIL bench's experiment software (dSPACE ControlDesk's fault-insertion panel, say)
talks to the simulator, not through the controller under test; the controller's link
takes an INJECT from its pinned peer only (:mod:`io_adapters.msgpack_endpoint`), and a
page in a browser is no such peer.  ``hil run --inject-port N`` opens one
(:class:`InjectPort`); :class:`InjectClient` sends to it.

Every datagram is counted in :attr:`InjectPortStats.datagrams` and in exactly one of:

* ``injections``: a well-formed INJECT (the codec's strict checks), queued in
  :attr:`InjectPort.requests` for the loop, which hands it to the axis's injector;
* ``malformed``: anything that does not decode as an INJECT (not msgpack, a wrong layout,
  a name too long, an INJECT of another version);
* ``foreign``: a message of the wire of another kind -- a setpoint, feedback, HELLO or
  WELCOME, told by its first bytes without decoding it: meant for a controller's link;
* ``refused_nonfinite``: an INJECT with a NaN or infinite number;
* ``overflow``: a well-formed INJECT that found :data:`MAX_WAITING` requests waiting.

No session, frame or peer is checked: the socket is bound to a loopback address, so only
this machine's programs reach it, and any of them may inject (the option opens it only
when asked).  Nothing is answered: what became of a request (started, refused for its
axis, its fault or a value) is in the run's events.

The socket blocks in its receive on a thread of its own (``hil-inject-port``), which the
emulator gives real-time priority below the loop's on the loop's CPU as its other helper
threads (:func:`hil.rt.scheduling.helper_threads_realtime`): it never spins, and each
datagram costs one receive, a look at its first bytes and, for an INJECT only, its
decoding.  At most :data:`MAX_PER_S` datagrams are read in a second; beyond them the
thread waits for the next second (``paused`` counts those waits), the kernel dropping
what its socket buffer cannot hold, so a flood of datagrams to the port costs the loop's
CPU a bounded share of its time.
"""

import ipaddress
import math
import secrets
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass

from io_adapters.base import AdapterConfigError, AdapterError, FrameError
from io_adapters.codec import (
    HEADER_LEN,
    KIND_FEEDBACK,
    KIND_HELLO,
    KIND_SETPOINT,
    KIND_WELCOME,
    VERSION,
    VERSION_GROUP,
    decode_inject,
    encode_inject,
    inject_request,
)
from io_adapters.messages import InjectRequest

#: the address an injection port binds: loopback only
HOST = "127.0.0.1"
#: the most requests waiting for the loop; a further INJECT is counted in ``overflow``
MAX_WAITING = 16
#: the most datagrams the receive thread reads in a second (module docstring)
MAX_PER_S = 200
#: the longest :meth:`InjectPort.close` waits for the receive thread to end, s
JOIN_S = 2.0
#: receive buffer, bytes: an INJECT is at most about 400 bytes (40-character names, 8
#: settings); a longer datagram is truncated, and then malformed
MAX_DATAGRAM = 2048
#: the message kinds of the wire other than INJECT, and their versions
_OTHER_KINDS = frozenset((KIND_SETPOINT, KIND_FEEDBACK, KIND_HELLO, KIND_WELCOME))
_VERSIONS = frozenset((VERSION, VERSION_GROUP))


@dataclass(slots=True)
class InjectPortStats:
    """Counters of an :class:`InjectPort` since it opened (module docstring):
    ``datagrams == injections + malformed + foreign + refused_nonfinite + overflow``."""
    datagrams: int = 0
    injections: int = 0
    malformed: int = 0
    foreign: int = 0
    refused_nonfinite: int = 0
    overflow: int = 0
    paused: int = 0


def parse_address(text: str) -> tuple[str, int]:
    """``"HOST:PORT"`` of an injection port (as :attr:`InjectPort.url` writes it) ->
    (host, port); :class:`~io_adapters.base.AdapterConfigError` unless HOST is a loopback
    address and PORT a port number."""
    host, sep, port = text.rpartition(":")
    try:
        loopback = ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        loopback = False
    if not sep or not loopback or not port.isdigit() or not 0 < int(port) <= 65535:
        raise AdapterConfigError(f"injection port {text!r}: expected a loopback "
                                 f"HOST:PORT, e.g. {HOST}:41000")
    return host.strip("[]"), int(port)


def header(data: bytes | memoryview) -> tuple[int, int] | None:
    """(version, kind) of a datagram that starts as a message of the wire does (a msgpack
    array of at least the header's four elements, the first two small positive integers),
    read from its first bytes without decoding it; None for one that does not."""
    if not len(data):
        return None
    lead = data[0]
    if 0x90 <= lead <= 0x9F:
        at, n = 1, lead - 0x90
    elif lead in (0xDC, 0xDD):  # array 16, array 32: the length big-endian
        at = 3 if lead == 0xDC else 5
        n = int.from_bytes(bytes(data[1:at]), "big") if len(data) >= at else 0
    else:
        return None
    if n < HEADER_LEN or len(data) < at + 2 or data[at] >= 0x80 or data[at + 1] >= 0x80:
        return None
    return data[at], data[at + 1]


class InjectPort:
    """The injection port of an emulator (module docstring): bound at once, receiving once
    :meth:`start` is called, until :meth:`close`.

    Args:
        port: the UDP port on :data:`HOST` (0: any free one, :attr:`address` says which).
        max_per_s: the most datagrams read in a second (> 0; module docstring).

    Attributes:
        requests: the well-formed requests (:class:`~io_adapters.messages.InjectRequest`)
            the loop has not taken, oldest first; appended by the receive thread, taken by
            the loop (``popleft``; a deque is safe between the two).
        stats: the counters (:class:`InjectPortStats`), written by the receive thread.

    Raises:
        AdapterConfigError: ``port`` is not 0..65535.
        AdapterError: the port cannot be bound (taken).
    """

    def __init__(self, port: int, max_per_s: int = MAX_PER_S):
        if not 0 <= port <= 65535:
            raise AdapterConfigError(f"injection port {port}: expected 0..65535 (0: any "
                                     f"free one)")
        if max_per_s < 1:
            raise AdapterConfigError(f"max_per_s={max_per_s}: expected at least 1 datagram "
                                     f"a second")
        self.max_per_s = max_per_s
        self.requests: deque[InjectRequest] = deque()
        self.stats = InjectPortStats()
        self._buf = bytearray(MAX_DATAGRAM)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((HOST, port))
        except OSError as e:
            self._sock.close()
            raise AdapterError(f"cannot bind the injection port {HOST}:{port}: {e}") from e
        self.address: tuple[str, int] = self._sock.getsockname()[:2]

    @property
    def url(self) -> str:
        """``HOST:PORT`` bound (what the run folder's metadata says)."""
        return f"{self.address[0]}:{self.address[1]}"

    def start(self) -> None:
        """Start the receive thread (before any priority change of the process: a helper
        thread is made real-time with the loop's others)."""
        if self._thread is None and not self._stop.is_set():
            self._thread = threading.Thread(target=self._run, name="hil-inject-port",
                                            daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the receive thread (waiting at most :data:`JOIN_S` for it) and close the
        socket (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread is not None:
            try:  # an empty datagram to itself wakes the blocked receive
                self._sock.sendto(b"", self.address)
            except OSError:  # else shutting it down does (Linux), ENOTCONN notwithstanding
                try:
                    self._sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
            self._thread.join(JOIN_S)
        self._sock.close()

    def __enter__(self) -> "InjectPort":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _run(self) -> None:
        window_end, read = time.monotonic() + 1.0, 0
        while not self._stop.is_set():
            try:
                n = self._sock.recv_into(self._buf)
            except OSError:  # closed under it
                return
            if self._stop.is_set():
                return
            self.take(memoryview(self._buf)[:n])
            read += 1
            now = time.monotonic()
            if now >= window_end:
                window_end, read = now + 1.0, 0
            elif read >= self.max_per_s:
                self.stats.paused += 1
                self._stop.wait(window_end - now)

    def take(self, data: bytes | memoryview) -> None:
        """Count one datagram and queue it if it is a well-formed INJECT (the receive
        thread's work on each; callable directly in a test)."""
        stats = self.stats
        stats.datagrams += 1
        head = header(data)
        if head is not None and head[1] in _OTHER_KINDS and head[0] in _VERSIONS:
            stats.foreign += 1
            return
        try:
            request = inject_request(decode_inject(data))
        except FrameError:
            stats.malformed += 1
            return
        if not all(map(math.isfinite, request.settings.values())):
            stats.refused_nonfinite += 1
        elif len(self.requests) >= MAX_WAITING:
            stats.overflow += 1
        else:
            stats.injections += 1
            self.requests.append(request)


class InjectClient:
    """Sends INJECT messages to an injection port (``hil scope``'s panel).

    Args:
        address: the port's (host, port), a loopback address.

    Attributes:
        session: this client's session, u32, drawn at random (the port does not check
            it; it tells the sender in a capture).
    """

    def __init__(self, address: tuple[str, int]):
        parse_address(f"{address[0]}:{address[1]}")
        self.address = address
        self.session = secrets.randbits(32)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((HOST, 0))

    def send(self, request: InjectRequest) -> None:
        """Send ``request``; :class:`~io_adapters.base.FrameError` if it does not fit the
        INJECT layout, :class:`~io_adapters.base.AdapterError` if the send fails."""
        payload = encode_inject(self.session, 0, request)
        try:
            self._sock.sendto(payload, self.address)
        except OSError as e:
            raise AdapterError(f"cannot send to the injection port "
                               f"{self.address[0]}:{self.address[1]}: {e}") from e

    def close(self) -> None:
        """Close the socket (idempotent)."""
        self._sock.close()

    def __enter__(self) -> "InjectClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
