"""A UDP device's defence against a flood of datagrams: a socket filter that lets only
the pinned controller's datagrams into the socket while a flood lasts.

The endpoint reads at most its receive budget of datagrams a call
(:attr:`io_adapters.udp.UdpEndpoint.rx_budget`) and leaves the rest in the socket.  A call
that stops at the budget with datagrams still queued starts a flood *episode*
(:class:`FloodGuard`, a notice); if strangers' datagrams were among those it read and the
pinned controller has been heard within ``takeover_ms``, the socket gets a classic BPF
filter (``SO_ATTACH_FILTER``) admitting datagrams from the controller's address and port
only: the kernel drops everything else before it is queued, so the controller's
datagrams no longer wait behind the flood, nor are they dropped for a receive buffer it
filled, and the loop reads nothing of it.  While the filter is on a stranger's HELLO
cannot get in either, so the filter comes off as soon as the pinned controller has been
silent for ``takeover_ms`` (the budget alone bounds the work from then on).  Every
:data:`FLOOD_CHECK_NS` the episode reads the kernel's drop count of the socket
(``SO_MEMINFO``: the filter's drops and a full buffer's, counted in ``stats.rx_dropped``,
read again when the socket closes); an interval with no drop and no call stopped at the
budget ends it (the filter off, a notice with the totals).

Where the kernel has no such filter (not Linux) or refuses it, the budget still bounds
the work; the episode says so.
"""

import ctypes
import socket
import struct
import sys
import time

from io_adapters.base import AdapterStats

#: Linux's SO_ATTACH_FILTER, SO_DETACH_FILTER and SO_MEMINFO (asm-generic/socket.h, as
#: io_adapters.udp's SO_TIMESTAMPNS); None: no socket filter on this platform
SO_ATTACH_FILTER, SO_DETACH_FILTER, SO_MEMINFO = (
    (26, 27, 55) if sys.platform == "linux" else (None, None, None))
#: SO_MEMINFO's u32 values (linux/sock_diag.h): SK_MEMINFO_DROPS is the ninth
MEMINFO = struct.Struct("@9I")
#: how often an episode counts the kernel's drops and looks whether the flood is over, ns
FLOOD_CHECK_NS = 100_000_000
#: classic BPF (linux/filter.h): a program is a list of (code, jt, jf, k)
_INSN = struct.Struct("@HBBI")
_LD_W_ABS, _LD_H_ABS, _LD_B_ABS = 0x20, 0x28, 0x30
_ALU_AND_K, _JEQ_K, _RET_K = 0x54, 0x15, 0x06
#: where a socket filter finds the network header (SKF_NET_OFF); offset 0 is the UDP
#: header, whose first half-word is the source port
_NET = -0x100000


def peer_program(peer: tuple) -> bytes:
    """The classic BPF program admitting datagrams from ``peer`` (a socket address:
    (host, port) or IPv6's (host, port, flow, scope)) and dropping every other one.

    An IPv4 peer (or an IPv4-mapped address on an IPv6 socket, whose datagrams come in
    IPv4 packets) is compared with the IPv4 header's source address, an IPv6 peer with
    the IPv6 header's; both after checking the header's version, then the source port."""
    address = socket.inet_pton(socket.AF_INET6, peer[0].partition("%")[0]) if ":" in peer[0] \
        else socket.inet_pton(socket.AF_INET, peer[0])
    if len(address) == 16 and address[:12] == b"\0" * 10 + b"\xff\xff":
        address = address[12:]  # IPv4-mapped: an IPv4 packet
    if len(address) == 4:
        version, source = 0x40, (_NET + 12,)
    else:
        version, source = 0x60, tuple(_NET + 8 + 4 * i for i in range(4))
    words = struct.unpack(f"!{len(address) // 4}I", address)
    checks = [(_LD_B_ABS, _NET), (_ALU_AND_K, 0xF0), (_JEQ_K, version)]
    for offset, word in zip(source, words):
        checks += [(_LD_W_ABS, offset), (_JEQ_K, word)]
    checks += [(_LD_H_ABS, 0), (_JEQ_K, peer[1])]
    program, n = [], len(checks)
    for i, check in enumerate(checks):
        code, k = check[0], check[1]
        # a failed comparison jumps to the last instruction (drop), past "accept"
        jf = n - i if code == _JEQ_K else 0
        program.append(_INSN.pack(code, 0, jf, k & 0xFFFFFFFF))
    program += [_INSN.pack(_RET_K, 0, 0, 0xFFFFFFFF), _INSN.pack(_RET_K, 0, 0, 0)]
    return b"".join(program)


def attach(sock: socket.socket, program: bytes) -> None:
    """Give ``sock`` the classic BPF ``program`` (the kernel copies it); raises OSError."""
    if SO_ATTACH_FILTER is None:
        raise OSError("socket filters are Linux's")
    code = ctypes.create_string_buffer(program, len(program))
    fprog = struct.pack("@HP", len(program) // _INSN.size, ctypes.addressof(code))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)


def kernel_drops(sock: socket.socket) -> int | None:
    """The kernel's count of datagrams dropped at ``sock`` (its filter, a full receive
    buffer), u32 wrapping; None where it cannot be read."""
    if SO_MEMINFO is None:
        return None
    try:
        return MEMINFO.unpack(sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO,
                                              MEMINFO.size))[8]
    except OSError:
        return None


class FloodGuard:
    """The flood episodes of one UDP device socket (see the module docstring).

    Args:
        sock: the device's socket.
        stats: the endpoint's counters (``rx_dropped`` is counted here).
        notice: the endpoint's ``_notice(kind, text)``.
    """

    def __init__(self, sock: socket.socket, stats: AdapterStats, notice):
        self._sock, self._stats, self._notice = sock, stats, notice
        self.active = False
        self.filtering: tuple | None = None  # the peer the filter admits (None: no filter)
        self._started_ns = self._check_ns = 0
        self._limited = self._limited_seen = 0
        self._dropped_at_start = 0
        self._drops_seen = kernel_drops(sock) or 0

    def limited(self, now_ns: int, budget: int, peer: tuple | None, peer_fresh: bool,
                strangers: bool) -> None:
        """A receive call stopped at its ``budget`` with datagrams still queued, having
        read strangers' datagrams or not: start an episode, and filter out all but
        ``peer`` if strangers flood it while it is ``peer_fresh`` (heard within
        ``takeover_ms``)."""
        self._limited += 1
        if not self.active:
            self.active = True
            self._started_ns, self._check_ns = now_ns, now_ns + FLOOD_CHECK_NS
            self._count_drops()  # those of before (a stall's full buffer) are not its own
            self._limited_seen, self._dropped_at_start = 0, self._stats.rx_dropped
            among = ", strangers' among them" if strangers else ""
            self._notice("receive budget met", f"a receive call met its budget of "
                         f"{budget} datagrams with more queued{among}: the rest waits in "
                         "the socket for the next calls")
        if self.filtering is None and strangers and peer_fresh and peer is not None:
            self._filter(peer)

    def watch(self, now_ns: int, peer: tuple | None, peer_fresh: bool) -> None:
        """At the start of each receive call during an episode: the filter off once the
        pinned peer has gone silent (or changed); every :data:`FLOOD_CHECK_NS` the
        kernel's drops counted, and the episode ended after an interval without drops
        or calls stopped at the budget."""
        if self.filtering is not None and (not peer_fresh or peer != self.filtering):
            self._unfilter("the pinned controller fell silent: a new one's HELLO may come")
        if now_ns < self._check_ns:
            return
        dropped = self._count_drops()
        quiet = not dropped and self._limited == self._limited_seen
        self._limited_seen, self._check_ns = self._limited, now_ns + FLOOD_CHECK_NS
        if quiet:
            self.end(now_ns)

    def end(self, now_ns: int) -> None:
        """End the episode (the filter off, a notice with its totals)."""
        if not self.active:
            return
        if self.filtering is not None:
            self._unfilter(None)
        self.active = False
        self._count_drops()
        self._notice("receive within budget again", f"after "
                     f"{(now_ns - self._started_ns) * 1e-9:.2f} s: "
                     f"{self._limited} receive call(s) met the budget, "
                     f"{self._stats.rx_dropped - self._dropped_at_start} datagram(s) "
                     "dropped by the kernel")
        self._limited = 0

    def _filter(self, peer: tuple) -> None:
        try:
            attach(self._sock, peer_program(peer))
        except OSError as e:
            self._notice("flood filter refused", f"the kernel refused the socket filter "
                         f"({e}): the receive budget alone bounds the work")
            return
        self.filtering = peer
        self._notice("flood filter on", f"the kernel now drops every datagram but the "
                     f"pinned controller's ({peer[0]} port {peer[1]})")

    def _unfilter(self, why: str | None) -> None:
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
        except OSError:
            pass  # a closed socket: nothing left to filter
        self.filtering = None
        if why is not None:
            self._notice("flood filter off", why)

    def _count_drops(self) -> int:
        """Add the kernel's drops since the last reading to ``stats.rx_dropped``; how
        many."""
        drops = kernel_drops(self._sock)
        if drops is None:
            return 0
        new = (drops - self._drops_seen) & 0xFFFFFFFF
        self._drops_seen = drops
        self._stats.rx_dropped += new
        return new

    def close(self) -> None:
        """Before the socket closes: the episode ended, the last drops counted."""
        if self.active:
            self.end(time.monotonic_ns())
        else:
            self._count_drops()
