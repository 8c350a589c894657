"""The frames of ``hil bench fuzz``: a master that enables the drives and runs a program of
valid setpoints, and mutations of what it sends, from numpy's seeded generator.

The master holds each axis in one mode and value for a random number of frames
(:class:`AxisProgram`: CST at a share of the peak current or at the peak itself, CSV at a
share of 6080h, CSP near the position actual), as a controller's program does, so that
the axes move and run into their limits.  The mutations come in weather
(:class:`Weather`): calm stretches with few, storms where half the frames are mutated,
so the drives both move and keep meeting faults.

Each generator returns what its transport sends: msgpack bytes (:class:`MsgpackFrames`,
wire version 1 for one axis, 2 for several; :func:`serial_bytes` frames them with the
serial link's framing mutations), a CAN frame (:class:`RpdoFrames`) or an SDO expedited
download request (:class:`SdoRequests`).
"""

import math
import struct
from dataclasses import dataclass

import msgpack
import numpy as np
from canopen.objectdictionary import ODVariable

from io_adapters import codec
from io_adapters.cia402_objects import drive_object_dictionary, rpdo_layouts
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    axis_records,
    message_pair,
)
from io_adapters.serial_link import MAX_PAYLOAD, SOF, frame

SPECIAL_FLOATS = (math.nan, math.inf, -math.inf, 1e308, -1e308, -0.0)
#: values just past the Arrow 500 X drive's bounds: 28 A, 600 V, 2**53 increments
PAST_BOUNDS = (math.nextafter(28.0, math.inf), 600.5, 2.0**53 + 2.0, 1e6)
FOREIGN_MODES = (42, 0, -128, 127, 11, 1, 6)
HUGE_INTS = (2**64 - 1, 2**63, 2**32, -1, -2**63)
WRONG_TYPES = ("x", None, True, (1,), b"\x01", {1: 2}, 1.5, 7)
SPECIAL_INTS = (0, 1, -1, 8, 9, 10, 42, -128, 127, 1000, 1001, -1001, 2**15 - 1, -2**15,
                2**31 - 1, -2**31, 0xFFFF)
#: (mode, share of frames) of the master's program
MODES = ((MODE_CST, 0.5), (MODE_CSV, 0.25), (MODE_CSP, 0.25))


@dataclass(frozen=True)
class AxisLimits:
    """What the master's program needs of one drive, wire units.

    Attributes:
        current_a: the peak current (CST), A.
        speed_counts_s: 6080h, increments/s.
        counts_per_mm: motor-encoder increments per mm of table travel.
    """
    current_a: float
    speed_counts_s: float
    counts_per_mm: float


class AxisProgram:
    """One axis's valid setpoints: a mode and a value held for a random number of frames
    (geometric, mean ``mean_frames``)."""

    def __init__(self, rng: np.random.Generator, limits: AxisLimits, mean_frames: float = 500.0):
        self.rng, self.limits, self.mean_frames = rng, limits, mean_frames
        self.left = 0
        self.mode, self.share = MODE_CST, 0.0

    def next(self, counts: float) -> tuple[int, float, float, float]:
        """(mode, target position in increments, target velocity in increments/s, q current
        in A) for this frame, ``counts`` the position actual."""
        rng, lim = self.rng, self.limits
        if self.left <= 0:
            self.left = int(rng.geometric(1.0 / self.mean_frames))
            self.mode = int(rng.choice([m for m, _ in MODES], p=[p for _, p in MODES]))
            self.share = float(rng.uniform(-1.0, 1.0))
            if self.mode == MODE_CST and rng.random() < 0.2:
                self.share = math.copysign(1.0, self.share)  # at the peak current
        self.left -= 1
        if self.mode == MODE_CST:
            return MODE_CST, 0.0, 0.0, self.share * lim.current_a
        if self.mode == MODE_CSV:
            return MODE_CSV, 0.0, 0.5 * self.share * lim.speed_counts_s, 0.0
        return MODE_CSP, counts + 0.5 * self.share * lim.counts_per_mm, 0.0, 0.0


class Weather:
    """Calm (1 % of the frames mutated) and storms (50 %) in turn, calm first, each lasting
    a random number of frames (geometric, mean ``mean_frames``)."""

    def __init__(self, rng: np.random.Generator, mean_frames: float = 2000.0):
        self.rng, self.mean_frames = rng, mean_frames
        self.storm, self.left = False, int(rng.geometric(1.0 / mean_frames))
        self.ended_storm = False

    def mutate(self) -> bool:
        """Whether this frame is mutated; ``ended_storm`` is True on the first frame after
        a storm."""
        self.ended_storm = False
        if self.left <= 0:
            self.ended_storm = self.storm
            self.storm = not self.storm
            self.left = int(self.rng.geometric(1.0 / self.mean_frames))
        self.left -= 1
        return self.rng.random() < (0.5 if self.storm else 0.01)


class MsgpackFrames:
    """Setpoint messages of ``n_axes`` axes (wire version 1 for one, 2 for several) of one
    session, a share of them mutated.

    Args:
        rng: the generator.
        limits: each axis's :class:`AxisLimits`.
    """

    VALUE = ("special float", "past bound", "foreign mode", "huge int", "wrong type", "drop",
             "extra", "version", "kind", "axes")
    SEQUENCE = ("stale session", "duplicate", "older", "hello")
    BYTES = ("truncate", "concatenate", "flip", "random")

    def __init__(self, rng: np.random.Generator, limits: list[AxisLimits]):
        self.rng = rng
        self.n_axes = len(limits)
        self.programs = [AxisProgram(rng, lim) for lim in limits]
        self.weather = Weather(rng)
        self.message = message_pair(self.n_axes)[0]
        self.session = int(rng.integers(0, 2**32))
        self.frame_no = 0
        self.last = b""

    def next(self, words: list[int], counts: list[float]) -> bytes:
        """The next message: the master's controlwords ``words`` and valid setpoints for
        axes at ``counts`` increments, perhaps mutated."""
        message = self.message
        message.seq = (message.seq + 1) & codec.U32
        for rec, program, word, c in zip(axis_records(message), self.programs, words, counts):
            rec.controlword = word
            rec.mode, rec.target_position_counts, rec.target_velocity_counts_s, \
                rec.iq_ref_a = program.next(c)
        data = codec.encode(message, self.session, self.frame_no)
        self.frame_no = (self.frame_no + 1) & codec.U32
        if self.weather.mutate():
            data = self._mutated(data)
        self.last = data
        return data

    def _mutated(self, data: bytes) -> bytes:
        rng = self.rng
        kind = str(rng.choice(self.VALUE + self.SEQUENCE + self.BYTES))
        if kind in self.BYTES:
            # a flipped bit that leaves a well-formed message with a frame number far ahead
            # locks the master out until its own count gets there: flips spare the header
            header = len(msgpack.packb(msgpack.unpackb(data)[:4]))
            return mutated_bytes(rng, kind, data, self.last, header)
        if kind == "hello":
            return codec.encode_hello(self.session, self.frame_no)
        values = msgpack.unpackb(data)
        if kind == "stale session":
            values[2] = (self.session + 1 + int(rng.integers(0, 2**31))) & codec.U32
        elif kind == "duplicate":
            values[3] = (values[3] - 1) & codec.U32
        elif kind == "older":
            values[3] = (values[3] - int(rng.integers(2, 1000))) & codec.U32
        elif kind == "version":
            values[0] = int(rng.choice([0, 3, 255, 2 if self.n_axes == 1 else 1]))
        elif kind == "kind":
            values[1] = int(rng.choice([0, 2, 5, 255]))
        elif kind == "axes":
            values = self._other_axes(values)
        else:
            self._value(kind, values)
        return msgpack.packb(values)

    def _value(self, kind: str, values: list) -> None:
        """One element of ``values`` (or of an axis array) changed as ``kind`` says."""
        rng = self.rng
        row = values[-1][int(rng.integers(0, self.n_axes))] if self.n_axes > 1 else values
        fields = codec.GROUP_SCHEMAS[type(self.message)].axis if self.n_axes > 1 else (
            codec.HEADER + codec.SETPOINT_FIELDS)
        floats = [i for i, f in enumerate(fields) if f.type is float]
        ints = [i for i, f in enumerate(fields) if f.type is int]
        mode = [f.name for f in fields].index("mode")
        if kind == "special float":
            row[int(rng.choice(floats))] = SPECIAL_FLOATS[rng.integers(len(SPECIAL_FLOATS))]
        elif kind == "past bound":
            row[int(rng.choice(floats))] = float(rng.choice(PAST_BOUNDS)) * rng.choice([1, -1])
        elif kind == "foreign mode":
            row[mode] = int(rng.choice(FOREIGN_MODES))
        elif kind == "huge int":
            row[int(rng.choice(ints))] = int(HUGE_INTS[rng.integers(len(HUGE_INTS))])
        elif kind == "wrong type":
            row[int(rng.integers(0, len(row)))] = WRONG_TYPES[rng.integers(len(WRONG_TYPES))]
        elif kind == "drop":
            del row[int(rng.integers(0, len(row)))]
        else:
            row.append(float(rng.normal()))

    def _other_axes(self, values: list) -> list:
        """The message as a group of another number of axes (a plain record for a group)."""
        n = int(self.rng.choice([k for k in (1, 2, 3) if k != self.n_axes]))
        other = message_pair(n)[0]
        return msgpack.unpackb(codec.encode(other, self.session, values[3]))


def mutated_bytes(rng: np.random.Generator, kind: str, data: bytes, last: bytes,
                  keep: int) -> bytes:
    """``data`` truncated, followed by (part of) ``last``, with a bit flipped past its
    first ``keep`` bytes, or random bytes."""
    if kind == "truncate":
        return data[:int(rng.integers(1, len(data)))]
    if kind == "concatenate":
        return data + (last or data)[:int(rng.integers(1, len(last or data) + 1))]
    if kind == "flip":
        i = int(rng.integers(keep, len(data)))
        return data[:i] + bytes([data[i] ^ 1 << int(rng.integers(0, 8))]) + data[i + 1:]
    return rng.bytes(int(rng.integers(1, 120)))


SERIAL_MUTATIONS = ("crc", "length", "cut", "garbage", "empty")


def serial_bytes(rng: np.random.Generator, payload: bytes, mutate: bool) -> bytes:
    """``payload`` in a serial frame (SOF, length, CRC), or, when ``mutate`` and one time in
    three, a frame with a flipped bit, a wrong length, cut short, behind garbage, or with
    length 0."""
    good = frame(payload[:MAX_PAYLOAD])
    if not mutate or rng.random() < 2.0 / 3.0:
        return good
    kind = str(rng.choice(SERIAL_MUTATIONS))
    if kind == "crc":
        i = int(rng.integers(2, len(good)))
        return good[:i] + bytes([good[i] ^ 1 << int(rng.integers(0, 8))]) + good[i + 1:]
    if kind == "length":
        return good[:2] + bytes([int(rng.integers(0, 256))]) + good[3:]
    if kind == "cut":
        return good[:int(rng.integers(1, len(good)))]
    if kind == "garbage":
        return rng.bytes(int(rng.integers(1, 40))) + good
    return SOF + b"\x00"


def packed(fmt: str, value: int) -> bytes:
    """``value`` wrapped into the little-endian integer field ``fmt``."""
    bits = 8 * struct.calcsize(fmt)
    value &= (1 << bits) - 1
    if fmt[-1].islower() and value >= 1 << bits - 1:
        value -= 1 << bits
    return struct.pack(fmt, value)


def _permille(current_a: float, rated_current_a: float) -> int:
    return round(current_a / rated_current_a * 1e3)


class RpdoFrames:
    """The RPDOs of one node: the master's controlword and mode (RPDO1), targets (RPDO2,
    RPDO3) and currents (RPDO4) from its program, a share of them mutated: a field at a
    special value, a DLC one byte off, random bytes, or any COB-ID (but NMT, SYNC and the
    node's SDO request).

    Args:
        rng: the generator.
        node: the node-ID.
        limits: the axis's :class:`AxisLimits`.
        rated_current_a: 6075h, the reference of the per-mille currents, A.
    """

    def __init__(self, rng: np.random.Generator, node: int, limits: AxisLimits,
                 rated_current_a: float):
        self.rng, self.rated_a = rng, rated_current_a
        self.layouts = rpdo_layouts(node)
        self.program = AxisProgram(rng, limits)
        self.weather = Weather(rng)
        self.other_ids = np.array([i for i in range(0x800)
                                   if i not in (0x000, 0x080, 0x600 + node)])

    def next(self, word: int, counts: float) -> tuple[int, bytes]:
        """(COB-ID, data) of the next frame for the controlword ``word`` at ``counts``."""
        rng = self.rng
        mode, position, velocity, iq = self.program.next(counts)
        values = ((word, mode), (_wrap_i32(position), 0), (_wrap_i32(velocity),),
                  (_permille(iq, self.rated_a), 0))
        n = int(rng.choice(4, p=(0.4, 0.15, 0.15, 0.3)))
        layout, fields = self.layouts[n], list(values[n])
        if not self.weather.mutate():
            return layout.cob_id, layout.frame.pack(*fields)
        kind = int(rng.integers(0, 4))
        if kind == 0:  # a field at a special value
            fields[int(rng.integers(0, len(fields)))] = int(rng.choice(SPECIAL_INTS))
            codes = layout.frame.format[1:]
            return layout.cob_id, b"".join(packed("<" + c, v) for c, v in zip(codes, fields))
        if kind == 1:  # the DLC one byte off
            data = layout.frame.pack(*values[n])
            return layout.cob_id, data[:-1] if rng.random() < 0.5 else data + b"\0"
        if kind == 2:  # random bytes on an RPDO
            return layout.cob_id, rng.bytes(int(rng.integers(0, 9)))
        return int(rng.choice(self.other_ids)), rng.bytes(int(rng.integers(0, 9)))


def _wrap_i32(value: float) -> int:
    return (round(value) + 2**31) % 2**32 - 2**31


def dictionary_entries(node: int, rated_current_ma: int) -> list[tuple[int, int, int, bool]]:
    """(index, sub-index, size in bytes, writable) of every object of the drive's
    dictionary."""
    entries = []
    for obj in drive_object_dictionary(node, rated_current_ma).values():
        for var in [obj] if isinstance(obj, ODVariable) else obj.values():
            entries.append((var.index, var.subindex, len(var) // 8, var.writable))
    return entries


#: the process-data inputs a master writes, with their wire types
INPUTS = {(0x6040, 0): "<H", (0x6060, 0): "<b", (0x607A, 0): "<i", (0x60B1, 0): "<i",
          (0x60FF, 0): "<i", (0x6071, 0): "<h", (0x60B2, 0): "<h"}


class SdoRequests:
    """SDO expedited download requests to one node: the master's controlword, mode, target
    and current from its program, a share of them mutated: an input at a special value, of
    the wrong size or sub-index, any object of the dictionary (parameters included) with
    any value, any index and sub-index.

    Args:
        rng: the generator.
        node: the node-ID.
        limits: the axis's :class:`AxisLimits`.
        rated_current_ma: 6075h, mA.
    """

    def __init__(self, rng: np.random.Generator, node: int, limits: AxisLimits,
                 rated_current_ma: int):
        self.rng, self.rated_a = rng, rated_current_ma / 1e3
        self.program = AxisProgram(rng, limits)
        self.weather = Weather(rng)
        self.entries = dictionary_entries(node, rated_current_ma)

    def next(self, word: int, counts: float) -> tuple[int, int, bytes]:
        """(index, sub-index, request) of the next download for ``word`` at ``counts``."""
        rng = self.rng
        mode, position, velocity, iq = self.program.next(counts)
        target = {MODE_CST: ((0x6071, 0), _permille(iq, self.rated_a)),
                  MODE_CSV: ((0x60FF, 0), _wrap_i32(velocity)),
                  MODE_CSP: ((0x607A, 0), _wrap_i32(position))}[mode]
        key, value = [((0x6040, 0), word), ((0x6060, 0), mode), target][
            int(rng.choice(3, p=(0.5, 0.2, 0.3)))]
        size = struct.calcsize(INPUTS[key])
        if self.weather.mutate():
            kind = int(rng.integers(0, 5))
            if kind == 0:
                value = int(rng.choice(SPECIAL_INTS))
            elif kind == 1:
                size = int(rng.choice([1, 2, 3, 4]))
            elif kind == 2:
                key = (key[0], int(rng.integers(1, 256)))
            elif kind == 3:
                index, sub, size, _ = self.entries[int(rng.integers(len(self.entries)))]
                key, value = (index, sub), int(rng.integers(-2**31, 2**32))
            else:
                key = (int(rng.integers(0, 0x10000)), int(rng.integers(0, 256)))
                size, value = int(rng.choice([1, 2, 3, 4])), int(rng.integers(-2**31, 2**32))
        data = packed("<q", value)[:size]
        request = bytes([0x23 | (4 - size) << 2]) + struct.pack("<HB", *key) + data.ljust(4, b"\0")
        return key[0], key[1], request
