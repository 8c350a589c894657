"""Property tests of the two msgpack decoders (UDP datagrams, serial frames), each a real
device endpoint fed by a raw peer over a real transport (a socket on 127.0.0.1, an
``os.openpty`` pair).

hypothesis draws a machine of 1 to 3 axes, the drive's bounds and a stream of messages:
well-formed setpoints with any floats (NaN, +-inf, 1e308, -0.0, values at and just past a
bound, modes in and out of the drive's), replays, messages of another session, and
garbage (random bytes, truncated, concatenated, wrong types, out-of-range integers,
wrong version or axis count); on serial also raw bytes between the frames.  The stream
always begins with a well-formed setpoint (the device pins its session) and ends with a
good one.  The expected outcome of every message comes from a reference written here
(:func:`reference_refusal`: ``math.isfinite`` and the bounds field by field), not from
the endpoint.  Properties: nothing raises; every ``recv_setpoint`` returns the next
message the reference takes, and no non-finite or out-of-bound value ever reaches the
record; ``refused_axes`` names exactly the axes the reference refuses among the
messages that call read; each counter holds what the reference says, and they add up to
the frames sent; the last good frame is taken after any garbage.  The same for feedback
on the controller side (non-finite values refused, WELCOMEs counted, never returned).
"""

import math
import os
import socket
import threading
from dataclasses import dataclass, field

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from io_adapters import codec
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    MODE_VOLTAGE,
    REFUSED_MODE,
    REFUSED_NONFINITE,
    REFUSED_RANGE,
    FeedbackGroup,
    SetpointBounds,
    SetpointGroup,
    message_pair,
)
from io_adapters.serial_link import MAX_PAYLOAD, SerialEndpoint, frame
from io_adapters.udp import UdpEndpoint
from tests.test_adapters import COUNTED

WAIT_S = 5.0
SESSION = 0x1234
OTHER_SESSION = 0x4321
FLOAT_NAMES = ("target_position_counts", "target_velocity_counts_s",
               "velocity_offset_counts_s", "iq_ref_a", "id_ref_a", "ud_v", "uq_v")
LIMIT_NAMES = ("position_counts", "velocity_counts_s", "velocity_counts_s", "current_a",
               "current_a", "voltage_v", "voltage_v")
DRIVE_MODES = (MODE_CSP, MODE_CSV, MODE_CST, MODE_VOLTAGE)
SETTINGS = settings(max_examples=100, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def reference_refusal(mode: int, floats: tuple, bounds: SetpointBounds) -> int:
    """What the drive should say of one axis's setpoint: the rules of SetpointBounds,
    field by field."""
    if not all(math.isfinite(v) for v in floats):
        return REFUSED_NONFINITE
    if mode not in bounds.modes:
        return REFUSED_MODE
    if any(abs(v) > getattr(bounds, limit) for v, limit in zip(floats, LIMIT_NAMES)):
        return REFUSED_RANGE
    return 0


# -- strategies --------------------------------------------------------------------------

LIMITS = st.sampled_from([0.0, 1.0, 250.5, 1e6, 2.0**53, math.inf])
SPECIAL = [math.nan, math.inf, -math.inf, 1e308, -1e308, -0.0, 0.0, 5e-324, 250.5,
           math.nextafter(250.5, math.inf), 2.0**53, math.nextafter(2.0**53, math.inf)]
FLOATS = st.one_of(st.sampled_from(SPECIAL), st.floats(), st.floats(-300.0, 300.0))
MODES = st.one_of(st.sampled_from(DRIVE_MODES), st.integers(-128, 127))
BOUNDS = st.builds(SetpointBounds, position_counts=LIMITS, velocity_counts_s=LIMITS,
                   current_a=LIMITS, voltage_v=LIMITS,
                   modes=st.frozensets(st.sampled_from(DRIVE_MODES), min_size=1))
WILD_AXIS = st.tuples(MODES, st.tuples(*[FLOATS] * len(FLOAT_NAMES)))


@st.composite
def taken_axis(draw, bounds: SetpointBounds) -> tuple:
    """An axis's setpoint within ``bounds``, then perhaps one field (or the mode) put at
    or just past its bound, or made non-finite."""
    limits = [getattr(bounds, name) for name in LIMIT_NAMES]
    floats = [draw(st.floats(-min(limit, 1e9), min(limit, 1e9))) for limit in limits]
    mode = draw(st.sampled_from(sorted(bounds.modes)))
    if draw(st.booleans()):
        i = draw(st.integers(0, len(floats)))
        if i == len(floats):
            mode = draw(MODES)
        else:
            past = math.nextafter(limits[i], math.inf)
            floats[i] = draw(st.sampled_from([limits[i], -limits[i], past, -past, math.nan,
                                              math.inf, -math.inf, 1e308, -0.0]))
    return mode, tuple(floats)


@dataclass
class Machine:
    """Axes and the bounds the device is given (one for every axis, or one per axis)."""
    n_axes: int
    bounds: tuple

    def axis_bounds(self, a: int) -> SetpointBounds:
        return self.bounds[a] if len(self.bounds) > 1 else self.bounds[0]


@st.composite
def machines(draw) -> Machine:
    n_axes = draw(st.integers(1, 3))
    n_bounds = n_axes if n_axes > 1 and draw(st.booleans()) else 1
    return Machine(n_axes, tuple(draw(st.lists(BOUNDS, min_size=n_bounds, max_size=n_bounds))))


def setpoint(machine: Machine, axes: list, seq: int):
    """A setpoint message of the machine's shape with ``axes`` [(mode, floats), ...]."""
    message = message_pair(machine.n_axes)[0]
    message.seq = seq
    records = message.axes if machine.n_axes > 1 else (message,)
    for rec, (mode, floats) in zip(records, axes):
        rec.mode = mode
        for name, v in zip(FLOAT_NAMES, floats):
            setattr(rec, name, v)
    return message


def good_axes(machine: Machine) -> list:
    return [(min(machine.axis_bounds(a).modes), (0.0,) * len(FLOAT_NAMES))
            for a in range(machine.n_axes)]


HUGE = (2**63, 2**64 - 1, -2**63)  # beyond every integer field, and no float
GARBAGE = ("random bytes", "truncated", "concatenated", "wrong type", "huge integer",
           "wrong version", "other axes", "feedback", "welcome")


def replace_one(draw, values: list, new) -> list:
    """``values`` (a decoded message; a group's axes as lists) with one element, of the
    message or of an axis array, replaced by ``new(draw, old)``."""
    axes = values[-1] if type(values[-1]) is list else None
    if axes and draw(st.booleans()):
        row = axes[draw(st.integers(0, len(axes) - 1))]
        i = draw(st.integers(0, len(row) - 1))
        row[i] = new(draw, row[i])
    else:
        i = draw(st.integers(0, len(values) - 1))
        values[i] = new(draw, values[i])
    return values


def wrong_type(draw, old):
    return draw(st.sampled_from([v for v in ("x", None, True, 1.5, 7, [1], b"\x01")
                                 if type(v) is not type(old)]))


def huge(draw, old):
    return draw(st.sampled_from(HUGE))


def garbage(draw, machine: Machine, good: bytes) -> bytes:
    """A message the device must drop as malformed, made from ``good``, a well-formed
    setpoint of the pinned session."""
    values = msgpack.unpackb(good)
    kind = draw(st.sampled_from(GARBAGE))
    if kind == "random bytes":
        return draw(st.binary(min_size=1, max_size=80).filter(not_a_handshake))
    if kind == "truncated":
        return good[:draw(st.integers(1, len(good) - 1))]
    if kind == "concatenated":
        return good + good
    if kind in ("wrong type", "huge integer"):
        return msgpack.packb(replace_one(draw, values,
                                         wrong_type if kind == "wrong type" else huge))
    if kind == "wrong version":
        values[0] = draw(st.sampled_from([0, 3, 255, 2 if machine.n_axes == 1 else 1]))
        return msgpack.packb(values)
    if kind == "other axes":  # a plain record for a group, a group of another size
        other = draw(st.sampled_from([n for n in (1, 2, 3) if n != machine.n_axes]))
        return codec.encode(message_pair(other)[0], SESSION, values[3])
    if kind == "feedback":
        return codec.encode(message_pair(machine.n_axes)[1], SESSION, values[3])
    return codec.encode_welcome(SESSION, values[3], True)


def not_a_handshake(data: bytes) -> bool:
    """Random bytes that happen to decode as [1, 3|4, ...] would be a HELLO attempt."""
    try:
        values = msgpack.unpackb(data)
    except (ValueError, TypeError):
        return True
    return not (isinstance(values, list) and len(values) > 1 and values[1] in (3, 4))


# -- the reference's account of a stream ----------------------------------------------------

COUNTER = {REFUSED_NONFINITE: "refused_nonfinite", REFUSED_MODE: "refused_mode",
           REFUSED_RANGE: "refused_range"}


@dataclass
class Expected:
    """What the device must do with a stream, from the reference."""
    takes: list = field(default_factory=list)      # (seq, axes) of each taken message
    refused: list = field(default_factory=list)    # refused axes before each take
    counts: dict = field(default_factory=lambda: dict.fromkeys(COUNTED, 0))
    messages: list = field(default_factory=list)   # (bytes, framed?) in sending order


@st.composite
def streams(draw, machine: Machine, raw_bytes: bool = False) -> Expected:
    exp, frame_no, seq, mask = Expected(), 0, 0, 0
    last_good = None

    def well_formed(axes) -> bytes:
        nonlocal frame_no, seq, mask, last_good
        message = codec.encode(setpoint(machine, axes, seq), SESSION, frame_no)
        reasons = [reference_refusal(mode, floats, machine.axis_bounds(a))
                   for a, (mode, floats) in enumerate(axes)]
        if any(reasons):  # counted once, under the lowest code of its axes
            exp.counts[COUNTER[min(r for r in reasons if r)]] += 1
            mask |= sum(1 << a for a, r in enumerate(reasons) if r)
        else:
            exp.counts["received"] += 1
            exp.takes.append((seq, axes))
            exp.refused.append(mask)
            mask = 0
        frame_no, seq, last_good = frame_no + 1, seq + 1, message
        return message

    axes_of_machine = st.one_of(
        st.lists(WILD_AXIS, min_size=machine.n_axes, max_size=machine.n_axes),
        st.tuples(*[taken_axis(machine.axis_bounds(a)) for a in range(machine.n_axes)]))
    exp.messages.append((well_formed(draw(axes_of_machine)), True))
    for _ in range(draw(st.integers(0, 12))):
        what = draw(st.sampled_from(["record", "record", "replay", "stale", "garbage"]
                                    + ["raw"] * raw_bytes))
        if what == "record":
            exp.messages.append((well_formed(draw(axes_of_machine)), True))
        elif what == "replay":
            exp.messages.append((last_good, True))
            exp.counts["duplicates"] += 1
        elif what == "stale":
            exp.messages.append((codec.encode(setpoint(machine, draw(axes_of_machine), 99),
                                              OTHER_SESSION, frame_no), True))
            exp.counts["stale_session"] += 1
        elif what == "garbage":
            bad = garbage(draw, machine, last_good)
            if len(bad) <= MAX_PAYLOAD:  # what a serial frame holds
                exp.messages.append((bad, True))
                exp.counts["malformed"] += 1
        else:
            exp.messages.append((draw(st.binary(min_size=1, max_size=40)), False))
    exp.messages.append((well_formed(good_axes(machine)), True))
    return exp


# -- the transports ------------------------------------------------------------------------

class UdpPeer:
    """A device (or controller) endpoint on 127.0.0.1 and a raw socket speaking to it."""

    def __init__(self, role: str):
        self.raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.raw.bind(("127.0.0.1", 0))
        self.endpoint = (UdpEndpoint("device", ("127.0.0.1", 0)) if role == "device" else
                         UdpEndpoint("controller", self.raw.getsockname()))

    def send(self, messages: list) -> int:
        for data, _ in messages:  # no raw stream bytes on UDP
            self.raw.sendto(data, self.endpoint.address)
        return len(messages)

    def close(self) -> None:
        self.endpoint.close()
        self.raw.close()


class SerialPeer:
    """An endpoint on a pty master and a raw writer on the slave; the writer is a thread,
    so that a stream longer than the pty's buffer goes through while the endpoint reads."""

    def __init__(self, role: str):
        master, self.slave = os.openpty()
        self.endpoint = SerialEndpoint(role, master)
        self.writer = None

    def send(self, messages: list) -> int:
        data = b"".join(frame(m) if framed else m for m, framed in messages)
        self.writer = threading.Thread(target=os.write, args=(self.slave, data))
        self.writer.start()
        return sum(framed for _, framed in messages)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.join(WAIT_S)
            assert not self.writer.is_alive()
        self.endpoint.close()
        os.close(self.slave)


def same(a: float, b: float) -> bool:
    """Equal as float64 bit patterns (the sign of -0.0 included)."""
    return math.copysign(1.0, a) == math.copysign(1.0, b) and a == b


def check_setpoint_stream(peer, machine: Machine, exp: Expected, exact_frames: bool) -> None:
    device = peer.endpoint
    device.setpoint_bounds = machine.bounds
    sent = peer.send(exp.messages)
    into = message_pair(machine.n_axes)[0]
    records = into.axes if machine.n_axes > 1 else (into,)
    for (seq, axes), refused in zip(exp.takes, exp.refused):
        assert device.recv_setpoint(into, WAIT_S), f"setpoint {seq} not taken"
        assert (into.seq, device.refused_axes) == (seq, refused)
        for a, (rec, (mode, floats)) in enumerate(zip(records, axes)):
            got = tuple(getattr(rec, name) for name in FLOAT_NAMES)
            assert rec.mode == mode and all(map(same, got, floats)), (a, rec)
            assert reference_refusal(rec.mode, got, machine.axis_bounds(a)) == 0, (a, rec)
    stats = device.stats
    assert stats.frames == sum(getattr(stats, name) for name in COUNTED), stats
    for name, count in exp.counts.items():
        if exact_frames or name != "malformed":
            assert getattr(stats, name) == count, (name, stats)
    if exact_frames:
        assert stats.frames == sent, stats


PEERS = {"udp": UdpPeer, "serial": SerialPeer}


@pytest.mark.parametrize("transport, raw_bytes", [
    ("udp", False),
    ("serial", False),  # whole frames with good CRCs: every frame counted once
    # raw bytes between the frames as well: they make candidate frames of their own
    # (counted as malformed, so the frame count is not the number sent), and every
    # frame behind them is still found
    ("serial", True),
])
@SETTINGS
@given(data=st.data())
def test_setpoint_decoder(transport, raw_bytes, data):
    machine = data.draw(machines())
    peer = PEERS[transport]("device")
    try:
        check_setpoint_stream(peer, machine, data.draw(streams(machine, raw_bytes)),
                              exact_frames=not raw_bytes)
    finally:
        peer.close()


# -- feedback on the controller side ---------------------------------------------------------

FB_AXIS_FLOATS = ("encoder_counts", "scale_counts", "velocity_counts_s", "iq_a", "id_a")


@st.composite
def feedback_streams(draw, n_axes: int) -> tuple[list, list, dict, bool]:
    """(messages, floats of each feedback the controller must take, counts, welcomed)."""
    messages, takes, frame_no, welcomed = [], [], 0, False
    counts = dict.fromkeys(COUNTED, 0)
    for _ in range(draw(st.integers(0, 10))):
        what = draw(st.sampled_from(["feedback", "feedback", "welcome", "garbage"]))
        if what == "welcome":
            accepted = draw(st.booleans())
            messages.append((codec.encode_welcome(SESSION, frame_no, accepted), True))
            counts["handshakes"] += 1
            welcomed = welcomed or accepted
        elif what == "garbage":
            messages.append((draw(st.binary(min_size=1, max_size=60).filter(
                not_a_handshake)), True))
            counts["malformed"] += 1
        else:
            floats = draw(st.lists(FLOATS, min_size=1 + n_axes * len(FB_AXIS_FLOATS),
                                   max_size=1 + n_axes * len(FB_AXIS_FLOATS)))
            messages.append((codec.encode(feedback(n_axes, frame_no, floats), SESSION,
                                          frame_no), True))
            frame_no += 1
            if all(map(math.isfinite, floats)):
                takes.append(floats)
                counts["received"] += 1
            else:
                counts["refused_nonfinite"] += 1
    floats = [0.0] * (1 + n_axes * len(FB_AXIS_FLOATS))
    messages.append((codec.encode(feedback(n_axes, frame_no, floats), SESSION, frame_no), True))
    takes.append(floats)
    counts["received"] += 1
    return messages, takes, counts, welcomed


def feedback(n_axes: int, seq: int, floats: list):
    """A feedback message: ``floats`` = time_s, then each axis's FB_AXIS_FLOATS."""
    message = message_pair(n_axes)[1]
    message.seq, message.time_s = seq, floats[0]
    records = message.axes if n_axes > 1 else (message,)
    for a, rec in enumerate(records):
        for i, name in enumerate(FB_AXIS_FLOATS):
            setattr(rec, name, floats[1 + a * len(FB_AXIS_FLOATS) + i])
    return message


def feedback_floats(message) -> list:
    records = message.axes if isinstance(message, FeedbackGroup) else (message,)
    return [message.time_s] + [getattr(r, n) for r in records for n in FB_AXIS_FLOATS]


@pytest.mark.parametrize("transport", sorted(PEERS))
@SETTINGS
@given(data=st.data(), n_axes=st.integers(1, 3))
def test_feedback_decoder_refuses_non_finite_values(transport, data, n_axes):
    messages, takes, counts, welcomed = data.draw(feedback_streams(n_axes))
    peer = PEERS[transport]("controller")
    try:
        ctl = peer.endpoint
        sent = peer.send(messages)
        into = message_pair(n_axes)[1]
        for floats in takes:
            assert ctl.recv_feedback(into, WAIT_S)
            got = feedback_floats(into)
            assert all(map(same, got, floats)) and all(map(math.isfinite, got))
        stats = ctl.stats
        assert {name: getattr(stats, name) for name in COUNTED} == counts
        assert stats.frames == sent and ctl.welcomed == welcomed
    finally:
        peer.close()


def test_the_refusal_arguments_are_the_wire_fields_in_order():
    """codec's slices hand SetpointBounds.refusal the fields it names, in its order."""
    names = ("mode",) + FLOAT_NAMES
    assert codec.REFUSAL_ARGS == names
    assert tuple(f.name for f in (codec.HEADER + codec.SETPOINT_FIELDS)[
        codec.SETPOINT_REFUSAL_ARGS]) == names
    assert tuple(f.name for f in codec.GROUP_SCHEMAS[SetpointGroup].axis[
        codec.GROUP_REFUSAL_ARGS]) == names
