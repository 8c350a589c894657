"""The contract every adapter fills: exceptions, statistics, and the abstract :class:`Endpoint`.

An endpoint is one side of the link.  The *device* side (the emulator) receives
:class:`~io_adapters.messages.Setpoint` records and answers with
:class:`~io_adapters.messages.Feedback`; the *controller* side does the reverse.
The public methods here do the bookkeeping common to every transport (role and
closed checks, timeouts, draining stale records, timestamps, statistics,
translating ``OSError`` into :class:`AdapterError`) and call a few private hooks
that a backend fills, as python-can's ``BusABC`` does:

* ``_write(record) -> bool``: send one record without waiting for room; False if there
  is nobody to send to yet or the transport has no room (counted in
  ``stats.send_dropped``).
* ``_read(into, timeout_s) -> bool``: wait up to ``timeout_s`` (None: forever) for
  one good record and write it into ``into``; a malformed frame is counted in
  :attr:`Endpoint.stats` and dropped, never raised; a setpoint that
  :attr:`Endpoint.setpoint_bounds` refuses is counted (:meth:`Endpoint._refuse`) and
  dropped whole, ``into`` untouched.
* ``_close()``: release the transport (called once).
* ``_fileno()``: optional, the file descriptor a loop can ``select``/``poll`` on.

Byte transports (UDP, serial) share
:class:`io_adapters.msgpack_endpoint.MsgpackEndpoint`, which fills ``_write``/``_read``
and leaves them byte-level hooks; a transport that maps records onto its own frames
(CAN PDOs) subclasses :class:`Endpoint` directly.  Endpoints are not thread-safe: use
each from one thread.
"""

import io
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from urllib.parse import parse_qsl

from io_adapters.messages import (
    REFUSED_MODE,
    REFUSED_NONFINITE,
    REFUSED_RANGE,
    Feedback,
    InjectRequest,
    Setpoint,
    SetpointBounds,
)

#: :meth:`Endpoint.link_conditions` bits: conditions of the link itself that the drive
#: reacts to
LINK_HEARTBEAT_LOST = 1  # the controller's heartbeat is overdue
LINK_STOPPED = 2         # the controller stopped the node's communication
LINK_RESET = 4           # the controller reset the node (an event, reported once)

#: notices an endpoint keeps for its caller (:attr:`Endpoint.notices`); later ones are
#: dropped until the caller takes them (the counters keep the count)
MAX_NOTICES = 64

_REFUSAL_COUNTERS = {REFUSED_NONFINITE: "refused_nonfinite", REFUSED_MODE: "refused_mode",
                     REFUSED_RANGE: "refused_range"}


class AdapterError(Exception):
    """Base of every error an adapter raises."""


class AdapterConfigError(AdapterError, ValueError):
    """A bad URL, option or registry entry (raised when opening, never in the loop)."""


class AdapterTimeout(AdapterError, TimeoutError):
    """The transport could not complete an operation in time (the built-in transports
    never wait for a peer: a send without room is dropped and counted instead)."""


class AdapterClosed(AdapterError, ConnectionError):
    """The endpoint is closed, or the transport under it has gone."""


class FrameError(AdapterError, ValueError):
    """A frame or record that cannot be encoded or decoded.  Receiving endpoints count
    and drop such frames; only encoding a bad record raises it to the caller."""


class Role(str, Enum):
    """Which side of the link an endpoint is."""
    DEVICE = "device"          #: the drive (emulator): receives setpoints, sends feedback
    CONTROLLER = "controller"  #: the CNC: sends setpoints, receives feedback


@dataclass(slots=True)
class AdapterStats:
    """Counters of one endpoint since it was opened (frames are whole messages).

    On the msgpack transports (UDP, serial) the counters of received frames add up::

        frames == received + malformed + refused_nonfinite + refused_mode + refused_range
                  + duplicates + out_of_order + foreign + stale_session + handshakes
                  + injections

    every frame counted in exactly one of them (a refused message in its reason's counter
    only, a drained record in ``received`` too).

    Attributes:
        frames: every message that reached the decoder: each datagram, whoever sent it;
            on serial each candidate frame after a start of frame, good CRC or not.
        sent: records sent (handshake messages are not records).
        received: good records accepted, including those superseded by draining.
        drained: accepted records overwritten by a newer one in the same ``recv_*`` call.
        timeouts: ``recv_*`` calls that returned False.
        malformed: frames dropped because they did not decode (bad CRC, bad msgpack,
            wrong version, kind, length, type or range).
        refused_nonfinite: well-formed messages dropped for a NaN or infinite value in a
            float field (setpoints and feedback).
        refused_mode: setpoints dropped for a mode of operation the drive does not take
            (:attr:`Endpoint.setpoint_bounds`).
        refused_range: setpoints dropped for a value beyond the drive's bound.
        duplicates: frames dropped because they repeated the last sequence number.
        out_of_order: frames dropped because they were older than the last accepted one,
            or jumped far from it (msgpack transports: the sequence rule of
            :mod:`io_adapters.msgpack_endpoint`).
        lost: frames missing between accepted sequence numbers.
        resyncs: times the sequence check followed the peer's frame numbers after a jump
            (msgpack transports; not a frame counter).
        peer_restarts: times the peer's session changed (the device: a handshake took the
            link over for a new session; the controller: the device was reopened).
        foreign: frames dropped because they came from someone other than the peer (a
            datagram from another address, or one outside the loopback network without
            ``allow_remote``), including a handshake the device refused.
        stale_session: frames dropped because they came from the peer's address with
            another session than the one the device is pinned to (not a handshake).
        handshakes: handshake messages taken: a HELLO the device accepted, a WELCOME the
            controller received.
        injections: fault-injection requests the device took (well-formed, from its peer;
            :attr:`Endpoint.injections`).
        send_dropped: messages not sent because the transport had no room (a full socket
            buffer, a serial peer that does not read): the loop never waits for a peer.
        rx_limited: receive calls that stopped at the endpoint's receive budget with
            datagrams still queued (UDP: :attr:`io_adapters.udp.UdpEndpoint.rx_budget`).
        rx_dropped: datagrams the kernel dropped at the socket before the endpoint read
            them: the flood filter's, and those a full receive buffer had no room for (UDP
            device, read during a flood and when it closes; not in ``frames``).
        bytes_sent, bytes_received: encoded message bytes, transport framing excluded.
        bytes_skipped: stream bytes discarded while looking for a start of frame.
    """
    frames: int = 0
    sent: int = 0
    received: int = 0
    drained: int = 0
    timeouts: int = 0
    malformed: int = 0
    refused_nonfinite: int = 0
    refused_mode: int = 0
    refused_range: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    lost: int = 0
    resyncs: int = 0
    peer_restarts: int = 0
    foreign: int = 0
    stale_session: int = 0
    handshakes: int = 0
    injections: int = 0
    send_dropped: int = 0
    rx_limited: int = 0
    rx_dropped: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    bytes_skipped: int = 0


class Endpoint(ABC):
    """One side of a controller <-> drive link.

    Args:
        role: ``Role.DEVICE``/"device" or ``Role.CONTROLLER``/"controller".
        drain: if true, every ``recv_*`` that gets a record also takes every record
            already waiting behind it, so the caller always works on the newest one
            (the skipped ones are counted in ``stats.drained``).

    Attributes:
        refused_axes: device side, a bit mask: bit ``a`` set when a setpoint (or axis
            ``a``'s record of a group message) was refused during the last
            :meth:`recv_setpoint` call (cleared at the start of each call).
        injections: device side, the fault-injection requests received
            (:class:`~io_adapters.messages.InjectRequest`), in order; the caller takes
            them and clears the list.
        notices: what the link noticed that its counters alone do not tell (a flood
            held off, frame numbers resynchronised), as (kind, text) pairs in order,
            each kind at most a few a second; the caller takes them and clears the list.
    """

    def __init__(self, role: Role | str, *, drain: bool = False):
        self.role = Role(role)
        self.drain = drain
        self.stats = AdapterStats()
        self.refused_axes = 0
        self.injections: list[InjectRequest] = []
        self.notices: list[tuple[str, str]] = []
        self._setpoint_bounds = (SetpointBounds(),)
        self._closed = False
        self._sp_t_ns = 0   # device side: t_ns and arrival time of the latest setpoint
        self._sp_rx_ns = 0

    @classmethod
    @abstractmethod
    def from_url(cls, url: str, role: Role | str) -> "Endpoint":
        """Open an endpoint from its URL (see :func:`io_adapters.registry.open_endpoint`)."""

    # -- device side -------------------------------------------------------------------
    @property
    def setpoint_bounds(self) -> tuple[SetpointBounds, ...]:
        """What the drive takes, one :class:`~io_adapters.messages.SetpointBounds` per
        axis in the machine's axis order, or one for every axis (the default,
        ``(SetpointBounds(),)``: finite values, the four modes, counts within 2**53).
        A setpoint that its axis's bounds refuse is dropped whole (no field of it reaches
        the record passed to :meth:`recv_setpoint`, which keeps the last good setpoint),
        counted once in ``stats.refused_*`` by its reason, and named in
        :attr:`refused_axes`; it still counts as heard from the peer (not lost)."""
        return self._setpoint_bounds

    @setpoint_bounds.setter
    def setpoint_bounds(self, bounds: tuple[SetpointBounds, ...]) -> None:
        bounds = tuple(bounds)
        if not bounds or not all(isinstance(b, SetpointBounds) for b in bounds):
            raise AdapterConfigError(f"setpoint_bounds={bounds!r}: expected one or more "
                                     f"SetpointBounds (one per axis, or one for all)")
        self._setpoint_bounds = bounds

    def recv_setpoint(self, into: Setpoint, timeout_s: float | None) -> bool:
        """Wait up to ``timeout_s`` seconds (0: poll, None: forever) for a setpoint and
        write it into ``into``; False if none came.  ``into.rx_ns`` is stamped.
        :attr:`refused_axes` names the axes whose setpoints this call refused."""
        self._check(Role.DEVICE, "recv_setpoint")
        self.refused_axes = 0
        if not self._receive(into, timeout_s):
            return False
        self._sp_t_ns = into.t_ns
        self._sp_rx_ns = into.rx_ns
        return True

    def send_feedback(self, fb: Feedback) -> bool:
        """Send ``fb`` after stamping ``fb.t_ns`` and echoing the latest setpoint's
        ``t_ns`` and arrival time into ``fb.sp_t_ns``/``fb.sp_rx_ns``.  False (nothing
        sent) while the transport does not know where the controller is yet."""
        self._check(Role.DEVICE, "send_feedback")
        fb.sp_t_ns = self._sp_t_ns
        fb.sp_rx_ns = self._sp_rx_ns
        return self._send(fb)

    # -- controller side ---------------------------------------------------------------
    def send_setpoint(self, sp: Setpoint) -> bool:
        """Send ``sp`` after stamping ``sp.t_ns``; True when sent."""
        self._check(Role.CONTROLLER, "send_setpoint")
        return self._send(sp)

    def recv_feedback(self, into: Feedback, timeout_s: float | None) -> bool:
        """Wait up to ``timeout_s`` seconds (0: poll, None: forever) for feedback and
        write it into ``into``; False if none came.  ``into.rx_ns`` is stamped."""
        self._check(Role.CONTROLLER, "recv_feedback")
        return self._receive(into, timeout_s)

    def send_injection(self, request: InjectRequest) -> bool:
        """Ask the emulated drive to inject a fault; True when sent.  Raises
        :class:`AdapterConfigError` on a transport that carries no such message (CAN:
        write object 2F00h by SDO instead), :class:`FrameError` for a request that does
        not encode."""
        self._check(Role.CONTROLLER, "send_injection")
        try:
            return self._write_injection(request)
        except AdapterError:
            raise
        except OSError as e:
            raise AdapterError(f"{self!r}: send failed: {e}") from e

    def link_conditions(self, axis: int) -> int:
        """Conditions of the link itself that the drive reacts to, a bit mask of
        LINK_HEARTBEAT_LOST = 1, LINK_STOPPED = 2, LINK_RESET = 4 (an event, reported
        once); 0 on transports that have none (this base, UDP, serial)."""
        return 0

    # -- life cycle --------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        """True once :meth:`close` has been called."""
        return self._closed

    def close(self) -> None:
        """Release the transport; calling it again does nothing."""
        if not self._closed:
            self._closed = True
            self._close()

    def fileno(self) -> int:
        """The file descriptor that becomes readable when data arrives, for
        ``select``/``poll``.  Bytes an earlier call already read are not signalled:
        call ``recv_*(into, 0)`` until it returns False before waiting on it.
        Raises ``io.UnsupportedOperation`` on transports without one."""
        if self._closed:
            raise AdapterClosed(f"{self!r} is closed")
        return self._fileno()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<{type(self).__name__} {self.role.value} {state}>"

    # -- bookkeeping -------------------------------------------------------------------
    def _check(self, role: Role, method: str) -> None:
        if self._closed:
            raise AdapterClosed(f"{method} on closed {self!r}")
        if self.role is not role:
            raise AdapterError(f"{method} is for the {role.value} side; this is {self!r}")

    def _send(self, record: Setpoint | Feedback) -> bool:
        record.t_ns = time.monotonic_ns()
        try:
            ok = self._write(record)
        except AdapterError:
            raise
        except OSError as e:
            raise AdapterError(f"{self!r}: send failed: {e}") from e
        if ok:
            self.stats.sent += 1
        return ok

    def _receive(self, into: Setpoint | Feedback, timeout_s: float | None) -> bool:
        try:
            if not self._read(into, timeout_s):
                self.stats.timeouts += 1
                return False
            while self.drain and self._read(into, 0.0):
                self.stats.drained += 1
        except AdapterError:
            raise
        except OSError as e:
            raise AdapterError(f"{self!r}: receive failed: {e}") from e
        into.rx_ns = time.monotonic_ns()
        return True

    def _notice(self, kind: str, text: str) -> None:
        """Add a notice (:attr:`notices`), unless :data:`MAX_NOTICES` are waiting."""
        if len(self.notices) < MAX_NOTICES:
            self.notices.append((kind, text))

    def _refuse(self, axes: int, reason: int) -> None:
        """Count one refused message in its reason's counter (``REFUSED_*``) and add
        ``axes`` (a bit mask, bit ``a`` for axis ``a``) to :attr:`refused_axes`."""
        counter = _REFUSAL_COUNTERS[reason]
        setattr(self.stats, counter, getattr(self.stats, counter) + 1)
        self.refused_axes |= axes

    # -- hooks -------------------------------------------------------------------------
    @abstractmethod
    def _write(self, record: Setpoint | Feedback) -> bool:
        """Send one record without waiting; False if there is nobody to send to yet or
        no room (counted in ``stats.send_dropped``)."""

    @abstractmethod
    def _read(self, into: Setpoint | Feedback, timeout_s: float | None) -> bool:
        """Wait up to ``timeout_s`` for one good record, write it into ``into``, count it
        in ``stats.received``; count and drop bad frames and refused records; False on
        timeout."""

    @abstractmethod
    def _close(self) -> None:
        """Release the transport (called once)."""

    def _write_injection(self, request: InjectRequest) -> bool:
        raise AdapterConfigError(f"{type(self).__name__} carries no injection requests")

    def _fileno(self) -> int:
        raise io.UnsupportedOperation(f"{type(self).__name__} has no file descriptor")


def flag(text: str) -> bool:
    """A URL option's boolean value: 1/true/yes/on or 0/false/no/off."""
    value = text.lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise ValueError(f"{text!r} is not a boolean (use 1 or 0)")


def positive_int(text: str) -> int:
    """A URL option's positive integer value."""
    value = int(text)
    if value <= 0:
        raise ValueError(f"{value} is not positive")
    return value


def positive_float(text: str) -> float:
    """A URL option's positive, finite float value."""
    value = float(text)
    if not 0.0 < value < float("inf"):
        raise ValueError(f"{value} is not positive and finite")
    return value


def parse_options(url: str, query: str, spec: dict[str, Callable[[str], object]]) -> dict:
    """The query string of ``url`` as ``{name: spec[name](text)}``; unknown, repeated or
    unreadable options raise :class:`AdapterConfigError` naming the URL and the key."""
    options = {}
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError as e:
        raise AdapterConfigError(f"{url!r}: bad query string: {e}") from e
    for key, text in pairs:
        if key not in spec:
            raise AdapterConfigError(f"{url!r}: unknown option {key!r}; "
                                     f"known: {', '.join(sorted(spec))}")
        if key in options:
            raise AdapterConfigError(f"{url!r}: option {key!r} given twice")
        try:
            options[key] = spec[key](text)
        except ValueError as e:
            raise AdapterConfigError(f"{url!r}: option {key}={text!r}: {e}") from e
    return options
