"""Network management and the bus of the CANopen drive, frame by frame on python-can's
``virtual`` bus: boot-up, the heartbeat producer (1017h) and the NMT states it reports,
an NMT start whose PDO configuration the bus cannot carry, the bus's room, and the bus
traffic written with python-can's ASC and BLF writers.

References: CiA 301 (boot-up message 700h + node-ID with 00h; heartbeat state bytes 7Fh
PRE-OPERATIONAL, 05h OPERATIONAL, 04h STOPPED; NMT reset communication restores 1017h;
the EMCY layout); the worst-case frame lengths summed by hand (:func:`worst_frame_bits`
of Davis et al., test_can_bus_time.py checks it); python-can's own log readers.
"""

import time
from pathlib import Path

import can
import pytest

from io_adapters import AdapterError, Feedback, Setpoint, open_endpoint
from io_adapters.can_bus_time import worst_frame_bits
from io_adapters.messages import MODE_CST
from tests.test_can_cia402 import (  # noqa: F401  (no_leaked_threads: autouse)
    frame,
    no_leaked_threads,
    recv_id,
    sdo_write_u32,
    virtual_channel,
    wait_for,
)

NODE = 5
QUERY = f"node={NODE}&rated_current_ma=28000"
DEVICE = "&sync_timeout_ms=60000"  # no cycle on the drive's own clock between our SYNCs
HEARTBEAT = 0x700 + NODE


def states(bus: can.BusABC, n: int) -> list[int]:
    """The state bytes of the next ``n`` heartbeats of the node."""
    return [recv_id(bus, HEARTBEAT).data[0] for _ in range(n)]


def test_boot_up_heartbeat_and_nmt_states():
    channel = virtual_channel()
    with can.Bus(interface="virtual", channel=channel) as bus, \
            open_endpoint(f"can://virtual/{channel}?{QUERY}{DEVICE}", "device") as ep:
        assert recv_id(bus, HEARTBEAT).data == bytearray([0x00])  # boot-up
        bus.send(can.Message(arbitration_id=0x605, is_extended_id=False,
                             data=bytes([0x2B, 0x17, 0x10, 0, 10, 0, 0, 0])))  # 1017h = 10 ms
        assert recv_id(bus, 0x585).data[0] == 0x60
        assert states(bus, 3) == [0x7F] * 3
        for command, state, name in ((0x01, 0x05, "OPERATIONAL"), (0x02, 0x04, "STOPPED"),
                                     (0x80, 0x7F, "PRE-OPERATIONAL")):
            bus.send(frame(0x000, f"{command:02X}{NODE:02X}"))
            wait_for(lambda name=name: ep.nmt_state == name, name)
            assert states(bus, 3)[-1] == state, name  # the first may predate the command
        bus.send(frame(0x000, f"82{NODE:02X}"))  # reset communication: 1017h back to 0
        while recv_id(bus, HEARTBEAT).data[0] != 0x00:
            pass  # heartbeats sent before the reset
        assert ep.nmt_state == "PRE-OPERATIONAL"
        with pytest.raises(AssertionError, match="no frame 0x705"):
            recv_id(bus, HEARTBEAT)


def emcy_frame(bus: can.BusABC) -> tuple[int, int, int, int]:
    data = recv_id(bus, 0x080 + NODE).data
    return (int.from_bytes(data[:2], "little"), data[2], int.from_bytes(data[3:5], "little"),
            int.from_bytes(data[5:8], "little"))


def emcys(bus: can.BusABC, quiet_s: float = 0.3) -> list[tuple[int, int, int, int]]:
    """Every EMCY of the node until none came for ``quiet_s``."""
    out = []
    while (msg := bus.recv(quiet_s)) is not None:
        if msg.arbitration_id == 0x080 + NODE:
            data = msg.data
            out.append((int.from_bytes(data[:2], "little"), data[2],
                        int.from_bytes(data[3:5], "little"), int.from_bytes(data[5:8], "little")))
    return out


def cycles(bus: can.BusABC, ep, n: int, period_s: float = 0.0) -> None:
    """``n`` SYNCs, ``period_s`` apart at the least (deadline by deadline), the drive's
    loop answering each (its feedback staged: the next SYNC sends its TPDOs)."""
    sp, fb = Setpoint(), Feedback()
    deadline = time.monotonic()
    for _ in range(n):
        deadline += period_s
        time.sleep(max(0.0, deadline - time.monotonic()))
        bus.send(frame(0x080, ""))
        assert ep.recv_setpoint(sp, 5.0) or ep.taken
        ep.send_feedback(fb)


#: CiA 301's 125 kbit/s: the drive's frames take long enough on the bus that the test's
#: SYNCs, paced at 1006h by sleeping, meet the bus's room as a master at that rate would
SLOW_BUS = "&bitrate=125000"


def test_a_start_the_bus_cannot_carry_starts_says_so_and_loses_frames_as_a_bus_would():
    """1006h = 2 ms at 125 kbit/s with the default mapping: SYNC (1 byte) and seven PDOs of
    3, 8, 4, 4, 5, 8 and 8 bytes need 850 bits per cycle at the worst, 340 % of the 250
    bits a cycle holds.  NMT start starts the node all the same (CiA 301: NMT commands are
    unconditional) with EMCY FF20h carrying 3400 per mille and 2000 µs, and our master
    stops saying why.  With a SYNC every 2 ms the node's three TPDOs (375 bits) and the
    SYNC (65) need 440 bits of the 250 the bus carries: the TPDOs wait for room, and with
    the transmit queue full (10) they are lost: EMCY 8110h "CAN overrun", frames delayed
    and lost counted, and no cycle holds more than the 250 bits the bus carries.  Started
    again at 10 ms, the plan fits (68 %) and the waiting frames go out: both errors are
    reset."""
    needed = sum(worst_frame_bits(n) for n in (1, 3, 8, 4, 4, 5, 8, 8))
    assert needed == 850
    channel = virtual_channel()
    url = f"can://virtual/{channel}?{QUERY}{SLOW_BUS}"
    with can.Bus(interface="virtual", channel=channel) as bus, \
            open_endpoint(url + DEVICE, "device") as ep:
        recv_id(bus, HEARTBEAT)
        sdo_write_u32(bus, NODE, 0x1006, 0, 2000)
        with open_endpoint(url, "controller") as master, \
                pytest.raises(AdapterError, match="node 5's PDO configuration needs 340 % "
                                                  "of the 2000 µs"):
            master.recv_feedback(Feedback(), 5.0)  # (it sent NMT start when opened)
        wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
        assert emcys(bus)[0] == (0xFF20, 0x81, round(needed / 250 * 1000), 2000)
        assert ep.stats.starts_over_plan == 1
        cycles(bus, ep, 40, 2e-3)
        assert (0x8110, 0x11) in [e[:2] for e in emcys(bus)]
        st = ep.stats
        assert st.frames_delayed > 0 and st.frames_lost > 0, st
        assert 0 < st.bus_load_max <= 1.0 and st.bus_bits_per_cycle_max <= 250, st
        bus.send(frame(0x000, f"80{NODE:02X}"))
        wait_for(lambda: ep.nmt_state == "PRE-OPERATIONAL", "PRE-OPERATIONAL")
        sdo_write_u32(bus, NODE, 0x1006, 0, 10000)
        bus.send(frame(0x000, f"01{NODE:02X}"))
        wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
        cycles(bus, ep, 20, 10e-3)
        assert [e[:2] for e in emcys(bus)].count((0, 0)) == 2  # plan and overrun reset
        assert ep.stats.bus_plan_load == pytest.approx(0.68)
        assert ep.bus_plan().describe().startswith("68% of the bus: 850 bits per 10 ms")


def test_a_master_whose_sync_outpaces_1006h_gets_no_more_than_the_bus_carries():
    """The bus's room grows with time at the bit rate, not per SYNC: a master that sends
    SYNC every 1 ms to a node told 1006h = 10 ms at 125 kbit/s (the plan fits: 850 bits of
    1250) has only 125 bits per SYNC, so the node's TPDOs wait and are lost, and neither
    the busiest cycle nor the mean carries more than the bit rate."""
    channel = virtual_channel()
    url = f"can://virtual/{channel}?{QUERY}&bitrate=125000"
    with can.Bus(interface="virtual", channel=channel) as bus, \
            open_endpoint(url + DEVICE, "device") as ep:
        recv_id(bus, HEARTBEAT)
        sdo_write_u32(bus, NODE, 0x1006, 0, 10000)
        bus.send(frame(0x000, f"01{NODE:02X}"))
        wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
        cycles(bus, ep, 40, 1e-3)
        st = ep.stats
        assert st.starts_over_plan == 0 and st.bus_plan_load == pytest.approx(0.68)
        assert st.frames_lost > 0, st
        assert 0 < st.bus_load_max <= 1.0 and 0 < st.bus_load_mean <= 1.0, st


def test_a_heartbeat_counts_at_its_rate_in_the_plan():
    """1017h = 100 ms adds one 1-byte frame (65 bits at the worst) every 100 cycles of
    1 ms: 0.65 bits per cycle, not a whole frame in every one."""
    channel = virtual_channel()
    with can.Bus(interface="virtual", channel=channel) as bus, \
            open_endpoint(f"can://virtual/{channel}?{QUERY}{DEVICE}", "device") as ep:
        recv_id(bus, HEARTBEAT)
        bus.send(frame(0x000, f"01{NODE:02X}"))
        wait_for(lambda: ep.nmt_state == "OPERATIONAL", "OPERATIONAL")
        before = ep.bus_plan().bits
        bus.send(frame(0x600 + NODE, "2B1710006400" + "0000"))  # 1017h = 100 ms (U16)
        assert recv_id(bus, 0x580 + NODE).data[0] == 0x60
        assert ep.bus_plan().bits - before == pytest.approx(worst_frame_bits(1) / 100)


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".mf4"])
def test_the_bus_traffic_is_logged_for_can_tools(tmp_path, suffix):
    """``log=FILE`` on the device side: python-can's reader for the suffix gets back the
    boot-up, every SYNC, the master's RPDOs and the drive's TPDOs, directions marked.  (A
    channel name ending in digits is no CAN channel number for the writer.)"""
    channel = virtual_channel() + "4294967296"
    log = tmp_path / f"bus{suffix}"
    url = f"can://virtual/{channel}?{QUERY}"
    with open_endpoint(f"{url}{DEVICE}&log={log}", "device") as device, \
            open_endpoint(url, "controller") as master:
        wait_for(lambda: device.nmt_state == "OPERATIONAL", "OPERATIONAL")
        sp, got = Setpoint(mode=MODE_CST, controlword=6, iq_ref_a=2.8), Setpoint()
        for k in range(5):
            master.send_setpoint(sp)
            assert device.recv_setpoint(got, 5.0)
            device.send_feedback(Feedback(statusword=0x0231, encoder_counts=float(k)))
        assert master.recv_feedback(Feedback(), 5.0)
    frames = list(can.LogReader(log))
    ids = [m.arbitration_id for m in frames]
    assert ids[0] == HEARTBEAT and frames[0].data == bytearray([0]) and not frames[0].is_rx
    assert ids.count(0x080) == 5 and ids.count(0x205) == 5 and ids.count(0x505) == 5
    assert ids.count(0x185) == 4  # SYNC 2-5 answer the cycles before them
    assert all(m.is_rx for m in frames if m.arbitration_id in (0x080, 0x205))
    assert all(not m.is_rx for m in frames if m.arbitration_id == 0x185)
    assert [m.timestamp for m in frames] == sorted(m.timestamp for m in frames)


def _logged_run(log: Path, url: str, k_max: int = 5) -> None:
    """Our master driving the node in CST at 100 per mille of the rated torque (2.8 of
    28 A) for ``k_max`` cycles; the drive answers statusword 0231h and position k."""
    with open_endpoint(f"{url}{DEVICE}&log={log}", "device") as device, \
            open_endpoint(url, "controller") as master:
        wait_for(lambda: device.nmt_state == "OPERATIONAL", "OPERATIONAL")
        sp, got = Setpoint(mode=MODE_CST, controlword=6, iq_ref_a=2.8), Setpoint()
        for k in range(k_max):
            master.send_setpoint(sp)
            assert device.recv_setpoint(got, 5.0)
            device.send_feedback(Feedback(statusword=0x0231, encoder_counts=float(k)))
        assert master.recv_feedback(Feedback(), 5.0)


def test_a_bus_log_decodes_into_named_signals_with_hil_eds_files(tmp_path):
    """hil eds's DBC decodes an MDF4 bus log (``log=bus.mf4``, python-can's writer) in
    asammdf's bus-logging extraction, and its can.viewer file decodes an ASC log's frames
    with can.viewer's own parser: the statusword, the positions answered, the target
    torque in per mille, each under its object's name."""
    from asammdf import MDF
    from can.viewer import CanViewer, _parse_viewer_args

    from hil.dbc import pdo_frames, write_dbc, write_viewer
    from hil.eds import device_values
    from io_adapters.can_node import SW_ECHO_MASK
    from tests.conftest import CONFIGS
    channel = virtual_channel()
    url = f"can://virtual/{channel}?{QUERY}"
    frames = pdo_frames(NODE, device_values(CONFIGS / "arrow500_x.toml", url)[0].values)
    dbc, viewer = write_dbc(frames, tmp_path / "nodes.dbc"), write_viewer(frames,
                                                                           tmp_path / "v.txt")
    _logged_run(tmp_path / "bus.mf4", url)
    with MDF(tmp_path / "bus.mf4") as mdf:
        decoded = mdf.extract_bus_logging({"CAN": [(str(dbc), 0)]})
        signals = {ch.name: ch for ch in decoded.iter_channels()}
    # (the statusword's bits 8, 14 and 15 echo the SYNC counter: io_adapters.can_cia402)
    assert [int(s) & ~SW_ECHO_MASK for s in signals["Statusword_6041"].samples] == [0x0231] * 4
    assert list(signals["Position_actual_value_6064"].samples) == [0, 1, 2, 3]
    assert signals["Position_actual_value_6064"].unit == "inc"
    assert set(signals["Target_torque_6071"].samples) == {100}
    assert signals["Target_torque_6071"].unit == "permille"
    _logged_run(tmp_path / "bus.asc", f"can://virtual/{virtual_channel()}?{QUERY}")
    _, structs = _parse_viewer_args(["-d", str(viewer)])
    tpdo2 = [CanViewer.unpack_data(m.arbitration_id, structs, m.data)
             for m in can.LogReader(tmp_path / "bus.asc") if m.arbitration_id == 0x285]
    assert [values[0] for values in tpdo2] == [0, 1, 2, 3]  # 6064h, then 606Ch


def test_a_log_name_without_a_can_suffix_is_refused():
    with pytest.raises(AdapterError, match="a CAN log is one of"):
        open_endpoint(f"can://virtual/x?{QUERY}&log=bus.txt", "device")


def test_the_ticks_between_syncs_are_not_silence():
    """The watchdog counts ticks (125 µs on the Arrow 500 X); a heard SYNC cycle stands for
    1.5 communication cycles (1006h = 1 ms): the 11 ticks after it are not silent, the 12th
    is, and at the 4th silent one a watchdog of 4 ticks gives the drive its cause."""
    from hil.drive import EmulatedDrive
    from hil.drive.faults import Cause
    from hil.drive.objects import DriveObjects
    from hil.runtime.watchdog import Watchdog
    from plant import Plant
    from plant.config import load_machine
    from tests.conftest import CONFIGS
    drive = EmulatedDrive(Plant(load_machine(CONFIGS / "arrow500_x.toml")))
    with open_endpoint(f"can://virtual/{virtual_channel()}?{QUERY}{DEVICE}", "device") as ep:
        ep.setpoint_bounds = (drive.setpoint_bounds(),)
        ep.objects = DriveObjects([drive], ep.rated_current_a)
        assert ep.heard_for_s == pytest.approx(1.5e-3)
        dog = Watchdog(4, 125e-6, lambda line: None)
        dog.update(True, 0, 1, drive, ep)
        silences, causes = [], []
        for tick in range(1, 16):
            dog.update(False, tick, 1, drive, ep)
            silences.append(dog.silent)
            causes.append(bool(drive.link_causes & Cause.WATCHDOG))
        assert silences == [0] * 11 + [1, 2, 3, 4]
        assert causes == [False] * 14 + [True]  # 8250h for the drive (6007h acts on it)
