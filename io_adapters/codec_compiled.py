"""The steady-state records of :mod:`io_adapters.codec` in compiled code: a version-1
Setpoint read from, and a version-1 Feedback written into, flat byte arrays, for a tick
compiled from the datagram to the answer (issue 12 part 6).

They take the common case only and say so rather than guess: :func:`decode_setpoint`
accepts a message that :func:`io_adapters.codec.decode` decodes as a Setpoint *and* whose
floats are all finite float64 (msgpack ``0xcb``), and returns False for anything else
(handshakes, INJECT, float32 or non-finite values, another layout, trailing bytes), for
the Python path to count and judge; it never writes the caller's arrays then.  Every
integer encoding msgpack has is read (a sender need not use the shortest one).
:func:`encode_feedback` writes the bytes ``msgpack.packb`` writes for the same values
(shortest integer encodings, float64 big-endian), for finite floats and integers in the
layout's ranges, and returns -1 otherwise (the Python encoder then takes the record).
Floats are taken apart and put together with ``frexp``/``ldexp``, exact for every finite
double (subnormals included), so no scratch array or byte-order view is needed.

Both versions are read and written: a single-axis link's version-1 records and a
machine's version-2 groups of up to :data:`MAX_AXES` axes (a msgpack fixarray of axes).

Layouts (compile-time indices), the same for both versions (a version-1 record is axis 0):

* ``ints`` int64[:data:`N_SP_INTS`] of a decoded setpoint: ``I_SESSION``, ``I_FRAME``,
  ``I_SEQ``, ``I_T_NS``; ``axis_ints`` int64[axes, 2]: each axis's controlword and mode
  (``A_CONTROLWORD``, ``A_MODE``); ``floats`` float64[axes, 7]: each axis's floats in
  wire order (:data:`SP_FLOAT_FIELDS`);
* ``fb_ints`` int64[:data:`N_FB_INTS`]: ``F_SESSION``, ``F_FRAME``, ``F_SEQ``,
  ``F_SP_T_NS``, ``F_SP_RX_NS``, ``F_T_NS``, ``F_TICK_NS``; ``fb_axis_ints``
  int64[axes, 2]: each axis's statusword and fault (``A_STATUSWORD``, ``A_FAULT``);
  ``fb_floats`` float64[axes, 6]: each axis's :data:`FB_FLOAT_FIELDS` (a group carries
  axis 0's ``time_s`` once, in its common part).
"""

import math

from numba import njit

from io_adapters.codec import (
    FEEDBACK_FIELDS,
    KIND_FEEDBACK,
    KIND_SETPOINT,
    SETPOINT_FIELDS,
    T_NS_MAX,
    U32,
    VERSION,
    VERSION_GROUP,
)

#: the setpoint's floats, in wire order
SP_FLOAT_FIELDS = tuple(f.name for f in SETPOINT_FIELDS if f.type is float)
#: the feedback's floats, in wire order
FB_FLOAT_FIELDS = tuple(f.name for f in FEEDBACK_FIELDS if f.type is float)
I_SESSION, I_FRAME, I_SEQ, I_T_NS, N_SP_INTS = range(5)
A_CONTROLWORD, A_MODE = range(2)
F_SESSION, F_FRAME, F_SEQ, F_SP_T_NS, F_SP_RX_NS, F_T_NS, F_TICK_NS, N_FB_INTS = range(8)
A_STATUSWORD, A_FAULT = range(2)
#: the most axes of a group read or written here (a msgpack fixarray of axes)
MAX_AXES = 15
#: a Setpoint's array: the header and its fields (15: a msgpack fixarray)
_SP_LENGTH = 4 + len(SETPOINT_FIELDS)
#: a Feedback's array (17: a msgpack array 16)
_FB_LENGTH = 4 + len(FEEDBACK_FIELDS)
#: a group's arrays: header, seq, t_ns, axes (7); header, seq, time_s, four stamps, axes
#: (11); an axis's: controlword, mode, 7 floats (9); statusword, fault, 5 floats (7)
_SPG_LENGTH, _FBG_LENGTH, _SPG_AXIS, _FBG_AXIS = 7, 11, 9, 7
_FAULT_MIN, _FAULT_MAX = -2**31, 2**31 - 1
_MANTISSA = 1 << 52
_INT64_MAX = 2**63 - 1


@njit(cache=True, inline="always")
def _be(buf, pos, n_bytes):
    """The unsigned big-endian integer of ``n_bytes`` bytes at ``pos`` (n_bytes <= 8;
    a value of 2**63 or more comes back negative: the caller refuses it)."""
    v = 0
    for k in range(n_bytes):
        v = (v << 8) | buf[pos + k]
    return v


@njit(cache=True, inline="always")
def _signed(v, bits):
    """Two's complement of an unsigned ``bits``-wide ``v``."""
    return v - (1 << bits) if v >= 1 << (bits - 1) else v


@njit(cache=True)
def _read_int(buf, pos, n, lo, hi):
    """(ok, value, next position) of a msgpack integer at ``pos`` within [lo, hi]."""
    if pos >= n:
        return False, 0, pos
    b = buf[pos]
    if b <= 0x7F:
        v, size = int(b), 1
    elif b >= 0xE0:
        v, size = int(b) - 256, 1
    elif 0xCC <= b <= 0xCF:  # uint 8, 16, 32, 64
        width = 1 << (b - 0xCC)
        if pos + 1 + width > n:
            return False, 0, pos
        v, size = _be(buf, pos + 1, width), 1 + width
        if v < 0:  # a uint 64 above int64's range: above every range here
            return False, 0, pos
    elif 0xD0 <= b <= 0xD3:  # int 8, 16, 32, 64
        width = 1 << (b - 0xD0)
        if pos + 1 + width > n:
            return False, 0, pos
        raw = _be(buf, pos + 1, width)
        v, size = (raw if width == 8 else _signed(raw, 8 * width)), 1 + width
    else:
        return False, 0, pos
    if v < lo or v > hi:
        return False, 0, pos
    return True, v, pos + size


@njit(cache=True)
def _read_finite(buf, pos, n):
    """(ok, value, next position) of a finite msgpack float 64 at ``pos``."""
    if pos + 9 > n or buf[pos] != 0xCB:
        return False, 0.0, pos
    bits = _be(buf, pos + 1, 8)
    exponent = (bits >> 52) & 0x7FF
    if exponent == 0x7FF:  # inf or NaN: the endpoint refuses it, in Python
        return False, 0.0, pos
    mantissa = bits & (_MANTISSA - 1)
    if exponent == 0:
        v = math.ldexp(float(mantissa), -1074)
    else:
        v = math.ldexp(float(mantissa | _MANTISSA), exponent - 1075)
    return True, (-v if bits < 0 else v), pos + 9


@njit(cache=True)
def _read_u32(buf, pos, n):
    return _read_int(buf, pos, n, 0, U32)


@njit(cache=True)
def _read_header(buf, pos, n, version, kind):
    """A record's header at ``pos``: its version and kind as given, then its session,
    frame and sequence numbers: (ok, session, frame, seq, next position)."""
    session = frame = seq = 0
    ok, _, pos = _read_int(buf, pos, n, version, version)
    if ok:
        ok, _, pos = _read_int(buf, pos, n, kind, kind)
    if ok:
        ok, session, pos = _read_u32(buf, pos, n)
    if ok:
        ok, frame, pos = _read_u32(buf, pos, n)
    if ok:
        ok, seq, pos = _read_u32(buf, pos, n)
    return ok, session, frame, seq, pos


@njit(cache=True)
def _read_axis(buf, pos, n):
    """Check an axis's controlword, mode and 7 finite floats at ``pos``: (ok, next)."""
    ok, _, pos = _read_int(buf, pos, n, 0, 0xFFFF)
    if ok:
        ok, _, pos = _read_int(buf, pos, n, -128, 127)
    k = 0
    while ok and k < 7:
        ok, _, pos = _read_finite(buf, pos, n)
        k += 1
    return ok, pos


@njit(cache=True)
def _take_axis(buf, pos, n, axis_ints, floats, a):
    """Write the axis checked by :func:`_read_axis` at ``pos``; the next position."""
    _, axis_ints[a, A_CONTROLWORD], pos = _read_int(buf, pos, n, 0, 0xFFFF)
    _, axis_ints[a, A_MODE], pos = _read_int(buf, pos, n, -128, 127)
    for k in range(7):
        _, floats[a, k], pos = _read_finite(buf, pos, n)
    return pos


@njit(cache=True, _nrt=False)
def decode_setpoint(buf, n, ints, axis_ints, floats):
    """Read the setpoint in ``buf[:n]`` (uint8) into ``ints``, ``axis_ints`` and
    ``floats`` (see the module docstring): a version-1 Setpoint when ``axis_ints`` has one
    row, else a version-2 SetpointGroup of that many axes.  False, with nothing written,
    unless it is one with every float finite."""
    n_axes = axis_ints.shape[0]
    group = n_axes > 1
    if n < 1 or buf[0] != 0x90 + (_SPG_LENGTH if group else _SP_LENGTH):
        return False
    ok, session, frame, seq, pos = _read_header(buf, 1, n, VERSION_GROUP if group
                                                else VERSION, KIND_SETPOINT)
    if not ok:
        return False
    if group:
        ok, t_ns, pos = _read_int(buf, pos, n, 0, T_NS_MAX)
        if not ok or pos >= n or buf[pos] != 0x90 + n_axes:
            return False
        pos += 1
        start = pos
        for _ in range(n_axes):
            if pos >= n or buf[pos] != 0x90 + _SPG_AXIS:
                return False
            ok, pos = _read_axis(buf, pos + 1, n)
            if not ok:
                return False
        if pos != n:
            return False
        pos = start
        for a in range(n_axes):
            pos = _take_axis(buf, pos + 1, n, axis_ints, floats, a)
    else:
        start = pos
        ok, pos = _read_axis(buf, pos, n)
        if not ok:
            return False
        ok, t_ns, pos = _read_int(buf, pos, n, 0, T_NS_MAX)
        if not ok or pos != n:
            return False
        _take_axis(buf, start, n, axis_ints, floats, 0)
    ints[I_SESSION], ints[I_FRAME], ints[I_SEQ], ints[I_T_NS] = session, frame, seq, t_ns
    return True


@njit(cache=True)
def _write_int(out, pos, v):
    """msgpack's shortest encoding of ``v`` at ``pos``; the next position."""
    if v >= 0:
        if v <= 0x7F:
            out[pos] = v
            return pos + 1
        if v <= 0xFF:
            out[pos], width = 0xCC, 1
        elif v <= 0xFFFF:
            out[pos], width = 0xCD, 2
        elif v <= 0xFFFFFFFF:
            out[pos], width = 0xCE, 4
        else:
            out[pos], width = 0xCF, 8
    else:
        if v >= -32:
            out[pos] = v + 256
            return pos + 1
        if v >= -128:
            out[pos], width = 0xD0, 1
        elif v >= -32768:
            out[pos], width = 0xD1, 2
        elif v >= -2**31:
            out[pos], width = 0xD2, 4
        else:
            out[pos], width = 0xD3, 8
    for k in range(width):
        out[pos + width - k] = (v >> (8 * k)) & 0xFF
    return pos + 1 + width


@njit(cache=True)
def _write_float(out, pos, x):
    """``x`` (finite) as a msgpack float 64 at ``pos``; the next position."""
    negative = x < 0.0 or (x == 0.0 and math.copysign(1.0, x) < 0.0)
    a = abs(x)
    if a == 0.0:
        bits = 0
    else:
        m, e = math.frexp(a)  # a = m 2**e, 0.5 <= m < 1
        biased = e + 1022
        if biased >= 1:
            bits = (biased << 52) | (int(math.ldexp(m, 53)) - _MANTISSA)
        else:  # subnormal
            bits = int(math.ldexp(a, 1074))
    out[pos] = 0xCB
    for k in range(8):
        out[pos + 8 - k] = (bits >> (8 * k)) & 0xFF
    if negative:
        out[pos + 1] |= 0x80
    return pos + 9


@njit(cache=True, _nrt=False)
def encode_feedback(out, fb_ints, fb_axis_ints, fb_floats):
    """The feedback of ``fb_ints``, ``fb_axis_ints`` and ``fb_floats`` into ``out`` (uint8,
    at least 64 + 54 bytes per axis): a version-1 Feedback for one row, else a version-2
    FeedbackGroup.  Its length, or -1 (nothing meaningful written) when a float is not
    finite or an integer is outside its field's range."""
    n_axes = fb_axis_ints.shape[0]
    for a in range(n_axes):
        for k in range(6):
            x = fb_floats[a, k]
            if x != x or abs(x) == math.inf:
                return -1
        if not (0 <= fb_axis_ints[a, A_STATUSWORD] <= 0xFFFF
                and _FAULT_MIN <= fb_axis_ints[a, A_FAULT] <= _FAULT_MAX):
            return -1
    if not (0 <= fb_ints[F_SESSION] <= U32 and 0 <= fb_ints[F_FRAME] <= U32
            and 0 <= fb_ints[F_SEQ] <= U32):
        return -1
    for k in range(F_SP_T_NS, N_FB_INTS):
        if fb_ints[k] < 0:
            return -1
    if n_axes > 1:
        out[0] = 0x90 + _FBG_LENGTH
        pos = _write_int(out, 1, VERSION_GROUP)
        pos = _write_int(out, pos, KIND_FEEDBACK)
        for k in range(F_SESSION, F_SP_T_NS):
            pos = _write_int(out, pos, fb_ints[k])
        pos = _write_float(out, pos, fb_floats[0, 0])
        for k in range(F_SP_T_NS, N_FB_INTS):
            pos = _write_int(out, pos, fb_ints[k])
        out[pos] = 0x90 + n_axes
        pos += 1
        for a in range(n_axes):
            out[pos] = 0x90 + _FBG_AXIS
            pos = _write_int(out, pos + 1, fb_axis_ints[a, A_STATUSWORD])
            pos = _write_int(out, pos, fb_axis_ints[a, A_FAULT])
            for k in range(1, 6):
                pos = _write_float(out, pos, fb_floats[a, k])
        return pos
    out[0], out[1], out[2] = 0xDC, 0, _FB_LENGTH
    pos = _write_int(out, 3, VERSION)
    pos = _write_int(out, pos, KIND_FEEDBACK)
    for k in range(F_SESSION, F_SP_T_NS):
        pos = _write_int(out, pos, fb_ints[k])
    pos = _write_int(out, pos, fb_axis_ints[0, A_STATUSWORD])
    pos = _write_int(out, pos, fb_axis_ints[0, A_FAULT])
    for k in range(6):
        pos = _write_float(out, pos, fb_floats[0, k])
    for k in range(F_SP_T_NS, N_FB_INTS):
        pos = _write_int(out, pos, fb_ints[k])
    return pos


@njit(cache=True)
def _read_feedback_axis(buf, pos, n, fb_axis_ints, fb_floats, a, first, write):
    """An axis's statusword, fault and finite floats ``first`` .. 5 at ``pos`` (checked,
    and with ``write`` written as axis ``a``): (ok, next position)."""
    ok, statusword, pos = _read_int(buf, pos, n, 0, 0xFFFF)
    if ok:
        ok, fault, pos = _read_int(buf, pos, n, _FAULT_MIN, _FAULT_MAX)
    if ok and write:
        fb_axis_ints[a, A_STATUSWORD], fb_axis_ints[a, A_FAULT] = statusword, fault
    k = first
    while ok and k < 6:
        ok, x, pos = _read_finite(buf, pos, n)
        if write:
            fb_floats[a, k] = x
        k += 1
    return ok, pos


@njit(cache=True)
def _read_stamps(buf, pos, n, fb_ints, write):
    """The four stamps (sp_t_ns, sp_rx_ns, t_ns, tick_ns) at ``pos``: (ok, next)."""
    ok = True
    for k in range(F_SP_T_NS, N_FB_INTS):
        ok, v, pos = _read_int(buf, pos, n, 0, T_NS_MAX)
        if not ok:
            return False, pos
        if write:
            fb_ints[k] = v
    return True, pos


@njit(cache=True, _nrt=False)
def decode_feedback(buf, n, fb_ints, fb_axis_ints, fb_floats):
    """Read the feedback in ``buf[:n]`` (uint8) into ``fb_ints``, ``fb_axis_ints`` and
    ``fb_floats`` (see the module docstring; a group's ``time_s`` into axis 0's column
    0): a version-1 Feedback (a msgpack array 16) when ``fb_axis_ints`` has one row, else
    a version-2 FeedbackGroup of that many axes.  False, with nothing written, unless it
    is one with every float finite (the controller's endpoint refuses the others)."""
    n_axes = fb_axis_ints.shape[0]
    group = n_axes > 1
    if group:
        if n < 1 or buf[0] != 0x90 + _FBG_LENGTH:
            return False
        pos = 1
    else:
        if n < 3 or buf[0] != 0xDC or buf[1] != 0 or buf[2] != _FB_LENGTH:
            return False
        pos = 3
    ok, session, frame, seq, pos = _read_header(buf, pos, n, VERSION_GROUP if group
                                                else VERSION, KIND_FEEDBACK)
    if not ok:
        return False
    start = pos
    for write in (False, True):  # check all, then write: nothing written on a refusal
        pos = start
        if group:
            ok, time_s, pos = _read_finite(buf, pos, n)
            if ok:
                ok, pos = _read_stamps(buf, pos, n, fb_ints, write)
            if not ok or pos >= n or buf[pos] != 0x90 + n_axes:
                return False
            pos += 1
            for a in range(n_axes):
                if pos >= n or buf[pos] != 0x90 + _FBG_AXIS:
                    return False
                ok, pos = _read_feedback_axis(buf, pos + 1, n, fb_axis_ints, fb_floats, a,
                                              1, write)
                if not ok:
                    return False
            if write:
                fb_floats[0, 0] = time_s
        else:
            ok, pos = _read_feedback_axis(buf, pos, n, fb_axis_ints, fb_floats, 0, 0, write)
            if ok:
                ok, pos = _read_stamps(buf, pos, n, fb_ints, write)
            if not ok:
                return False
        if pos != n:
            return False
    fb_ints[F_SESSION], fb_ints[F_FRAME], fb_ints[F_SEQ] = session, frame, seq
    return True


@njit(cache=True, _nrt=False)
def encode_setpoint(out, ints, axis_ints, floats):
    """The setpoint of ``ints``, ``axis_ints`` and ``floats`` into ``out`` (uint8, at
    least 40 + 75 bytes per axis): a version-1 Setpoint for one row, else a version-2
    SetpointGroup, the bytes ``msgpack.packb`` writes.  Its length, or -1 (nothing
    meaningful written) when a float is not finite or an integer is outside its field's
    range."""
    n_axes = axis_ints.shape[0]
    for a in range(n_axes):
        for k in range(7):
            x = floats[a, k]
            if x != x or abs(x) == math.inf:
                return -1
        if not (0 <= axis_ints[a, A_CONTROLWORD] <= 0xFFFF
                and -128 <= axis_ints[a, A_MODE] <= 127):
            return -1
    if not (0 <= ints[I_SESSION] <= U32 and 0 <= ints[I_FRAME] <= U32
            and 0 <= ints[I_SEQ] <= U32 and 0 <= ints[I_T_NS] <= T_NS_MAX):
        return -1
    if n_axes > 1:
        out[0] = 0x90 + _SPG_LENGTH
        pos = _write_int(out, 1, VERSION_GROUP)
    else:
        out[0] = 0x90 + _SP_LENGTH
        pos = _write_int(out, 1, VERSION)
    pos = _write_int(out, pos, KIND_SETPOINT)
    for k in range(I_SESSION, I_T_NS):
        pos = _write_int(out, pos, ints[k])
    if n_axes > 1:
        pos = _write_int(out, pos, ints[I_T_NS])
        out[pos] = 0x90 + n_axes
        pos += 1
    for a in range(n_axes):
        if n_axes > 1:
            out[pos] = 0x90 + _SPG_AXIS
            pos += 1
        pos = _write_int(out, pos, axis_ints[a, A_CONTROLWORD])
        pos = _write_int(out, pos, axis_ints[a, A_MODE])
        for k in range(7):
            pos = _write_float(out, pos, floats[a, k])
    if n_axes == 1:
        pos = _write_int(out, pos, ints[I_T_NS])
    return pos
