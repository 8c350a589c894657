"""PDO mapping by SDO (CiA 301), the transmission types, and the factor group (608Fh,
6091h, 6092h) of the CANopen drive.

References: CiA 301's remapping order and abort codes (io_adapters.can_pdo's table, row by
row); canopen's own ``PdoMap.save`` (a master nobody here wrote) remapping the drive over
a ``virtual`` bus, and the frames that come back read off the raw bus; the transmission
types' definitions (synchronous every n-th SYNC, acyclic on change, event-driven with
inhibit time and event timer), exercised with explicit times; the factor group's
formula on the Arrow 500 X (4194304 increments per revolution, 10 mm lead: a feed
constant of 10000 per revolution makes the unit the µm of table travel).
"""

import math

import can
import pytest
from canopen.sdo import SdoAbortedError

from hil.drive import EmulatedDrive
from hil.drive.objects import DriveObjects
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.can_catalog import SDO_ABORT_DEVICE_STATE
from io_adapters.can_pdo import NOT_VALID, PdoSet
from io_adapters.cia402_objects import ObjectAccessError, mapping_entry
from plant import Plant
from plant.config import load_machine
from tests.conftest import CONFIGS
from tests.test_can_cia402 import (  # noqa: F401  (no_leaked_threads: autouse)
    frame,
    master_network,
    no_leaked_threads,
    recv_id,
    virtual_channel,
    wait_for,
)

ARROW = CONFIGS / "arrow500_x.toml"
NODE = 5
QUERY = f"node={NODE}&rated_current_ma=28000&sync_timeout_ms=60000"
E = mapping_entry
STATUSWORD, POSITION, DEMAND, FE = (0x6041, 0), (0x6064, 0), (0x6062, 0), (0x60F4, 0)


def refused(code: int, pdos: PdoSet, index: int, sub: int, value: int,
            pre_operational: bool = True) -> None:
    with pytest.raises(ObjectAccessError) as e:
        pdos.write(index, sub, value, pre_operational)
    assert e.value.abort_code == code, f"{index:04X}h:{sub:02X} = {value:#x}"


def test_every_refusal_of_the_table():
    pdos = PdoSet(NODE)
    refused(0x0800_0022, pdos, 0x1800, 2, 1, pre_operational=False)  # not PRE-OPERATIONAL
    refused(0x0800_0022, pdos, 0x1A00, 1, E(POSITION))   # an entry of a valid PDO
    refused(0x0800_0022, pdos, 0x1A00, 0, 2)             # its count while valid
    pdos.write(0x1800, 1, NOT_VALID | 0x185, True)
    refused(0x0800_0022, pdos, 0x1A00, 1, E(POSITION))   # count not 0 yet
    pdos.write(0x1A00, 0, 0, True)
    refused(0x0602_0000, pdos, 0x1A00, 1, 0x2000_0010)   # no such object
    refused(0x0604_0041, pdos, 0x1A00, 1, E((0x6065, 0)))  # not PDO-mappable
    pdos.write(0x1400, 1, NOT_VALID | 0x205, True)
    pdos.write(0x1600, 0, 0, True)
    refused(0x0604_0041, pdos, 0x1600, 1, E(STATUSWORD))   # read-only into an RPDO
    refused(0x0604_0041, pdos, 0x1A00, 1, 0x6041_0008)     # 8 of its 16 bits
    refused(0x0609_0031, pdos, 0x1A00, 0, 9)               # more than 8 entries
    for k in (1, 2, 3):
        pdos.write(0x1A00, k, E(POSITION), True)
    refused(0x0604_0042, pdos, 0x1A00, 0, 3)               # 96 bits
    refused(0x0609_0030, pdos, 0x1800, 1, 1 << 29 | 0x185)  # an extended frame
    refused(0x0609_0030, pdos, 0x1800, 1, 0x705)           # a heartbeat's (Table 7)
    refused(0x0609_0030, pdos, 0x1801, 1, 0x190)           # another CAN-ID while valid
    refused(0x0609_0030, pdos, 0x1800, 2, 250)             # RTR-only types not offered
    refused(0x0609_0030, pdos, 0x1801, 3, 10)              # inhibit time while valid
    assert pdos.tpdos[0].layout is None and pdos.tpdos[1].layout is not None


def test_a_remapping_in_cia301s_order_makes_the_new_frame():
    pdos = PdoSet(NODE)
    writes = [(0x1803, 1, NOT_VALID | 0x485), (0x1A03, 0, 0), (0x1A03, 1, E(POSITION)),
              (0x1A03, 2, E(FE)), (0x1A03, 0, 2), (0x1803, 2, 2), (0x1803, 1, 0x485)]
    for index, sub, value in writes:
        pdos.write(index, sub, value, True)
        assert pdos.read(index, sub) == value
    tpdo4 = pdos.tpdos[3]
    assert tpdo4.layout.objects == (POSITION, FE) and tpdo4.layout.frame.size == 8
    assert tpdo4.trans_type == 2
    pdos.reset()
    assert pdos.tpdos[3].layout is None  # NMT reset communication: the default mapping


@pytest.fixture
def node_rig():
    """A device endpoint with an Arrow 500 X drive's objects, its first node, a raw bus."""
    channel = virtual_channel()
    drive = EmulatedDrive(Plant(load_machine(ARROW), table_pos=0.25))
    with can.Bus(interface="virtual", channel=channel) as bus, \
            open_endpoint(f"can://virtual/{channel}?{QUERY}", "device") as ep:
        ep.setpoint_bounds = (drive.setpoint_bounds(),)
        ep.objects = DriveObjects([drive], ep.rated_current_a)
        recv_id(bus, 0x700 + NODE)  # boot-up
        yield ep, ep._nodes[0], bus, drive, channel


def configure(ep, node, writes) -> None:
    for index, sub, value in writes:
        node.dict.write(index, sub, value, pre_operational=True)
    ep.pdos_changed()


def test_transmission_types_at_explicit_times(node_rig):
    """TPDO1 synchronous every 3rd SYNC; TPDO2 acyclic synchronous (type 0: at a SYNC,
    when its data changed); TPDO3 event-driven (255) with a 10 ms inhibit time and a
    50 ms event timer."""
    ep, node, _, _, _ = node_rig
    configure(ep, node, [(0x1800, 2, 3), (0x1801, 2, 0), (0x1802, 1, NOT_VALID | 0x385),
                         (0x1802, 2, 255), (0x1802, 3, 100), (0x1802, 5, 50),
                         (0x1802, 1, 0x385)])
    fb = Feedback(statusword=0x0237)
    with node.lock:
        node.stage(fb)
        ids = [[m.arbitration_id for m in node.sync_frames(True, None, 0.0)]
               for _ in range(6)]
    assert [0x185 in i for i in ids] == [False, False, True, False, False, True]
    assert [0x285 in i for i in ids] == [True, False, False, False, False, False]
    sent = []
    for t_ms in range(200):
        # 6078h changes every ms for 30 ms (28 mA = one per mille), then stands
        fb.iq_a = 0.028 * (t_ms + 1) if t_ms < 30 else 2.8
        with node.lock:
            node.stage(fb)
            if node.event_frames(t_ms * 1e-3):
                sent.append(t_ms)
    # changing every ms: no sooner than 10 ms apart; then unchanged: the 50 ms timer
    assert sent == [0, 10, 20, 30, 80, 130, 180]


def test_canopens_master_remaps_the_drive_and_gets_the_new_frames(node_rig):
    """canopen's PdoMap.save in PRE-OPERATIONAL: TPDO4 = 6064h + 60F4h every 2nd SYNC,
    TPDO2 and TPDO3 switched off; then NMT start and SYNCs: TPDO4 on the raw bus at every
    other SYNC with the drive's values; a remapping while OPERATIONAL is refused."""
    ep, node, bus, _, channel = node_rig
    network = master_network()
    try:
        network.connect(interface="virtual", channel=channel)
        master = network.add_node(NODE, node.local.object_dictionary)
        master.sdo.RESPONSE_TIMEOUT = 2.0
        master.tpdo.read()
        tpdo4 = master.tpdo[4]
        tpdo4.clear()
        tpdo4.add_variable(0x6064)
        tpdo4.add_variable(0x60F4)
        tpdo4.trans_type, tpdo4.enabled = 2, True
        for n in (2, 3):
            master.tpdo[n].enabled = False
        master.tpdo.save()
        assert node.dict.pdos.tpdos[3].layout.objects == (POSITION, FE)
        assert [p.valid for p in node.dict.pdos.tpdos] == [True, False, False, True]
        master.nmt.state = "OPERATIONAL"
        wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
        for _ in range(4):
            ep.send_feedback(Feedback(statusword=0x0250, encoder_counts=123456.0))
            bus.send(frame(0x080, ""))
            recv_id(bus, 0x185)  # TPDO1 answers every SYNC ...
        tpdo4_frame = recv_id(bus, 0x485)  # ... TPDO4 every other one
        position = int.from_bytes(tpdo4_frame.data[:4], "little", signed=True)
        assert position == 123456 and len(tpdo4_frame.data) == 8
        assert node.tpdo.tx[4].syncs == 4
        with pytest.raises(SdoAbortedError) as e:
            master.sdo[0x1A03][0].raw = 0
        assert e.value.code == SDO_ABORT_DEVICE_STATE
    finally:
        network.disconnect()


def test_the_factor_group_makes_the_unit_a_micrometre(node_rig):
    """6092h = 10000 per revolution (10 mm lead): position, speed and acceleration
    objects in µm, µm/s and µm/s²; the table at 250 mm reads 250000; writes scale back;
    6091h and 6092h change in PRE-OPERATIONAL only."""
    ep, node, _, drive, _ = node_rig
    configure(ep, node, [(0x6092, 1, 10000), (0x6092, 2, 1)])
    assert node.dict.factor == pytest.approx(4194304 / 10000)
    ep.send_feedback(Feedback(encoder_counts=0.25 / 0.01 * 4194304))  # the table at 250 mm
    assert node.value(POSITION) == 250000
    rad_per_um = 2 * math.pi / 10000
    node.dict.write(0x6081, 0, 50000, pre_operational=True)  # 50 mm/s
    assert drive.params.profile_velocity == pytest.approx(50000 * rad_per_um)
    assert node.dict.read(0x6081, 0) == 50000
    node.dict.write(0x6085, 0, 2_000_000, pre_operational=True)  # 2 m/s²
    assert drive.params.quick_stop_decel == pytest.approx(2e6 * rad_per_um)
    gear = (0x6091, 1, 2)
    node.local.nmt.state = "OPERATIONAL"
    with pytest.raises(ObjectAccessError) as e:
        node.dict.write(*gear, pre_operational=False)
    assert e.value.abort_code == SDO_ABORT_DEVICE_STATE
    # an RPDO target in µm reaches the drive in increments
    node.image[(0x607A, 0)] = 1000
    node.latched = tuple(node.image[k] for k in node.image)
    sp = Setpoint()
    with node.lock:
        node.fill(sp, 1)
    assert sp.target_position_counts == pytest.approx(1000 * 4194304 / 10000)
