"""Every fault and watchdog path of the emulated drive with the emulator (``hil run``) in
its own process and the test as the controller over real sockets, pty pairs and CAN buses.

The references are the CiA 402 state table (statusword patterns, the fault-reset edge),
the drive's error codes (hil.drive.faults, CiA 301/402), the stroke of the machine file and
the emulator's own recording and report.  The machine is the Arrow 500 X at 2 kHz
(``runtime_helpers.SLOW_2KHZ``).  No wall-clock duration is asserted; the stalled-peer test
bounds the overruns a blocking send would have caused (every tick, 100 ms each).
"""

import json
import math
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hil.cia402 import DISABLE_VOLTAGE, State, statusword_state
from hil.drive.faults import ERROR_CODE, Cause
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_VOLTAGE
from plant.config import load_machine
from tests.runtime_helpers import (
    ANSWER_S,
    EXIT_S,
    SLOW_2KHZ,
    Children,
    enable,
    exchange,
    machine_variant,
    read_run,
    terminate,
)

START_MM = 250.0
IQ_A = 0.3
REFUSED = ERROR_CODE[Cause.SETPOINT_REFUSED]
#: 1 mm/s of table speed in motor-encoder increments/s (2**22 per rev, 10 mm lead)
MM_S_COUNTS = 1e-3 / 0.01 * 2**22


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


def until_state(ep, sp, fb, state: State, limit: int = 4000) -> None:
    """Answer feedback until the drive reports ``state``."""
    for _ in range(limit):
        exchange(ep, sp, fb, 1)
        if statusword_state(fb.statusword) == state:
            return
    raise AssertionError(f"drive not in {state.name}: 0x{fb.statusword:04X}")


def check_recording(run_dir: Path) -> tuple[dict, dict]:
    """The run's report and recording, with what must hold whatever happened: the plant
    state finite, every setpoint applied finite and within the power stage, the table
    inside the stroke and its end stops."""
    report, rec = read_run(run_dir)
    table = load_machine(report["machine_file"]).table
    for name in ("plant_table_pos", "plant_motor_vel", "plant_iq_a"):
        assert np.isfinite(rec[name]).all(), name
    for name in ("sp_iq_ref_a", "sp_uq_v", "sp_target_position_counts"):
        assert np.isfinite(rec[name]).all(), f"{name}: a refused value was applied"
    assert (np.abs(rec["sp_iq_ref_a"]) <= 28.0).all()
    x = rec["plant_table_pos"]
    over = table.end_stop_overtravel_m
    assert -over < x.min() and x.max() < table.travel_m + over
    return report, rec


# -- UDP ------------------------------------------------------------------------------

BAD_SETPOINTS = [  # mode, field, value
    (MODE_CST, "iq_ref_a", math.nan), (MODE_CST, "iq_ref_a", math.inf),
    (MODE_CST, "iq_ref_a", 1e308), (MODE_VOLTAGE, "uq_v", math.nan),
    (MODE_CSP, "target_position_counts", 1e308), (42, "iq_ref_a", 0.0)]


@pytest.mark.parametrize("mode, field, value", BAD_SETPOINTS)
def test_a_bad_udp_setpoint_leaves_the_axis_at_rest_with_a_fault_a_reset_clears(
        config, tmp_path, mode, field, value):
    run_dir = tmp_path / "run"
    sp, fb = Setpoint(mode=MODE_CST), Feedback()
    with Children(tmp_path) as children:
        proc, url = children.emulator(config, "udp://127.0.0.1:0", run_dir,
                                      "--start", START_MM)
        with open_endpoint(url, "controller") as ep:
            ep.send_setpoint(sp)
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 20, seq, IQ_A)
            assert ep.recv_feedback(fb, ANSWER_S)
            bad = Setpoint(seq=sp.seq + 1, controlword=sp.controlword, mode=mode)
            setattr(bad, field, value)
            ep.send_setpoint(bad)
            sp.seq += 1
            sp.iq_ref_a = 0.0
            until_state(ep, sp, fb, State.FAULT)
            exchange(ep, sp, fb, 200)  # torque off: the currents died away, friction holds
            assert fb.fault == REFUSED and fb.iq_a == pytest.approx(0.0, abs=0.1)
            # at rest: below 1 mm/s of table speed (the free rotor rings a little on the
            # screw while the table sticks)
            assert abs(fb.velocity_counts_s) < MM_S_COUNTS
            seq = enable(ep, sp, fb)  # fault reset, then the enable sequence
            exchange(ep, sp, fb, 20, seq, IQ_A)
            assert fb.fault == 0 and statusword_state(fb.statusword) == State.OPERATION_ENABLED
            sp.controlword = DISABLE_VOLTAGE.value
            exchange(ep, sp, fb, 3)
        assert terminate(proc) == 0, children.log("emulator")
    report, rec = check_recording(run_dir)
    stats = report["adapter"]["stats"]
    assert stats["refused_nonfinite"] + stats["refused_range"] + stats["refused_mode"] == 1
    events = report["faults"]["X"]["events"]
    assert [(e["kind"], e["code"]) for e in events] == [("fault", REFUSED), ("reset", 0)]


def test_foreign_senders_cannot_move_the_axis(config, tmp_path):
    """The pinned controller holds the axis enabled at rest; a second controller on
    another port, with its own session, runs a whole enable sequence and asks for 5 A, and
    datagrams come from a non-loopback address of this machine: none of it reaches the
    drive (counted as foreign), and the axis does not move."""
    run_dir = tmp_path / "run"
    sp, fb = Setpoint(), Feedback()
    with Children(tmp_path) as children:
        proc, url = children.emulator(config, "udp://127.0.0.1:0", run_dir,
                                      "--start", START_MM)
        with open_endpoint(url, "controller") as ep, \
                open_endpoint(url, "controller") as intruder:
            ep.send_setpoint(sp)
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 10, seq)
            start = fb.encoder_counts
            other, other_fb = Setpoint(mode=MODE_CST), Feedback()
            intruder_seq = enable_blind(intruder, other)
            for k in range(200):
                other.seq += 1
                other.controlword = intruder_seq
                other.iq_ref_a = 5.0
                intruder.send_setpoint(other)
                send_from_outside(url, k)
                exchange(ep, sp, fb, 1, seq)
            assert not intruder.recv_feedback(other_fb, 0.05), "the drive answered a stranger"
            assert abs(fb.encoder_counts - start) < 1000, "the axis moved"
            sp.controlword = DISABLE_VOLTAGE.value
            exchange(ep, sp, fb, 3)
        assert terminate(proc) == 0
    report, _ = check_recording(run_dir)
    stats = report["adapter"]["stats"]
    assert stats["foreign"] >= 200 and stats["peer_restarts"] == 0


def enable_blind(ep, sp: Setpoint) -> int:
    """The enable sequence's words sent without waiting for answers; the last word."""
    for word in (0x0000, 0x0080, 0x0006, 0x0007, 0x000F):
        sp.seq += 1
        sp.controlword = word
        ep.send_setpoint(sp)
    return 0x000F


def outside_address() -> str | None:
    """A non-loopback IPv4 address of this machine, if it has one."""
    try:
        out = subprocess.run(["ip", "-4", "-o", "addr"], capture_output=True, text=True,
                             timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    for line in out.splitlines():
        address = line.split()[3].partition("/")[0]
        if not address.startswith("127."):
            return address
    return None


def send_from_outside(url: str, k: int) -> None:
    """One setpoint datagram from this machine's non-loopback address to the drive."""
    from io_adapters.codec import encode
    address = outside_address()
    if address is None:
        return
    host, port = url.removeprefix("udp://").rsplit(":", 1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((address, 0))
        s.sendto(encode(Setpoint(seq=k, controlword=0x000F, iq_ref_a=5.0), 7, k),
                 (host, int(port)))


def test_a_restarted_controller_gets_back_in_through_the_handshake(config, tmp_path):
    """A controller that dies leaves the drive to its watchdog (FAULT); a new controller
    process (new port, new session) is welcomed once the old one has been silent for the
    takeover time, resets the fault and moves the axis again."""
    run_dir = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, url = children.emulator(config, "udp://127.0.0.1:0", run_dir,
                                      "--start", START_MM)
        sp, fb = Setpoint(), Feedback()
        with open_endpoint(url, "controller") as first:
            first.send_setpoint(sp)
            seq = enable(first, sp, fb)
            exchange(first, sp, fb, 20, seq, IQ_A)
        child = children.start("second", [sys.executable, "-c", SECOND_CONTROLLER, url],
                               ready=True)
        assert child.wait(timeout=EXIT_S) == 0, children.log("second")
        result = json.loads(child.stdout.read())
        assert terminate(proc) == 0
    assert result["welcomed"] and result["first_state"] == "FAULT"
    assert result["first_fault"] == ERROR_CODE[Cause.WATCHDOG]
    assert result["state"] == "OPERATION_ENABLED" and result["fault"] == 0
    report, _ = check_recording(run_dir)
    assert report["adapter"]["stats"]["peer_restarts"] == 1


SECOND_CONTROLLER = """
import json, sys
from hil.cia402 import statusword_state
from io_adapters import Feedback, Setpoint, open_endpoint
from tests.runtime_helpers import enable, exchange
sp, fb = Setpoint(), Feedback()
with open_endpoint(sys.argv[1], "controller") as ep:
    while not ep.recv_feedback(fb, 0.05):   # HELLO until welcomed, then feedback
        sp.seq += 1
        ep.send_setpoint(sp)
    first = (statusword_state(fb.statusword).name, fb.fault)
    seq = enable(ep, sp, fb)
    exchange(ep, sp, fb, 20, seq, 0.3)
    print(json.dumps({"welcomed": ep.welcomed, "first_state": first[0],
                      "first_fault": first[1], "state": statusword_state(fb.statusword).name,
                      "fault": fb.fault}))
    sp.controlword = 0
    exchange(ep, sp, fb, 3)
"""


# -- serial ---------------------------------------------------------------------------

def pty_pair(folder: Path, children: Children) -> tuple[Path, Path]:
    """A socat pty pair with named links (device side, controller side)."""
    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (bash .ci/test-deps installs it)")
    a, b = folder / "pty-device", folder / "pty-controller"
    children.start("socat", ["socat", "-d", "-d", f"pty,raw,echo=0,link={a}",
                             f"pty,raw,echo=0,link={b}"])
    deadline = time.monotonic() + 10.0
    while not (a.exists() and b.exists()):
        assert time.monotonic() < deadline, children.log("socat")
        time.sleep(0.01)
    return a, b


def test_a_nan_over_serial_faults_and_a_reset_clears(config, tmp_path):
    run_dir = tmp_path / "run"
    sp, fb = Setpoint(), Feedback()
    with Children(tmp_path) as children:
        device, controller = pty_pair(tmp_path, children)
        proc, _ = children.emulator(config, f"serial://{device}", run_dir, "--start", START_MM)
        with open_endpoint(f"serial://{controller}", "controller") as ep:
            ep.send_setpoint(sp)
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 20, seq, IQ_A)
            assert ep.recv_feedback(fb, ANSWER_S)
            ep.send_setpoint(Setpoint(seq=sp.seq + 1, controlword=sp.controlword,
                                      iq_ref_a=math.nan))
            sp.seq += 1
            until_state(ep, sp, fb, State.FAULT)
            assert fb.fault == REFUSED
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 20, seq, IQ_A)
            assert fb.fault == 0
            sp.controlword = DISABLE_VOLTAGE.value
            exchange(ep, sp, fb, 3)
        assert terminate(proc) == 0, children.log("emulator")
    report, _ = check_recording(run_dir)
    assert report["adapter"]["stats"]["refused_nonfinite"] == 1


def test_a_serial_peer_that_stops_reading_costs_no_overrun(config, tmp_path):
    """The controller writes setpoints for 3 s and never reads: the pty's buffer fills,
    the emulator drops its feedback frames (counted) and keeps its period.  With a
    blocking write every tick would overrun by the write timeout; the bound on overruns
    (5 % of the ticks) is far from that and leaves room for a loaded VM."""
    run_dir = tmp_path / "run"
    with Children(tmp_path) as children:
        device, controller = pty_pair(tmp_path, children)
        proc, _ = children.emulator(config, f"serial://{device}", run_dir)
        with open_endpoint(f"serial://{controller}", "controller") as ep:
            sp = Setpoint()
            end = time.monotonic() + 3.0
            while time.monotonic() < end:
                sp.seq += 1
                ep.send_setpoint(sp)
                time.sleep(0.0005)
            assert terminate(proc) == 0, children.log("emulator")
    report, _ = check_recording(run_dir)
    loop, stats = report["loop"], report["adapter"]["stats"]
    assert stats["send_dropped"] > 0 and report["adapter_errors"]["send"] == 0
    assert loop["overruns"] <= 0.05 * loop["ticks"], loop


# -- CANopen, with canopen's master -----------------------------------------------------

CAN_NODE, CAN_RATED_MA = 5, 28000
SYNC_S = 0.002  # the master's SYNC period; hil run runs one tick per SYNC (--rate 500)
MASTER_HEARTBEAT = 0x77F  # the master's heartbeat as node 127


def wait_until(predicate, what: str, limit_s: float = 10.0) -> None:
    end = time.monotonic() + limit_s
    while not predicate():
        assert time.monotonic() < end, f"gave up waiting for {what}"
        time.sleep(0.002)


def emcy_codes(node) -> list[int]:
    return [e.code for e in node.emcy.log]


def recover(network, node) -> None:
    """SYNC and process data on, the target at the actual position, a fault reset and
    the enable sequence back to OPERATION ENABLED (canopen's BaseNode402 state setter)."""
    from tests.test_can_cia402 import WAIT_S
    rpdo2 = node.rpdo[2]
    rpdo2[0x607A].raw = node.sdo[0x6064].raw
    rpdo2[0x60B1].raw = 0
    node.state = "OPERATION ENABLED"
    assert node.state == "OPERATION ENABLED"
    assert node.tpdo[1].wait_for_reception(WAIT_S) is not None
    assert node.sdo[0x603F].raw == 0


def test_a_canopen_master_lost_in_every_way_faults_the_drive(config, tmp_path,
                                                             multicast_group):
    """hil run as a CiA 402 node on udp_multicast; canopen's BaseNode402 enables it in
    CSP at a 2 ms SYNC with its heartbeat consumed (1016h, 100 ms).  Then, each followed
    by a fault reset: the heartbeat stops (8130h), NMT stop (8100h), SYNC and RPDOs stop
    (the watchdog: 8250h; the drive's own cycles are not heard), and a mode 42 in RPDO1
    (FF10h).  Every fault is the drive's FAULT with its EMCY and 603Fh; the recording
    holds them in order."""
    from tests.test_can_cia402 import enable_and_move_csp, master_network, master_node
    group, port = multicast_group
    url = (f"can://udp_multicast/{group}?node={CAN_NODE}&rated_current_ma={CAN_RATED_MA}"
           f"&port={port}&heartbeat_consumer=127:100")
    run_dir = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, _ = children.emulator(config, url, run_dir, "--rate", 500, "--start", START_MM)
        network = master_network()
        heartbeat = None
        try:
            network.connect(interface="udp_multicast", channel=group, port=port)
            node = master_node(network)
            heartbeat = network.send_periodic(MASTER_HEARTBEAT, [0x05], 0.02)
            enable_and_move_csp(network, node, distance_counts=41943, steps=25)

            heartbeat.stop()  # 1: the master's heartbeat stops
            wait_until(lambda: 0x8130 in emcy_codes(node), "EMCY 8130h")
            wait_until(lambda: node.state == "FAULT", "FAULT")
            assert node.sdo[0x603F].raw == 0x8130
            heartbeat = network.send_periodic(MASTER_HEARTBEAT, [0x05], 0.02)
            recover(network, node)

            node.nmt.state = "STOPPED"  # 2: NMT stop
            wait_until(lambda: node.sdo[0x603F].raw == 0x8100, "603Fh 8100h")
            node.nmt.state = "OPERATIONAL"
            wait_until(lambda: node.state == "FAULT", "FAULT after NMT stop")
            recover(network, node)

            network.sync.stop()  # 3: SYNC and process data stop
            node.rpdo[2].stop()
            wait_until(lambda: 0x8250 in emcy_codes(node), "EMCY 8250h")
            network.sync.start(SYNC_S)
            node.rpdo[2].start(SYNC_S)
            recover(network, node)

            node.rpdo[1][0x6060].raw = 42  # 4: a mode the drive does not take
            node.rpdo[1].transmit()
            wait_until(lambda: 0xFF10 in emcy_codes(node), "EMCY FF10h")
            node.rpdo[1][0x6060].raw = 8
            node.rpdo[1].transmit()
            recover(network, node)
        finally:
            if heartbeat is not None:
                heartbeat.stop()
            network.sync.stop()
            network.disconnect()
        assert terminate(proc) == 0, children.log("emulator")
    report, _ = check_recording(run_dir)
    faults = [e["code"] for e in report["faults"]["X"]["events"] if e["kind"] == "fault"]
    assert faults == [0x8130, 0x8100, 0x8250, 0xFF10]
    assert report["adapter"]["stats"]["refused_mode"] == 1
    kinds = [e["kind"] for e in report["watchdog"]["events"]]
    assert "heartbeat lost" in kinds and "NMT stopped" in kinds and "tripped" in kinds
