"""Fuzz properties of the CANopen device endpoint (io_adapters.can_cia402) over
python-can's ``virtual`` bus: RPDOs of any COB-ID, DLC and bytes, SDO expedited downloads
to any index, sub-index and value, one frame at a time with the drive's parameter objects
behind the node (the msgpack decoders: tests/test_fuzz_decoders.py, whose helpers this
file uses).

References: the PDO mapping and objects of io_adapters.cia402_objects, the abort codes
of CiA 301.  One frame, then SYNC, then one cycle.  An RPDO frame to the node is counted
exactly once: malformed (its DLC is not the mapping's 3, 8, 4 or 4 bytes), refused
(refused_mode or refused_range, refused_axes = 1), or taken into the image (the cycle is
heard); a frame on any other COB-ID changes nothing.  An SDO download to a process-data
input is taken (response 60h, the cycle heard), refused (abort 0609 0030h, 0031h or
0032h, counted; the abort answers it, the drive does not fault: refused_axes = 0) or
aborted for its form (nothing counted); to any other object it is never a refusal.  The
record after each cycle holds exactly what the frames taken wrote (an image kept here
from the frames and the drive's answers) and is within the bounds.
"""

import math
import struct
import time
import uuid
from dataclasses import dataclass, field, replace

import can
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from hil.bench.fuzz_frames import INPUTS, SPECIAL_INTS, dictionary_entries, packed
from hil.bench.fuzz_links import SDO_REFUSED
from hil.drive import EmulatedDrive
from hil.drive.objects import DriveObjects
from io_adapters import open_endpoint
from io_adapters.can_dictionary import offered_modes
from io_adapters.cia402_objects import rpdo_layouts
from io_adapters.messages import MODE_CST, SetpointBounds, message_pair
from plant import Plant
from plant.config import load_machine
from tests.test_adapter_decoders import BOUNDS, Machine
from tests.test_fuzz_decoders import ARROW, SETTINGS, WAIT_S, assert_record_within

NODE = 9
RATED_MA = 28000
LAYOUTS = {p.cob_id: p for p in rpdo_layouts(NODE)}
#: every COB-ID but those with a protocol of their own here (NMT, SYNC, this node's SDO
#: requests)
OTHER_IDS = [i for i in range(0x800) if i not in (0x000, 0x080, 0x600 + NODE)]


@pytest.fixture(scope="module")
def arrow_objects() -> DriveObjects:
    """The parameter objects of the Arrow 500 X's drive, made once: a reset (at each rig)
    puts back the machine file's values."""
    drive = EmulatedDrive(Plant(load_machine(ARROW), table_pos=0.25))
    return DriveObjects([drive], RATED_MA / 1e3)


@st.composite
def can_bounds(draw, drive_bounds: SetpointBounds) -> SetpointBounds:
    """The drive's bounds, or bounds drawn with CST among the modes (a node with no mode of
    operation, 6060h = 0, gives a CST record with no current) and the current bound on the
    wire's per-mille grid, as the drive's 28 A is (a bound between two steps:
    test_can_device_never_puts_a_current_beyond_its_bound_in_the_record)."""
    if draw(st.booleans()):
        return drive_bounds
    b = draw(BOUNDS)
    current = b.current_a if math.isinf(b.current_a) else (
        math.floor(b.current_a * 1e6 / RATED_MA) * RATED_MA / 1e6)
    return SetpointBounds(b.position_counts, b.velocity_counts_s, current, b.voltage_v,
                          b.modes | {MODE_CST})


@st.composite
def rpdo_frames(draw) -> can.Message:
    """An RPDO of this node with its own layout and any values, or any COB-ID, DLC and
    bytes."""
    if draw(st.booleans()):
        layout = draw(st.sampled_from(sorted(LAYOUTS.values(), key=lambda p: p.cob_id)))
        codes = layout.frame.format[1:]
        data = b"".join(packed("<" + c, draw(st.sampled_from(SPECIAL_INTS) | st.integers()))
                        for c in codes)
        cob_id = layout.cob_id
        if draw(st.integers(0, 3)) == 0:  # one byte too many or too few
            data = data + b"\0" if draw(st.booleans()) else data[:-1]
    else:
        cob_id = draw(st.sampled_from(sorted(LAYOUTS)) | st.sampled_from(OTHER_IDS))
        data = draw(st.binary(max_size=8))
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)


ENTRIES = dictionary_entries(NODE, RATED_MA)
WRITABLE = [e for e in ENTRIES if e[3]]


@st.composite
def sdo_downloads(draw) -> tuple[int, int, bytes]:
    """(index, sub-index, request) of an expedited download of 1 to 4 bytes, the size
    given or not: to a writable object with its own size, to any object of the
    dictionary, or to any index and sub-index."""
    where = draw(st.sampled_from(["writable", "writable", "dictionary", "any"]))
    if where == "any":
        index, sub = draw(st.integers(0, 0xFFFF)), draw(st.integers(0, 255))
        size = draw(st.sampled_from([1, 2, 3, 4, None]))
    else:
        index, sub, own, _ = draw(st.sampled_from(WRITABLE if where == "writable" else ENTRIES))
        size = own if draw(st.integers(0, 3)) else draw(st.sampled_from([1, 2, 3, 4, None]))
    value = draw(st.sampled_from(SPECIAL_INTS) | st.integers(-2**31, 2**32 - 1))
    data = packed("<i", value) if size is None else packed("<q", value)[:size]
    command = 0x22 if size is None else 0x23 | (4 - size) << 2
    request = bytes([command]) + struct.pack("<HB", index, sub) + data[:4].ljust(4, b"\0")
    return index, sub, request


class CanRig:
    """A device endpoint (node NODE, OPERATIONAL, no free-running cycle) with the drive's
    parameter objects (reset to the machine file's values) and bounds, and a raw bus to
    it."""

    def __init__(self, objects: DriveObjects, bounds: SetpointBounds):
        channel = f"fuzz-{uuid.uuid4().hex[:12]}"
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.ep = open_endpoint(f"can://virtual/{channel}?node={NODE}&rated_current_ma="
                                f"{RATED_MA}&sync_timeout_ms=60000", "device")
        objects.reset_application(0)
        self.ep.objects = objects
        self.ep.setpoint_bounds = (bounds,)
        self.bus.send(can.Message(arbitration_id=0x000, data=bytes([0x01, NODE]),
                                  is_extended_id=False))
        end = time.monotonic() + WAIT_S
        while self.ep.nmt_state != "OPERATIONAL":
            assert time.monotonic() < end, "the node did not start"
            time.sleep(0.001)

    def close(self) -> None:
        self.ep.close()
        self.bus.shutdown()

    def sdo(self, request: bytes) -> bytes:
        self.bus.send(can.Message(arbitration_id=0x600 + NODE, data=request,
                                  is_extended_id=False))
        end = time.monotonic() + WAIT_S
        while (left := end - time.monotonic()) > 0:
            msg = self.bus.recv(left)
            if msg is not None and msg.arbitration_id == 0x580 + NODE:
                return bytes(msg.data)
        raise AssertionError(f"no SDO response to {request.hex()} in {WAIT_S} s")

    def cycle(self, into) -> bool:
        """SYNC, then the cycle it starts; whether it was heard."""
        taken = self.ep.taken
        self.bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        heard = self.ep.recv_setpoint(into, WAIT_S)
        assert self.ep.taken == taken + 1, "SYNC started no cycle"
        return heard


@dataclass
class Image:
    """The process-data inputs as the frames taken wrote them (0 at boot)."""
    values: dict = field(default_factory=lambda: dict.fromkeys(INPUTS, 0))

    def check(self, sp) -> None:
        """The record of a cycle is this image as the can_cia402 docstring converts it."""
        v = self.values
        mode = v[(0x6060, 0)]
        torque = (v[(0x6071, 0)] if mode == MODE_CST else 0) + v[(0x60B2, 0)]
        assert (sp.controlword, sp.mode) == (v[(0x6040, 0)], mode or MODE_CST)
        assert (sp.target_position_counts, sp.velocity_offset_counts_s,
                sp.target_velocity_counts_s) == (v[(0x607A, 0)], v[(0x60B1, 0)],
                                                 v[(0x60FF, 0)])
        assert sp.iq_ref_a == (torque * RATED_MA / 1e6 if mode else 0.0)


def refusals(stats) -> int:
    return stats.refused_mode + stats.refused_range + stats.refused_nonfinite


@settings(SETTINGS, max_examples=120)
@given(data=st.data())
def test_can_device_counts_every_rpdo_and_sdo_write_once(data, arrow_objects):
    bounds = data.draw(can_bounds(arrow_objects.drives[0].setpoint_bounds()))
    machine, image = Machine(1, (replace(bounds, modes=offered_modes(bounds)),)), Image()
    rig = CanRig(arrow_objects, bounds)
    sp = message_pair(1)[0]
    try:
        for _ in range(data.draw(st.integers(1, 20))):
            stats = rig.ep.stats
            malformed, refused = stats.malformed, refusals(stats)
            if data.draw(st.booleans()):
                msg = data.draw(rpdo_frames())
                rig.bus.send(msg)
                heard = rig.cycle(sp)
                layout = LAYOUTS.get(msg.arbitration_id)
                new_malformed, new_refused = stats.malformed - malformed, refusals(stats) - refused
                rpdo_refused = bool(new_refused)
                if layout is None:
                    assert (heard, new_malformed, new_refused) == (False, 0, 0)
                else:
                    assert heard + new_malformed + new_refused == 1, (heard, stats)
                    assert new_malformed == (len(msg.data) != layout.frame.size)
                    event(f"RPDO heard {heard} malformed {new_malformed} refused {new_refused}")
                    if heard:
                        image.values.update(zip(layout.objects,
                                                layout.frame.unpack(bytes(msg.data))))
            else:
                rpdo_refused = False
                index, sub, request = data.draw(sdo_downloads())
                answer = rig.sdo(request)
                heard = rig.cycle(sp)
                new_refused = refusals(stats) - refused
                assert stats.malformed == malformed
                code = int.from_bytes(answer[4:8], "little") if answer[0] == 0x80 else 0
                assert answer[0] in (0x60, 0x80) and answer[1:4] == request[1:4], answer.hex()
                key = (index, sub)
                event(f"SDO {key in INPUTS and 'input' or 'other'} answer {code:08X}")
                assert heard == (key in INPUTS and answer[0] == 0x60)
                assert new_refused == (key in INPUTS and code in SDO_REFUSED), hex(code)
                if heard:
                    fmt = INPUTS[key]
                    image.values[key] = struct.unpack(fmt, request[4:4 + struct.calcsize(fmt)])[0]
            assert rig.ep.refused_axes == (1 if rpdo_refused else 0)
            image.check(sp)
            assert_record_within(sp, machine)
    finally:
        rig.close()


@pytest.mark.parametrize("cob_offset, data, field_name", [
    (0x300, struct.pack("<ii", 1001, 0), "target_position_counts"),
    (0x300, struct.pack("<ii", 0, -1001), "velocity_offset_counts_s"),
    (0x400, struct.pack("<i", 1001), "target_velocity_counts_s")],
    ids=["607Ah", "60B1h", "60FFh"])
def test_can_device_refuses_targets_beyond_the_position_and_speed_bounds(
        arrow_objects, cob_offset, data, field_name):
    """Bounds of 1000 increments and 1000 increments/s: an RPDO2 or RPDO3 with 1001 is
    refused (refused_range, refused_axes = 1) and the record keeps 0 (hypothesis found
    60B1h = 2**24 taken with velocity_counts_s = 0)."""
    bounds = SetpointBounds(position_counts=1000.0, velocity_counts_s=1000.0,
                            current_a=28.0, modes=frozenset({MODE_CST}))
    rig = CanRig(arrow_objects, bounds)
    sp = message_pair(1)[0]
    try:
        rig.bus.send(can.Message(arbitration_id=cob_offset + NODE, data=data,
                                 is_extended_id=False))
        assert not rig.cycle(sp)
        assert (rig.ep.stats.refused_range, rig.ep.refused_axes) == (1, 1)
        assert getattr(sp, field_name) == 0.0
    finally:
        rig.close()


def test_can_device_never_puts_a_current_beyond_its_bound_in_the_record(arrow_objects):
    """A 1 A bound with 28 mA per mille: 36 per mille (1.008 A) is within half a step of
    the bound; it may be refused or taken at the bound, but 1.008 A must not reach the
    record (the drive's own check would refuse it and fault, FF10h)."""
    bounds = SetpointBounds(current_a=1.0, modes=frozenset({MODE_CST}))
    rig = CanRig(arrow_objects, bounds)
    sp = message_pair(1)[0]
    try:
        for cob_offset, data in ((0x200, struct.pack("<Hb", 6, MODE_CST)),
                                 (0x500, struct.pack("<hh", 36, 0))):
            rig.bus.send(can.Message(arbitration_id=cob_offset + NODE, data=data,
                                     is_extended_id=False))
        rig.cycle(sp)
        assert abs(sp.iq_ref_a) <= bounds.current_a, sp
    finally:
        rig.close()
