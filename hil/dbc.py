"""The nodes' PDO frames as CAN tools decode them: a DBC (the CAN database format of
Vector's tools, asammdf's and canmatrix's, written with canmatrix) and a decode file for
python-can's ``can.viewer``, from a node's mapping (``hil eds``: the one it powers up with).

Each valid PDO of each node is a frame (``TPDO2_node5``: its COB-ID, its length); each
object mapped into it a little-endian signal at its bit offset, signed as its data type,
named after CiA's name and its index (``Position_actual_value_6064``), with its unit:
position, velocity and acceleration objects in the factor group's units (increments at
power-on: ``inc``, ``inc/s``, ``inc/s2``), torques and currents in per mille of the rated
value.  A dummy entry (an index below 1000h, CiA 301's data type objects) is padding.

The viewer file has one line per frame, ``COBID:<struct format>`` (``185:<HHl``), as
``python -m can.viewer -d FILE`` reads it: values in the order of the frame's signals.
"""

from dataclasses import dataclass
from pathlib import Path

import canmatrix
import canmatrix.formats

from io_adapters.can_catalog import ACCELERATION, POSITION, VELOCITY, spec

#: RPDO and TPDO communication and mapping parameter indices (the first of four each)
PDO_KINDS = (("RPDO", 0x1400, 0x1600), ("TPDO", 0x1800, 0x1A00))
#: the COB-ID's bit that makes a PDO not valid (CiA 301)
NOT_VALID = 1 << 31
#: canopen's signed data types: INTEGER8, 16, 32
SIGNED_TYPES = frozenset((0x2, 0x3, 0x4))
#: units of the factor group's objects at power-on (CiA 402)
UNITS = {POSITION: "inc", VELOCITY: "inc/s", ACCELERATION: "inc/s2"}
#: objects in per mille of the rated torque or current (CiA 402)
PER_MILLE = frozenset((0x6071, 0x6072, 0x6073, 0x6074, 0x6077, 0x6078, 0x60B2))
#: the longest signal name a DBC takes
MAX_NAME = 32
#: struct format codes of whole-byte integers, by (bytes, signed)
STRUCT_CODES = {(1, False): "B", (1, True): "b", (2, False): "H", (2, True): "h",
                (4, False): "L", (4, True): "l"}


@dataclass(frozen=True)
class PdoSignal:
    """One object mapped into a PDO.

    Attributes:
        name: a C identifier of at most :data:`MAX_NAME` characters: CiA's name (cut
            short where needed) and the index (and sub-index if not 0).
        index, subindex: the object.
        start_bit: its first bit in the frame (little-endian).
        bits: its length.
        signed: a signed data type.
        unit: see the module docstring ("" for none).
    """
    name: str
    index: int
    subindex: int
    start_bit: int
    bits: int
    signed: bool
    unit: str


@dataclass(frozen=True)
class PdoFrame:
    """One valid PDO of a node: ``name`` (``RPDO1_node5``), ``cob_id``, its length in
    bytes and its signals."""
    name: str
    cob_id: int
    size: int
    signals: tuple[PdoSignal, ...]


def _signal(entry: int, start_bit: int) -> PdoSignal | None:
    """The signal of a mapping entry (index << 16 | sub-index << 8 | bits), None for a
    dummy entry or an object the dictionary does not have."""
    index, subindex, bits = entry >> 16, entry >> 8 & 0xFF, entry & 0xFF
    s = spec(index, subindex) if index >= 0x1000 else None
    if s is None:
        return None
    words = "".join(c if c.isalnum() else "_" for c in s.name).strip("_")
    suffix = f"_{index:04X}" + (f"_{subindex}" if subindex else "")
    name = words[:MAX_NAME - len(suffix)].rstrip("_") + suffix
    unit = "permille" if index in PER_MILLE else UNITS.get(s.unit, "")
    return PdoSignal(name, index, subindex, start_bit, bits, s.data_type in SIGNED_TYPES,
                     unit)


def pdo_frames(node: int, values: dict) -> list[PdoFrame]:
    """Every valid PDO of node ``node`` whose objects are ``values`` ((index, sub-index)
    -> value, as :class:`hil.eds.DeviceValues` has them), RPDOs then TPDOs."""
    frames = []
    for kind, comm, mapping in PDO_KINDS:
        for n in range(4):
            cob_id = values[(comm + n, 1)]
            if cob_id & NOT_VALID:
                continue
            signals, at = [], 0
            for k in range(1, values[(mapping + n, 0)] + 1):
                entry = values[(mapping + n, k)]
                signal = _signal(entry, at)
                if signal is not None:
                    signals.append(signal)
                at += entry & 0xFF
            frames.append(PdoFrame(f"{kind}{n + 1}_node{node}", cob_id & 0x7FF,
                                   (at + 7) // 8, tuple(signals)))
    return frames


def write_dbc(frames: list[PdoFrame], path: Path) -> Path:
    """The DBC of ``frames`` at ``path`` (canmatrix's writer)."""
    db = canmatrix.CanMatrix()
    for f in frames:
        frame = canmatrix.Frame(f.name, arbitration_id=canmatrix.ArbitrationId(
            f.cob_id, extended=False), size=f.size)
        for s in f.signals:
            frame.add_signal(canmatrix.Signal(
                s.name, start_bit=s.start_bit, size=s.bits, is_little_endian=True,
                is_signed=s.signed, unit=s.unit,
                comment=f"{s.index:04X}h sub {s.subindex} ({spec(s.index, s.subindex).name})"))
        db.add_frame(frame)
    canmatrix.formats.dumpp({"": db}, str(path))
    return path


def viewer_line(frame: PdoFrame) -> str | None:
    """``can.viewer``'s decode line of ``frame`` (None: a signal or gap that is not whole
    bytes, which a struct format cannot say)."""
    codes, at = [], 0
    for s in frame.signals:
        if s.start_bit % 8 or s.start_bit < at or (s.bits // 8, s.signed) not in STRUCT_CODES \
                or s.bits % 8:
            return None
        codes.append("x" * ((s.start_bit - at) // 8) + STRUCT_CODES[(s.bits // 8, s.signed)])
        at = s.start_bit + s.bits
    return f"{frame.cob_id:X}:<{''.join(codes)}{'x' * (frame.size - at // 8)}"


def write_viewer(frames: list[PdoFrame], path: Path) -> Path:
    """``can.viewer``'s decode file of ``frames`` at ``path`` (module docstring)."""
    lines = [line for line in map(viewer_line, frames) if line is not None]
    path.write_text("\n".join(lines) + "\n")
    return path
