"""What the msgpack transports (UDP, serial) share above their bytes: frame numbering,
the sequence check, who may talk to a device, the handshake and refused values.

The wire format and the handshake are described in :mod:`io_adapters.codec`.  Every
message that reaches :meth:`MsgpackEndpoint._accept` is counted in ``stats.frames`` and
in exactly one of the counters below, checked in this order:

1. ``foreign``: it comes from someone other than the peer (UDP: another address than the
   pinned one, or an address outside the loopback network without ``allow_remote``; a
   controller's peer is the device's address).  Only a well-formed HELLO from a stranger
   is looked at, and it becomes ``handshakes`` if the device accepts it (see the codec's
   handshake rules).
2. ``malformed``: it does not decode as a record or a handshake message of this side.
3. ``handshakes``: a HELLO the device accepted, a WELCOME on the controller; a HELLO the
   device refused is ``foreign``.  ``injections``: an INJECT of the pinned peer's session
   (device), appended to :attr:`~io_adapters.base.Endpoint.injections`; of another session
   it is ``stale_session``, with a NaN or infinite number ``refused_nonfinite``.
4. ``stale_session`` (device): another session than the pinned one.  A controller takes a
   new session of its device as the device reopened (``peer_restarts``).
5. ``duplicates``, ``out_of_order``: the frame number repeats, goes back, or jumps (the
   sequence rule below).
6. ``refused_nonfinite``, ``refused_mode``, ``refused_range``: a NaN or infinite float
   (setpoints and feedback), or a setpoint its axis's
   :attr:`~io_adapters.base.Endpoint.setpoint_bounds` does not take.  The message is
   dropped whole but was heard: it advances the frame counter and keeps the peer pinned.
   A group message is counted once, under the lowest ``REFUSED_*`` code of its axes
   (non-finite before mode before range), and
   :attr:`~io_adapters.base.Endpoint.refused_axes` names every refused axis.
7. ``received``: the record is written into the caller's.

The device pins the first peer whose well-formed setpoint or HELLO it receives; a frame
of that peer that passes 5 (taken or refused) or an accepted HELLO counts as hearing from
it, for ``takeover_ms``.

**The sequence rule** (RFC 3550's, appendix A.1, with windows of our own), on the frame
number of the peer's session against the last one that passed 5:

* 1 to :data:`MAX_DROPOUT` ahead: in sequence; the frames in between count as ``lost``;
* the same number: ``duplicates``; 1 to :data:`MAX_MISORDER` behind: a late frame,
  ``out_of_order``;
* anything else is a *jump* (far ahead, or far behind), dropped as ``out_of_order`` and
  remembered: if the very next frame of the session continues it (its number is the
  jump's plus one), the check resynchronises to that frame (``resyncs``, a notice), which
  passes 5 as if in sequence (nothing counted lost).  Two frames in sequence are needed
  because one is not enough to tell a peer that restarted its count from a stray or
  forged frame: a single frame far ahead, repeated from an old run or forged, costs the
  peer nothing, and its following frames are taken; a peer whose count did jump (frames
  lost beyond the window) loses one frame.  A frame taken in sequence forgets the jump.

A frame forged from the peer's address and session J frames ahead (J up to
``MAX_DROPOUT``) is taken; the peer's own next frames are then late, or a jump: J of them
are dropped for J up to ``MAX_MISORDER`` + 1, one otherwise (the check follows the peer
back at the frame after it).  A HELLO that pins a new peer starts the check afresh.
"""

import math
import secrets
import time
from abc import abstractmethod
from itertools import repeat

from io_adapters.base import AdapterConfigError, AdapterError, Endpoint, FrameError, Role
from io_adapters.codec import (
    GROUP_REFUSAL_ARGS,
    GROUP_SCHEMAS,
    HELLO_INTERVAL_NS,
    KIND_HELLO,
    KIND_INJECT,
    KIND_WELCOME,
    SCHEMAS,
    SETPOINT_REFUSAL_ARGS,
    U32,
    decode,
    decode_hello,
    encode,
    encode_hello,
    encode_inject,
    encode_welcome,
    fill,
    inject_request,
)
from io_adapters.messages import (
    REFUSED_NONFINITE,
    Feedback,
    InjectRequest,
    Setpoint,
    SetpointGroup,
    axis_records,
)
from io_adapters.wire import Wire

#: how long a pinned controller must have been silent before a HELLO of another one
#: takes the device over, ms (URL option ``takeover_ms``)
DEFAULT_TAKEOVER_MS = 500.0
#: the sequence rule's windows (module docstring), frames: the most a frame may be ahead
#: of the last one and be in sequence (frames lost in between: 4 s of an 8 kHz
#: controller's), and the most it may be behind and be a late frame rather than a jump
#: (a forged frame just ahead costs the peer at most this many frames plus one: 33 ms of
#: a 1 kHz controller's, a third of the emulator's default watchdog)
MAX_DROPOUT = 2**15
MAX_MISORDER = 32
#: the first bytes a HELLO can start with: a msgpack array of 4 (fixarray, array 16 or
#: array 32); a stranger's datagram starting otherwise is foreign without decoding it
HELLO_LEADS = frozenset((0x94, 0xDC, 0xDD))
#: resynchronisations noticed at most once in this long (the counter has every one), ns
NOTICE_GAP_NS = 1_000_000_000


def _finite(values: tuple, record_type: type) -> bool:
    return (GROUP_SCHEMAS.get(record_type) or SCHEMAS[record_type]).finite(values)


#: the msgpack wire (:mod:`io_adapters.codec`), every endpoint's default
MSGPACK_WIRE = Wire("msgpack", encode, decode, fill, _finite, encode_hello, decode_hello,
                    encode_welcome, encode_inject, HELLO_LEADS)


class MsgpackEndpoint(Endpoint):
    """An :class:`~io_adapters.base.Endpoint` over a transport that moves whole messages
    (datagrams, serial frames); see the module docstring for what it checks.

    Args:
        role: "device" or "controller".
        drain: see :class:`~io_adapters.base.Endpoint`.
        takeover_ms: device side: how long the pinned controller must have sent nothing
            valid before another one's HELLO is accepted, ms (> 0).
        wire: how messages are laid out in bytes (:mod:`io_adapters.wire`; default
            msgpack).

    Attributes:
        session: this endpoint's session, u32, drawn at random when it opens.
        welcomed: controller side: a WELCOME accepted=1 has arrived (HELLOs stop).

    A backend fills ``_send_bytes(payload, to) -> bool`` (send one message without
    waiting, to the peer or, for a handshake answer, to ``to``, the origin of the HELLO;
    False: nobody to send to yet, or no room: then counted in ``stats.send_dropped``),
    ``_recv_bytes(timeout_s) -> bytes | None`` (one message, or None if none came in
    ``timeout_s``; returning None early is allowed; it sets ``self._origin`` to where the
    message came from, if the transport has addresses), ``_close()`` and optionally
    ``_fileno()``, ``_admissible(origin)`` and ``_exhausted()``; a controller calls
    :meth:`_greet` once its transport is open.
    """

    def __init__(self, role: Role | str, *, drain: bool = False,
                 takeover_ms: float = DEFAULT_TAKEOVER_MS, wire: Wire = MSGPACK_WIRE):
        super().__init__(role, drain=drain)
        self.wire = wire
        if not 0.0 < takeover_ms < float("inf"):
            raise AdapterConfigError(f"takeover_ms={takeover_ms}: expected a positive, "
                                     f"finite time in ms")
        self.session = secrets.randbits(32)
        self.welcomed = False
        self._device = self.role is Role.DEVICE
        self._takeover_ns = round(takeover_ms * 1e6)
        self._frame = 0
        self._origin = None        # where the message being decoded came from (UDP: address)
        self._peer_origin = None   # the peer's (device: pinned; controller: the device's)
        self._peer_session = None  # the peer's session (device: pinned; None: no peer yet)
        self._peer_frame = 0       # the peer's latest frame number
        self._after_jump = None    # the frame number that would continue a jump dropped
        self._resync_noticed_ns = None  # when a resynchronisation was last noticed
        self._heard_ns = 0         # device: when the pinned peer last sent something valid
        self._hello_ns = None      # controller: when the latest HELLO went out

    # -- sending -----------------------------------------------------------------------
    def _write(self, record: Setpoint | Feedback) -> bool:
        payload = self.wire.encode(record, self.session, self._frame)
        if not (self._device or self.welcomed):
            self._hello_if_due()
        return self._send_record(payload)

    def _send_record(self, payload: bytes | memoryview) -> bool:
        """Send one record already encoded with this endpoint's session and next frame
        number (:meth:`_write`, or a compiled encoder: :mod:`io_adapters.udp_steady`) and
        count it; False if nobody or no room took it."""
        if not self._send_message(payload, None):
            return False
        self._frame = (self._frame + 1) & U32
        return True

    def _greet(self) -> None:
        """Controller: the HELLO sent when the endpoint opens; closes the endpoint and
        raises :class:`~io_adapters.base.AdapterError` if the transport fails."""
        if self._device:
            return
        try:
            self._hello_if_due()
        except OSError as e:
            self.close()
            raise AdapterError(f"{self!r}: cannot send the opening HELLO: {e}") from e

    def _hello_if_due(self) -> None:
        now = time.monotonic_ns()
        if self._hello_ns is None or now - self._hello_ns >= HELLO_INTERVAL_NS:
            if self._send_message(self.wire.encode_hello(self.session, self._frame), None):
                self._hello_ns = now

    def _send_message(self, payload: bytes, to) -> bool:
        if not self._send_bytes(payload, to):
            return False
        self.stats.bytes_sent += len(payload)
        return True

    # -- receiving ---------------------------------------------------------------------
    def _read(self, into: Setpoint | Feedback, timeout_s: float | None) -> bool:
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        wait = timeout_s
        while True:
            data = self._recv_bytes(wait)
            if data is not None and self._accept(data, into):
                return True
            if data is None and self._exhausted():
                return False
            if deadline is not None:
                if data is None and wait <= 0.0:
                    return False
                wait = max(0.0, deadline - time.monotonic())

    def _accept(self, data: bytes | memoryview, into) -> bool:
        """Decode one message into ``into`` if it is good, new and taken; count it in
        exactly one counter either way (module docstring)."""
        stats = self.stats
        stats.frames += 1
        stats.bytes_received += len(data)
        origin = self._origin
        if origin != self._peer_origin and not (
                self._device and self._peer_session is None and self._admissible(origin)):
            self._from_stranger(data, origin)
            return False
        try:
            values = self.wire.decode(data, type(into), len(axis_records(into)))
        except FrameError:
            stats.malformed += 1
            return False
        if values[1] == KIND_INJECT:  # decode lets it through on the device only
            self._injection(values)
            return False
        if values[1] >= KIND_HELLO:  # a handshake message (decode let only ours through)
            self._handshake(values, origin)
            return False
        if not self._in_sequence(values[2], values[3], origin):
            return False
        if self._device:
            if self._refused(values, into):
                return False
        elif not self.wire.finite(values, type(into)):
            self._refuse(0, REFUSED_NONFINITE)
            return False
        self.wire.fill(into, values)
        stats.received += 1
        return True

    def _from_stranger(self, data: bytes | memoryview, origin) -> None:
        """A message from someone other than the peer: foreign, unless it is a HELLO
        to a device from an admissible origin."""
        if self._device and len(data) and data[0] in self.wire.hello_leads \
                and self._admissible(origin):
            try:
                values = self.wire.decode_hello(data)
            except FrameError:
                pass
            else:
                self._hello(values, origin)
                return
        self.stats.foreign += 1

    def _injection(self, values: tuple) -> None:
        """Device: an INJECT from the pinned peer's address (checked by the caller), or
        from anyone admissible while no peer is pinned (then it is foreign)."""
        if self._peer_session is None:
            self.stats.foreign += 1
            return
        if values[2] != self._peer_session:
            self.stats.stale_session += 1
            return
        request = inject_request(values)
        if not all(map(math.isfinite, request.settings.values())):
            self._refuse(0, REFUSED_NONFINITE)
            return
        self.stats.injections += 1
        self.injections.append(request)

    def _write_injection(self, request: InjectRequest) -> bool:
        return self._send_message(self.wire.encode_inject(self.session, self._frame, request),
                                  None)

    def _handshake(self, values: tuple, origin) -> None:
        if values[1] == KIND_WELCOME:
            self.stats.handshakes += 1
            self.welcomed = self.welcomed or values[4] == 1
        else:
            self._hello(values, origin)

    def _hello(self, values: tuple, origin) -> None:
        """Device: accept a HELLO (re-pin, reset the sequence check) or refuse it; answer
        with a WELCOME either way, to its sender."""
        session, now = values[2], time.monotonic_ns()
        same = session == self._peer_session and origin == self._peer_origin
        if same or self._peer_session is None or now - self._heard_ns >= self._takeover_ns:
            if not same:
                if self._peer_session is not None:
                    self.stats.peer_restarts += 1
                self._peer_session, self._peer_origin = session, origin
                # a HELLO does not advance its sender's counter: the next frame has its number
                self._peer_frame = (values[3] - 1) & U32
                self._after_jump = None
            self._heard_ns = now
            self.stats.handshakes += 1
            accepted = True
        else:
            self.stats.foreign += 1
            accepted = False
        self._send_message(self.wire.encode_welcome(self.session, self._frame, accepted),
                           origin)

    def _in_sequence(self, session: int, frame: int, origin) -> bool:
        """Check a record's session and frame number, counting what is dropped; pin the
        first peer (device) or follow a reopened device (controller)."""
        stats = self.stats
        if session != self._peer_session:
            if self._device and self._peer_session is not None:
                stats.stale_session += 1
                return False
            if self._peer_session is not None:
                stats.peer_restarts += 1
            self._peer_session, self._peer_origin = session, origin
        else:
            ahead = (frame - self._peer_frame) & U32
            if ahead == 0:
                stats.duplicates += 1
                return False
            if ahead <= MAX_DROPOUT:
                stats.lost += ahead - 1
            elif ahead >= U32 + 1 - MAX_MISORDER:  # a late frame
                stats.out_of_order += 1
                return False
            elif frame != self._after_jump:  # a jump: taken only if the next frame follows
                self._after_jump = (frame + 1) & U32
                stats.out_of_order += 1
                return False
            else:
                self._resynchronised(frame)
        self._after_jump = None
        self._peer_frame = frame
        if self._device:
            self._heard_ns = time.monotonic_ns()
        return True

    def _resynchronised(self, frame: int) -> None:
        """Count a resynchronisation to ``frame`` and notice it (at most once in
        :data:`NOTICE_GAP_NS`)."""
        self.stats.resyncs += 1
        now = time.monotonic_ns()
        if self._resync_noticed_ns is None or now - self._resync_noticed_ns >= NOTICE_GAP_NS:
            self._resync_noticed_ns = now
            self._notice(
                "frames resynchronised",
                f"the peer's frame numbers jumped from {self._peer_frame} to "
                f"{(frame - 1) & U32} and went on from there: the sequence check follows "
                f"them ({self.stats.resyncs} resynchronisation(s) so far; at most one "
                f"notice a second)")

    def _refused(self, values: tuple, into: Setpoint | SetpointGroup) -> bool:
        """Device: True (and counted) if the setpoint's bounds refuse any axis of it."""
        bounds = self._setpoint_bounds
        if type(into) is not SetpointGroup:
            if len(bounds) != 1:
                raise AdapterConfigError(f"{self!r}: {len(bounds)} setpoint_bounds for a "
                                         f"single-axis link")
            reason = bounds[0].refusal(*values[SETPOINT_REFUSAL_ARGS])
            if reason:
                self._refuse(1, reason)
            return reason != 0
        axes = values[-1]
        if len(bounds) != 1 and len(bounds) != len(axes):
            raise AdapterConfigError(f"{self!r}: {len(bounds)} setpoint_bounds for "
                                     f"{len(axes)} axes (give one per axis, or one)")
        mask = reason = 0
        for a, (b, record) in enumerate(zip(bounds if len(bounds) > 1 else repeat(bounds[0]),
                                            axes)):
            axis_reason = b.refusal(*record[GROUP_REFUSAL_ARGS])
            if axis_reason:
                mask |= 1 << a
                reason = min(reason, axis_reason) if reason else axis_reason
        if mask:
            self._refuse(mask, reason)
        return mask != 0

    def _admissible(self, origin) -> bool:
        """Whether a message from ``origin`` may be considered at all (UDP: loopback or
        ``allow_remote``)."""
        return True

    def _exhausted(self) -> bool:
        """The receive call may read no more messages (UDP: its budget is spent), so a
        wait would be for nothing."""
        return False

    @abstractmethod
    def _send_bytes(self, payload: bytes, to) -> bool:
        """Send one message without waiting, to the peer (``to`` None) or to ``to``."""

    @abstractmethod
    def _recv_bytes(self, timeout_s: float | None) -> bytes | memoryview | None:
        """One received message (valid until the next call), or None if none came."""
