"""The fixed binary wire: Setpoint and Feedback as C structs, little-endian (``wire=fixed``).

The same records, handshake and rules as the msgpack wire (:mod:`io_adapters.codec`), in a
layout a C client reads and writes with one struct: every field at a fixed offset,
naturally aligned, explicit reserved fields instead of padding, no options.  The C header
``io_adapters/include/feeddrive_wire.h`` is the reference for the offsets (a test compiles
it and compares them with the tables here).  One layout serves one axis and several: a
message carries ``n_axes`` axis blocks after its common part (a single-axis link's records
are a group of one on this wire).

Header, 16 bytes, every message::

    0   u8[2]  magic     "FD" (0x46 0x44)
    2   u8     version   1 (anything else is refused)
    3   u8     kind      1 Setpoint, 2 Feedback, 3 HELLO, 4 WELCOME (as on msgpack)
    4   u32    session   drawn at random when the sending endpoint opens
    8   u32    frame     the sender's frame counter (wraps at 2**32)
    12  u16    n_axes    axis blocks that follow (0 in HELLO and WELCOME)
    14  u16    accepted  WELCOME: 1 the device takes this controller now, 0 not; else 0

Setpoint (kind 1): the header, then 16 + 64 bytes per axis::

    16  u32  seq    the controller's cycle counter
    20  u32  reserved (0)
    24  i64  t_ns   controller monotonic clock at sending, ns (>= 0)
    32 + 64 i, axis i:
        0  u16  controlword (6040h)     2  i8  mode (6060h)     3  u8  reserved (0)
        4  u32  reserved (0)
        8  f64  target_position_counts     16 f64  target_velocity_counts_s
        24 f64  velocity_offset_counts_s   32 f64  iq_ref_a     40 f64  id_ref_a
        48 f64  ud_v                       56 f64  uq_v

Feedback (kind 2): the header, then 48 + 64 bytes per axis::

    16  u32  seq       seq of the setpoint answered     20  u32  reserved (0)
    24  f64  time_s    drive time at the end of the cycle, s
    32  i64  sp_t_ns   40  i64  sp_rx_ns   48  i64  t_ns   56  i64  tick_ns  (ns, >= 0)
    64 + 64 i, axis i:
        0  u16  statusword (6041h)      2  u16  digital_inputs (60FDh)
        4  i32  fault (603Fh)
        8  f64  encoder_counts          16 f64  scale_counts     24 f64  velocity_counts_s
        32 f64  iq_a                    40 f64  id_a
        48 f64  index_counts            the position of the index mark last passed
        56 i32  index_marks             index marks below the encoder position
        60 u32  reserved (0)

Fields mean what they mean on :class:`~io_adapters.messages.Setpoint` and
:class:`~io_adapters.messages.Feedback`; the feedback also carries the drive's digital
inputs and index mark, which the msgpack wire does not.  HELLO and WELCOME are the header
alone.  INJECT (a test bench's fault injection message) is not carried: a fault is
injected on the msgpack wire, over CAN, or by ``hil run --inject``.

Decoding is strict: a message of another length than its kind and number of axes give, a
bad magic, version or kind, another number of axes than the receiver's, a reserved field
that is not 0, a negative stamp or an ``accepted`` that is not 0 or 1 raises
:class:`~io_adapters.base.FrameError` (the endpoint counts it ``malformed``); NaN and
infinite floats decode and are refused as values by the endpoint, as on msgpack.  The
decoded form is the msgpack wire's arrays (:func:`io_adapters.codec.decode`), the feedback
extended by ``digital_inputs``, ``index_marks`` and ``index_counts`` (per axis in a group),
so the endpoint's checks after decoding are the same for both wires.
"""

import math
import operator
import struct
from functools import cache

from io_adapters import codec
from io_adapters.base import FrameError
from io_adapters.codec import (
    KIND_FEEDBACK,
    KIND_HELLO,
    KIND_INJECT,
    KIND_SETPOINT,
    KIND_WELCOME,
)
from io_adapters.messages import Feedback, FeedbackGroup, Setpoint, SetpointGroup
from io_adapters.wire import Wire

MAGIC = b"FD"
VERSION = 1
T_NS_MAX = codec.T_NS_MAX

#: the layout, block by block: (C struct, ((field, struct format code), ...)); a field
#: named ``reserved*`` must be 0; the C header names the same structs and fields
HEADER_FIELDS = (("magic", "2s"), ("version", "B"), ("kind", "B"), ("session", "I"),
                 ("frame", "I"), ("n_axes", "H"), ("accepted", "H"))
SETPOINT_COMMON = (("seq", "I"), ("reserved", "I"), ("t_ns", "q"))
SETPOINT_AXIS = (("controlword", "H"), ("mode", "b"), ("reserved0", "B"), ("reserved1", "I"),
                 ("target_position_counts", "d"), ("target_velocity_counts_s", "d"),
                 ("velocity_offset_counts_s", "d"), ("iq_ref_a", "d"), ("id_ref_a", "d"),
                 ("ud_v", "d"), ("uq_v", "d"))
FEEDBACK_COMMON = (("seq", "I"), ("reserved", "I"), ("time_s", "d"), ("sp_t_ns", "q"),
                   ("sp_rx_ns", "q"), ("t_ns", "q"), ("tick_ns", "q"))
FEEDBACK_AXIS = (("statusword", "H"), ("digital_inputs", "H"), ("fault", "i"),
                 ("encoder_counts", "d"), ("scale_counts", "d"), ("velocity_counts_s", "d"),
                 ("iq_a", "d"), ("id_a", "d"), ("index_counts", "d"), ("index_marks", "i"),
                 ("reserved", "I"))
#: C struct -> its fields; a record struct's axis blocks follow it (a flexible array)
STRUCTS = {"fdw_header": HEADER_FIELDS,
           "fdw_setpoint": HEADER_FIELDS + SETPOINT_COMMON,
           "fdw_setpoint_axis": SETPOINT_AXIS,
           "fdw_feedback": HEADER_FIELDS + FEEDBACK_COMMON,
           "fdw_feedback_axis": FEEDBACK_AXIS}
#: the most axes a message carries (a datagram of 64 + 64 * 64 bytes at most)
MAX_AXES = 64

HEADER = struct.Struct("<" + "".join(code for _, code in HEADER_FIELDS))
HEADER_SIZE = HEADER.size
#: the stamps, whose range (0 to 2**63 - 1) is narrower than their format code's
STAMPS = frozenset(("t_ns", "sp_t_ns", "sp_rx_ns", "tick_ns"))


def offsets(fields: tuple) -> list[tuple[str, int, str]]:
    """``[(field, byte offset, format code), ...]`` of a block laid out as ``fields``."""
    out, at = [], 0
    for name, code in fields:
        out.append((name, at, code))
        at += struct.calcsize("<" + code)
    return out


@cache
def _layout(kind: int, n_axes: int) -> struct.Struct:
    """The whole message of ``kind`` with ``n_axes`` axis blocks."""
    common, axis = ((SETPOINT_COMMON, SETPOINT_AXIS) if kind == KIND_SETPOINT
                    else (FEEDBACK_COMMON, FEEDBACK_AXIS))
    return struct.Struct("<" + "".join(c for _, c in HEADER_FIELDS + common)
                         + "".join(c for _, c in axis) * n_axes)


def largest_message(n_axes: int) -> int:
    """Bytes of this wire's longest message of ``n_axes`` axes (the feedback: 64 + 64 per
    axis; the setpoint is 32 + 64 per axis)."""
    return max(_layout(kind, n_axes).size for kind in (KIND_SETPOINT, KIND_FEEDBACK))


@cache
def _stamps(kind: int) -> tuple[int, ...]:
    """Where the stamps are among a message's values (in its common part)."""
    common = SETPOINT_COMMON if kind == KIND_SETPOINT else FEEDBACK_COMMON
    return tuple(i for i, (f, _) in enumerate(HEADER_FIELDS + common) if f in STAMPS)


@cache
def _names(kind: int, n_axes: int) -> tuple[str, ...]:
    """Every value's name in a message of ``kind`` with ``n_axes`` axis blocks, for the
    error messages (``axes[i].field`` in a group)."""
    common, axis = ((SETPOINT_COMMON, SETPOINT_AXIS) if kind == KIND_SETPOINT
                    else (FEEDBACK_COMMON, FEEDBACK_AXIS))
    return tuple(f for f, _ in HEADER_FIELDS + common) + tuple(
        f"axes[{i}].{f}" if n_axes > 1 else f for i in range(n_axes) for f, _ in axis)


def _is_setpoint(record_type: type) -> bool:
    return record_type is Setpoint or record_type is SetpointGroup


# -- encoding ------------------------------------------------------------------------------

def _pack(kind: int, n_axes: int, values: tuple, what: str) -> bytes:
    """``values`` packed as a message of ``kind`` with ``n_axes`` axis blocks, or
    FrameError naming the first field that does not fit."""
    layout, names = _layout(kind, n_axes), _names(kind, n_axes)
    for i in _stamps(kind):
        value = values[i]
        if not (hasattr(value, "__index__") and 0 <= operator.index(value) <= T_NS_MAX):
            raise FrameError(f"{what}.{names[i]}={value!r}: not an integer in [0, "
                             f"{T_NS_MAX}]")
    try:
        return layout.pack(*values)
    except struct.error as e:
        for name, code, value in zip(names, _codes(layout.format[1:]), values):
            try:
                struct.pack("<" + code, value)
            except struct.error:
                raise FrameError(f"{what}.{name}={value!r} does not fit its field "
                                 f"({_CODE_NAMES[code]})") from e
        raise FrameError(f"{what}: {e}") from e


def _codes(fmt: str) -> list[str]:
    """The format codes of ``fmt``, one per value (``2s`` is one)."""
    out, i = [], 0
    while i < len(fmt):
        width = 2 if fmt[i].isdigit() else 1
        out.append(fmt[i:i + width])
        i += width
    return out


_CODE_NAMES = {"B": "u8", "b": "i8", "H": "u16", "I": "u32", "i": "i32", "q": "i64",
               "d": "f64", "2s": "2 bytes"}


def encode(record: Setpoint | Feedback | SetpointGroup | FeedbackGroup, session: int,
           frame: int) -> bytes:
    """One message carrying ``record`` (one axis block for a plain record).  Integers take
    anything with ``__index__`` and floats anything ``float()`` takes; FrameError names a
    field whose value does not fit."""
    kind = KIND_SETPOINT if _is_setpoint(type(record)) else KIND_FEEDBACK
    axes = record.axes if isinstance(record, (SetpointGroup, FeedbackGroup)) else (record,)
    n = len(axes)
    if not 1 <= n <= MAX_AXES:
        raise FrameError(f"{type(record).__name__} of {n} axes: 1 to {MAX_AXES} are carried")
    if kind == KIND_SETPOINT:
        common = (record.seq, 0, record.t_ns)
        per_axis = [(sp.controlword, sp.mode, 0, 0, sp.target_position_counts,
                     sp.target_velocity_counts_s, sp.velocity_offset_counts_s, sp.iq_ref_a,
                     sp.id_ref_a, sp.ud_v, sp.uq_v) for sp in axes]
    else:
        common = (record.seq, 0, record.time_s, record.sp_t_ns, record.sp_rx_ns,
                  record.t_ns, record.tick_ns)
        per_axis = [(fb.statusword, fb.digital_inputs, fb.fault, fb.encoder_counts,
                     fb.scale_counts, fb.velocity_counts_s, fb.iq_a, fb.id_a,
                     fb.index_counts, fb.index_marks, 0) for fb in axes]
    values = (MAGIC, VERSION, kind, session, frame, n, 0) + common + tuple(
        v for block in per_axis for v in block)
    return _pack(kind, n, values, type(record).__name__)


def encode_hello(session: int, frame: int) -> bytes:
    """A HELLO (controller -> device): the header alone."""
    return HEADER.pack(MAGIC, VERSION, KIND_HELLO, session, frame, 0, 0)


def encode_welcome(session: int, frame: int, accepted: bool) -> bytes:
    """A WELCOME (device -> controller): the header, ``accepted`` 1 or 0."""
    return HEADER.pack(MAGIC, VERSION, KIND_WELCOME, session, frame, 0, int(accepted))


def encode_inject(session: int, frame: int, request) -> bytes:
    """Not carried on this wire: FrameError."""
    raise FrameError("the fixed wire carries no INJECT: inject faults on the msgpack wire, "
                     "over CAN (2F00h) or with hil run --inject")


# -- decoding ------------------------------------------------------------------------------

def _header(data) -> tuple:
    """The checked header of ``data`` (magic and version)."""
    if len(data) < HEADER_SIZE:
        raise FrameError(f"{len(data)} bytes: shorter than the {HEADER_SIZE}-byte header")
    head = HEADER.unpack_from(data)
    if head[0] != MAGIC:
        raise FrameError(f"magic {head[0]!r}, expected {MAGIC!r}: not a fixed-wire message")
    if head[1] != VERSION:
        raise FrameError(f"version {head[1]}, expected {VERSION}")
    return head


def _handshake(data, head: tuple, kind: int) -> tuple:
    name = "HELLO" if kind == KIND_HELLO else "WELCOME"
    if len(data) != HEADER_SIZE:
        raise FrameError(f"{len(data)} bytes, expected {HEADER_SIZE} for {name}")
    _, _, _, session, frame, n_axes, accepted = head
    if n_axes != 0:
        raise FrameError(f"{name} n_axes={n_axes}: expected 0")
    if kind == KIND_HELLO:
        if accepted != 0:
            raise FrameError(f"HELLO accepted={accepted}: expected 0")
        return VERSION, kind, session, frame
    if accepted > 1:
        raise FrameError(f"WELCOME accepted={accepted}: expected 0 or 1")
    return VERSION, kind, session, frame, accepted


def decode_hello(data) -> tuple:
    """The checked array of a HELLO; FrameError for anything else."""
    head = _header(data)
    if head[2] != KIND_HELLO:
        raise FrameError(f"kind {head[2]}, expected {KIND_HELLO} (HELLO)")
    return _handshake(data, head, KIND_HELLO)


def decode(data, record_type: type, n_axes: int = 1) -> tuple:
    """The checked array of one message for ``record_type`` (a group of ``n_axes`` axes
    for the group types), or of the handshake message its receiver takes, in the msgpack
    wire's decoded form (module docstring); FrameError saying what is wrong otherwise."""
    head = _header(data)
    kind = head[2]
    setpoints = _is_setpoint(record_type)
    handshake = KIND_HELLO if setpoints else KIND_WELCOME
    if kind == handshake:
        return _handshake(data, head, kind)
    if kind == KIND_INJECT and setpoints:
        raise FrameError("INJECT: the fixed wire carries none")
    expected = KIND_SETPOINT if setpoints else KIND_FEEDBACK
    if kind != expected:
        raise FrameError(f"kind {kind}, expected {expected} ({record_type.__name__})")
    if head[5] != n_axes:
        raise FrameError(f"{record_type.__name__}: {head[5]} axes, expected {n_axes}")
    layout = _layout(kind, n_axes)
    if len(data) != layout.size:
        raise FrameError(f"{len(data)} bytes, expected {layout.size} for "
                         f"{record_type.__name__} of {n_axes} ax{'es' if n_axes > 1 else 'is'}")
    if head[6] != 0:
        raise FrameError(f"{record_type.__name__} accepted={head[6]}: expected 0")
    raw = layout.unpack(data)
    group = record_type is SetpointGroup or record_type is FeedbackGroup
    return (_setpoint if setpoints else _feedback)(raw, group, record_type.__name__)


def _check(name: str, what: str, value: int, lo: int, hi: int) -> None:
    if not lo <= value <= hi:
        raise FrameError(f"{what} {name}={value}: outside [{lo}, {hi}]")


def _setpoint(raw: tuple, group: bool, what: str) -> tuple:
    """The decoded array of a setpoint's unpacked values ``raw`` (header first)."""
    head, (seq, reserved, t_ns) = raw[1:5], raw[7:10]
    _check("reserved", what, reserved, 0, 0)
    _check("t_ns", what, t_ns, 0, T_NS_MAX)
    axes = []
    for i in range(10, len(raw), len(SETPOINT_AXIS)):
        cw, mode, r0, r1, *floats = raw[i:i + len(SETPOINT_AXIS)]
        if r0 or r1:
            raise FrameError(f"{what} axis {len(axes)}: reserved={r0 or r1}: expected 0")
        axes.append((cw, mode, *floats))
    version, kind, session, frame = (VERSION,) + head[1:]
    if group:
        return version, kind, session, frame, seq, t_ns, tuple(axes)
    return (version, kind, session, frame, seq) + axes[0] + (t_ns,)


def _feedback(raw: tuple, group: bool, what: str) -> tuple:
    """The decoded array of a feedback's unpacked values ``raw`` (header first)."""
    head = raw[1:5]
    seq, reserved, time_s, *stamps = raw[7:14]
    _check("reserved", what, reserved, 0, 0)
    for name, value in zip(("sp_t_ns", "sp_rx_ns", "t_ns", "tick_ns"), stamps):
        _check(name, what, value, 0, T_NS_MAX)
    axes = []
    for i in range(14, len(raw), len(FEEDBACK_AXIS)):
        (sw, di, fault, enc, scale, vel, iq, id_, index_counts, index_marks,
         r) = raw[i:i + len(FEEDBACK_AXIS)]
        if r:
            raise FrameError(f"{what} axis {len(axes)}: reserved={r}: expected 0")
        axes.append((sw, fault, enc, scale, vel, iq, id_, di, index_marks, index_counts))
    version, kind, session, frame = (VERSION,) + head[1:]
    if group:
        return (version, kind, session, frame, seq, time_s, *stamps, tuple(axes))
    sw, fault, enc, scale, vel, iq, id_, di, index_marks, index_counts = axes[0]
    return (version, kind, session, frame, seq, sw, fault, time_s, enc, scale, vel, iq, id_,
            *stamps, di, index_marks, index_counts)


def fill(into: Setpoint | Feedback | SetpointGroup | FeedbackGroup, values: tuple) -> None:
    """Write a decoded record into ``into`` (no new record)."""
    codec.fill(into, values)  # the msgpack wire's fields; the extras come last
    if type(into) is Feedback:
        into.digital_inputs, into.index_marks, into.index_counts = values[-3:]
    elif type(into) is FeedbackGroup:
        for rec, a in zip(into.axes, values[-1]):
            rec.digital_inputs, rec.index_marks, rec.index_counts = a[-3:]


def finite(values: tuple, record_type: type) -> bool:
    """Every float of a decoded record is finite."""
    schema = codec.GROUP_SCHEMAS.get(record_type) or codec.SCHEMAS[record_type]
    if not schema.finite(values):
        return False
    if record_type is Feedback:
        return math.isfinite(values[-1])
    if record_type is FeedbackGroup:
        return all(math.isfinite(a[-1]) for a in values[-1])
    return True


FIXED_WIRE = Wire(name="fixed", encode=encode, decode=decode, fill=fill, finite=finite,
                  encode_hello=encode_hello, decode_hello=decode_hello,
                  encode_welcome=encode_welcome, encode_inject=encode_inject,
                  hello_leads=frozenset(MAGIC[:1]))
