"""The msgpack wire format of Setpoint and Feedback and the handshake, shared by the UDP
and serial adapters.

Every message is one msgpack array: a four-element header, then the record's
fields in a fixed order.  Integers are msgpack ints, floats are float64.

Header (version 1)::

    0  version   int  1 (a receiver drops any other version)
    1  kind      int  1 = Setpoint, 2 = Feedback, 3 = HELLO, 4 = WELCOME (handshake)
    2  session   int  u32, drawn at random when the sending endpoint opens
    3  frame     int  u32, the sender's frame counter: 0, 1, 2, ... (wraps at 2**32)

Setpoint (kind 1), header then::

    4  seq          int    u32, the controller's cycle counter
    5  controlword  int    u16, CiA 402 controlword (6040h)
    6  mode                      int    i8, CiA 402 mode of operation (6060h; MODE_*)
    7  target_position_counts    float  motor-encoder increments (CSP)
    8  target_velocity_counts_s  float  increments/s (CSV)
    9  velocity_offset_counts_s  float  increments/s, speed feed-forward (CSP)
    10 iq_ref_a                  float  A, q-current setpoint
    11 id_ref_a                  float  A, d-current setpoint
    12 ud_v                      float  V, d-voltage setpoint
    13 uq_v                      float  V, q-voltage setpoint
    14 t_ns                      int    ns, controller monotonic clock at sending,
                                        0 <= t_ns < 2**63

Feedback (kind 2), header then::

    4  seq             int    u32, seq of the setpoint answered
    5  statusword      int    u16, CiA 402 statusword (6041h)
    6  fault           int    i32, the drive's error code 603Fh (0 = none)
    7  time_s          float  s, drive time at the end of the cycle
    8  encoder_counts  float  motor encoder counts
    9  scale_counts    float  linear scale counts
    10 velocity_counts_s float increments/s, the drive's speed actual value
    11 iq_a            float  A, sampled q current
    12 id_a            float  A, sampled d current
    13 sp_t_ns         int    ns, t_ns of the latest setpoint received (controller clock)
    14 sp_rx_ns        int    ns, drive monotonic clock when it arrived (UDP: the
                              kernel's receive stamp; serial: when the adapter read it)
    15 t_ns            int    ns, drive monotonic clock at sending
    16 tick_ns         int    ns, drive monotonic clock at the start of the tick that
                              produced it (0: not given)

Version 2: several axes in one message (:class:`~io_adapters.messages.SetpointGroup`,
:class:`~io_adapters.messages.FeedbackGroup`).  The same four-element header with version
2, then the message's common fields and one array per axis, in the machine's axis order::

    SetpointGroup (kind 1):  4 seq int u32    5 t_ns int ns
                             6 axes: N arrays [controlword, mode, target_position_counts,
                               target_velocity_counts_s, velocity_offset_counts_s,
                               iq_ref_a, id_ref_a, ud_v, uq_v]   (types as in version 1)
    FeedbackGroup (kind 2):  4 seq int u32    5 time_s float s    6 sp_t_ns   7 sp_rx_ns
                             8 t_ns   9 tick_ns (int ns, as in version 1)
                             10 axes: N arrays [statusword, fault, encoder_counts,
                               scale_counts, velocity_counts_s, iq_a, id_a]

A single-axis link keeps version 1 on the wire (plain records): a version-1 peer never
meets a version-2 message, and a receiver drops a message whose version is not the one
of the record it reads into (counted as malformed).  A group message with another
number of axes than the receiver's is malformed too ("3 axes, expected 2").

Handshake (kinds 3 and 4, version 1 on every link, single- or multi-axis: they carry no
axis data)::

    HELLO (kind 3, controller -> device):    the header only
    WELCOME (kind 4, device -> controller):  the header, then
        4  accepted  int  1: the device takes this controller's setpoints now; 0: it
                          serves another one (try again later)

A handshake message carries its sender's frame counter without advancing it and is no
part of the sequence check: the frame after it has the same number.

Fault injection (kind 5, version 1 on every link; controller -> device, a test bench's
message that no real drive has)::

    INJECT:  the header, then
        4  axis      int  0-255, the axis (0-based, the machine's order)
        5  fault     str  the fault's name, 1-40 characters
        6  settings  map  1-8 entries: key (str, 1-40 characters) -> number (int or
                          float), as in the machine file's [inject.FAULT] table

Like a handshake it carries the frame counter without advancing it; the device takes it
only from its pinned peer and session (else ``foreign`` / ``stale_session``), counts it in
``injections`` and hands it on as an :class:`~io_adapters.messages.InjectRequest`; a NaN
or infinite number is ``refused_nonfinite``.

Who may talk to a device (:mod:`io_adapters.msgpack_endpoint`): the device pins the first
peer that sends it a well-formed setpoint or HELLO, its session and (UDP) its address,
and drops everything else: frames from another address (``foreign``), frames of another
session from that address (``stale_session``).  A HELLO is accepted (the device re-pins to
its sender's address and session, resets the sequence check and answers WELCOME
accepted=1) when the device has no peer, when it comes from the pinned peer itself (same
address and session), or when the pinned peer has sent nothing valid for ``takeover_ms``;
otherwise the device answers WELCOME accepted=0 and counts the HELLO as foreign.  A
controller sends a HELLO when it opens and again, at most every
:data:`HELLO_INTERVAL_NS`, before its setpoints until a WELCOME accepted=1 arrives, so a
restarted controller gets back in once its dead predecessor has been silent for
``takeover_ms``.

Decoding is strict: anything but an array of exactly this length, version,
kind, element types and integer ranges raises :class:`FrameError`.  NaN and infinite
floats decode (they are well-formed); the receiving endpoint refuses them, and setpoints
beyond the drive's bounds, as values: counted apart from malformed frames
(``stats.refused_*``), dropped whole (:class:`~io_adapters.messages.SetpointBounds`).  The
receiver uses session and frame to drop duplicates, late frames and jumps and to count
lost ones, and follows a jump that the next frame continues (the sequence rule of
:mod:`io_adapters.msgpack_endpoint`, after RFC 3550's).
"""

import math
import operator
from collections import deque
from collections.abc import Callable
from itertools import repeat
from typing import NamedTuple

import msgpack

from io_adapters.base import FrameError
from io_adapters.messages import (
    Feedback,
    FeedbackGroup,
    InjectRequest,
    Setpoint,
    SetpointGroup,
)

VERSION = 1
VERSION_GROUP = 2
HANDSHAKE_VERSION = 1
KIND_SETPOINT = 1
KIND_FEEDBACK = 2
KIND_HELLO = 3
KIND_WELCOME = 4
KIND_INJECT = 5
#: an INJECT's longest names and most settings
INJECT_NAME_MAX = 40
INJECT_SETTINGS_MAX = 8
HEADER_LEN = 4
U32 = 0xFFFFFFFF
#: a controller not yet welcomed repeats its HELLO at most this often, ns
HELLO_INTERVAL_NS = 100_000_000


class Field(NamedTuple):
    """One array element: record attribute, type (int or float), integer range."""
    name: str
    type: type
    lo: int = 0
    hi: int = 0


def _int(name: str, lo: int, hi: int) -> Field:
    return Field(name, int, lo, hi)


def _float(name: str) -> Field:
    return Field(name, float)


T_NS_MAX = 2**63 - 1
HEADER = (_int("version", VERSION, VERSION), _int("kind", 1, 2), _int("session", 0, U32),
          _int("frame", 0, U32))
SETPOINT_FIELDS = (
    _int("seq", 0, U32), _int("controlword", 0, 0xFFFF), _int("mode", -128, 127),
    _float("target_position_counts"), _float("target_velocity_counts_s"),
    _float("velocity_offset_counts_s"), _float("iq_ref_a"), _float("id_ref_a"),
    _float("ud_v"), _float("uq_v"),
    _int("t_ns", 0, T_NS_MAX))
FEEDBACK_FIELDS = (
    _int("seq", 0, U32), _int("statusword", 0, 0xFFFF), _int("fault", -2**31, 2**31 - 1),
    _float("time_s"), _float("encoder_counts"), _float("scale_counts"),
    _float("velocity_counts_s"), _float("iq_a"),
    _float("id_a"), _int("sp_t_ns", 0, T_NS_MAX), _int("sp_rx_ns", 0, T_NS_MAX),
    _int("t_ns", 0, T_NS_MAX), _int("tick_ns", 0, T_NS_MAX))


def _items(indices: list[int]) -> Callable[[tuple], tuple]:
    """A function returning the elements at ``indices`` as a tuple (``itemgetter`` of one
    index returns the element itself)."""
    if len(indices) > 1:
        return operator.itemgetter(*indices)
    return lambda values: tuple(values[i] for i in indices)


def _float_getter(fields: tuple[Field, ...]) -> Callable[[tuple], tuple]:
    """A function returning the float elements of an array laid out as ``fields``."""
    return _items([i for i, f in enumerate(fields) if f.type is float])


class _Check:
    """:func:`_valid` for one layout with its parts precomputed: a handful of C-level
    calls, where the per-element loop costs a microsecond per array."""

    def __init__(self, fields: tuple[Field, ...]):
        self.types = tuple(f.type for f in fields)
        ints = [i for i, f in enumerate(fields) if f.type is int]
        self.get_ints = _items(ints)
        self.ranges = tuple(range(fields[i].lo, fields[i].hi + 1) for i in ints)

    def __call__(self, values: tuple) -> bool:
        """Every element of ``values`` (as long as the layout) of its type exactly, every
        integer in its range."""
        return tuple(map(type, values)) == self.types and all(
            map(operator.contains, self.ranges, self.get_ints(values)))


class Schema:
    """The message layout of one record type, with the checks precomputed so that a
    good message costs a few C-level calls (about 2 us each way)."""

    def __init__(self, record_type: type, kind: int, fields: tuple[Field, ...]):
        self.record_type = record_type
        self.kind = kind
        self.fields = fields
        self.all_fields = HEADER + fields
        self.names = tuple(f.name for f in fields)
        self.get = operator.attrgetter(*self.names)
        self.convert = tuple(operator.index if f.type is int else float for f in fields)
        self.types = tuple(f.type for f in self.all_fields)
        self.field_types = self.types[HEADER_LEN:]
        ints = [i for i, f in enumerate(self.all_fields) if f.type is int]
        self.get_ints = operator.itemgetter(*ints)
        self.ranges = tuple(range(self.all_fields[i].lo, self.all_fields[i].hi + 1)
                            for i in ints)
        self.get_floats = _float_getter(self.all_fields)

    def in_range(self, values: tuple) -> bool:
        """True if every integer of a full message (header first) is in its range."""
        return all(map(operator.contains, self.ranges, self.get_ints(values)))

    def finite(self, values: tuple) -> bool:
        """True if every float of a decoded message is finite."""
        return all(map(math.isfinite, self.get_floats(values)))

    def explain(self, values: tuple) -> str:
        """Which element of a full message breaks the schema, for the error message."""
        return _explain(self.all_fields, values)


SCHEMAS = {Setpoint: Schema(Setpoint, KIND_SETPOINT, SETPOINT_FIELDS),
           Feedback: Schema(Feedback, KIND_FEEDBACK, FEEDBACK_FIELDS)}


def _explain(fields: tuple[Field, ...], values: tuple) -> str:
    """Which element breaks ``fields``, for the error message."""
    for f, value in zip(fields, values):
        if type(value) is not f.type:
            return f"{f.name}={value!r}: expected {f.type.__name__}"
        if f.type is int and not f.lo <= value <= f.hi:
            return f"{f.name}={value}: outside [{f.lo}, {f.hi}]"
    return "no error"


def _converted(fields: tuple[Field, ...], raw: tuple, what: str) -> tuple:
    """``raw`` with ints as ints and floats as floats, range-checked; FrameError naming
    the field otherwise."""
    try:
        out = tuple([operator.index(v) if f.type is int else float(v)
                     for f, v in zip(fields, raw)])
    except (TypeError, ValueError) as e:
        bad = next(f for f, v in zip(fields, raw)
                   if not _converts(operator.index if f.type is int else float, v))
        raise FrameError(f"{what}.{bad.name}={raw[fields.index(bad)]!r} is not "
                         f"{bad.type.__name__}") from e
    for f, v in zip(fields, out):
        if f.type is int and not f.lo <= v <= f.hi:
            raise FrameError(f"{what} {f.name}={v}: outside [{f.lo}, {f.hi}]")
    return out


def _valid(fields: tuple[Field, ...], values: tuple) -> bool:
    return all(type(v) is f.type and (f.type is float or f.lo <= v <= f.hi)
               for f, v in zip(fields, values))


class GroupSchema:
    """The version-2 layout of a group message: common fields, then one array per axis
    (see the module docstring)."""

    def __init__(self, group_type: type, kind: int, common: tuple[Field, ...],
                 axis: tuple[Field, ...], copied: tuple[str, ...]):
        self.group_type, self.kind = group_type, kind
        self.header = (_int("version", VERSION_GROUP, VERSION_GROUP),) + HEADER[1:]
        self.common, self.axis = common, axis
        self.get_common = operator.attrgetter(*(f.name for f in common))
        self.get_axis = operator.attrgetter(*(f.name for f in axis))
        self.common_names = tuple(f.name for f in common)
        self.axis_names = tuple(f.name for f in axis)
        self.copied = copied  # common fields also written into every axis's record
        self.length = HEADER_LEN + len(common) + 1
        self.get_common_floats = _float_getter(self.header + common)
        self.get_axis_floats = _float_getter(axis)
        self.valid_head = _Check(self.header + common)
        self.valid_common = _Check(common)
        self.valid_axis = _Check(axis)

    def encode(self, group, session: int, frame: int) -> bytes:
        name = self.group_type.__name__
        common = self.get_common(group)
        axes = tuple(map(self.get_axis, group.axes))
        # values of the exact types and in range are what _converted would return
        if not self.valid_common(common):
            common = _converted(self.common, common, name)
        if not all(map(self.valid_axis, axes)):
            axes = tuple(_converted(self.axis, a, f"{name}.axes[{i}]")
                         for i, a in enumerate(axes))
        return msgpack.packb((VERSION_GROUP, self.kind, session, frame) + common + (axes,))

    def check(self, values: tuple, n_axes: int) -> None:
        """Raise FrameError unless ``values`` (version and kind already checked) is a
        well-formed group message of ``n_axes`` axes."""
        name = self.group_type.__name__
        if len(values) != self.length:
            raise FrameError(f"{len(values)} elements, expected {self.length} for {name}")
        head = HEADER_LEN + len(self.common)
        fields = self.header + self.common
        if not self.valid_head(values[:head]):
            raise FrameError(f"{name} {_explain(fields, values[:head])}")
        axes = values[head]
        if type(axes) is not tuple:
            raise FrameError(f"{name} axes={axes!r:.40}: expected an array")
        if len(axes) != n_axes:
            raise FrameError(f"{name}: {len(axes)} axes, expected {n_axes}")
        for i, a in enumerate(axes):
            if type(a) is not tuple or len(a) != len(self.axis):
                raise FrameError(f"{name} axes[{i}]={a!r:.60}: expected an array of "
                                 f"{len(self.axis)}")
            if not self.valid_axis(a):
                raise FrameError(f"{name} axes[{i}] {_explain(self.axis, a)}")

    def finite(self, values: tuple) -> bool:
        """True if every float of a decoded group message is finite."""
        return all(map(math.isfinite, self.get_common_floats(values))) and all(
            all(map(math.isfinite, self.get_axis_floats(a))) for a in values[-1])

    def fill(self, into, values: tuple) -> None:
        head = HEADER_LEN + len(self.common)
        common = values[HEADER_LEN:head]
        deque(map(setattr, repeat(into), self.common_names, common), 0)
        copied = [(n, getattr(into, n)) for n in self.copied]
        for rec, a in zip(into.axes, values[head]):
            deque(map(setattr, repeat(rec), self.axis_names, a), 0)
            for n, v in copied:
                setattr(rec, n, v)


_STAMP = (0, T_NS_MAX)
GROUP_SCHEMAS = {
    SetpointGroup: GroupSchema(
        SetpointGroup, KIND_SETPOINT, (_int("seq", 0, U32), _int("t_ns", *_STAMP)),
        SETPOINT_FIELDS[1:-1], ("seq", "t_ns")),
    FeedbackGroup: GroupSchema(
        FeedbackGroup, KIND_FEEDBACK,
        (_int("seq", 0, U32), _float("time_s"), _int("sp_t_ns", *_STAMP),
         _int("sp_rx_ns", *_STAMP), _int("t_ns", *_STAMP), _int("tick_ns", *_STAMP)),
        tuple(f for f in FEEDBACK_FIELDS if f.name in (
            "statusword", "fault", "encoder_counts", "scale_counts", "velocity_counts_s",
            "iq_a", "id_a")),
        ("seq", "time_s", "sp_t_ns", "sp_rx_ns", "t_ns", "tick_ns")),
}


def _span(fields: tuple[Field, ...], names: tuple[str, ...], offset: int) -> slice:
    """Where the consecutive fields ``names`` are in an array laid out as ``fields``."""
    first = [f.name for f in fields].index(names[0]) + offset
    return slice(first, first + len(names))


#: the setpoint fields :meth:`~io_adapters.messages.SetpointBounds.refusal` takes, in its
#: order; they are consecutive on the wire
REFUSAL_ARGS = ("mode", "target_position_counts", "target_velocity_counts_s",
                "velocity_offset_counts_s", "iq_ref_a", "id_ref_a", "ud_v", "uq_v")
#: where they are in a decoded version-1 setpoint, and in an axis array of version 2
SETPOINT_REFUSAL_ARGS = _span(SETPOINT_FIELDS, REFUSAL_ARGS, HEADER_LEN)
GROUP_REFUSAL_ARGS = _span(GROUP_SCHEMAS[SetpointGroup].axis, REFUSAL_ARGS, 0)


def encode(record: Setpoint | Feedback | SetpointGroup | FeedbackGroup, session: int,
           frame: int) -> bytes:
    """One message carrying ``record`` (version 1 for a plain record, 2 for a group).
    Integers accept anything with ``__index__`` and floats anything ``float()`` takes
    (numpy scalars included; NaN and infinities too, which a receiving endpoint refuses);
    raises :class:`FrameError` naming the field if a value does not convert or is out of
    range."""
    group = GROUP_SCHEMAS.get(type(record))
    if group is not None:
        return group.encode(record, session, frame)
    schema = SCHEMAS[type(record)]
    raw = schema.get(record)
    if tuple(map(type, raw)) != schema.field_types:
        try:
            raw = tuple([conv(v) for conv, v in zip(schema.convert, raw)])
        except (TypeError, ValueError) as e:
            bad = next(f for f, v, conv in zip(schema.fields, raw, schema.convert)
                       if not _converts(conv, v))
            raise FrameError(f"{schema.record_type.__name__}.{bad.name}="
                             f"{getattr(record, bad.name)!r} is not {bad.type.__name__}") from e
    values = (VERSION, schema.kind, session, frame) + raw
    if not schema.in_range(values):
        raise FrameError(f"{schema.record_type.__name__} {schema.explain(values)}")
    return msgpack.packb(values)


def _converts(conv, value) -> bool:
    try:
        conv(value)
    except (TypeError, ValueError):
        return False
    return True


def encode_hello(session: int, frame: int) -> bytes:
    """A HELLO (controller -> device): the header only."""
    return msgpack.packb((HANDSHAKE_VERSION, KIND_HELLO, session, frame))


def encode_welcome(session: int, frame: int, accepted: bool) -> bytes:
    """A WELCOME (device -> controller): the header and whether the HELLO was accepted."""
    return msgpack.packb((HANDSHAKE_VERSION, KIND_WELCOME, session, frame, int(accepted)))


def _handshake_fields(kind: int) -> tuple[Field, ...]:
    head = (_int("version", HANDSHAKE_VERSION, HANDSHAKE_VERSION), _int("kind", kind, kind),
            _int("session", 0, U32), _int("frame", 0, U32))
    return head + ((_int("accepted", 0, 1),) if kind == KIND_WELCOME else ())


HANDSHAKE_FIELDS = {KIND_HELLO: _handshake_fields(KIND_HELLO),
                    KIND_WELCOME: _handshake_fields(KIND_WELCOME)}
#: an INJECT's header and axis (its fault name and settings are checked apart)
INJECT_HEAD = _handshake_fields(KIND_INJECT) + (_int("axis", 0, 255),)
#: the handshake message a receiver of each record kind takes besides the records
HANDSHAKE_TAKEN = {KIND_SETPOINT: KIND_HELLO, KIND_FEEDBACK: KIND_WELCOME}


def _unpack(data: bytes | memoryview) -> tuple:
    try:
        values = msgpack.unpackb(data, use_list=False, raw=False)
    except ValueError as e:  # msgpack's decoding errors are all ValueErrors
        raise FrameError(f"not a msgpack message: {e}") from e
    if type(values) is not tuple or len(values) < 2:
        raise FrameError(f"not a message array: {values!r:.60}")
    return values


def encode_inject(session: int, frame: int, request: InjectRequest) -> bytes:
    """An INJECT (controller -> device); :class:`FrameError` if ``request`` does not fit
    the layout (see the module docstring)."""
    values = (HANDSHAKE_VERSION, KIND_INJECT, session, frame, request.axis, request.fault,
              dict(request.settings))
    _check_inject(values)
    return msgpack.packb(values)


def _name_ok(name) -> bool:
    return type(name) is str and 0 < len(name) <= INJECT_NAME_MAX


def _check_inject(values: tuple) -> tuple:
    """``values`` if it is a well-formed INJECT, else :class:`FrameError` saying why."""
    if len(values) != 7:
        raise FrameError(f"{len(values)} elements, expected 7 for INJECT")
    if not _valid(INJECT_HEAD, values[:5]):
        raise FrameError(f"INJECT {_explain(INJECT_HEAD, values[:5])}")
    fault, settings = values[5], values[6]
    if not _name_ok(fault):
        raise FrameError(f"INJECT fault={fault!r:.60}: expected a name of 1-"
                         f"{INJECT_NAME_MAX} characters")
    if type(settings) is not dict or not 0 < len(settings) <= INJECT_SETTINGS_MAX:
        raise FrameError(f"INJECT settings={settings!r:.60}: expected a map of 1-"
                         f"{INJECT_SETTINGS_MAX} entries")
    for k, v in settings.items():
        if not _name_ok(k) or type(v) not in (int, float):
            raise FrameError(f"INJECT settings {k!r:.60}: {v!r:.40}: expected a name and a "
                             f"number")
    return values


def decode_inject(data: bytes | memoryview) -> tuple:
    """The checked array of an INJECT; raises :class:`FrameError` for anything else (a
    bench's injection port takes nothing but INJECTs: :mod:`io_adapters.inject_port`)."""
    values = _unpack(data)
    if values[1] != KIND_INJECT:
        raise FrameError(f"kind {values[1]!r:.20}, expected {KIND_INJECT} (INJECT)")
    return _check_inject(values)


def inject_request(values: tuple) -> InjectRequest:
    """The request of a checked INJECT array (settings as floats)."""
    return InjectRequest(values[4], values[5], {k: float(v) for k, v in values[6].items()})


def _check_handshake(values: tuple, kind: int) -> tuple:
    fields = HANDSHAKE_FIELDS[kind]
    name = "HELLO" if kind == KIND_HELLO else "WELCOME"
    if len(values) != len(fields):
        raise FrameError(f"{len(values)} elements, expected {len(fields)} for {name}")
    if not _valid(fields, values):
        raise FrameError(f"{name} {_explain(fields, values)}")
    return values


def decode_hello(data: bytes | memoryview) -> tuple:
    """The checked array of a HELLO; raises :class:`FrameError` for anything else."""
    return _check_handshake(_unpack(data), KIND_HELLO)


def decode(data: bytes | memoryview, record_type: type, n_axes: int = 1) -> tuple:
    """The checked array of one message for ``record_type`` (header first; a group of
    ``n_axes`` axes for the group types), or of the handshake message its receiver takes
    (``values[1]`` says which: a HELLO where setpoints are read, a WELCOME where feedback
    is), or an INJECT where setpoints are read; raises :class:`FrameError` saying what is
    wrong.  Nothing is written anywhere."""
    values = _unpack(data)
    group = GROUP_SCHEMAS.get(record_type)
    kind = (group or SCHEMAS[record_type]).kind
    handshake = HANDSHAKE_TAKEN[kind]
    if values[1] == handshake:
        return _check_handshake(values, handshake)
    if values[1] == KIND_INJECT and kind == KIND_SETPOINT:
        return _check_inject(values)
    version = VERSION if group is None else VERSION_GROUP
    if values[0] != version:
        raise FrameError(f"version {values[0]!r}, expected {version}")
    if group is not None:
        if values[1] != group.kind:
            raise FrameError(f"kind {values[1]!r}, expected {group.kind} "
                             f"({record_type.__name__})")
        group.check(values, n_axes)
        return values
    schema = SCHEMAS[record_type]
    if values[1] != schema.kind:
        raise FrameError(f"kind {values[1]!r}, expected {schema.kind} ({record_type.__name__})")
    if len(values) != len(schema.types):
        raise FrameError(f"{len(values)} elements, expected {len(schema.types)} "
                         f"for {record_type.__name__}")
    if tuple(map(type, values)) != schema.types or not schema.in_range(values):
        raise FrameError(f"{record_type.__name__} {schema.explain(values)}")
    return values


def fill(into: Setpoint | Feedback | SetpointGroup | FeedbackGroup, values: tuple) -> None:
    """Write the record part of a decoded message into ``into`` (no new record)."""
    group = GROUP_SCHEMAS.get(type(into))
    if group is not None:
        group.fill(into, values)
        return
    # setattr for every field in one C-level pass; the zero-length deque just drains the map
    deque(map(setattr, repeat(into), SCHEMAS[type(into)].names, values[HEADER_LEN:]), 0)
