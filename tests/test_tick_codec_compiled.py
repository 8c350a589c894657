"""The compiled steady-state codec (:mod:`io_adapters.codec_compiled`) against the Python
codec it stands for (:mod:`io_adapters.codec`, msgpack's own packer and unpacker): the
emulator's side (setpoints read, feedback written) and the controller's (feedback read,
setpoints written).

A setpoint (a version-1 Setpoint, or a version-2 group) the compiled reader accepts must
be one that :func:`io_adapters.codec.decode` accepts with finite floats, with the same
values to the bit; anything else (a mutated byte, a cut or lengthened message, another
kind, non-finite or float32 values, integers out of range, in any of msgpack's integer
encodings) must be declined with the caller's arrays untouched.  A feedback (or group)
the compiled writer encodes must be the bytes ``msgpack.packb`` gives for the same
record. hypothesis draws the values.
"""

import math
import struct

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from io_adapters import codec_compiled as K
from io_adapters.base import FrameError
from io_adapters.codec import decode, encode
from io_adapters.messages import (
    Feedback,
    FeedbackGroup,
    Setpoint,
    SetpointGroup,
    axis_records,
    message_pair,
)

_FINITE = st.floats(allow_nan=False, allow_infinity=False)
_U32 = st.integers(0, 2**32 - 1)
_T_NS = st.integers(0, 2**63 - 1)


def _setpoint(draw) -> Setpoint:
    return Setpoint(seq=draw(_U32), controlword=draw(st.integers(0, 0xFFFF)),
                    mode=draw(st.integers(-128, 127)),
                    **{name: draw(_FINITE) for name in K.SP_FLOAT_FIELDS},
                    t_ns=draw(_T_NS))


def _compiled(payload: bytes, n_axes: int = 1):
    """(accepted, ints, axis ints, floats) of the compiled reader; the arrays start as
    sentinels."""
    buf = np.zeros(2048, np.uint8)
    buf[:len(payload)] = np.frombuffer(payload, np.uint8)
    ints = np.full(K.N_SP_INTS, -7, np.int64)
    axis_ints, floats = np.full((n_axes, 2), -7, np.int64), np.full((n_axes, 7), -7.0)
    ok = K.decode_setpoint(buf, len(payload), ints, axis_ints, floats)
    return ok, ints, axis_ints, floats


def _python(payload: bytes):
    """The Python codec's values, or None where it does not take a finite Setpoint."""
    try:
        values = decode(payload, Setpoint)
    except FrameError:
        return None
    if values[1] != 1 or not all(map(math.isfinite, values[7:14])):
        return None
    return values


def _agree(payload: bytes, float64: bool = True) -> None:
    """The compiled reader says what the Python codec says (``float64`` False: the
    message carries a float32, which the compiled reader declines by design)."""
    ok, ints, axis_ints, floats = _compiled(payload)
    reference = _python(payload) if float64 else None
    assert ok == (reference is not None), payload.hex()
    if not ok:
        assert (ints == -7).all() and (axis_ints == -7).all() and (floats == -7.0).all()
        return
    assert list(ints) == [reference[i] for i in (2, 3, 4, 14)]
    assert list(axis_ints[0]) == [reference[5], reference[6]]
    assert np.array(reference[7:14]).tobytes() == floats.tobytes()


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_reads_what_msgpack_writes(data):
    sp = _setpoint(data.draw)
    payload = encode(sp, data.draw(_U32), data.draw(_U32))
    ok, ints, axis_ints, floats = _compiled(payload)
    assert ok
    assert list(ints) == [*_reference_header(payload), sp.seq, sp.t_ns]
    assert list(axis_ints[0]) == [sp.controlword, sp.mode]
    assert np.array([getattr(sp, n) for n in K.SP_FLOAT_FIELDS]).tobytes() == \
        floats.tobytes()


def _reference_header(payload: bytes) -> list[int]:
    return list(msgpack.unpackb(payload)[2:4])


def _int_any_width(draw, value: int) -> bytes:
    """``value`` in any msgpack integer encoding wide enough for it."""
    forms = []
    if 0 <= value <= 0x7F:
        forms.append(bytes([value]))
    if -32 <= value < 0:
        forms.append(bytes([value + 256]))
    for code, fmt, lo, hi in ((0xCC, ">B", 0, 2**8 - 1), (0xCD, ">H", 0, 2**16 - 1),
                              (0xCE, ">I", 0, 2**32 - 1), (0xCF, ">Q", 0, 2**64 - 1),
                              (0xD0, ">b", -2**7, 2**7 - 1), (0xD1, ">h", -2**15, 2**15 - 1),
                              (0xD2, ">i", -2**31, 2**31 - 1), (0xD3, ">q", -2**63, 2**63 - 1)):
        if lo <= value <= hi:
            forms.append(bytes([code]) + struct.pack(fmt, value))
    return draw(st.sampled_from(forms))


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_every_integer_encoding_and_range(data):
    """Integers in any encoding, in or out of their field's range (and version, kind)."""
    wide = st.integers(-2**63, 2**64 - 1)
    ints = [data.draw(st.one_of(st.just(1), st.integers(-3, 6))),        # version
            data.draw(st.one_of(st.just(1), st.integers(-3, 6))),        # kind
            data.draw(st.one_of(_U32, wide)), data.draw(st.one_of(_U32, wide)),
            data.draw(st.one_of(_U32, wide)),
            data.draw(st.one_of(st.integers(0, 0xFFFF), wide)),
            data.draw(st.one_of(st.integers(-128, 127), wide))]
    floats = b"".join(b"\xcb" + struct.pack(">d", data.draw(_FINITE)) for _ in range(7))
    t_ns = data.draw(st.one_of(_T_NS, wide))
    payload = (b"\x9f" + b"".join(_int_any_width(data.draw, v) for v in ints) + floats
               + _int_any_width(data.draw, t_ns))
    _agree(payload)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_mutated_messages(data):
    """One byte changed, a cut, bytes appended, a float as float32, NaN or infinity."""
    sp = _setpoint(data.draw)
    payload = bytearray(encode(sp, data.draw(_U32), data.draw(_U32)))
    how = data.draw(st.sampled_from(["byte", "cut", "append", "float32", "nonfinite"]))
    if how == "byte":
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    elif how == "cut":
        payload = payload[:data.draw(st.integers(0, len(payload) - 1))]
    elif how == "append":
        payload += bytes(data.draw(st.lists(st.integers(0, 255), min_size=1, max_size=3)))
    else:
        values = list(msgpack.unpackb(bytes(payload)))
        i = data.draw(st.integers(7, 13))
        if how == "nonfinite":
            values[i] = data.draw(st.sampled_from([math.nan, math.inf, -math.inf]))
            payload = msgpack.packb(values)
        else:
            payload = (b"\x9f" + b"".join(map(msgpack.packb, values[:i])) + b"\xca"
                       + struct.pack(">f", data.draw(_FINITE.filter(lambda v: abs(v) < 1e38)))
                       + b"".join(map(msgpack.packb, values[i + 1:])))
    _agree(bytes(payload), float64=how != "float32")


@pytest.mark.parametrize("value", [0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308,
                                   2.225073858507201e-308, 1.7976931348623157e308,
                                   -1.7976931348623157e308, 1.0, -1.5, 0.1])
def test_float_extremes(value):
    """Signed zeros, the smallest subnormal, the largest subnormal, the smallest normal,
    the largest double: both ways."""
    sp = Setpoint(target_position_counts=value, uq_v=value)
    payload = encode(sp, 1, 2)
    ok, _, _, floats = _compiled(payload)
    assert ok and np.array([value]).tobytes() == floats[0, 0:1].tobytes()
    fb = Feedback(encoder_counts=value, id_a=value)
    _assert_encodes_as_msgpack(fb, 3, 4)


def _assert_encodes_as_msgpack(fb, session: int, frame: int) -> None:
    """``fb`` a Feedback or a FeedbackGroup."""
    ints = np.array([session, frame, fb.seq, fb.sp_t_ns, fb.sp_rx_ns, fb.t_ns, fb.tick_ns],
                    np.int64)
    axes = axis_records(fb)
    axis_ints = np.array([[f.statusword, f.fault] for f in axes], np.int64)
    floats = np.array([[getattr(f, n) for n in K.FB_FLOAT_FIELDS] for f in axes])
    if isinstance(fb, FeedbackGroup):
        floats[0, 0] = fb.time_s  # a group carries one time_s
    out = np.zeros(1024, np.uint8)
    n = K.encode_feedback(out, ints, axis_ints, floats)
    assert out[:n].tobytes() == encode(fb, session, frame)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_writes_what_msgpack_writes(data):
    ints = st.one_of(st.integers(0, 300), _T_NS)
    fb = Feedback(seq=data.draw(_U32), statusword=data.draw(st.integers(0, 0xFFFF)),
                  fault=data.draw(st.integers(-2**31, 2**31 - 1)),
                  **{name: data.draw(_FINITE) for name in K.FB_FLOAT_FIELDS},
                  sp_t_ns=data.draw(ints), sp_rx_ns=data.draw(ints), t_ns=data.draw(ints),
                  tick_ns=data.draw(ints))
    _assert_encodes_as_msgpack(fb, data.draw(_U32), data.draw(_U32))


@pytest.mark.parametrize("n_axes", [1, 2])
def test_declines_what_it_cannot_write(n_axes):
    out = np.zeros(1024, np.uint8)
    good = np.array([1, 2, 3, 4, 5, 6, 7], np.int64)
    axis_ints = np.array([[0x1237, 0]] * n_axes, np.int64)
    zeros = np.zeros((n_axes, 6))
    assert K.encode_feedback(out, good, axis_ints, zeros) > 0
    for k, bad in ((0, 2**32), (2, -1), (5, -1)):
        ints = good.copy()
        ints[k] = bad
        assert K.encode_feedback(out, ints, axis_ints, zeros) == -1
    for k, bad in ((0, 0x10000), (1, 2**31)):
        wrong = axis_ints.copy()
        wrong[-1, k] = bad
        assert K.encode_feedback(out, good, wrong, zeros) == -1
    for value in (math.nan, -math.inf):
        floats = zeros.copy()
        floats[-1, 3] = value
        assert K.encode_feedback(out, good, axis_ints, floats) == -1


def _group_setpoint(draw, n_axes: int) -> SetpointGroup:
    sp, _ = message_pair(n_axes)
    sp.seq, sp.t_ns = draw(_U32), draw(_T_NS)
    for s in sp.axes:
        one = _setpoint(draw)
        for name in ("controlword", "mode", *K.SP_FLOAT_FIELDS):
            setattr(s, name, getattr(one, name))
    return sp


@settings(max_examples=200, deadline=None)
@given(st.data(), st.integers(2, 4))
def test_groups_both_ways(data, n_axes):
    """Version 2: a group msgpack writes is read with the same values; a mutated one is
    read only when the Python codec takes it; a group of feedback is written as msgpack
    writes it."""
    sp = _group_setpoint(data.draw, n_axes)
    session, frame = data.draw(_U32), data.draw(_U32)
    payload = bytearray(encode(sp, session, frame))
    ok, ints, axis_ints, floats = _compiled(bytes(payload), n_axes)
    assert ok and list(ints) == [session, frame, sp.seq, sp.t_ns]
    assert axis_ints.tolist() == [[s.controlword, s.mode] for s in sp.axes]
    assert np.array([[getattr(s, n) for n in K.SP_FLOAT_FIELDS] for s in sp.axes]
                    ).tobytes() == floats.tobytes()
    assert not _compiled(bytes(payload), n_axes + 1)[0]  # another number of axes
    payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    try:
        values = decode(bytes(payload), SetpointGroup, n_axes)
        taken = values[1] == 1 and all(math.isfinite(v) for a in values[-1] for v in a[2:])
    except FrameError:
        taken = False
    ok, ints, axis_ints, floats = _compiled(bytes(payload), n_axes)
    assert ok == taken
    if ok:
        assert list(ints) == [values[2], values[3], values[4], values[5]]
        assert axis_ints.tolist() == [list(a[:2]) for a in values[-1]]
        assert np.array([a[2:] for a in values[-1]]).tobytes() == floats.tobytes()
    _, fb = message_pair(n_axes)
    fb.seq, fb.time_s = data.draw(_U32), data.draw(_FINITE)
    fb.sp_t_ns, fb.sp_rx_ns, fb.t_ns, fb.tick_ns = (data.draw(_T_NS) for _ in range(4))
    for f in fb.axes:
        f.statusword, f.fault = data.draw(st.integers(0, 0xFFFF)), data.draw(
            st.integers(-2**31, 2**31 - 1))
        for name in K.FB_FLOAT_FIELDS[1:]:
            setattr(f, name, data.draw(_FINITE))
    _assert_encodes_as_msgpack(fb, session, frame)


def _feedback(draw, n_axes: int) -> Feedback | FeedbackGroup:
    _, fb = message_pair(n_axes)
    fb.seq = draw(_U32)
    fb.sp_t_ns, fb.sp_rx_ns, fb.t_ns, fb.tick_ns = (draw(_T_NS) for _ in range(4))
    fb.time_s = draw(_FINITE)
    for f in axis_records(fb):
        f.statusword, f.fault = draw(st.integers(0, 0xFFFF)), draw(
            st.integers(-2**31, 2**31 - 1))
        for name in K.FB_FLOAT_FIELDS[1:]:
            setattr(f, name, draw(_FINITE))
    return fb


def _read_feedback(payload: bytes, n_axes: int):
    """(accepted, ints, axis ints, floats) of the compiled feedback reader; the arrays
    start as sentinels."""
    buf = np.zeros(2048, np.uint8)
    buf[:len(payload)] = np.frombuffer(payload, np.uint8)
    ints = np.full(K.N_FB_INTS, -7, np.int64)
    axis_ints, floats = np.full((n_axes, 2), -7, np.int64), np.full((n_axes, 6), -7.0)
    ok = K.decode_feedback(buf, len(payload), ints, axis_ints, floats)
    return ok, ints, axis_ints, floats


@settings(max_examples=300, deadline=None)
@given(st.data(), st.sampled_from([1, 2, 5]))
def test_the_controller_side_both_ways(data, n_axes):
    """A controller's compiled loop (hil.runtime.controller_steady): feedback msgpack
    writes is read with the same values (a group's time_s once), a mutated one only where
    the Python codec takes it with finite floats (the caller's arrays untouched
    otherwise), and a setpoint is written as msgpack writes it."""
    fb = _feedback(data.draw, n_axes)
    session, frame = data.draw(_U32), data.draw(_U32)
    payload = bytearray(encode(fb, session, frame))
    ok, ints, axis_ints, floats = _read_feedback(bytes(payload), n_axes)
    assert ok
    assert list(ints) == [session, frame, fb.seq, fb.sp_t_ns, fb.sp_rx_ns, fb.t_ns,
                          fb.tick_ns]
    assert axis_ints.tolist() == [[f.statusword, f.fault] for f in axis_records(fb)]
    assert np.array([[getattr(f, n) for n in K.FB_FLOAT_FIELDS[1:]]
                     for f in axis_records(fb)]).tobytes() == floats[:, 1:].tobytes()
    assert np.float64(fb.time_s).tobytes() == floats[0, 0].tobytes()
    assert not _read_feedback(bytes(payload), n_axes + 1)[0]  # another number of axes
    payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    record = type(fb)
    try:
        values = decode(bytes(payload), record, n_axes)
        floats_of = ([values[5]] + [v for a in values[-1] for v in a[2:]] if n_axes > 1
                     else values[7:13])
        taken = values[1] == 2 and all(map(math.isfinite, floats_of))
    except FrameError:
        taken = False
    ok, ints, axis_ints, floats = _read_feedback(bytes(payload), n_axes)
    assert ok == taken, payload.hex()
    if not ok:
        assert (ints == -7).all() and (axis_ints == -7).all() and (floats == -7.0).all()
    sp = _group_setpoint(data.draw, n_axes) if n_axes > 1 else _setpoint(data.draw)
    out = np.zeros(1024, np.uint8)
    n = K.encode_setpoint(
        out, np.array([session, frame, sp.seq, sp.t_ns], np.int64),
        np.array([[s.controlword, s.mode] for s in axis_records(sp)], np.int64),
        np.array([[getattr(s, name) for name in K.SP_FLOAT_FIELDS]
                  for s in axis_records(sp)]))
    assert out[:n].tobytes() == encode(sp, session, frame)
