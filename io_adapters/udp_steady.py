"""A UDP device endpoint's side of a tick compiled from the datagram to the answer
(issue 12 part 6): the socket calls stay here, in Python, the bytes go to compiled code
(:mod:`io_adapters.codec_compiled`), and the endpoint's books are kept as its Python path
keeps them.

:meth:`SteadyLink.receive` reads every datagram queued for the tick (up to
:data:`MAX_QUEUED`, and within the endpoint's receive budget,
:attr:`~io_adapters.udp.UdpEndpoint.rx_budget`) into buffers of its own and offers them
to the compiled tick only in the common cases: a device whose peer is pinned, and the
datagrams all from that peer (the newest is applied, the older ones are taken and
superseded, as the endpoint's drain does), or none (a silent tick).  A stranger's datagram
that the endpoint would not decode (:meth:`~io_adapters.udp.UdpEndpoint._may_be_hello`)
is counted foreign there and then, as the endpoint counts it, and its buffer reused.
Anything else -- more than :data:`MAX_QUEUED`, the budget spent with datagrams still
queued, a stranger's datagram that may be a HELLO, a receive error -- and any datagrams
the compiled tick then declines (:meth:`SteadyLink.decline`) are handed back to the
endpoint, whose next receives return them first and go on within what is left of the
same budget, so the Python path counts, judges and takes them exactly as if the compiled
tick had never looked.  After a tick that took them, :meth:`SteadyLink.take` counts them
as :meth:`~io_adapters.msgpack_endpoint.MsgpackEndpoint._accept` and the drain would
(frames, bytes, lost, received, drained; the peer's frame and last-heard time) and
remembers the setpoint's stamps for the Python path's answers; after a silent one,
:meth:`SteadyLink.idle` counts the empty receive.  :meth:`SteadyLink.send` sends the
answer the compiled tick encoded in :attr:`SteadyLink.out`, counted as ``send_feedback``
counts it.
"""

import select
import time

import numpy as np

from io_adapters.base import AdapterConfigError, AdapterError, Role
from io_adapters.codec_compiled import (
    F_FRAME,
    F_SESSION,
    I_T_NS,
    MAX_AXES,
    N_FB_INTS,
    N_SP_INTS,
)
from io_adapters.udp import MAX_DATAGRAM, UdpEndpoint

#: datagrams a compiled tick takes at most (more queued: the Python tick drains them)
MAX_QUEUED = 64
#: ``link``: the pinned peer's session and last frame number, the newest datagram's
#: arrival (monotonic ns: the kernel's stamp, else when it was read), when the compiled
#: tick's call began (monotonic ns, written by it), two words of room for its clock
#: readings (a struct timespec), then the datagrams' lengths and (written by the compiled
#: tick) their frame numbers, oldest first
L_PEER_SESSION, L_PEER_FRAME, L_RX_NS, L_CALL_NS, L_CLOCK = range(5)
L_LENGTHS = L_CLOCK + 2
L_FRAMES = L_LENGTHS + MAX_QUEUED
N_LINK = L_FRAMES + MAX_QUEUED
#: room for one encoded Feedback or FeedbackGroup (at most 120 bytes; 64 + 54 per axis)
OUT_BYTES = 1024


class SteadyLink:
    """The compiled tick's face of the UDP device endpoint ``endpoint`` of a machine of
    ``n_axes`` axes (see the module docstring).

    Attributes:
        bufs: uint8[:data:`MAX_QUEUED`, MAX_DATAGRAM], the datagrams :meth:`receive`
            read, oldest first (``link[L_LENGTHS + i]`` bytes of row i).
        sp_ints, axis_ints, sp_floats: the compiled reader's output arrays
            (:func:`io_adapters.codec_compiled.decode_setpoint`).
        link: int64[:data:`N_LINK`], written by :meth:`receive` (the frames by the
            compiled tick).
        fb_ints, fb_axis_ints, fb_floats: the answer's values
            (:mod:`io_adapters.codec_compiled` layout); its session and frame are
            written by :meth:`receive`, the rest by the compiled tick and its caller.
        out: uint8[:data:`OUT_BYTES`], the encoded answer.
    """

    def __init__(self, endpoint: UdpEndpoint, n_axes: int = 1):
        if not isinstance(endpoint, UdpEndpoint) or endpoint.role is not Role.DEVICE:
            raise AdapterConfigError(f"{endpoint!r}: a compiled tick needs a UDP device")
        if not 1 <= n_axes <= MAX_AXES:
            raise AdapterConfigError(f"a compiled tick takes 1 to {MAX_AXES} axes, not "
                                     f"{n_axes}")
        self.endpoint = endpoint
        self.bufs = np.zeros((MAX_QUEUED, MAX_DATAGRAM), np.uint8)
        self._slots = [(memoryview(row),) for row in self.bufs]
        self.sp_ints = np.zeros(N_SP_INTS, np.int64)
        self.axis_ints = np.zeros((n_axes, 2), np.int64)
        self.sp_floats = np.zeros((n_axes, 7))
        self.link = np.zeros(N_LINK, np.int64)
        self.fb_ints = np.zeros(N_FB_INTS, np.int64)
        self.fb_axis_ints = np.zeros((n_axes, 2), np.int64)
        self.fb_floats = np.zeros((n_axes, 6))
        self.out = np.zeros(OUT_BYTES, np.uint8)
        self._out_view = memoryview(self.out)
        self._poll = select.poll()
        self._poll.register(endpoint._sock, select.POLLIN)
        # what receive() read, oldest first: (n, origin, kernel stamp) or a receive error
        self._datagrams: list[tuple | OSError] = []

    def receive(self) -> int:
        """Read the tick's datagrams (module docstring): how many, when the compiled tick
        may take them (0: none came); -1 when they went back to the endpoint."""
        ep = self.endpoint
        if ep._peer_session is None or ep._stash:
            return -1
        ep._begin_receive()
        link, got, slots = self.link, self._datagrams, self._slots
        sock, ancillary, peer, poll = ep._sock, ep._ancillary, ep._peer_origin, self._poll
        left = ep._left  # the call's budget, written back before anything else reads it
        while left > 0:
            i = len(got)
            if i == MAX_QUEUED:
                ep._left = left
                self.decline()
                return -1
            try:
                n, anc, _, origin = sock.recvmsg_into(slots[i], ancillary)
            except BlockingIOError:
                break
            except OSError as e:
                left -= 1
                got.append(e)
                break
            left -= 1
            if origin != peer and not ep._may_be_hello(slots[i][0][:n]):
                ep._foreign_datagram(n)
            else:
                link[L_LENGTHS + i] = n
                got.append((n, origin, ep._kernel_ns(anc)))
                if origin != peer:
                    break
            if not poll.poll(0):
                break
        else:  # the budget spent: the endpoint's receive stops there and counts it
            if poll.poll(0):
                ep._left = left
                self.decline()
                return -1
        ep._left = left
        if got:
            if isinstance(got[-1], OSError) or got[-1][1] != peer:
                self.decline()
                return -1
            link[L_RX_NS] = got[-1][2] or time.monotonic_ns()
        link[L_PEER_SESSION] = ep._peer_session
        link[L_PEER_FRAME] = ep._peer_frame
        self.fb_ints[F_SESSION] = ep.session
        self.fb_ints[F_FRAME] = ep._frame
        return len(got)

    def decline(self) -> None:
        """Hand the datagrams :meth:`receive` read back to the endpoint, whose next
        receive goes on within the same budget."""
        self.endpoint._continued = True
        self.endpoint._stash.extend(
            d if isinstance(d, OSError) else (*d, self.bufs[i, :d[0]].tobytes())
            for i, d in enumerate(self._datagrams))
        self._datagrams.clear()

    def take(self) -> int:
        """Count the datagrams the compiled tick took (the newest one's setpoint is the
        one applied); how many older ones it superseded."""
        ep, st = self.endpoint, self.endpoint.stats
        got = self._datagrams
        for i, (n, _, _) in enumerate(got):
            st.frames += 1
            st.bytes_received += n
            # the kernel checked session and frame; the owner's check books them
            ep._in_sequence(ep._peer_session, int(self.link[L_FRAMES + i]), ep._peer_origin)
            st.received += 1
        superseded = len(got) - 1
        st.drained += superseded
        got.clear()
        ep.refused_axes = 0
        ep._sp_t_ns = int(self.sp_ints[I_T_NS])
        ep._sp_rx_ns = int(self.link[L_RX_NS])
        return superseded

    def idle(self) -> None:
        """Count a tick's receive that found nothing, as ``recv_setpoint`` counts it."""
        self.endpoint.stats.timeouts += 1
        self.endpoint.refused_axes = 0

    def send(self, n_out: int) -> bool:
        """Send the answer ``out[:n_out]`` (``n_out`` 0: none was encoded, the caller's
        Python path sends it); True when sent (False: nothing to send, nobody to send to,
        or no room, counted in ``stats.send_dropped``).  Raises
        :class:`~io_adapters.base.AdapterError` when the send fails otherwise, as
        ``send_feedback`` does."""
        if n_out <= 0:
            return False
        ep = self.endpoint
        try:
            sent = ep._send_record(self._out_view[:n_out])
        except OSError as e:
            raise AdapterError(f"{ep!r}: send failed: {e}") from e
        ep.stats.sent += sent
        return sent
