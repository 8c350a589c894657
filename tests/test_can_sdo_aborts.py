"""What the CANopen drive answers to SDO requests and RPDOs it cannot take, on python-can's
``virtual`` bus with the Arrow 500 X drive's objects behind the node: canopen's own SDO
client (a master nobody here wrote) and raw frames.

References: CiA 301's SDO protocol and abort codes (0602 0000h object does not exist,
0609 0011h sub-index does not exist, 0504 0001h command specifier not valid, 0607 0012h
length too high; SDO frames of 8 bytes) and its EMCY 8210h "PDO not processed due to
length error" (error register 1001h: bit 0 generic, bit 4 communication); the objects and
sub-indices are io_adapters.can_catalog's, which the EDS declares (tests/test_can_eds.py).
Nothing the node is sent may raise in its receive thread or log: every test here checks
that no record of WARNING or above was logged and nothing reached stderr.
"""

import logging
import struct
import uuid
from dataclasses import asdict

import can
import pytest
from canopen.sdo import SdoAbortedError
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from hil.drive import EmulatedDrive
from hil.drive.objects import DriveObjects
from io_adapters import Setpoint, open_endpoint
from io_adapters.can_catalog import (
    COMPOUNDS,
    SDO_ABORT_COMMAND,
    SDO_ABORT_LENGTH_HIGH,
    SDO_ABORT_NO_OBJECT,
    SDO_ABORT_NO_SUBINDEX,
    VARIABLES,
    VENDOR_ID,
    entries,
)
from plant import Plant
from plant.config import load_machine
from tests.conftest import CONFIGS
from tests.test_can_cia402 import (  # noqa: F401  (no_leaked_threads: autouse)
    frame,
    master_network,
    no_leaked_threads,
    recv_id,
    wait_for,
)

NODE = 5
QUERY = f"node={NODE}&rated_current_ma=28000&sync_timeout_ms=60000"
ARROW = CONFIGS / "arrow500_x.toml"
REQUEST, RESPONSE, EMCY = 0x600 + NODE, 0x580 + NODE, 0x080 + NODE
#: canopen's SDO server answers an exception it did not expect with this, and logs it
GENERAL_ERROR = 0x0800_0000
#: the EMCY of an RPDO of the wrong length and its error register: generic, communication
PDO_LENGTH, COMMUNICATION = 0x8210, 0x11
#: a read that every state of the node answers: 1018h:01, the vendor-ID
PROBE = bytes([0x40]) + struct.pack("<HB", 0x1018, 1) + bytes(4)


@pytest.fixture(scope="module")
def arrow_drive() -> EmulatedDrive:
    """The Arrow 500 X's drive, made once (each rig's node starts from a reset)."""
    return EmulatedDrive(Plant(load_machine(ARROW), table_pos=0.25))


class Rig:
    """A device endpoint (node 5, PRE-OPERATIONAL, no cycle on its own clock) with the
    drive's objects (back to the machine file's values) and a raw bus to it."""

    def __init__(self, drive: EmulatedDrive):
        self.channel = f"hil-{uuid.uuid4().hex[:12]}"
        self.bus = can.Bus(interface="virtual", channel=self.channel)
        self.ep = open_endpoint(f"can://virtual/{self.channel}?{QUERY}", "device")
        objects = DriveObjects([drive], self.ep.rated_current_a)
        objects.reset_application(0)
        self.ep.objects = objects
        self.ep.setpoint_bounds = (drive.setpoint_bounds(),)
        self.node = self.ep._nodes[0]
        self.drive = drive
        recv_id(self.bus, 0x700 + NODE)  # boot-up

    def close(self) -> None:
        self.ep.close()
        self.bus.shutdown()

    def state(self) -> tuple:
        """What an SDO request could change: the drive's parameters, the node's process
        image and communication objects, canopen's stored values."""
        node = self.node
        return (asdict(self.drive.params), dict(node.image), node.dict.consumer_entry,
                node.dict.producer_ms, repr(node.dict.pdos.rpdos + node.dict.pdos.tpdos),
                repr(node.local.data_store))

    def responses_to(self, requests: list[bytes]) -> list[bytes]:
        """Send ``requests`` and then :data:`PROBE`; the responses before the probe's (the
        server answers in order)."""
        for data in requests + [PROBE]:
            self.bus.send(can.Message(arbitration_id=REQUEST, data=data,
                                      is_extended_id=False))
        answers = []
        while (answer := bytes(recv_id(self.bus, RESPONSE).data)) != probe_answer():
            answers.append(answer)
        return answers


def probe_answer() -> bytes:
    return bytes([0x43]) + PROBE[1:4] + VENDOR_ID.to_bytes(4, "little")


@pytest.fixture
def rig(arrow_drive):
    rig = Rig(arrow_drive)
    yield rig
    rig.close()


@pytest.fixture
def quiet(caplog, capfd):
    """Checks after the test that nothing was logged at WARNING or above (canopen logs an
    exception its SDO server catches, with its traceback, at ERROR) and nothing printed."""
    yield
    assert_quiet(caplog.get_records("call"), capfd)


def assert_quiet(records: list[logging.LogRecord], capfd) -> None:
    loud = [f"{r.name}: {r.getMessage()}" for r in records if r.levelno >= logging.WARNING]
    assert loud == [], loud
    assert capfd.readouterr().err == ""


def abort_frame(index: int, sub: int, code: int) -> bytes:
    return bytes([0x80]) + struct.pack("<HBI", index, sub, code)


# -- sub-indices and objects the dictionary does not have ------------------------------

def missing_subindices() -> list[tuple[int, int]]:
    """Every object's sub-index after its last and 255, and the holes of a record (TPDO
    communication parameters have no sub-index 4)."""
    out = [(index, s) for index in VARIABLES for s in (1, 255)]
    for index, comp in COMPOUNDS.items():
        last = max(comp.members)
        holes = [s for s in range(1, last) if s not in comp.members]
        out += [(index, s) for s in (*holes, last + 1, 255)]
    return out


def missing_objects() -> list[int]:
    """The indices next to each object of the dictionary that are none, and the ends."""
    have = {i for i, _ in entries()}
    near = {i + d for i in have for d in (-1, 1)} | {0x0000, 0xFFFF}
    return sorted(near - have)


@pytest.fixture
def master(rig):
    """canopen's SDO client for node 5 on the rig's bus."""
    network = master_network()
    network.connect(interface="virtual", channel=rig.channel)
    node = network.add_node(NODE, rig.node.local.object_dictionary)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    yield node
    network.disconnect()


def aborted(action) -> int:
    with pytest.raises(SdoAbortedError) as e:
        action()
    return e.value.code


def test_607dh_has_sub_indices_0_to_2_only(rig, master, quiet):
    """The attack of the issue: a write of 607Dh:09 and reads of 607Dh:03 and :09 (607Dh,
    an array, has the minimum and maximum position limit only)."""
    before = rig.state()
    assert aborted(lambda: master.sdo.download(0x607D, 9, bytes(4))) == SDO_ABORT_NO_SUBINDEX
    for sub in (3, 9):
        assert aborted(lambda sub=sub: master.sdo.upload(0x607D, sub)) == SDO_ABORT_NO_SUBINDEX
    assert rig.state() == before
    assert master.sdo.upload(0x607D, 0) == bytes([2])


def test_every_sub_index_the_dictionary_lacks_is_aborted(rig, master, quiet):
    """A read and a write of each missing sub-index: 0609 0011h, whatever the object's
    type and access (a read-only one's too: the sub-index does not exist before it is
    read-only), and nothing changed."""
    before = rig.state()
    keys = missing_subindices()
    for key in keys:
        assert aborted(lambda: master.sdo.upload(*key)) == SDO_ABORT_NO_SUBINDEX, key
        assert aborted(lambda: master.sdo.download(*key, bytes(4))) == SDO_ABORT_NO_SUBINDEX, key
    assert rig.state() == before
    assert len(keys) > 100


def test_every_object_the_dictionary_lacks_is_aborted(rig, master, quiet):
    """A read and a write of each index next to one the dictionary has: 0602 0000h."""
    before = rig.state()
    indices = missing_objects()
    for index in indices:
        for sub in (0, 1):
            assert aborted(lambda: master.sdo.upload(index, sub)) == SDO_ABORT_NO_OBJECT
            assert aborted(lambda: master.sdo.download(index, sub, bytes(4))) \
                == SDO_ABORT_NO_OBJECT
    assert rig.state() == before
    assert len(indices) > 50


# -- frames no request of CiA 301 makes ---------------------------------------------------

def request(command: int, index: int = 0x6040, sub: int = 0, data: bytes = bytes(4)) -> bytes:
    return bytes([command]) + struct.pack("<HB", index, sub) + data


SEGMENT_DL_6040 = request(0x21, data=(2).to_bytes(4, "little"))  # segmented, 2 bytes
CASES = [  # what, requests, their responses
    ("a download segment before any transfer: 0504 0001h, the multiplexer 0000h:00",
     [bytes(8)], [abort_frame(0, 0, SDO_ABORT_COMMAND)]),
    ("an upload segment after an expedited upload: no transfer in progress",
     [request(0x40), bytes([0x60]) + bytes(7)],
     [bytes.fromhex("4B40600000000000"), abort_frame(0x6040, 0, SDO_ABORT_COMMAND)]),
    ("an upload segment during a segmented download: not its direction",
     [SEGMENT_DL_6040, bytes([0x60]) + bytes(7)],
     [bytes.fromhex("6040600000000000"), abort_frame(0x6040, 0, SDO_ABORT_COMMAND)]),
    ("a segmented download of 6040h in one segment of two bytes: taken",
     [SEGMENT_DL_6040, bytes([0x0B, 0x06, 0x00]) + bytes(5)],
     [bytes.fromhex("6040600000000000"), bytes.fromhex("2000000000000000")]),
    ("a segmented download longer than 6040h's two bytes: 0607 0012h",
     [SEGMENT_DL_6040, bytes([0x00]) + bytes(7)],
     [bytes.fromhex("6040600000000000"), abort_frame(0x6040, 0, SDO_ABORT_LENGTH_HIGH)]),
    ("a segment after that abort: the transfer ended",
     [SEGMENT_DL_6040, bytes(8), bytes([0x10]) + bytes(7)],
     [bytes.fromhex("6040600000000000"), abort_frame(0x6040, 0, SDO_ABORT_LENGTH_HIGH),
      abort_frame(0x6040, 0, SDO_ABORT_COMMAND)]),
    ("the master's abort ends a transfer without an answer",
     [SEGMENT_DL_6040, abort_frame(0x6040, 0, 0x0504_0000), bytes([0x0B, 6]) + bytes(6)],
     [bytes.fromhex("6040600000000000"), abort_frame(0x6040, 0, SDO_ABORT_COMMAND)]),
    ("a block download (not offered)", [request(0xC6, 0x607A)],
     [abort_frame(0x607A, 0, SDO_ABORT_COMMAND)]),
    ("a block upload (not offered)", [request(0xA4, 0x607A, data=bytes([0x7F, 0, 0, 0]))],
     [abort_frame(0x607A, 0, SDO_ABORT_COMMAND)]),
    ("the reserved command specifier 7", [request(0xE0, 0x1018, 1)],
     [abort_frame(0x1018, 1, SDO_ABORT_COMMAND)]),
    ("frames of 7 bytes, 1 byte and none: dropped, no answer",
     [request(0x40)[:7], b"\x40", b""], []),
]


@pytest.mark.parametrize("what, requests, responses", CASES, ids=[c[0] for c in CASES])
def test_requests_out_of_place_are_aborted_as_cia301_has_it(rig, quiet, what, requests,
                                                            responses):
    assert rig.responses_to(requests) == responses
    assert rig.ep.stats.malformed == sum(len(r) != 8 for r in requests)


def test_canopens_client_downloads_in_segments(rig, master, quiet):
    """canopen's client, segmented (force_segment): 6040h = 6 is taken; the drive's
    1006h = 2000 µs too."""
    master.sdo.download(0x6040, 0, (6).to_bytes(2, "little"), force_segment=True)
    master.sdo.download(0x1006, 0, (2000).to_bytes(4, "little"), force_segment=True)
    assert rig.node.image[(0x6040, 0)] == 6
    assert rig.drive.params.communication_cycle_s == pytest.approx(2e-3)


COMMANDS = [0x40, 0x2F, 0x2B, 0x27, 0x23, 0x22, 0x21, 0x20, 0x00, 0x01, 0x0B, 0x0F, 0x10,
            0x11, 0x1D, 0x60, 0x70, 0x80, 0xA0, 0xA4, 0xA3, 0xA2, 0xA1, 0xC0, 0xC6, 0xC1,
            0xE0, 0xFF]
KEYS = entries() + missing_subindices()


@st.composite
def sdo_frames(draw) -> bytes:
    """An SDO frame: a command of each kind (expedited and segmented transfers, segments,
    aborts, block transfers, reserved) or any byte; an object of the dictionary, a
    sub-index it lacks, or any index and sub-index; any data; mostly 8 bytes."""
    command = draw(st.sampled_from(COMMANDS) | st.integers(0, 0xFF))
    index, sub = draw(st.sampled_from(KEYS) | st.tuples(st.integers(0, 0xFFFF),
                                                        st.integers(0, 0xFF)))
    data = request(command, index, sub, draw(st.binary(min_size=4, max_size=4)))
    if draw(st.integers(0, 5)) == 0:
        data = data[:draw(st.integers(0, 7))]
    return data


def reads_probe(frame: bytes) -> bool:
    """Whether ``frame`` is itself an upload request of the probe's object (any 40h-5Fh
    command, any reserved bytes): its answer is the probe's, which would end
    :meth:`Rig.responses_to`'s collection early."""
    return len(frame) == 8 and frame[0] & 0xE0 == 0x40 and frame[1:4] == PROBE[1:4]


@settings(max_examples=60, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(frames=st.lists(sdo_frames().filter(lambda f: not reads_probe(f)),
                       min_size=1, max_size=12))
def test_the_sdo_server_survives_any_frames(arrow_drive, caplog, capfd, frames):
    """Any frames (but a read of the probe's object), then a read of 1018h:01: each frame
    of 8 bytes but the master's abort (80h-9Fh) has one answer, in order, and never
    canopen's general error (the trace of an exception it caught); the others are counted
    ``malformed``; the read is answered; nothing was logged or printed."""
    caplog.clear()
    capfd.readouterr()
    rig = Rig(arrow_drive)
    try:
        answers = rig.responses_to(frames)
        answered = [f for f in frames if len(f) == 8 and f[0] & 0xE0 != 0x80]
        assert len(answers) == len(answered), [a.hex() for a in answers]
        for f, a in zip(answered, answers):
            code = int.from_bytes(a[4:], "little") if a[0] == 0x80 else 0
            event(f"answer {code:08X}h" if code else "answer taken")
            assert code != GENERAL_ERROR, f"{f.hex()}: {a.hex()}"
        assert rig.ep.stats.malformed == len(frames) - sum(len(f) == 8 for f in frames)
    finally:
        rig.close()
    assert_quiet(caplog.records, capfd)


# -- RPDOs of the wrong length -------------------------------------------------------------

def emcy(bus: can.BusABC) -> bytes:
    return bytes(recv_id(bus, EMCY).data)


def test_an_rpdo_of_the_wrong_length_sends_emcy_8210h(rig, quiet):
    """OPERATIONAL, default mapping (RPDO1 3 bytes, RPDO2 8): RPDO1 of 2 bytes is counted
    malformed, not processed (the cycle is not heard, the drive is not faulted) and
    reported by EMCY 8210h (1001h 11h; bytes 3-5: RPDO 1, 2 bytes, 3 mapped), and 1001h
    reads 11h.  Then RPDO1 of 4 bytes sends none (its error stands), RPDO2 of 7 bytes its
    own (RPDO 2, 7 bytes, 8 mapped), RPDO1 of 3 bytes is taken and sends none (RPDO2's
    error stands); RPDO2 of 8 bytes ends the last error: the error reset EMCY (0000h,
    1001h 00h), and the cycle is heard."""
    ep, bus = rig.ep, rig.bus
    bus.send(frame(0x000, f"01{NODE:02X}"))
    wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
    sp = Setpoint()
    bus.send(frame(0x200 + NODE, "0600"))
    assert emcy(bus) == bytes.fromhex("1082110102030000")
    bus.send(frame(0x080, ""))
    assert not ep.recv_setpoint(sp, 5.0)
    assert (ep.stats.malformed, ep.refused_axes) == (1, 0)
    assert rig.responses_to([request(0x40, 0x1001)]) == [bytes.fromhex("4F01100011000000")]
    for cob_id, data in ((0x200, "06000A00"), (0x300, "00" * 7), (0x200, "06000A")):
        bus.send(frame(cob_id + NODE, data))
    assert emcy(bus) == bytes.fromhex("1082110207080000")
    bus.send(frame(0x300 + NODE, "00" * 8))
    assert emcy(bus) == bytes(8)
    bus.send(frame(0x080, ""))
    assert ep.recv_setpoint(sp, 5.0) and sp.controlword == 6
    assert (ep.stats.malformed, ep.refused_axes) == (3, 0)
    assert rig.responses_to([request(0x40, 0x1001)]) == [bytes.fromhex("4F01100000000000")]
