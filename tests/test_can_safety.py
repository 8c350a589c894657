"""The CANopen drive's own protection, frame by frame on python-can's ``virtual`` bus: SDO
writes checked with the abort codes of CiA 301, the drive's parameter objects, network
management (NMT stop and reset, the heartbeat consumer), EMCY, and which cycles count as
hearing the master; and ``udp_multicast`` kept on this machine.

The reference for every frame is CiA 301 (SDO expedited transfer and abort codes, NMT
commands, EMCY layout) and CiA 402 (the objects' meaning); the drive parameters are checked
against the machine file's values converted by hand.  The same paths through ``hil run``
in another process are in tests/test_drive_safety_processes.py.
"""

import shutil
import struct
import subprocess
import sys
import time
import uuid
from dataclasses import asdict

import can
import pytest

from hil.drive import EmulatedDrive
from hil.drive.objects import DriveObjects
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.base import LINK_HEARTBEAT_LOST, LINK_RESET, LINK_STOPPED
from io_adapters.can_loopback import LoopbackMulticastBus
from io_adapters.messages import MODE_CST
from plant import Plant
from plant.config import load_machine
from tests.conftest import CONFIGS
from tests.test_can_cia402 import frame, recv_id, wait_for

NODE = 5
QUERY = f"node={NODE}&rated_current_ma=28000&sync_timeout_ms=60000"
WAIT_S = 5.0
ARROW = CONFIGS / "arrow500_x.toml"


def sdo(bus: can.BusABC, request: str) -> str:
    bus.send(frame(0x600 + NODE, request))
    return recv_id(bus, 0x580 + NODE).data.hex().upper()


def download(index: int, sub: int, value: int, size: int, signed: bool = False) -> str:
    """An expedited SDO download request (CiA 301: 23h/2Bh/2Fh for 4/2/1 bytes)."""
    command = {4: 0x23, 2: 0x2B, 1: 0x2F}[size]
    data = value.to_bytes(size, "little", signed=signed).ljust(4, b"\0")
    return (bytes([command]) + struct.pack("<HB", index, sub) + data).hex()


def abort(index: int, sub: int, code: int) -> str:
    return (bytes([0x80]) + struct.pack("<HBI", index, sub, code)).hex().upper()


def upload(index: int, sub: int) -> str:
    return (bytes([0x40]) + struct.pack("<HB", index, sub) + bytes(4)).hex()


@pytest.fixture
def rig():
    """A drive of the Arrow 500 X behind a device endpoint whose parameter objects are the
    drive's, and a raw bus to talk to it."""
    channel = f"hil-{uuid.uuid4().hex[:12]}"
    drive = EmulatedDrive(Plant(load_machine(ARROW), table_pos=0.25))
    with can.Bus(interface="virtual", channel=channel) as bus, \
            open_endpoint(f"can://virtual/{channel}?{QUERY}", "device") as ep:
        ep.objects = DriveObjects([drive], ep.rated_current_a)
        ep.setpoint_bounds = (drive.setpoint_bounds(),)
        recv_id(bus, 0x700 + NODE)  # boot-up
        yield ep, bus, drive


SDO_REFUSALS = [  # what, request, response (abort code, CiA 301)
    ("6060h: mode 42 is not offered", download(0x6060, 0, 42, 1), abort(0x6060, 0, 0x06090030)),
    ("6040h has no sub-index 5", download(0x6040, 5, 6, 2), abort(0x6040, 5, 0x06090011)),
    ("6041h has no sub-index 1 either", upload(0x6041, 1), abort(0x6041, 1, 0x06090011)),
    # the option codes' ranges are their EDS limits: beyond them is "too high" (0031)
    ("605Ah: 9 is no quick stop option", download(0x605A, 0, 9, 2), abort(0x605A, 0, 0x06090031)),
    ("605Eh: 5 is no fault reaction", download(0x605E, 0, 5, 2), abort(0x605E, 0, 0x06090031)),
    ("6007h: 4 is no abort option", download(0x6007, 0, 4, 2), abort(0x6007, 0, 0x06090031)),
    ("6098h: method 3 needs a positive home switch", download(0x6098, 0, 3, 1),
     abort(0x6098, 0, 0x06090030)),
    ("1006h: 1130 µs is no whole number of 125 µs drive cycles", download(0x1006, 0, 1130, 4),
     abort(0x1006, 0, 0x06090030)),
    ("1006h: 20 ms is beyond 10 ms", download(0x1006, 0, 20000, 4), abort(0x1006, 0, 0x06090031)),
    ("608Fh:01 is the encoder's, read-only", download(0x608F, 1, 2, 4),
     abort(0x608F, 1, 0x06010002)),
    ("6072h: 2000 per mille of 28 A is above the peak", download(0x6072, 0, 2000, 2),
     abort(0x6072, 0, 0x06090031)),
    ("6085h: a zero deceleration", download(0x6085, 0, 0, 4), abort(0x6085, 0, 0x06090032)),
    # a reaction ramp stops the axis from 1.1 x 6080h within 2 s (hil.drive.braking)
    ("6085h: 1 increment/s^2 would never stop the axis", download(0x6085, 0, 1, 4),
     abort(0x6085, 0, 0x06090032)),
    ("6084h: 0.1 m/s^2 is below a stop from 660 mm/s in 2 s",
     download(0x6084, 0, round(0.1 / 0.01 * 2**22), 4), abort(0x6084, 0, 0x06090032)),
    ("6080h: 4.8 m/s would take 6084h's 2 m/s^2 longer than 2 s",
     download(0x6080, 0, 2_000_000_000, 4), abort(0x6080, 0, 0x06090031)),
    ("607Dh:01 above the maximum", download(0x607D, 1, 2**31 - 2, 4, True),
     abort(0x607D, 1, 0x06090036)),
    ("60FDh is read-only", download(0x60FD, 0, 1, 4), abort(0x60FD, 0, 0x06010002)),
    ("6071h: 1100 per mille of 28 A is above the peak", download(0x6071, 0, 1100, 2, True),
     abort(0x6071, 0, 0x06090031)),
]


@pytest.mark.parametrize("what, asked, response", SDO_REFUSALS)
def test_sdo_writes_are_checked(rig, what, asked, response):
    """The abort, and nothing changed: the drive's parameters, its state machine's option,
    the node's process image, no refusal reported to the loop (an SDO abort is the whole
    answer; the drive does not fault)."""
    ep, bus, drive = rig
    node = ep._nodes[0]
    before = (asdict(drive.params), drive.sm.quick_stop_option, dict(node.image))
    assert sdo(bus, asked) == response, what
    assert (asdict(drive.params), drive.sm.quick_stop_option, dict(node.image)) == before
    assert not node.refused


def test_parameter_objects_are_the_drives(rig):
    """Writes land in the drive's parameters in its units (increments, ms, per mille);
    reads give them back; an NMT reset node restores the machine file's values."""
    ep, bus, drive = rig
    rpc, p = drive.rad_per_count, drive.params
    initial = (p.fe_window, p.quick_stop_option, p.limit_max)
    writes = [(0x6065, 0, 1000, 4), (0x6066, 0, 20, 2), (0x6072, 0, 500, 2),
              (0x6085, 0, 2_000_000_000, 4), (0x605A, 0, 6, 2), (0x607D, 2, 100_000_000, 4)]
    for index, sub, value, size in writes:
        assert sdo(bus, download(index, sub, value, size)) == f"60{index & 0xFF:02X}" \
            f"{index >> 8:02X}{sub:02X}00000000"
    assert p.fe_window == pytest.approx(1000 * rpc) and p.fe_time_s == pytest.approx(0.02)
    assert p.max_current_a == pytest.approx(14.0) and p.quick_stop_decel == pytest.approx(
        2e9 * rpc)
    assert drive.sm.quick_stop_option == 6 and p.limit_max == pytest.approx(1e8 * rpc)
    for index, sub, value, size in writes:
        reply = bytes.fromhex(sdo(bus, upload(index, sub)))
        assert int.from_bytes(reply[4:4 + size], "little") == value, hex(index)
    limit_counts = round(initial[2] / rpc)  # 607Dh:02 as the machine file gave it
    bus.send(frame(0x000, f"81{NODE:02X}"))  # NMT reset node
    assert recv_id(bus, 0x700 + NODE).data == bytearray([0])  # boot-up
    wait_for(lambda: (p.fe_window, p.quick_stop_option, p.limit_max) == initial,
             "the machine file's values back")
    reply = bytes.fromhex(sdo(bus, upload(0x607D, 2)))
    assert int.from_bytes(reply[4:], "little", signed=True) == limit_counts


def test_nmt_stop_and_reset_are_link_conditions(rig):
    ep, bus, _ = rig
    bus.send(frame(0x000, f"01{NODE:02X}"))  # start
    wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
    assert ep.link_conditions(0) == 0
    bus.send(frame(0x000, f"02{NODE:02X}"))  # stop
    wait_for(lambda: ep.link_conditions(0) == LINK_STOPPED, "STOPPED")
    bus.send(frame(0x000, f"01{NODE:02X}"))
    wait_for(lambda: ep.link_conditions(0) == 0, "OPERATIONAL again")
    bus.send(frame(0x000, "8200"))  # reset communication, every node
    assert recv_id(bus, 0x700 + NODE).data == bytearray([0])
    assert ep.link_conditions(0) == LINK_RESET, "the reset is reported ..."
    assert ep.link_conditions(0) == 0, "... once"
    assert ep.nmt_state == "PRE-OPERATIONAL"


def test_a_reset_clears_the_masters_process_data_and_stopped_answers_no_sdo(rig):
    """After an NMT reset node the latched controlword and mode are 0 (disable voltage,
    no mode), not the master's last words; in STOPPED an SDO request goes unanswered
    (CiA 301)."""
    ep, bus, _ = rig
    bus.send(frame(0x000, f"01{NODE:02X}"))
    wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
    bus.send(frame(0x200 + NODE, "0F000A"))  # RPDO1: enable operation, CST
    bus.send(frame(0x080, ""))
    sp = Setpoint()
    assert ep.recv_setpoint(sp, WAIT_S) and (sp.controlword, sp.mode) == (0x0F, MODE_CST)
    bus.send(frame(0x000, f"81{NODE:02X}"))  # reset node
    recv_id(bus, 0x700 + NODE)
    bus.send(frame(0x080, ""))
    ep.recv_setpoint(sp, WAIT_S)
    assert (sp.controlword, sp.mode, sp.iq_ref_a) == (0, MODE_CST, 0.0)
    bus.send(frame(0x000, f"02{NODE:02X}"))  # stop
    wait_for(lambda: ep.nmt_state == "STOPPED", "STOPPED")
    bus.send(frame(0x600 + NODE, upload(0x6041, 0)))
    assert all(m.arbitration_id != 0x580 + NODE for m in iter(lambda: bus.recv(0.2), None))


def test_a_bus_that_takes_no_frame_drops_them_and_the_cycle_goes_on(rig):
    """A full transmit queue (no node acknowledging on a real bus; here the bus's send
    refuses): the TPDOs and the EMCY are dropped and counted, the cycle is latched and
    handed to the loop all the same."""
    ep, bus, _ = rig
    bus.send(frame(0x000, f"01{NODE:02X}"))
    wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")

    def refuse(msg, timeout=None):
        raise can.CanOperationError("transmit buffer full")

    ep.network.bus.send = refuse
    ep.send_feedback(Feedback(statusword=0x0218, fault=0x8611))
    bus.send(frame(0x080, ""))
    assert not ep.recv_setpoint(Setpoint(), WAIT_S) and ep.taken == 1
    assert ep.stats.send_dropped == 3 + 1  # TPDO1-3 and the EMCY


def test_a_heartbeat_consumer_reports_a_lost_master(rig):
    """1016h:01 = node 7Fh, 50 ms: nothing before the first heartbeat, lost once it is
    overdue, back with the next one."""
    ep, bus, _ = rig
    assert sdo(bus, download(0x1016, 1, 0x7F << 16 | 50, 4)).startswith("60")
    assert ep.link_conditions(0) == 0, "monitoring starts with the first heartbeat"
    bus.send(frame(0x77F, "05"))
    wait_for(lambda: ep.link_conditions(0) == LINK_HEARTBEAT_LOST, "the heartbeat lost")
    bus.send(frame(0x77F, "05"))
    wait_for(lambda: ep.link_conditions(0) == 0, "the heartbeat back")
    assert sdo(bus, download(0x1016, 1, 0, 4)).startswith("60")  # no consumer
    time.sleep(0.06)
    assert ep.link_conditions(0) == 0


def test_emcy_follows_the_error_code(rig):
    """A new 603Fh goes out as EMCY at the next cycle (code, 1001h, five zero bytes), its
    clearing as the error reset EMCY."""
    ep, bus, _ = rig
    sp = Setpoint()
    for code, register, emcy in ((0x8611, 0x21, "1186210000000000"),
                                 (0, 0, "0000000000000000")):
        ep.send_feedback(Feedback(statusword=0x0218 if code else 0x0250, fault=code))
        bus.send(frame(0x080, ""))
        assert recv_id(bus, 0x080 + NODE).data.hex() == emcy
        ep.recv_setpoint(sp, WAIT_S)
        assert int.from_bytes(bytes.fromhex(sdo(bus, upload(0x1001, 0)))[4:5],
                              "little") == register


def test_only_a_sync_after_new_process_data_is_heard(rig):
    ep, bus, _ = rig
    bus.send(frame(0x000, f"01{NODE:02X}"))
    wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
    sp = Setpoint()
    bus.send(frame(0x080, ""))
    assert not ep.recv_setpoint(sp, WAIT_S) and ep.taken == 1
    bus.send(frame(0x200 + NODE, "06000A"))  # RPDO1: controlword 6, CST
    bus.send(frame(0x080, ""))
    assert ep.recv_setpoint(sp, WAIT_S) and sp.controlword == 6
    bus.send(frame(0x080, ""))
    assert not ep.recv_setpoint(sp, WAIT_S) and ep.stats.received == 1


# -- udp_multicast stays on this machine ---------------------------------------------------

NETNS = "hil-remote"
REMOTE_GROUP = "239.255.77.1"


@pytest.fixture
def remote_host():
    """A network namespace joined to this one by a veth pair (10.77.0.1 here, 10.77.0.2
    there): a host on the network, for the test's frames from outside.  The group is
    routed to the veth here, so python-can's own bus joins it on the network side."""
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command for a network namespace")

    def ip(*args, check=True):
        return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)

    ip("netns", "del", NETNS, check=False)
    made = ip("netns", "add", NETNS, check=False)
    if made.returncode != 0:
        pytest.skip(f"cannot make a network namespace: {made.stderr.strip()}")
    try:
        ip("link", "add", "hilv0", "type", "veth", "peer", "name", "hilv1")
        ip("link", "set", "hilv1", "netns", NETNS)
        ip("addr", "add", "10.77.0.1/24", "dev", "hilv0")
        ip("link", "set", "hilv0", "up")
        ip("route", "add", f"{REMOTE_GROUP}/32", "dev", "hilv0")  # python-can joins there
        for cmd in (["addr", "add", "10.77.0.2/24", "dev", "hilv1"], ["link", "set", "hilv1", "up"],
                    ["route", "add", "224.0.0.0/4", "dev", "hilv1"]):
            ip("netns", "exec", NETNS, "ip", *cmd)
        yield lambda *argv: subprocess.run(["ip", "netns", "exec", NETNS, *argv],
                                           capture_output=True, text=True, timeout=30)
    finally:
        ip("link", "del", "hilv0", check=False)
        ip("netns", "del", NETNS, check=False)


SEND_FROM_REMOTE = """
import socket, sys
from can import Message
from can.interfaces.udp_multicast.utils import pack_message
group, port, host = sys.argv[1], int(sys.argv[2]), sys.argv[3]
data = pack_message(Message(arbitration_id=0, data=bytes((2, 5)), is_extended_id=False))
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
for _ in range(20):
    s.sendto(data, (group, port))  # to the group, on the wire
    s.sendto(data, (host, port))   # and straight to the host's port
"""


def test_udp_multicast_takes_no_frame_from_another_host(remote_host):
    """An NMT stop sent by another host, to the group over the network and by unicast to
    the drive's port: the loopback bus takes none; python-can's own bus (every interface)
    takes them, which shows that they arrive."""
    group, port = REMOTE_GROUP, 47000 + uuid.uuid4().int % 1000
    ours = LoopbackMulticastBus(group, "127.0.0.1", port=port)
    theirs = can.Bus(interface="udp_multicast", channel=group, port=port)
    try:
        got = None
        for _ in range(50):  # a veth just brought up may drop the first datagrams
            sent = remote_host(sys.executable, "-c", SEND_FROM_REMOTE, group, str(port),
                               "10.77.0.1")
            assert sent.returncode == 0, sent.stderr
            got = theirs.recv(0.2)
            if got is not None:
                break
        assert got is not None and bytes(got.data) == b"\x02\x05"
        assert ours.recv(0.5) is None
    finally:
        ours.shutdown()
        theirs.shutdown()


def test_loopback_bus_talks_to_python_cans_own_bus_over_lo(multicast_group):
    """A peer on python-can's own bus with the group routed over lo (docs/canopen.md's one
    setting) reaches the drive's bus, and the other way round; the drive's bus never
    receives its own frames."""
    group, port = multicast_group
    ours = LoopbackMulticastBus(group, "127.0.0.1", port=port)
    theirs = can.Bus(interface="udp_multicast", channel=group, port=port)
    try:
        theirs.send(can.Message(arbitration_id=0x123, data=b"hi", is_extended_id=False))
        msg = ours.recv(WAIT_S)
        assert msg is not None and msg.arbitration_id == 0x123
        ours.send(can.Message(arbitration_id=0x321, data=b"yo", is_extended_id=False))
        msg = theirs.recv(WAIT_S)
        while msg is not None and msg.arbitration_id != 0x321:  # its own frame first
            msg = theirs.recv(WAIT_S)
        assert msg is not None
        # ours does not hear itself, as a CAN controller does not: its own frame is dropped
        # in the kernel (socket filter), the next frame is the peer's
        theirs.send(can.Message(arbitration_id=0x124, data=b"", is_extended_id=False))
        msg = ours.recv(WAIT_S)
        assert msg is not None and msg.arbitration_id == 0x124 and ours.own == 0
    finally:
        ours.shutdown()
        theirs.shutdown()


def test_multicast_interface_option_is_checked():
    from io_adapters import AdapterConfigError
    with pytest.raises(AdapterConfigError, match="multicast_if"):
        open_endpoint(f"can://virtual/x?{QUERY}&multicast_if=127.0.0.1", "device")
    with pytest.raises(AdapterConfigError, match="multicast_if"):
        open_endpoint(f"can://udp_multicast/239.1.1.1?{QUERY}&multicast_if=nowhere",
                      "device")


def test_the_master_endpoint_produces_its_heartbeat():
    """``heartbeat=127:10``: our master sends 77Fh with state OPERATIONAL (05h) after a
    SYNC, for a drive's consumer."""
    channel = f"hil-{uuid.uuid4().hex[:12]}"
    with can.Bus(interface="virtual", channel=channel) as bus, open_endpoint(
            f"can://virtual/{channel}?node={NODE}&rated_current_ma=28000&heartbeat=127:10",
            "controller") as master:
        master.send_setpoint(Setpoint())
        assert recv_id(bus, 0x77F).data == bytearray([0x05])
