"""UDP transport: one message per datagram (msgpack, :mod:`io_adapters.codec`, or the
fixed layout with ``wire=fixed``, :mod:`io_adapters.codec_fixed`).

URL: ``udp://HOST:PORT[?option=value&...]``.  HOST:PORT is the device's address
on both sides, so both can be given the same URL:

* the device binds HOST:PORT (port 0 picks a free one; see :attr:`UdpEndpoint.address`),
  pins the address and session of the first controller that sends it a well-formed
  setpoint or HELLO, takes datagrams from that address only (others: ``stats.foreign``)
  and answers it, or a fixed ``peer``; another controller gets in through the handshake
  once the pinned one has been silent for ``takeover_ms`` (:mod:`io_adapters.codec`);
* the controller binds an ephemeral port on the same loopback address (or ``bind``),
  sends a HELLO when it opens, sends to HOST:PORT and drops datagrams from any other
  address (``stats.foreign``).

Options:

* ``bind=HOST:PORT`` — controller only: its own address.
* ``peer=HOST:PORT`` — device only: always send feedback there.
* ``allow_remote=1`` — allow addresses outside the loopback network (refused otherwise,
  and so are datagrams from such a source address); :attr:`UdpEndpoint.exposed` then
  says whether the endpoint is reachable from the network.
* ``drain=1`` — each receive also takes every datagram already queued behind the
  first, so the loop works on the newest record (see :class:`~io_adapters.base.Endpoint`).
* ``rcvbuf=BYTES`` — the socket's receive buffer (SO_RCVBUF; the kernel doubles it).
* ``takeover_ms=MS`` — device side (a controller ignores it, so both can share a URL):
  how long the pinned controller must have been silent before another one's HELLO is
  accepted, default 500 ms.
* ``wire=msgpack|fixed`` — how messages are laid out (:mod:`io_adapters.wire`): msgpack
  (the default) or the fixed little-endian C structs of :mod:`io_adapters.codec_fixed`.

A receive call (``recv_setpoint``, ``recv_feedback``) reads at most
:attr:`UdpEndpoint.rx_budget` datagrams from the socket (None, the default: no bound; ``hil
run`` sets it from its ``--rx-share`` of the period) and leaves the rest queued there for
the next call: a call that stops at the budget with datagrams left is counted in
``stats.rx_limited`` and, on a device, starts a flood episode
(:mod:`io_adapters.udp_flood`: while strangers flood a pinned controller that is still
talking, the kernel drops all but its datagrams).  A receive call decodes at most one
stranger's datagram, the first that may be a HELLO (its first byte a msgpack array's of
4, or the fixed wire's magic): every other one is counted foreign on its address alone (a further HELLO in the same
call is neither taken nor answered; its sender repeats it).

The socket is non-blocking; waits use ``select``, which keeps microsecond timeouts
(``poll`` rounds up to milliseconds); a send that finds the socket buffer full
(``BlockingIOError``, ``ENOBUFS``) drops the datagram, counts ``stats.send_dropped`` and
returns False (on Linux loopback a receiver that does not read never fills the sender's
buffer: the kernel drops the datagram at the receiving socket).  SO_REUSEADDR is
deliberately not set: on Linux it lets a second UDP socket bind the same port and take
its datagrams, so a second emulator on a busy port is refused instead of silently
splitting the setpoints.  A device has nobody to answer before the first setpoint or
HELLO arrives (no ``peer``): ``send_feedback`` then returns False.

Arrival stamps: ``Setpoint.rx_ns`` and ``Feedback.rx_ns`` are the kernel's receive time of
the datagram (``SO_TIMESTAMPNS``, read from ``recvmsg``'s ancillary data), not the time the
adapter returned it, so a setpoint that waited in the socket for the drive's tick has an
arrival before that tick.  The kernel's stamp is on CLOCK_REALTIME; :class:`RealtimeToMonotonic`
moves it to ``time.monotonic_ns()`` with an offset measured when the socket opens and again
when a stamp is more than :data:`OFFSET_REFRESH_NS` from the last measurement.  The
converted stamp is never later than the true arrival and at most
:attr:`RealtimeToMonotonic.window_ns` (the measurement's bracket, a few hundred ns) earlier,
plus any step of the realtime clock (``settimeofday``, an NTP step, a leap second) since the
last measurement, which lasts until the next one (at most :data:`OFFSET_REFRESH_NS` plus
the step later); NTP's slewing changes both clocks' rate alike and does not move the
offset.  Where the option is refused, or a datagram comes
without the stamp, ``rx_ns`` is the user-space stamp of :class:`~io_adapters.base.Endpoint`
(after the adapter read it), as on the serial transport (:attr:`UdpEndpoint.kernel_stamps`
says which).
"""

import errno
import ipaddress
import select
import socket
import struct
import sys
import time

from io_adapters.base import (
    AdapterConfigError,
    AdapterError,
    Role,
    flag,
    parse_options,
    positive_float,
    positive_int,
)
from io_adapters.msgpack_endpoint import (
    DEFAULT_TAKEOVER_MS,
    MSGPACK_WIRE,
    MsgpackEndpoint,
)
from io_adapters.udp_flood import FloodGuard
from io_adapters.wire import Wire, wire_named

#: receive buffer, bytes: far above any message (about 100 bytes)
MAX_DATAGRAM = 2048
#: Linux's SO_TIMESTAMPNS (SO_TIMESTAMPNS_OLD of asm-generic/socket.h, used by x86, Arm,
#: RISC-V, PowerPC, s390 and MIPS; Python's socket module does not name it); the control
#: message carrying the stamp has the same type and a struct timespec of two C longs.
#: None: no kernel stamps on this platform
SO_TIMESTAMPNS = 35 if sys.platform == "linux" else None
TIMESPEC = struct.Struct("@ll")
#: the realtime-to-monotonic offset is measured again when a stamp is this far from the
#: last measurement, ns
OFFSET_REFRESH_NS = 1_000_000_000
#: readings per offset measurement; the narrowest bracket is kept
OFFSET_TRIES = 5
#: what reading one stranger's datagram that is not decoded costs a receive call, CPU
#: ns: 2.8 µs in the Python path, 2.5 µs in the compiled tick's read (with the poll
#: that looks for more), on the 2-vCPU VM of docs/platform-notes.md (2026-11); the unit
#: of :func:`rx_budget_for`
DATAGRAM_COST_NS = 3000
#: the smallest receive budget :func:`rx_budget_for` gives: a setpoint and one more
MIN_RX_BUDGET = 2


def host_port(text: str) -> tuple[str, int]:
    """``"HOST:PORT"`` or ``"[V6HOST]:PORT"`` -> (host, port)."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise ValueError(f"{text!r} is not HOST:PORT")
    return host.strip("[]"), int(port)


def rx_budget_for(share: float, period_ns: int) -> int:
    """The receive budget (:attr:`UdpEndpoint.rx_budget`) that lets a flood of strangers'
    datagrams take at most ``share`` of a period of ``period_ns``: that time in
    :data:`DATAGRAM_COST_NS`, at least :data:`MIN_RX_BUDGET` (10 at 8 kHz with a quarter
    of the period).  The call also decodes at most one stranger's datagram (a HELLO and
    its answer: about 10 µs) and the peer's own (about 6 µs each in the Python path)."""
    return max(MIN_RX_BUDGET, int(share * period_ns) // DATAGRAM_COST_NS)


def _sockaddr(host: str, port: int) -> tuple[int, tuple]:
    try:
        family, _, _, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
    except socket.gaierror as e:
        raise AdapterConfigError(f"cannot resolve {host!r}: {e}") from e
    return family, addr


def _is_loopback(addr: tuple) -> bool:
    return ipaddress.ip_address(addr[0].partition("%")[0]).is_loopback


class RealtimeToMonotonic:
    """CLOCK_REALTIME ns -> ``time.monotonic_ns()`` ns, by an offset measured now and again.

    A measurement reads monotonic, realtime, monotonic (m0, r, m1), :data:`OFFSET_TRIES`
    times, and keeps the narrowest bracket: the true offset is between r - m1 and r - m0,
    and r - m0 is used, so a converted time is never late and at most ``window_ns`` =
    m1 - m0 early (while the realtime clock is not stepped; see the module docstring).

    Attributes:
        offset_ns: realtime minus monotonic, ns, as last measured.
        window_ns: the width of that measurement's bracket, ns.
    """

    def __init__(self):
        self.offset_ns = self.window_ns = self._measured_at_ns = 0
        self.measure()

    def measure(self) -> None:
        """Measure the offset again."""
        best = None
        for _ in range(OFFSET_TRIES):
            m0 = time.monotonic_ns()
            r = time.clock_gettime_ns(time.CLOCK_REALTIME)
            m1 = time.monotonic_ns()
            if best is None or m1 - m0 < best[2] - best[0]:
                best = (m0, r, m1)
        m0, r, m1 = best
        self.offset_ns, self.window_ns, self._measured_at_ns = r - m0, m1 - m0, r

    def monotonic_ns(self, realtime_ns: int) -> int:
        """``realtime_ns`` on the monotonic clock, measuring the offset first when
        ``realtime_ns`` is more than :data:`OFFSET_REFRESH_NS` from the last measurement."""
        if abs(realtime_ns - self._measured_at_ns) > OFFSET_REFRESH_NS:
            self.measure()
        return realtime_ns - self.offset_ns


class UdpEndpoint(MsgpackEndpoint):
    """One side of a UDP link; see the module docstring for addressing and options.

    Args:
        role: "device" or "controller".
        address: the device's (host, port).
        bind: controller only: its own (host, port); default the loopback address of
            ``address``'s family, ephemeral port (any address if ``address`` is remote).
        peer: device only: the (host, port) to send feedback to instead of the sender.
        allow_remote: allow non-loopback addresses.
        drain: see :class:`~io_adapters.base.Endpoint`.
        rcvbuf: SO_RCVBUF in bytes (None: the system default).
        takeover_ms, wire: see :class:`~io_adapters.msgpack_endpoint.MsgpackEndpoint`.

    Attributes:
        rx_budget: the most datagrams one receive call reads from the socket (None: no
            bound; see the module docstring); set it before the first receive.
    """

    def __init__(self, role: Role | str, address: tuple[str, int], *,
                 bind: tuple[str, int] | None = None, peer: tuple[str, int] | None = None,
                 allow_remote: bool = False, drain: bool = False, rcvbuf: int | None = None,
                 takeover_ms: float = DEFAULT_TAKEOVER_MS, wire: Wire = MSGPACK_WIRE):
        super().__init__(role, drain=drain, takeover_ms=takeover_ms, wire=wire)
        device = self.role is Role.DEVICE
        if device and bind is not None:
            raise AdapterConfigError("bind= is for the controller side; the device binds "
                                     "the URL's address")
        if not device and peer is not None:
            raise AdapterConfigError("peer= is for the device side; the controller sends "
                                     "to the URL's address")
        family, target = _sockaddr(*address)
        if not device and target[1] == 0:
            raise AdapterConfigError(f"controller needs the device's port, not 0: {address}")
        if device:
            local = target
        elif bind is not None:
            local = _sockaddr(*bind)[1]
        else:
            local = (target[0] if _is_loopback(target) else "", 0) + target[2:]
        self._fixed_peer = _sockaddr(*peer)[1] if peer is not None else (
            None if device else target)
        for addr in (target, local, self._fixed_peer):
            if addr is not None and addr[0] and not allow_remote and not _is_loopback(addr):
                raise AdapterConfigError(f"{addr[0]} is not a loopback address; add "
                                         f"allow_remote=1 to use the network")
        self._allow_remote = allow_remote
        if not device:
            self._peer_origin = target  # a controller hears its device only
        self._from_ns = self._arrival_ns = 0  # kernel stamps (monotonic) or 0: none
        # datagrams (n, origin, stamp, bytes) and receive errors that the compiled tick
        # read and handed back (io_adapters.udp_steady), oldest first: the next receives
        # return them first
        self._stash: list[tuple | OSError] = []
        self.rx_budget: int | None = None
        # datagrams the current receive call may still read from the socket (< 0: it
        # stopped at the budget), its start's foreign count, and whether the compiled
        # tick's read (io_adapters.udp_steady) began the call the next receive continues
        self._left, self._foreign_at, self._continued = sys.maxsize, 0, False
        self._hello_looked = False  # the call decoded a stranger's datagram already
        self._buf = bytearray(MAX_DATAGRAM)
        self._bufs = (self._buf,)
        self._view = memoryview(self._buf)
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            if rcvbuf is not None:
                self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            self._sock.bind(local)
            self._sock.setblocking(False)
        except OSError as e:
            self._sock.close()
            raise AdapterError(f"cannot bind UDP {local[0]}:{local[1]}: {e}") from e
        self._clock = self._kernel_stamps_on()
        self._ancillary = socket.CMSG_SPACE(TIMESPEC.size) if self._clock else 0
        self._flood = FloodGuard(self._sock, self.stats, self._notice) if device else None
        self._greet()

    def _kernel_stamps_on(self) -> RealtimeToMonotonic | None:
        """Ask for SO_TIMESTAMPNS; the clock converting its stamps, None if refused."""
        if SO_TIMESTAMPNS is None:
            return None
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError:
            return None
        return RealtimeToMonotonic()

    @classmethod
    def from_url(cls, url: str, role: Role | str) -> "UdpEndpoint":
        """``udp://HOST:PORT?options`` (see the module docstring)."""
        rest = url.partition("://")[2]
        netloc, _, query = rest.partition("?")
        try:
            address = host_port(netloc.rstrip("/"))
        except ValueError as e:
            raise AdapterConfigError(f"{url!r}: expected udp://HOST:PORT ({e})") from e
        options = parse_options(url, query, {
            "bind": host_port, "peer": host_port, "allow_remote": flag, "drain": flag,
            "rcvbuf": positive_int, "takeover_ms": positive_float, "wire": wire_named})
        return cls(role, address, **options)

    @property
    def address(self) -> tuple:
        """The local socket address (host, port, ...) actually bound."""
        return self._sock.getsockname()

    @property
    def kernel_stamps(self) -> bool:
        """True when ``rx_ns`` comes from the kernel's receive stamp (module docstring)."""
        return self._clock is not None

    @property
    def clock(self) -> RealtimeToMonotonic | None:
        """The conversion of the kernel's stamps (None without them)."""
        return self._clock

    @property
    def peer(self) -> tuple | None:
        """Where the next message goes (None: a device that has not heard from anyone)."""
        return self._fixed_peer or self._peer_origin

    @property
    def exposed(self) -> bool:
        """True when the endpoint is bound to or sends to an address outside the loopback
        network (possible with ``allow_remote=1`` only): a daemon warns about it."""
        if self._closed:
            return False
        peer = self.peer
        return not _is_loopback(self.address) or (peer is not None and not _is_loopback(peer))

    def __repr__(self) -> str:
        host, port = self._sock.getsockname()[:2] if not self._closed else ("-", "-")
        # the other end too: a message about a drive that does not answer names the drive
        other = self.peer
        peer = "" if other is None else (
            f", {'controller' if self.role is Role.DEVICE else 'drive'} {other[0]}:{other[1]}")
        return (f"<UdpEndpoint {self.role.value} {host}:{port}{peer}"
                f"{' closed' * self._closed}>")

    def _send_bytes(self, payload: bytes, to) -> bool:
        to = to or self.peer
        if to is None:
            return False
        try:
            self._sock.sendto(payload, to)
        except BlockingIOError:
            self.stats.send_dropped += 1
            return False
        except OSError as e:
            if e.errno != errno.ENOBUFS:
                raise
            self.stats.send_dropped += 1
            return False
        return True

    def _begin_receive(self) -> None:
        """A receive call starts: its budget, and the flood episode's watch; unless it
        continues the compiled tick's read, which began it."""
        if self._continued:
            self._continued = False
            return
        self._left = self.rx_budget if self.rx_budget is not None else sys.maxsize
        self._foreign_at, self._hello_looked = self.stats.foreign, False
        flood = self._flood
        if flood is not None and flood.active:
            now = time.monotonic_ns()
            flood.watch(now, self._peer_origin, self._peer_fresh(now))

    def _peer_fresh(self, now_ns: int) -> bool:
        """A device's pinned peer has been heard within ``takeover_ms``."""
        return self._peer_session is not None and now_ns - self._heard_ns < self._takeover_ns

    def _at_budget(self) -> None:
        """The call has read its budget: if datagrams are still queued, count it and
        tell the flood episode (once per call)."""
        self._left = -1
        if not select.select((self._sock,), (), (), 0.0)[0]:
            return
        self.stats.rx_limited += 1
        if self._flood is not None:
            now = time.monotonic_ns()
            self._flood.limited(now, self.rx_budget, self._peer_origin, self._peer_fresh(now),
                                self.stats.foreign > self._foreign_at)

    def _exhausted(self) -> bool:
        return self._left <= 0 and not self._stash

    def _from_stranger(self, data, origin) -> None:
        """The base class's judgement of the call's first stranger's datagram that may be
        a HELLO; any other one is foreign at once (module docstring)."""
        if self._hello_looked:
            self.stats.foreign += 1
            return
        self._hello_looked = self._may_be_hello(data)
        super()._from_stranger(data, origin)

    def _may_be_hello(self, data) -> bool:
        """A stranger's datagram this call would decode as a possible HELLO."""
        return (not self._hello_looked and len(data) > 0
                and data[0] in self.wire.hello_leads)

    def _foreign_datagram(self, n: int) -> None:
        """Count a stranger's datagram of ``n`` bytes that this call does not decode, as
        :meth:`_accept` counts it (for the compiled tick's read)."""
        st = self.stats
        st.frames += 1
        st.bytes_received += n
        st.foreign += 1

    def _recv_bytes(self, timeout_s: float | None) -> memoryview | None:
        if self._stash:
            return self._unstash()
        if self._left <= 0:
            if self._left == 0:
                self._at_budget()
            return None
        sock = self._sock
        if timeout_s != 0.0 and not select.select((sock,), (), (), timeout_s)[0]:
            return None
        self._left -= 1
        try:
            n, ancillary, _, addr = sock.recvmsg_into(self._bufs, self._ancillary)
        except BlockingIOError:
            self._left += 1
            return None
        self._origin = addr
        self._from_ns = self._kernel_ns(ancillary)
        return self._view[:n]

    def _unstash(self) -> memoryview:
        stash = self._stash.pop(0)
        if isinstance(stash, OSError):
            raise stash
        n, self._origin, self._from_ns, data = stash
        self._buf[:n] = data
        return self._view[:n]

    def _admissible(self, origin: tuple) -> bool:
        return self._allow_remote or _is_loopback(origin)

    def _kernel_ns(self, ancillary: list) -> int:
        """The kernel's receive stamp in ``ancillary``, monotonic ns; 0 if it has none."""
        for level, kind, data in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS \
                    and len(data) == TIMESPEC.size:
                sec, nsec = TIMESPEC.unpack(data)
                return self._clock.monotonic_ns(sec * 1_000_000_000 + nsec)
        return 0

    def _accept(self, data, into) -> bool:
        ok = super()._accept(data, into)
        if ok:
            self._arrival_ns = self._from_ns
        return ok

    def _receive(self, into, timeout_s: float | None) -> bool:
        """The base class's receive within the call's budget, then ``into.rx_ns`` = the
        kernel's stamp of the record kept (the newest, when draining) if it had one."""
        self._begin_receive()
        if not super()._receive(into, timeout_s):
            return False
        if self._arrival_ns:
            into.rx_ns = self._arrival_ns
        return True

    def _close(self) -> None:
        if self._flood is not None:
            self._flood.close()
        self._sock.close()

    def _fileno(self) -> int:
        return self._sock.fileno()
