"""Serial transport: msgpack messages (:mod:`io_adapters.codec`), or the fixed wire's
(``wire=fixed``, :mod:`io_adapters.codec_fixed`), in CRC-checked frames.

Frame on the wire::

    0xA5 0x5A   start of frame (SOF)
    LEN         payload length in bytes, 1..255
    PAYLOAD     one message
    CRC         2 bytes, big-endian: CRC-16/CCITT-FALSE over LEN and PAYLOAD
                (polynomial 0x1021, initial value 0xFFFF, not reflected, no final
                XOR; check value 0x29B1 for b"123456789")

The receiver skips bytes up to the next SOF (``stats.bytes_skipped``).  A
candidate whose length is 0 or whose CRC does not match is counted in
``stats.malformed`` (and ``stats.frames``) and the search resumes one byte after its
SOF, so a frame hidden behind garbage is still found.  While a candidate is incomplete
the receiver waits for more bytes, unless a complete frame with a good CRC already
follows it in the buffer: the candidate was then garbage holding a SOF, and is
dropped at once rather than delaying the good frame.

URL: ``serial://PORT[?option=value&...]`` where PORT is

* a device path, opened with pyserial: ``serial:///dev/ttyUSB0?baud=115200``;
* a pyserial URL: ``serial://loop://`` (its own query options are not supported);
* ``fd/N``: an open file descriptor, e.g. the master side of ``os.openpty()``,
  which pyserial cannot open by name.  A terminal is switched to raw mode.

Options: ``baud=N`` (bit/s; default 115200 for pyserial ports, unchanged for a
descriptor), ``drain=1`` (see :class:`~io_adapters.base.Endpoint`), ``takeover_ms=MS``
(device side, a controller ignores it: how long the pinned controller must have been
silent before another one's HELLO is accepted, default 500 ms; the same session pinning
and handshake as on UDP, :mod:`io_adapters.codec`, without addresses),
``wire=msgpack|fixed`` (how messages are laid out, :mod:`io_adapters.wire`; a frame holds
:data:`MAX_AXES_BY_WIRE` axes per message on each).

A send never waits for the peer.  Writes are non-blocking; a frame the port takes only
in part stays pending, and is finished (by the next send or receive) before another
frame is started, so the stream stays framed.  While it cannot be finished, every
further frame is dropped whole (``stats.send_dropped``, the send returns False).
Descriptors and pyserial ports that have one are written with ``os.write`` on the
non-blocking descriptor: pyserial 3.5's own ``write`` does not do this (with
``write_timeout=0`` it retries EAGAIN in a busy loop until the peer reads, and with
a timeout it waits).  A pyserial URL without a descriptor (``loop://``)
is opened with ``write_timeout=0`` and taken at its word: ``write`` returns the bytes it
took, and ``SerialTimeoutException`` means none (pyserial 3.5's ``loop://`` raises it
for every write then: over ``loop://`` an endpoint only receives what is written into
the port).

In code, :class:`SerialEndpoint` also takes a descriptor (int) or an open
Serial-like object (``read``, ``write``, ``close``, ``in_waiting``, ``timeout``;
``fileno`` if it has one).  Either way the endpoint owns the port and closes it.  An
object without a descriptor is written as it is configured: give it ``write_timeout=0``
for writes that never wait.
"""

import binascii
import os
import select
import termios
import tty

import serial

from io_adapters.base import (
    AdapterClosed,
    AdapterConfigError,
    AdapterError,
    AdapterStats,
    FrameError,
    Role,
    flag,
    parse_options,
    positive_float,
    positive_int,
)
from io_adapters.codec_fixed import MAX_AXES as FIXED_MAX_AXES
from io_adapters.codec_fixed import largest_message
from io_adapters.msgpack_endpoint import (
    DEFAULT_TAKEOVER_MS,
    MSGPACK_WIRE,
    MsgpackEndpoint,
)
from io_adapters.wire import Wire, wire_named

SOF = b"\xa5\x5a"
MAX_PAYLOAD = 255
#: the most axes a msgpack group message (codec version 2) may carry here: with every
#: integer at its widest, 3 axes take 232 bytes (setpoint) and 226 (feedback), 4 axes 300
#: and 280
MAX_AXES = 3
#: the most axes a message may carry here, per wire (the fixed wire's: as many as its
#: feedback, 64 + 64 per axis bytes, fits a frame)
MAX_AXES_BY_WIRE = {"msgpack": MAX_AXES,
                    "fixed": max(n for n in range(1, FIXED_MAX_AXES + 1)
                                 if largest_message(n) <= MAX_PAYLOAD)}
DEFAULT_BAUD = 115200
#: bytes asked for per read of the port
READ_CHUNK = 4096


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF, no reflection, no XOR)."""
    return binascii.crc_hqx(data, 0xFFFF)


def frame(payload: bytes) -> bytes:
    """``payload`` wrapped in SOF, length and CRC."""
    n = len(payload)
    if not 0 < n <= MAX_PAYLOAD:
        raise FrameError(f"payload of {n} bytes; a frame holds 1..{MAX_PAYLOAD}")
    body = bytes((n,)) + payload
    return SOF + body + crc16(body).to_bytes(2, "big")


class FrameReader:
    """Reassembles frames from stream chunks of any size, counting what it rejects in
    ``stats`` (``malformed``, ``bytes_skipped``)."""

    def __init__(self, stats: AdapterStats):
        self.stats = stats
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        """Append bytes read from the stream."""
        self._buf += data

    def next_payload(self) -> bytes | None:
        """The payload of the next good frame in the buffer, or None until one is complete."""
        buf = self._buf
        while True:
            start = buf.find(SOF)
            if start < 0:
                self._skip(len(buf) - (1 if buf.endswith(SOF[:1]) else 0))  # keep half a SOF
                return None
            self._skip(start)
            end = self._check(0)
            if end > 0:
                payload = bytes(buf[3:end - 2])
                del buf[:end]
                return payload
            if end < 0:  # bad length or CRC: resume one byte after this SOF
                drop = 1
            else:  # incomplete: wait for more, unless a good frame already follows
                drop = self._next_complete()
                if drop < 0:
                    return None
            self.stats.malformed += 1
            self.stats.frames += 1
            self._skip(drop)

    def _check(self, i: int) -> int:
        """End of a good frame starting at ``i``; 0 if incomplete, -1 if bad."""
        buf = self._buf
        if len(buf) < i + 3:
            return 0
        n = buf[i + 2]
        if n == 0:
            return -1
        end = i + 5 + n
        if len(buf) < end:
            return 0
        return end if crc16(buf[i + 2:end - 2]) == int.from_bytes(buf[end - 2:end], "big") else -1

    def _next_complete(self) -> int:
        """Start of the first good, complete frame after position 0, or -1."""
        i = self._buf.find(SOF, 1)
        while i > 0 and self._check(i) <= 0:
            i = self._buf.find(SOF, i + 1)
        return i

    def _skip(self, n: int) -> None:
        if n:
            del self._buf[:n]
            self.stats.bytes_skipped += n


class _FdPort:
    """The part of pyserial's Serial the endpoint uses, on an open file descriptor."""

    def __init__(self, fd: int, baud: int | None):
        self.fd = fd
        if os.isatty(fd):
            tty.setraw(fd)
            if baud is not None:
                speed = getattr(termios, f"B{baud}", None)
                if speed is None:
                    raise AdapterConfigError(f"baud={baud} is not a termios speed")
                attrs = termios.tcgetattr(fd)
                attrs[4] = attrs[5] = speed
                termios.tcsetattr(fd, termios.TCSANOW, attrs)
        os.set_blocking(fd, False)

    def fileno(self) -> int:
        return self.fd

    def read(self, size: int) -> bytes:
        try:
            data = os.read(self.fd, size)
        except BlockingIOError:
            return b""
        if not data:
            raise AdapterClosed(f"end of stream on descriptor {self.fd}")
        return data

    def close(self) -> None:
        os.close(self.fd)


class SerialEndpoint(MsgpackEndpoint):
    """One side of a serial link; see the module docstring for the frame and the URL.

    Args:
        role: "device" or "controller".
        port: a device path or pyserial URL (str), an open file descriptor (int), or
            an open Serial-like object; the endpoint closes it.
        baud: bit/s (None: 115200 for a path or URL, unchanged for a descriptor or object).
        drain: see :class:`~io_adapters.base.Endpoint`.
        takeover_ms, wire: see :class:`~io_adapters.msgpack_endpoint.MsgpackEndpoint`.
    """

    def __init__(self, role: Role | str, port, *, baud: int | None = None,
                 drain: bool = False, takeover_ms: float = DEFAULT_TAKEOVER_MS,
                 wire: Wire = MSGPACK_WIRE):
        super().__init__(role, drain=drain, takeover_ms=takeover_ms, wire=wire)
        self.name = f"fd/{port}" if isinstance(port, int) else str(getattr(port, "port", port))
        if isinstance(port, int):
            try:
                port = _FdPort(port, baud)
            except (OSError, termios.error) as e:  # the descriptor stays the caller's
                raise AdapterError(f"cannot use descriptor {port} as a serial port: {e}") from e
        elif isinstance(port, str):
            try:
                port = serial.serial_for_url(port, baudrate=baud or DEFAULT_BAUD, timeout=0,
                                             write_timeout=0)
            except (serial.SerialException, ValueError) as e:
                raise AdapterError(f"cannot open serial port {port!r}: {e}") from e
        self._port = port
        self._reader = FrameReader(self.stats)
        self._pending = b""  # the unwritten rest of a frame the port took in part
        try:
            self._fd = port.fileno()
        except (AttributeError, OSError, ValueError):  # loop:// and other fd-less ports
            self._fd = None
        if self._fd is not None:
            if not isinstance(port, _FdPort):
                port.timeout = 0  # select() waits; read takes what is there
            os.set_blocking(self._fd, False)  # writes go to it (module docstring)
        self._greet()

    @classmethod
    def from_url(cls, url: str, role: Role | str) -> "SerialEndpoint":
        """``serial://PORT?options`` (see the module docstring)."""
        target, _, query = url.partition("://")[2].partition("?")
        options = parse_options(url, query, {
            "baud": positive_int, "drain": flag, "takeover_ms": positive_float,
            "wire": wire_named})
        if target.startswith("fd/"):
            if not target[3:].isdigit():
                raise AdapterConfigError(f"{url!r}: expected serial://fd/N, N a descriptor")
            target = int(target[3:])
        elif not target:
            raise AdapterConfigError(f"{url!r}: expected serial://PATH, serial://fd/N or "
                                     f"serial://PYSERIAL-URL")
        return cls(role, target, **options)

    def __repr__(self) -> str:
        return (f"<SerialEndpoint {self.role.value} {self.name}"
                f"{' closed' * self._closed}>")

    def _send_bytes(self, payload: bytes, to) -> bool:
        data = frame(payload)
        if self._pending and not self._finish_pending():
            self.stats.send_dropped += 1
            return False
        n = self._write_some(data)
        if n == 0:
            self.stats.send_dropped += 1
            return False
        self._pending = memoryview(data)[n:]
        return True

    def _finish_pending(self) -> bool:
        """Write what the port takes of the pending frame; True once nothing is left."""
        self._pending = self._pending[self._write_some(self._pending):]
        return not self._pending

    def _write_some(self, data: bytes | memoryview) -> int:
        """Write what the port takes now of ``data`` without waiting; the bytes written."""
        if self._fd is not None:
            try:
                return os.write(self._fd, data)
            except BlockingIOError:
                return 0
        try:
            return self._port.write(data) or 0
        except serial.SerialTimeoutException:
            return 0

    def _recv_bytes(self, timeout_s: float | None) -> bytes | None:
        if self._pending:
            self._finish_pending()
        payload = self._reader.next_payload()
        if payload is None:
            chunk = self._read_chunk(timeout_s)
            if chunk:
                self._reader.feed(chunk)
                payload = self._reader.next_payload()
        return payload

    def _read_chunk(self, timeout_s: float | None) -> bytes:
        port = self._port
        if self._fd is not None:
            if timeout_s != 0.0 and not select.select((self._fd,), (), (), timeout_s)[0]:
                return b""
            return port.read(READ_CHUNK)
        port.timeout = timeout_s  # a port without a descriptor waits by itself
        first = port.read(1)
        return first + port.read(port.in_waiting) if first else first

    def _close(self) -> None:
        self._port.close()

    def _fileno(self) -> int:
        if self._fd is None:
            return super()._fileno()
        return self._fd
