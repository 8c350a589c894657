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

Layouts (compile-time indices):

* ``ints`` int64[:data:`N_SP_INTS`] of a decoded setpoint: ``I_SESSION``, ``I_FRAME``,
  ``I_SEQ``, ``I_CONTROLWORD``, ``I_MODE``, ``I_T_NS`` (the header's session and frame,
  then the record's integers);
* ``floats`` float64[7]: the setpoint's floats in wire order (:data:`SP_FLOAT_FIELDS`);
* ``fb_ints`` int64[:data:`N_FB_INTS`]: ``F_SESSION``, ``F_FRAME``, ``F_SEQ``,
  ``F_STATUSWORD``, ``F_FAULT``, ``F_SP_T_NS``, ``F_SP_RX_NS``, ``F_T_NS``, ``F_TICK_NS``;
  ``fb_floats`` float64[6]: :data:`FB_FLOAT_FIELDS`.
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
)

#: the setpoint's floats, in wire order
SP_FLOAT_FIELDS = tuple(f.name for f in SETPOINT_FIELDS if f.type is float)
#: the feedback's floats, in wire order
FB_FLOAT_FIELDS = tuple(f.name for f in FEEDBACK_FIELDS if f.type is float)
I_SESSION, I_FRAME, I_SEQ, I_CONTROLWORD, I_MODE, I_T_NS, N_SP_INTS = range(7)
(F_SESSION, F_FRAME, F_SEQ, F_STATUSWORD, F_FAULT, F_SP_T_NS, F_SP_RX_NS, F_T_NS, F_TICK_NS,
 N_FB_INTS) = range(10)
#: a Setpoint's array: the header and its fields (15: a msgpack fixarray)
_SP_LENGTH = 4 + len(SETPOINT_FIELDS)
#: a Feedback's array (17: a msgpack array 16)
_FB_LENGTH = 4 + len(FEEDBACK_FIELDS)
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


@njit(cache=True, _nrt=False)
def decode_setpoint(buf, n, ints, floats):
    """Read the version-1 Setpoint in ``buf[:n]`` (uint8) into ``ints`` and ``floats``
    (see the module docstring); False, with nothing written, unless it is one with
    finite floats."""
    if n < 1 or buf[0] != 0x90 + _SP_LENGTH:
        return False
    ok, version, pos = _read_int(buf, 1, n, VERSION, VERSION)
    if not ok:
        return False
    ok, kind, pos = _read_int(buf, pos, n, KIND_SETPOINT, KIND_SETPOINT)
    if not ok:
        return False
    ok, session, pos = _read_int(buf, pos, n, 0, U32)
    if not ok:
        return False
    ok, frame, pos = _read_int(buf, pos, n, 0, U32)
    if not ok:
        return False
    ok, seq, pos = _read_int(buf, pos, n, 0, U32)
    if not ok:
        return False
    ok, controlword, pos = _read_int(buf, pos, n, 0, 0xFFFF)
    if not ok:
        return False
    ok, mode, pos = _read_int(buf, pos, n, -128, 127)
    if not ok:
        return False
    start = pos
    for _ in range(7):
        ok, v, pos = _read_finite(buf, pos, n)
        if not ok:
            return False
    ok, t_ns, pos = _read_int(buf, pos, n, 0, T_NS_MAX)
    if not ok or pos != n:
        return False
    pos = start
    for k in range(7):
        ok, v, pos = _read_finite(buf, pos, n)
        floats[k] = v
    ints[I_SESSION], ints[I_FRAME], ints[I_SEQ] = session, frame, seq
    ints[I_CONTROLWORD], ints[I_MODE], ints[I_T_NS] = controlword, mode, t_ns
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
def encode_feedback(out, fb_ints, fb_floats):
    """The version-1 Feedback of ``fb_ints`` and ``fb_floats`` into ``out`` (uint8, at
    least 120 bytes); its length, or -1 (nothing meaningful written) when a float is not
    finite or an integer is outside its field's range."""
    for k in range(6):
        x = fb_floats[k]
        if x != x or abs(x) == math.inf:
            return -1
    if not (0 <= fb_ints[F_SESSION] <= U32 and 0 <= fb_ints[F_FRAME] <= U32
            and 0 <= fb_ints[F_SEQ] <= U32 and 0 <= fb_ints[F_STATUSWORD] <= 0xFFFF
            and _FAULT_MIN <= fb_ints[F_FAULT] <= _FAULT_MAX):
        return -1
    for k in range(F_SP_T_NS, N_FB_INTS):
        if fb_ints[k] < 0:
            return -1
    out[0], out[1], out[2] = 0xDC, 0, _FB_LENGTH
    pos = _write_int(out, 3, VERSION)
    pos = _write_int(out, pos, KIND_FEEDBACK)
    for k in range(F_SESSION, F_SP_T_NS):
        pos = _write_int(out, pos, fb_ints[k])
    for k in range(6):
        pos = _write_float(out, pos, fb_floats[k])
    for k in range(F_SP_T_NS, N_FB_INTS):
        pos = _write_int(out, pos, fb_ints[k])
    return pos
