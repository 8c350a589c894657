"""A UDP device endpoint's socket calls in compiled code, for the emulator's compiled
steady loop (issue 29): the datagrams read, the answer sent and the endpoint's books kept
as its Python path keeps them, without the interpreter.

:func:`receive` reads the datagrams queued for a tick with non-blocking ``recvmsg``
calls (the C library's, reached by name as the tick reaches ``clock_gettime``), up to
:data:`MAX_QUEUED` and within the endpoint's receive budget
(:attr:`~io_adapters.udp.UdpEndpoint.rx_budget`), each with the kernel's receive stamp
(``SO_TIMESTAMPNS``, converted to the monotonic clock with the endpoint's measured
offset) and its sender's address, compared byte for byte with the pinned peer's.  It
offers them to the compiled tick only in the common cases: every datagram from the peer
(the newest is applied, the older ones are taken and superseded, as the endpoint's drain
does), or none (a silent tick).  A stranger's datagram that the endpoint would not
decode (its first byte cannot start a HELLO: :meth:`~io_adapters.udp.UdpEndpoint.
_may_be_hello`) is counted foreign there and then, as the endpoint counts it, and its
buffer reused.  Anything else -- more than :data:`MAX_QUEUED`, the budget spent with
datagrams still queued (a peek says so), a stranger's datagram that may be a HELLO, a
receive error -- and any datagrams the compiled tick then declines are handed back to
the endpoint (:meth:`SteadyLink.hand_back`), whose next receives return them first and
go on within what is left of the same budget, so the Python path counts, judges and
takes them exactly as if the compiled code had never looked.

After a tick that took them, :func:`take` counts them as
:meth:`~io_adapters.msgpack_endpoint.MsgpackEndpoint._accept` and the drain would
(frames, bytes, lost, received, drained; the peer's frame and last-heard time); after a
silent one, :func:`idle` counts the empty receive.  :func:`send` sends the answer the
compiled tick encoded in ``out`` to the endpoint's peer, counted as ``send_feedback``
counts it (the endpoint's frame number advanced; no room: ``send_dropped``).  The counts
go into ``books`` (:data:`BOOKS`, deltas), and :meth:`SteadyLink.settle` adds them to the
endpoint's :class:`~io_adapters.base.AdapterStats` and writes its peer's frame, last
heard time, own frame number and setpoint stamps, after every call of compiled code and
before anything in Python reads them.

The C structures are flat int64 words (LP64 Linux: x86-64, AArch64): ``hdr`` a
``struct msghdr``, ``iov`` a ``struct iovec``, ``ctrl`` the ancillary buffer (one
``cmsghdr`` and a ``timespec``).
"""

import errno
import ipaddress
import os
import socket
import sys
import time

import numpy as np
from numba import njit, types

from io_adapters.base import AdapterConfigError, AdapterError, Role
from io_adapters.codec import U32
from io_adapters.codec_compiled import (
    F_FRAME,
    F_SESSION,
    F_SP_RX_NS,
    F_SP_T_NS,
    MAX_AXES,
    N_FB_INTS,
    N_SP_INTS,
)
from io_adapters.udp import MAX_DATAGRAM, SO_TIMESTAMPNS, UdpEndpoint

#: datagrams one compiled tick takes at most (more queued: the Python tick drains them)
MAX_QUEUED = 64
#: ``link``: the pinned peer's session and last frame number, the newest datagram's
#: arrival (monotonic ns: the kernel's stamp, else when it was read), two words of room
#: for the compiled code's clock readings (a struct timespec); the socket, the receive
#: budget of a tick, what the last receive left of it, kernel stamps on (1/0), realtime
#: minus monotonic (ns), the datagrams the last receive read and kept (handed back on a
#: decline), a receive error's errno, a send error's errno, when the peer was last heard
#: (monotonic ns), the foreign datagrams the last receive counted, the peer's and the
#: answer's address lengths (0: nobody to send to); then per datagram read, oldest first:
#: its length, (written by the compiled tick) its frame number, its kernel stamp, its
#: sender's address length
(L_PEER_SESSION, L_PEER_FRAME, L_RX_NS, L_CLOCK, _L_CLOCK_2, L_FD, L_BUDGET, L_LEFT,
 L_STAMPS_ON, L_OFFSET, L_N, L_ERRNO, L_SEND_ERRNO, L_HEARD_NS, L_FOREIGN, L_PEER_LEN,
 L_SEND_LEN, L_LENGTHS) = range(18)
L_FRAMES = L_LENGTHS + MAX_QUEUED
L_STAMPS = L_FRAMES + MAX_QUEUED
L_NAME_LENS = L_STAMPS + MAX_QUEUED
N_LINK = L_NAME_LENS + MAX_QUEUED
#: the endpoint's counters :func:`take`, :func:`idle`, :func:`receive` and :func:`send`
#: keep (:class:`~io_adapters.base.AdapterStats` names), in ``books`` in this order
BOOKS = ("frames", "bytes_received", "received", "drained", "lost", "timeouts", "foreign",
         "sent", "bytes_sent", "send_dropped")
(B_FRAMES, B_BYTES, B_RECEIVED, B_DRAINED, B_LOST, B_TIMEOUTS, B_FOREIGN, B_SENT,
 B_BYTES_SENT, B_SEND_DROPPED) = range(len(BOOKS))
#: room for one encoded Feedback or FeedbackGroup (at most 64 + 54 per axis bytes)
OUT_BYTES = 1024
#: room for a sender's address (a sockaddr_in6 is 28 bytes)
NAME_BYTES = 32
#: ``struct msghdr`` words: name, name length, iov, iov count, control, control length,
#: flags
H_NAME, H_NAME_LEN, H_IOV, H_IOV_LEN, H_CONTROL, H_CONTROL_LEN, H_FLAGS, N_HDR = range(8)
#: the ancillary buffer, int64 words: cmsg_len, level | type << 32, tv_sec, tv_nsec
N_CTRL = 8
_STAMP_HEAD = socket.SOL_SOCKET | ((SO_TIMESTAMPNS or 0) << 32)
_MSG_DONTWAIT, _MSG_PEEK = socket.MSG_DONTWAIT, socket.MSG_PEEK
_EAGAIN, _ENOBUFS = errno.EAGAIN, errno.ENOBUFS
#: the compiled loop runs where these structures are as written above
AVAILABLE = sys.platform == "linux" and sys.maxsize == 2 ** 63 - 1

_recvmsg = types.ExternalFunction("recvmsg",
                                  types.int64(types.int32, types.voidptr, types.int32))
_recv = types.ExternalFunction("recv", types.int64(types.int32, types.voidptr, types.uint64,
                                                   types.int32))
_sendto = types.ExternalFunction("sendto", types.int64(types.int32, types.voidptr,
                                                       types.uint64, types.int32,
                                                       types.voidptr, types.uint32))
_errno_location = types.ExternalFunction("__errno_location", types.CPointer(types.int32)())
_clock_gettime = types.ExternalFunction("clock_gettime",
                                        types.int32(types.int32, types.voidptr))
CLOCK_MONOTONIC = time.CLOCK_MONOTONIC


@njit(cache=True, inline="always")
def monotonic_ns(timespec):
    """``CLOCK_MONOTONIC`` in ns (``time.monotonic_ns``'s clock); ``timespec``: two
    int64 words of room."""
    _clock_gettime(CLOCK_MONOTONIC, timespec.ctypes)
    return timespec[0] * 1_000_000_000 + timespec[1]


@njit(cache=True, inline="always")
def _same_address(names, i, n_name, peer_name, n_peer):
    if n_name != n_peer:
        return False
    for b in range(n_name):
        if names[i, b] != peer_name[b]:
            return False
    return True


@njit(cache=True, inline="always")
def _stamp(ctrl, hdr, link):
    """The kernel's receive stamp of the datagram just read, monotonic ns; 0: none."""
    if link[L_STAMPS_ON] and hdr[H_CONTROL_LEN] >= 32 and ctrl[1] == _STAMP_HEAD:
        return ctrl[2] * 1_000_000_000 + ctrl[3] - link[L_OFFSET]
    return 0


@njit(cache=True)
def receive(link, bufs, hdr, iov, slots, name_slots, names, ctrl, peer_name, hello_leads,
            peek, books):
    """Read one tick's datagrams (module docstring) into ``bufs`` (``slots``,
    ``name_slots``: the addresses of ``bufs``' and ``names``' rows); how many, all the
    peer's, for the compiled tick to take (0: none came); -1: the Python path's, handed
    back by :meth:`SteadyLink.hand_back` (``link[L_N]`` datagrams kept, then the
    receive error ``link[L_ERRNO]`` if any)."""
    left, i, declined = link[L_BUDGET], 0, False
    fd = link[L_FD]
    link[L_ERRNO] = link[L_FOREIGN] = 0
    while left > 0:
        if i == MAX_QUEUED:
            declined = True
            break
        iov[0] = slots[i]
        iov[1] = MAX_DATAGRAM
        hdr[H_NAME] = name_slots[i]
        hdr[H_NAME_LEN] = NAME_BYTES
        hdr[H_CONTROL_LEN] = N_CTRL * 8
        hdr[H_FLAGS] = 0
        n = _recvmsg(fd, hdr.ctypes, _MSG_DONTWAIT)
        if n < 0:
            e = _errno_location()[0]
            if e != _EAGAIN:
                left -= 1
                link[L_ERRNO] = e
                declined = True
            break
        left -= 1
        n_name = hdr[H_NAME_LEN] & U32
        if not _same_address(names, i, n_name, peer_name, link[L_PEER_LEN]):
            if n > 0 and hello_leads[bufs[i, 0]]:
                declined = True  # the endpoint decodes it: a HELLO may take the link over
            else:  # foreign at once, as the endpoint counts it; the slot is reused
                books[B_FRAMES] += 1
                books[B_BYTES] += n
                books[B_FOREIGN] += 1
                link[L_FOREIGN] += 1
                continue
        link[L_LENGTHS + i] = n
        link[L_STAMPS + i] = _stamp(ctrl, hdr, link)
        link[L_NAME_LENS + i] = n_name
        i += 1
        if declined:
            break
    if not declined and left <= 0 and _recv(fd, peek.ctypes, 1, _MSG_DONTWAIT | _MSG_PEEK) >= 0:
        declined = True  # the budget spent with datagrams queued: the endpoint counts it
    link[L_LEFT] = left
    link[L_N] = i
    if declined:
        return -1
    if i:
        stamp = link[L_STAMPS + i - 1]
        link[L_RX_NS] = stamp if stamp else monotonic_ns(link[L_CLOCK:])
    return i


@njit(cache=True, inline="always")
def take(link, n, books):
    """Count the ``n`` datagrams a compiled tick took (their frame numbers in
    ``link[L_FRAMES:]``, each 1 to MAX_DROPOUT after the one before)."""
    for i in range(n):
        books[B_FRAMES] += 1
        books[B_BYTES] += link[L_LENGTHS + i]
        books[B_RECEIVED] += 1
        frame = link[L_FRAMES + i]
        books[B_LOST] += ((frame - link[L_PEER_FRAME]) & U32) - 1
        link[L_PEER_FRAME] = frame
    books[B_DRAINED] += n - 1
    link[L_N] = 0
    link[L_HEARD_NS] = monotonic_ns(link[L_CLOCK:])


@njit(cache=True, inline="always")
def idle(books):
    """Count a tick's receive that found nothing, as ``recv_setpoint`` counts it."""
    books[B_TIMEOUTS] += 1


@njit(cache=True, inline="always")
def send(link, out, n_out, head, send_name, books):
    """Send the record ``out[:n_out]`` to the peer (``n_out`` 0: none was encoded), its
    session and frame number in ``head[0]`` and ``head[1]`` (an answer's ``fb_ints``, a
    setpoint's ``sp_ints``: the frame advanced when sent); 0, or -1 after a send error
    other than no room (``link[L_SEND_ERRNO]``: the caller's Python raises it)."""
    if n_out <= 0 or link[L_SEND_LEN] == 0:
        return 0
    if _sendto(link[L_FD], out.ctypes, n_out, _MSG_DONTWAIT, send_name.ctypes,
               link[L_SEND_LEN]) < 0:
        e = _errno_location()[0]
        if e == _EAGAIN or e == _ENOBUFS:
            books[B_SEND_DROPPED] += 1
            return 0
        link[L_SEND_ERRNO] = e
        return -1
    books[B_BYTES_SENT] += n_out
    books[B_SENT] += 1
    head[F_FRAME] = (head[F_FRAME] + 1) & U32
    return 0


def sockaddr(address: tuple, family: int) -> bytes:
    """``address`` as the kernel writes it into a ``struct sockaddr_in`` or
    ``sockaddr_in6`` (what ``recvmsg`` gives as the sender's)."""
    port = address[1].to_bytes(2, "big")
    if family == socket.AF_INET:
        return (socket.AF_INET.to_bytes(2, sys.byteorder) + port
                + socket.inet_pton(socket.AF_INET, address[0]) + bytes(8))
    flow, scope = (address[2], address[3]) if len(address) >= 4 else (0, 0)
    host = address[0].split("%")[0]
    return (socket.AF_INET6.to_bytes(2, sys.byteorder) + port
            + flow.to_bytes(4, "big") + socket.inet_pton(socket.AF_INET6, host)
            + scope.to_bytes(4, sys.byteorder))


def address_of(name: bytes) -> tuple:
    """The (host, port[, flowinfo, scope_id]) tuple Python's ``recvmsg`` gives for the
    sender's address ``name``."""
    family = int.from_bytes(name[:2], sys.byteorder)
    port = int.from_bytes(name[2:4], "big")
    if family == socket.AF_INET:
        return str(ipaddress.IPv4Address(name[4:8])), port
    return (socket.inet_ntop(socket.AF_INET6, name[8:24]), port,
            int.from_bytes(name[4:8], "big"), int.from_bytes(name[24:28], sys.byteorder))


class SteadyLink:
    """The compiled code's face of the UDP endpoint ``endpoint`` of a machine of
    ``n_axes`` axes (see the module docstring): a device, which reads setpoints and
    answers with feedback, or a controller, which reads feedback and sends setpoints (a
    stranger's datagram is foreign to it, whatever its first byte).

    Attributes:
        bufs: uint8[:data:`MAX_QUEUED`, MAX_DATAGRAM], the datagrams :func:`receive`
            read, oldest first (``link[L_LENGTHS + i]`` bytes of row i).
        sp_ints, axis_ints, sp_floats: the compiled reader's output arrays
            (:func:`io_adapters.codec_compiled.decode_setpoint`).
        link: int64[:data:`N_LINK`] (layout above).
        books: int64[len(:data:`BOOKS`)], the counts since the last :meth:`settle`.
        fb_ints, fb_axis_ints, fb_floats: the feedback's values
            (:mod:`io_adapters.codec_compiled` layout): a device's answer, a controller's
            feedback read.
        head: the record sent's ints (a device's ``fb_ints``, a controller's
            ``sp_ints``): its session and frame written by :meth:`prepare`, the frame
            advanced by :func:`send`.
        out: uint8[:data:`OUT_BYTES`], the encoded record sent.
        hdr, iov, slots, name_slots, names, ctrl, peer_name, send_name, hello_leads,
            peek: the C structures and buffers :func:`receive` and :func:`send` use.
    """

    def __init__(self, endpoint: UdpEndpoint, n_axes: int = 1):
        if not isinstance(endpoint, UdpEndpoint):
            raise AdapterConfigError(f"{endpoint!r}: a compiled tick needs a UDP endpoint")
        if not 1 <= n_axes <= MAX_AXES:
            raise AdapterConfigError(f"a compiled tick takes 1 to {MAX_AXES} axes, not "
                                     f"{n_axes}")
        self.endpoint = endpoint
        self.bufs = np.zeros((MAX_QUEUED, MAX_DATAGRAM), np.uint8)
        self.sp_ints = np.zeros(N_SP_INTS, np.int64)
        self.axis_ints = np.zeros((n_axes, 2), np.int64)
        self.sp_floats = np.zeros((n_axes, 7))
        self.link = np.zeros(N_LINK, np.int64)
        self.books = np.zeros(len(BOOKS), np.int64)
        self.fb_ints = np.zeros(N_FB_INTS, np.int64)
        self.fb_axis_ints = np.zeros((n_axes, 2), np.int64)
        self.fb_floats = np.zeros((n_axes, 6))
        self.out = np.zeros(OUT_BYTES, np.uint8)
        self.names = np.zeros((MAX_QUEUED, NAME_BYTES), np.uint8)
        self.hdr = np.zeros(N_HDR, np.int64)
        self.iov = np.zeros(2, np.int64)
        self.ctrl = np.zeros(N_CTRL, np.int64)
        self.hdr[H_IOV], self.hdr[H_IOV_LEN] = self.iov.ctypes.data, 1
        self.hdr[H_CONTROL] = self.ctrl.ctypes.data
        self.slots = self.bufs.ctypes.data + MAX_DATAGRAM * np.arange(MAX_QUEUED,
                                                                      dtype=np.int64)
        self.name_slots = self.names.ctypes.data + NAME_BYTES * np.arange(MAX_QUEUED,
                                                                          dtype=np.int64)
        self.peer_name = np.zeros(NAME_BYTES, np.uint8)
        self.send_name = np.zeros(NAME_BYTES, np.uint8)
        self.hello_leads = np.zeros(256, np.uint8)
        self.device = endpoint.role is Role.DEVICE
        if self.device:  # a controller counts every stranger's datagram foreign
            self.hello_leads[list(endpoint.wire.hello_leads)] = 1
        self.head = self.fb_ints if self.device else self.sp_ints
        self.peek = np.zeros(1, np.uint8)
        self.link[L_FD] = endpoint._sock.fileno()
        self.link[L_STAMPS_ON] = endpoint._clock is not None
        self._family = endpoint._sock.family
        self._peer = self._send_to = None  # the addresses written into the arrays

    def ready(self) -> bool:
        """The compiled code may read: nothing handed back still waiting in the endpoint;
        a controller welcomed by its drive (a device without a peer yet takes no
        setpoint compiled: every datagram is a stranger's)."""
        ep = self.endpoint
        return not ep._stash and (self.device or (ep._peer_session is not None
                                                  and ep.welcomed))

    def prepare(self) -> None:
        """Before a call of compiled code: the endpoint's state into the arrays (its peer,
        budget, frame numbers, the clock offset of its kernel stamps), and a flood
        episode's watch, as a receive call starts it (once per call: a call of several
        ticks watches at its start, at most ``hil.runtime.steady_tick.BURST_S`` apart)."""
        ep, link = self.endpoint, self.link
        flood = ep._flood
        if flood is not None and flood.active:
            now = time.monotonic_ns()
            flood.watch(now, ep._peer_origin, ep._peer_fresh(now))
        if ep._peer_origin != self._peer:
            self._peer = ep._peer_origin
            name = sockaddr(self._peer, self._family) if self._peer is not None else b""
            self.peer_name[:len(name)] = np.frombuffer(name, np.uint8)
            link[L_PEER_LEN] = len(name)
        to = ep.peer
        if to != self._send_to:
            self._send_to = to
            name = sockaddr(to, self._family) if to is not None else b""
            self.send_name[:len(name)] = np.frombuffer(name, np.uint8)
            link[L_SEND_LEN] = len(name)
        if ep._clock is not None:  # measured again when a second old, as _kernel_ns does
            clock = ep._clock
            clock.monotonic_ns(time.clock_gettime_ns(time.CLOCK_REALTIME))
            link[L_OFFSET] = clock.offset_ns
        link[L_BUDGET] = ep.rx_budget if ep.rx_budget is not None else sys.maxsize
        link[L_PEER_SESSION] = ep._peer_session if ep._peer_session is not None else -1
        link[L_PEER_FRAME] = ep._peer_frame
        link[L_HEARD_NS] = ep._heard_ns
        self.head[F_SESSION] = ep.session
        self.head[F_FRAME] = ep._frame

    def settle(self, took: bool) -> None:
        """After a call of compiled code: the counts and states it kept into the endpoint
        (``took``: it took a setpoint or ran a silent tick, which ends the receive's
        refused axes)."""
        ep, link, books = self.endpoint, self.link, self.books
        st = ep.stats
        for k, name in enumerate(BOOKS):
            if books[k]:
                setattr(st, name, getattr(st, name) + int(books[k]))
        books.fill(0)
        ep._frame = int(self.head[F_FRAME])
        if took:
            ep.refused_axes = 0
        if ep._peer_frame != link[L_PEER_FRAME]:
            ep._peer_frame = int(link[L_PEER_FRAME])
            ep._after_jump = None
            if self.device:
                ep._heard_ns = int(link[L_HEARD_NS])
                ep._sp_t_ns = int(self.fb_ints[F_SP_T_NS])
                ep._sp_rx_ns = int(self.fb_ints[F_SP_RX_NS])

    def hand_back(self) -> None:
        """Hand the datagrams the last :func:`receive` read (and its receive error) back
        to the endpoint, whose next receive goes on within the same budget."""
        ep, link = self.endpoint, self.link
        ep._continued = True
        ep._left = int(link[L_LEFT])
        ep._foreign_at = ep.stats.foreign - int(link[L_FOREIGN])
        ep._hello_looked = False
        for i in range(int(link[L_N])):
            n, n_name = int(link[L_LENGTHS + i]), int(link[L_NAME_LENS + i])
            name = self.names[i, :n_name].tobytes()
            origin = (ep._peer_origin if name == self.peer_name[:n_name].tobytes()
                      else address_of(name))
            ep._stash.append((n, origin, int(link[L_STAMPS + i]), self.bufs[i, :n].tobytes()))
        if link[L_ERRNO]:
            e = int(link[L_ERRNO])
            ep._stash.append(OSError(e, os.strerror(e)))
        link[L_N] = link[L_ERRNO] = 0

    def send_error(self) -> AdapterError:
        """The error of a send that failed otherwise than for room (``link[L_SEND_ERRNO]``),
        as ``send_feedback`` raises it."""
        e = int(self.link[L_SEND_ERRNO])
        self.link[L_SEND_ERRNO] = 0
        return AdapterError(f"{self.endpoint!r}: send failed: [Errno {e}] {os.strerror(e)}")
