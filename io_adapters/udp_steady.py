"""A UDP device endpoint's side of a tick compiled from the datagram to the answer
(issue 12 part 6): the socket calls stay here, in Python, the bytes go to compiled code
(:mod:`io_adapters.codec_compiled`), and the endpoint's books are kept as its Python path
keeps them.

:meth:`SteadyLink.receive` reads one datagram into the endpoint's own receive buffer and
offers it to the compiled tick only in the common case: a device whose peer is pinned,
the datagram from that peer's address, nothing queued behind it.  Anything else -- and
any datagram the compiled tick then declines (:meth:`SteadyLink.decline`) -- is handed
back to the endpoint, whose next receive returns it first, so the Python path counts,
judges and takes it exactly as if the compiled tick had never looked.  A receive error is
handed back the same way.  After a tick that took it, :meth:`SteadyLink.commit` counts
the datagram as :meth:`~io_adapters.msgpack_endpoint.MsgpackEndpoint._accept` would
(frames, bytes, lost, received; the peer's frame and last-heard time), remembers the
setpoint's stamps for the Python path's answers, and sends the answer the compiled tick
encoded in :attr:`SteadyLink.out`, counted as ``send_feedback`` counts it.
"""

import select
import time

import numpy as np

from io_adapters.base import AdapterConfigError, AdapterError, Role
from io_adapters.codec import U32
from io_adapters.codec_compiled import (
    F_FRAME,
    F_SESSION,
    I_FRAME,
    I_T_NS,
    MAX_AXES,
    N_FB_INTS,
    N_SP_INTS,
)
from io_adapters.udp import UdpEndpoint

#: ``link``: the pinned peer's session and last frame number, the datagram's arrival
#: (monotonic ns: the kernel's stamp, else when it was read), then two words of room for
#: the compiled tick's clock reading (a struct timespec)
L_PEER_SESSION, L_PEER_FRAME, L_RX_NS, L_CLOCK = range(4)
N_LINK = L_CLOCK + 2
#: room for one encoded Feedback or FeedbackGroup (at most 120 bytes; 64 + 54 per axis)
OUT_BYTES = 1024


class SteadyLink:
    """The compiled tick's face of the UDP device endpoint ``endpoint`` of a machine of
    ``n_axes`` axes (see the module docstring).

    Attributes:
        buf: uint8 view of the endpoint's receive buffer (the datagram :meth:`receive`
            read, ``receive()`` bytes long).
        sp_ints, axis_ints, sp_floats: the compiled reader's output arrays
            (:func:`io_adapters.codec_compiled.decode_setpoint`).
        link: int64[:data:`N_LINK`], written by :meth:`receive`.
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
        self.buf = np.frombuffer(endpoint._buf, np.uint8)
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
        self._datagram: tuple | None = None

    def receive(self) -> int:
        """Read one datagram; its length when the compiled tick may take it, else 0
        (none came, or it went back to the endpoint: see the module docstring)."""
        ep = self.endpoint
        if ep._peer_session is None or ep._stash is not None:
            return 0
        try:
            n, ancillary, _, origin = ep._sock.recvmsg_into(ep._bufs, ep._ancillary)
        except BlockingIOError:
            return 0
        except OSError as e:
            ep._stash = e
            return 0
        from_ns = ep._kernel_ns(ancillary)
        self._datagram = (n, origin, from_ns)
        if origin != ep._peer_origin or self._poll.poll(0):
            self.decline()
            return 0
        link = self.link
        link[L_PEER_SESSION] = ep._peer_session
        link[L_PEER_FRAME] = ep._peer_frame
        link[L_RX_NS] = from_ns or time.monotonic_ns()
        self.fb_ints[F_SESSION] = ep.session
        self.fb_ints[F_FRAME] = ep._frame
        return n

    def decline(self) -> None:
        """Hand the datagram :meth:`receive` read back to the endpoint."""
        self.endpoint._stash, self._datagram = self._datagram, None

    def commit(self, n_out: int) -> bool:
        """Count the datagram taken (its setpoint is the one applied) and send the answer,
        ``out[:n_out]`` (``n_out`` 0: none was encoded, the caller's Python path sends
        it); True when sent (False: nothing to send, nobody to send to, or no room,
        counted in ``stats.send_dropped``).  Raises :class:`~io_adapters.base.AdapterError`
        when the send fails otherwise, as ``send_feedback`` does."""
        ep, st = self.endpoint, self.endpoint.stats
        n = self._datagram[0]
        self._datagram = None
        frame = int(self.sp_ints[I_FRAME])
        st.frames += 1
        st.bytes_received += n
        st.lost += ((frame - ep._peer_frame) & U32) - 1
        st.received += 1
        ep._peer_frame = frame
        ep._heard_ns = time.monotonic_ns()
        ep.refused_axes = 0
        ep._sp_t_ns = int(self.sp_ints[I_T_NS])
        ep._sp_rx_ns = int(self.link[L_RX_NS])
        if n_out <= 0:
            return False
        try:
            sent = ep._send_bytes(self._out_view[:n_out], None)
        except OSError as e:
            raise AdapterError(f"{ep!r}: send failed: {e}") from e
        if sent:
            st.bytes_sent += n_out
            st.sent += 1
            ep._frame = (ep._frame + 1) & U32
        return sent
