"""Fuzz properties of every setpoint decoder, each a real device endpoint fed frame by frame:
the msgpack decoder over a UDP socket pair on 127.0.0.1 (wire version 1, and version 2 with
2 axes) and the serial framing over an ``os.openpty`` pair; and ``python3 -m
hil.bench.fuzz``, which runs every decoder.

tests/test_adapter_decoders.py follows streams of well-formed messages with an exact
reference of the sequence check; here frames are mutated with no model of what they
become: any element of a message replaced by any msgpack object (maps, arrays, extension
types, strings, integers up to 2**64 - 1) or by NaN, +-inf, +-1e308, -0.0 or a value just
past its bound, elements dropped or added, other sessions, frame numbers and HELLOs, and
the bytes truncated, concatenated, bit-flipped or random.  What is asserted holds whatever
a frame became:

* nothing raises out of ``recv_setpoint``;
* UDP: each datagram is counted in exactly one counter of the identity in AdapterStats'
  docstring; serial: the identity holds after every call;
* a setpoint taken is a frame's own values (decoded here with msgpack), and no field of
  the record is ever non-finite or beyond the bounds given (``reference_refusal``, field
  by field);
* ``refused_axes`` is non-zero exactly in the call that counted a refusal; on UDP it names
  exactly the axes whose values the bounds refuse.

The CANopen device endpoint: tests/test_fuzz_can_decoder.py.
"""

import json
import math
import os
import select
import socket
import subprocess
import sys
from dataclasses import dataclass

import msgpack
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from hil.drive import EmulatedDrive
from io_adapters import codec
from io_adapters.messages import (
    REFUSED_MODE,
    REFUSED_NONFINITE,
    REFUSED_RANGE,
    SetpointBounds,
    axis_records,
    message_pair,
)
from io_adapters.serial_link import SerialEndpoint, frame
from io_adapters.udp import UdpEndpoint
from plant import Plant
from plant.config import load_machine
from tests.conftest import CONFIGS, ROOT
from tests.test_adapter_decoders import (
    BOUNDS,
    FLOAT_NAMES,
    Machine,
    reference_refusal,
    same,
    setpoint,
    taken_axis,
)
from tests.test_adapters import COUNTED, assert_counts_add_up

WAIT_S = 5.0
ARROW = CONFIGS / "arrow500_x.toml"
SESSION = 0x5EED
SETTINGS = settings(max_examples=200, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
REFUSAL_COUNTERS = {REFUSED_NONFINITE: "refused_nonfinite", REFUSED_MODE: "refused_mode",
                    REFUSED_RANGE: "refused_range"}


@pytest.fixture(scope="module")
def arrow_drive() -> EmulatedDrive:
    """The Arrow 500 X's drive, for its bounds."""
    return EmulatedDrive(Plant(load_machine(ARROW), table_pos=0.25))


def counters(stats) -> dict:
    return {name: getattr(stats, name) for name in ("frames",) + COUNTED}


def changed(before: dict, after: dict) -> dict:
    return {k: after[k] - before[k] for k in after if after[k] != before[k]}


def mask_of(reasons: list) -> int:
    return sum(1 << a for a, r in enumerate(reasons) if r)


def assert_record_within(message, machine: Machine) -> None:
    """No field of any axis's record is non-finite or beyond its bounds (mode included)."""
    for a, rec in enumerate(axis_records(message)):
        floats = tuple(getattr(rec, name) for name in FLOAT_NAMES)
        assert reference_refusal(rec.mode, floats, machine.axis_bounds(a)) == 0, (a, rec)


# -- msgpack frames: well-formed, then mutated ----------------------------------------------

SPECIAL = (math.nan, math.inf, -math.inf, 1e308, -1e308, -0.0)
HUGE_INTS = (2**63, 2**64 - 1, -2**63, 2**32, -1)
MSGPACK_OBJECTS = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats()
    | st.text(max_size=4) | st.binary(max_size=4)
    | st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=4)),
    lambda inner: st.lists(inner, max_size=3)
    | st.dictionaries(st.integers(0, 3) | st.text(max_size=2), inner, max_size=2),
    max_leaves=6)
VALUE_MUTATIONS = ("special", "past bound", "object", "huge", "drop", "extra", "session",
                   "frame")
BYTE_MUTATIONS = ("truncate", "concatenate", "flip", "insert", "random")


@st.composite
def fuzz_machines(draw, n_axes: int, drive_bounds: SetpointBounds) -> Machine:
    """The Arrow 500 X drive's bounds on every axis, or bounds drawn per axis."""
    if draw(st.booleans()):
        return Machine(n_axes, (drive_bounds,))
    return Machine(n_axes, tuple(draw(st.lists(BOUNDS, min_size=n_axes, max_size=n_axes))))


@dataclass
class Sender:
    """The peer's frame counter, for well-formed messages of the pinned session."""
    machine: Machine
    frame_no: int = 0

    def values(self, draw) -> list:
        """A well-formed setpoint message (as msgpack arrays, lists) within the bounds,
        perhaps with one field at or past its bound (``taken_axis``)."""
        axes = [draw(taken_axis(self.machine.axis_bounds(a)))
                for a in range(self.machine.n_axes)]
        message = setpoint(self.machine, axes, self.frame_no)
        for rec in axis_records(message):
            rec.controlword = draw(st.integers(0, 0xFFFF))
        data = codec.encode(message, SESSION, self.frame_no)
        self.frame_no = (self.frame_no + 1) & codec.U32
        return msgpack.unpackb(data)


def element_path(draw, values: list) -> tuple[list, int]:
    """A list of ``values`` (the message, or an axis array of a group) and an index in it."""
    axes = values[-1] if type(values[-1]) is list else None
    if axes and draw(st.booleans()):
        row = axes[draw(st.integers(0, len(axes) - 1))]
        return row, draw(st.integers(0, len(row) - 1))
    return values, draw(st.integers(0, len(values) - 1))


@st.composite
def fuzz_messages(draw, sender: Sender) -> bytes:
    values = sender.values(draw)
    kind = draw(st.sampled_from(("well-formed",) * 3 + VALUE_MUTATIONS + BYTE_MUTATIONS
                                + ("hello",)))
    if kind == "hello":
        return codec.encode_hello(SESSION, draw(st.integers(0, codec.U32)))
    if kind in VALUE_MUTATIONS:
        row, i = element_path(draw, values)
        if kind == "special":
            row[i] = draw(st.sampled_from(SPECIAL))
        elif kind == "past bound":
            limit = draw(st.sampled_from([2.0**53, 28.0, 600.0, 1e6, 250.5]))
            row[i] = draw(st.sampled_from([1, -1])) * math.nextafter(limit, math.inf)
        elif kind == "object":
            row[i] = draw(MSGPACK_OBJECTS)
        elif kind == "huge":
            row[i] = draw(st.sampled_from(HUGE_INTS))
        elif kind == "drop":
            del row[i]
        elif kind == "extra":
            row.insert(i, draw(MSGPACK_OBJECTS))
        elif kind == "session":
            values[2] = draw(st.integers(0, codec.U32) | st.sampled_from(HUGE_INTS))
        else:
            values[3] = draw(st.integers(0, codec.U32))
    data = msgpack.packb(values)
    if kind == "truncate":
        return data[:draw(st.integers(1, len(data) - 1))]
    if kind == "concatenate":
        return data + data[:draw(st.integers(1, len(data)))]
    if kind == "flip":
        i = draw(st.integers(0, len(data) - 1))
        return data[:i] + bytes([data[i] ^ 1 << draw(st.integers(0, 7))]) + data[i + 1:]
    if kind == "insert":
        i = draw(st.integers(0, len(data)))
        return data[:i] + draw(st.binary(min_size=1, max_size=3)) + data[i:]
    if kind == "random":
        return draw(st.binary(min_size=1, max_size=120))
    return data


def wire_axes(data: bytes, n_axes: int) -> list[tuple]:
    """(mode, floats) of each axis of a message that the device took as a well-formed
    setpoint, as msgpack decodes it (the codec's refusal slices name the fields)."""
    values = msgpack.unpackb(data, use_list=False)
    rows = [values[codec.SETPOINT_REFUSAL_ARGS]] if n_axes == 1 else [
        axis[codec.GROUP_REFUSAL_ARGS] for axis in values[-1]]
    return [(row[0], tuple(row[1:])) for row in rows]


def check_taken(message, axes: list[tuple]) -> None:
    """The record is the frame's values, bit for bit."""
    for rec, (mode, floats) in zip(axis_records(message), axes):
        got = tuple(getattr(rec, name) for name in FLOAT_NAMES)
        assert rec.mode == mode and all(map(same, got, floats)), (rec, mode, floats)


# -- UDP ----------------------------------------------------------------------------------

@SETTINGS
@given(data=st.data(), n_axes=st.sampled_from([1, 2]))
def test_udp_decoder_counts_refuses_and_takes_each_mutated_datagram(data, n_axes, arrow_drive):
    machine = data.draw(fuzz_machines(n_axes, arrow_drive.setpoint_bounds()))
    sender, into = Sender(machine), message_pair(n_axes)[0]
    taken = False
    with UdpEndpoint("device", ("127.0.0.1", 0)) as device, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        device.setpoint_bounds = machine.bounds
        raw.bind(("127.0.0.1", 0))
        message = None
        for sent in range(1, data.draw(st.integers(1, 25)) + 1):
            if message is None or data.draw(st.integers(0, 5)):
                message = data.draw(fuzz_messages(sender))
            before = counters(device.stats)
            raw.sendto(message, device.address)
            assert select.select((device,), (), (), WAIT_S)[0], "the datagram did not arrive"
            got = device.recv_setpoint(into, 0.0)
            delta = changed(before, counters(device.stats))
            assert delta.pop("frames") == 1 and list(delta.values()) == [1], delta
            assert_counts_add_up(device.stats, sent)
            (counter,) = delta
            event(counter)
            assert got == (counter == "received")
            if counter.startswith("refused_"):
                reasons = [reference_refusal(mode, floats, machine.axis_bounds(a))
                           for a, (mode, floats) in enumerate(wire_axes(message, n_axes))]
                assert REFUSAL_COUNTERS[min(r for r in reasons if r)] == counter, reasons
                assert device.refused_axes == mask_of(reasons)
            else:
                assert device.refused_axes == 0
            if got:
                axes = wire_axes(message, n_axes)
                check_taken(into, axes)
                taken = True
            if taken:
                assert_record_within(into, machine)


# -- serial -------------------------------------------------------------------------------

@st.composite
def serial_chunks(draw, sender: Sender) -> tuple[bytes, bytes | None]:
    """(bytes to write, the msgpack message framed in them or None): a framed message, a
    frame with a flipped bit, a wrong length or cut short, or raw bytes."""
    message = draw(fuzz_messages(sender))
    framed = frame(message[:255])
    kind = draw(st.sampled_from(["frame"] * 4 + ["flip", "length", "cut", "raw"]))
    if kind == "flip":
        i = draw(st.integers(2, len(framed) - 1))
        return framed[:i] + bytes([framed[i] ^ 1 << draw(st.integers(0, 7))]) + framed[i + 1:], \
            None
    if kind == "length":  # another length than the frame's (the same one is the frame)
        return framed[:2] + bytes([draw(st.integers(0, 255).filter(
            lambda n: n != framed[2]))]) + framed[3:], None
    if kind == "cut":
        return framed[:draw(st.integers(1, len(framed) - 1))], None
    if kind == "raw":
        return draw(st.binary(min_size=1, max_size=60)), None
    return framed, message[:255]


@SETTINGS
@given(data=st.data(), n_axes=st.sampled_from([1, 2]))
def test_serial_decoder_never_lets_a_bad_value_through(data, n_axes, arrow_drive):
    """The stream's bytes may form frames across chunks, so a refusal or a take is not
    tied to one chunk: a taken record must be the values of some frame written, and
    ``refused_axes`` is set exactly in the calls that count a refusal."""
    machine = data.draw(fuzz_machines(n_axes, arrow_drive.setpoint_bounds()))
    sender, into = Sender(machine), message_pair(n_axes)[0]
    written, taken = [], False
    master, slave = os.openpty()
    try:
        with SerialEndpoint("device", master) as device:
            device.setpoint_bounds = machine.bounds
            for _ in range(data.draw(st.integers(1, 25))):
                chunk, message = data.draw(serial_chunks(sender))
                if message is not None:
                    written.append(message)
                os.write(slave, chunk)
                assert select.select((device,), (), (), WAIT_S)[0], "the bytes did not arrive"
                while True:
                    before = counters(device.stats)
                    got = device.recv_setpoint(into, 0.0)
                    delta = changed(before, counters(device.stats))
                    assert_counts_add_up(device.stats)
                    refused = sum(v for k, v in delta.items() if k.startswith("refused_"))
                    assert (device.refused_axes != 0) == (refused > 0), delta
                    if not got:
                        break
                    assert any(candidate_taken(into, m, n_axes) for m in written), into
                    taken = True
                if taken:
                    assert_record_within(into, machine)
    finally:
        os.close(slave)


def candidate_taken(message, data: bytes, n_axes: int) -> bool:
    """Whether the record holds the setpoint values of ``data``, bit for bit."""
    try:
        axes = wire_axes(data, n_axes)
        check_taken(message, axes)
    except (AssertionError, ValueError, TypeError, IndexError):
        return False
    return True


# -- the fuzz command ---------------------------------------------------------------------

def test_fuzz_command_json_reports_every_decoder_passing():
    """``python3 -m hil.bench.fuzz --frames 2000 --json``: every decoder ran its frames,
    every check passed, the counters add up, and faults were met and reset."""
    proc = subprocess.run([sys.executable, "-m", "hil.bench.fuzz", "--frames", "2000",
                           "--seed", "3", "--json"], cwd=ROOT, capture_output=True, text=True,
                          timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads(proc.stdout)
    assert report["seed"] == 3 and report["ok"] is True
    rows = {row["decoder"]: row for row in report["decoders"]}
    assert set(rows) == {"udp-v1", "udp-v2", "serial", "can-rpdo", "can-sdo"}
    for name, row in rows.items():
        assert row["frames"] >= 2000, name
        assert row["checks"] and set(row["checks"].values()) == {"PASS"}, (name, row["checks"])
        if name == "can-sdo":  # a refused SDO write is answered by its abort: no fault
            assert row["counters"]["refused_mode"] + row["counters"]["refused_range"] > 0
        else:
            assert sum(row["faults"].values()) > 0 and row["fault_resets"] > 0, (name, row)
        stats = row["counters"]
        if name.startswith(("udp", "serial")):
            assert stats["frames"] == sum(stats[k] for k in COUNTED), (name, stats)
