"""Serial framing: the CRC against its published check value and a bit-by-bit
reference, the frame layout, resynchronisation (garbage, split reads, bad CRCs, false
starts), then the endpoint over pyserial's ``loop://`` and over a real pty pair.  (A peer
that stops reading: tests/test_adapter_stalled.py.)"""

import io
import os
import random

import pytest
import serial

from io_adapters import (
    AdapterConfigError,
    AdapterError,
    AdapterStats,
    FrameError,
    codec,
)
from io_adapters.messages import Feedback, Setpoint
from io_adapters.registry import open_endpoint
from io_adapters.serial_link import FrameReader, SerialEndpoint, crc16, frame

WAIT_S = 5.0
QUIET_S = 0.02


def crc16_reference(data: bytes) -> int:
    """CRC-16/CCITT-FALSE bit by bit: poly 0x1021, init 0xFFFF, MSB first, no final XOR."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def test_crc_check_value():
    assert crc16(b"123456789") == crc16_reference(b"123456789") == 0x29B1


def test_crc_matches_the_reference():
    rng = random.Random(1)
    for _ in range(200):
        data = rng.randbytes(rng.randrange(0, 300))
        assert crc16(data) == crc16_reference(data), data.hex()


def test_frame_layout():
    body = bytes([3, 1, 2, 3])
    assert frame(b"\x01\x02\x03") == b"\xa5\x5a" + body + crc16_reference(body).to_bytes(2, "big")


@pytest.mark.parametrize("size", [0, 256])
def test_frame_refuses_empty_and_oversize_payloads(size):
    with pytest.raises(FrameError, match=f"{size} bytes"):
        frame(bytes(size))


def read_all(reader: FrameReader) -> list[bytes]:
    out = []
    while (payload := reader.next_payload()) is not None:
        out.append(payload)
    return out


A, B, C = b"first", b"second payload", bytes(range(1, 200))  # no 0xA5 0x5A inside


def reader_with(*chunks: bytes) -> tuple[FrameReader, list[bytes], AdapterStats]:
    stats = AdapterStats()
    reader, got = FrameReader(stats), []
    for chunk in chunks:
        reader.feed(chunk)
        got += read_all(reader)
    return reader, got, stats


def test_back_to_back_frames():
    _, got, stats = reader_with(frame(A) + frame(B) + frame(C))
    assert got == [A, B, C]
    assert (stats.malformed, stats.bytes_skipped) == (0, 0)


def test_garbage_between_frames_is_skipped_and_counted():
    garbage = b"\x00\xff\x13\xa5\x00\x5a"  # holds a lone 0xA5, no start of frame
    _, got, stats = reader_with(garbage + frame(A) + garbage * 2 + frame(B) + garbage)
    assert got == [A, B]
    assert (stats.malformed, stats.bytes_skipped) == (0, 4 * len(garbage))


def test_frames_split_at_every_point():
    data = frame(A) + frame(B)
    for cut in range(len(data) + 1):
        _, got, stats = reader_with(data[:cut], data[cut:])
        assert got == [A, B], cut
        assert (stats.malformed, stats.bytes_skipped) == (0, 0), cut


def test_frames_fed_byte_by_byte():
    data = b"\x01\x02" + frame(A) + frame(C)
    _, got, stats = reader_with(*(data[i:i + 1] for i in range(len(data))))
    assert got == [A, C]
    assert stats.bytes_skipped == 2


@pytest.mark.parametrize("where", [-1, 5])  # in the CRC, in the payload
def test_corrupted_frame_is_dropped_and_the_next_one_found(where):
    bad = bytearray(frame(A))
    bad[where] ^= 0x40
    _, got, stats = reader_with(bytes(bad) + frame(B))
    assert got == [B]
    assert (stats.malformed, stats.bytes_skipped) == (1, len(bad))
    assert stats.frames == 1  # the bad candidate; good payloads are counted by the endpoint


def test_zero_length_is_not_a_frame():
    _, got, stats = reader_with(b"\xa5\x5a\x00" + frame(A))
    assert got == [A]
    assert (stats.malformed, stats.bytes_skipped) == (1, 3)


def test_false_start_does_not_delay_a_good_frame():
    """Garbage 'A5 5A FF' announces 255 bytes; the good frame behind it is not held back."""
    _, got, stats = reader_with(b"\xa5\x5a\xff" + frame(A))
    assert got == [A]
    assert stats.malformed == 1


def test_false_start_overlapping_a_frame():
    """'A5 5A' right before a frame: the false candidate takes the real SOF as its length
    (0xA5), fails its CRC, and the search resumes inside it."""
    _, got, stats = reader_with(b"\xa5\x5a" + frame(C))
    assert got == [C]
    assert (stats.malformed, stats.bytes_skipped) == (1, 2)


def test_incomplete_frame_waits_for_its_bytes():
    data = frame(C)
    reader, got, stats = reader_with(data[:1])
    assert got == [] and stats.bytes_skipped == 0  # half a start of frame is kept
    reader.feed(data[1:-1])
    assert reader.next_payload() is None
    reader.feed(data[-1:])
    assert reader.next_payload() == C


def test_random_garbage_then_frames():
    rng = random.Random(7)
    garbage = bytes(rng.randrange(256) for _ in range(5000)) + b"\xa5\x5a"
    _, got, _ = reader_with(garbage + frame(A) + frame(B), frame(C))
    assert got == [A, B, C]


# -- the endpoint --------------------------------------------------------------------

def setpoint_frame(seq: int, frame_no: int | None = None) -> bytes:
    return frame(codec.encode(Setpoint(seq=seq), 1, seq if frame_no is None else frame_no))


def test_endpoint_over_pyserial_loop():
    port = serial.serial_for_url("loop://")
    with SerialEndpoint("device", port) as ep:
        port.write(b"junk" + setpoint_frame(1) + b"\xa5\x5a\x05xx" + setpoint_frame(2))
        sp = Setpoint()
        assert ep.recv_setpoint(sp, WAIT_S) and sp.seq == 1
        assert ep.recv_setpoint(sp, WAIT_S) and sp.seq == 2
        assert not ep.recv_setpoint(sp, QUIET_S)
        assert (ep.stats.received, ep.stats.malformed, ep.stats.timeouts) == (2, 1, 1)
        assert ep.stats.frames == 3
        with pytest.raises(io.UnsupportedOperation):
            ep.fileno()
    assert not port.is_open  # the endpoint owns what it was given


def test_loop_url_opens_and_its_writes_never_wait():
    """pyserial 3.5's loop:// refuses every write with write_timeout=0 (it compares the
    transmit time with the timeout): the opening HELLO, the HELLO tried again before the
    setpoint (none went out yet) and the setpoint are dropped and counted, not waited for."""
    with open_endpoint("serial://loop://?baud=9600", "controller") as ep:
        assert ep.name == "loop://" and not ep.recv_feedback(Feedback(), 0.0)
        assert not ep.send_setpoint(Setpoint())
        assert (ep.stats.send_dropped, ep.stats.sent) == (3, 0)


@pytest.fixture
def pty_device():
    """A device endpoint on a pty master; yields (endpoint, slave fd, master fd)."""
    master, slave = os.openpty()
    ep = open_endpoint(f"serial://fd/{master}", "device")
    yield ep, slave, master
    ep.close()
    os.close(slave)


def test_pty_resynchronises_across_real_reads(pty_device):
    ep, slave, _ = pty_device
    first = setpoint_frame(1)
    sp = Setpoint()
    os.write(slave, b"\x00\x13" + first[:6])
    assert not ep.recv_setpoint(sp, QUIET_S)  # half a frame arrived
    corrupt = bytearray(setpoint_frame(2))
    corrupt[-2] ^= 1
    os.write(slave, first[6:] + bytes(corrupt) + setpoint_frame(3))
    assert ep.recv_setpoint(sp, WAIT_S) and sp.seq == 1
    assert ep.recv_setpoint(sp, WAIT_S) and sp.seq == 3
    s = ep.stats
    assert (s.received, s.malformed, s.lost) == (2, 1, 1)
    assert s.frames == 3


def test_descriptor_is_owned_and_closed(pty_device):
    ep, _, master = pty_device
    ep.close()
    with pytest.raises(OSError):
        os.fstat(master)


@pytest.mark.parametrize("url, error, match", [
    ("serial://", AdapterConfigError, "expected serial://PATH"),
    ("serial://fd/x", AdapterConfigError, "fd/N"),
    ("serial://loop://?baud=0", AdapterConfigError, "baud"),
    ("serial://loop://?parity=E", AdapterConfigError, "unknown option 'parity'"),
    ("serial://loop://?write_timeout_s=0.1", AdapterConfigError,
     "unknown option 'write_timeout_s'"),
    ("serial://loop://?takeover_ms=0", AdapterConfigError, "takeover_ms"),
    ("serial:///dev/no-such-tty", AdapterError, "cannot open serial port"),
])
def test_bad_serial_urls(url, error, match):
    with pytest.raises(error, match=match):
        open_endpoint(url, "device")
