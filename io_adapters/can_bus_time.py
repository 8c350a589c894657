"""What a CAN frame costs on the wire, and what a PDO configuration asks of the bus.

A classic CAN 2.0A frame (11-bit identifier) is SOF, identifier, RTR, IDE, r0, DLC, the
data bytes and the 15-bit CRC -- the part the transmitter bit-stuffs: after five equal bits
in a row it inserts one of the opposite value, and a stuff bit counts in the next run --
then CRC delimiter, ACK slot, ACK delimiter, 7 bits of end of frame and the 3 bits of
intermission before the next frame may start (ISO 11898-1).  :func:`frame_bits` counts
them for one frame as sent (the CRC computed, the stuff bits counted);
:func:`worst_frame_bits` is the bound over every identifier and data of that length,
``8n + 47 + floor((33 + 8n) / 4)`` bits (Davis, Burns, Bril, Lukkien 2007, eq. 4 with
the intermission): 55 bits for an empty frame, 135 for eight bytes.

:class:`BusPlan` is one communication cycle of a configuration: the frames it sends,
each at its rate (:func:`plan_cycle`; a frame sent every n cycles counts 1/n), their bits
at the worst stuffing and the bus load at a bit rate.
"""

from dataclasses import dataclass

#: ISO 11898-1 CRC-15 generator x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1
CRC15_POLY = 0x4599
#: bits after the CRC that are never stuffed: delimiter, ACK slot and delimiter, EOF, IFS
TRAILER_BITS = 1 + 1 + 1 + 7 + 3
#: the bit rates of CiA 301 (bit/s)
BIT_RATES = (10_000, 20_000, 50_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)


def _crc15(bits: list[int]) -> int:
    crc = 0
    for bit in bits:
        top = (crc >> 14) & 1
        crc = (crc << 1) & 0x7FFF
        if bit ^ top:
            crc ^= CRC15_POLY
    return crc


def _bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def frame_bits(can_id: int, data: bytes) -> int:
    """Bits one data frame with an 11-bit ``can_id`` and ``data`` (0-8 bytes) takes on
    the bus, stuff bits and intermission included."""
    if not 0 <= can_id < 0x800 or len(data) > 8:
        raise ValueError(f"not a classic 11-bit data frame: id {can_id:#x}, {len(data)} bytes")
    head = [0] + _bits(can_id, 11) + [0, 0, 0] + _bits(len(data), 4)
    for byte in data:
        head += _bits(byte, 8)
    stuffed = head + _bits(_crc15(head), 15)
    stuff, run, last = 0, 0, None
    for bit in stuffed:
        if bit == last:
            run += 1
        else:
            run, last = 1, bit
        if run == 5:  # a stuff bit of the other value, which starts the next run
            stuff += 1
            run, last = 1, 1 - bit
    return len(stuffed) + stuff + TRAILER_BITS


def worst_frame_bits(n_bytes: int) -> int:
    """The most bits a data frame of ``n_bytes`` (0-8) with an 11-bit identifier can
    take, intermission included."""
    if not 0 <= n_bytes <= 8:
        raise ValueError(f"{n_bytes} bytes: a classic CAN frame holds 0 to 8")
    return 8 * n_bytes + 47 + (33 + 8 * n_bytes) // 4


@dataclass(frozen=True)
class BusPlan:
    """One communication cycle of a configuration: every frame at its rate, each at its
    worst stuffing.

    Attributes:
        frames: (what, frames per cycle, data bytes) of every kind of frame counted.
        bits: the bits they take per cycle (worst-case stuffing), the fractions of a
            frame sent only every n cycles counted as such.
        cycle_s: the communication cycle period (1006h), s.
        bitrate: bit/s.
    """
    frames: tuple[tuple[str, float, int], ...]
    bits: float
    cycle_s: float
    bitrate: int

    @property
    def load(self) -> float:
        """The share of the cycle the frames occupy (1.0: the whole cycle)."""
        return self.bits / (self.bitrate * self.cycle_s)

    @property
    def fits(self) -> bool:
        return self.load <= 1.0

    def describe(self) -> str:
        """One line: load, bits, cycle and bit rate."""
        return (f"{self.load:.0%} of the bus: {self.bits:.0f} bits per {self.cycle_s * 1e3:g} ms "
                f"cycle at {self.bitrate / 1e3:g} kbit/s ({len(self.frames)} kinds of frame)")

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"load": self.load, "bits_per_cycle": self.bits, "cycle_s": self.cycle_s,
                "bitrate": self.bitrate,
                "frames": [{"what": w, "per_cycle": n, "bytes": b} for w, n, b in self.frames]}


def plan_cycle(frames: list[tuple[str, float, int]], cycle_s: float, bitrate: int) -> BusPlan:
    """The plan of ``frames``, (what, frames per cycle, data bytes) each, at the worst
    stuffing."""
    bits = sum(n * worst_frame_bits(size) for _, n, size in frames)
    return BusPlan(tuple(frames), bits, cycle_s, bitrate)


def per_cycle(period_s: float, cycle_s: float) -> float:
    """Frames per cycle, on average, of something sent every ``period_s``: a heartbeat
    every 100 ms is 0.01 frame of a 1 ms cycle, not one (0 for a period of 0: never)."""
    return 0.0 if period_s <= 0.0 else cycle_s / period_s
