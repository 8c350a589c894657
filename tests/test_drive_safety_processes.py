"""The emulated drive's refusals, strangers, a restarted controller and a stalled peer with
the emulator (``hil run``) in its own process and the test as the controller over real
sockets and pty pairs (the drive's monitoring and CAN: test_drive_monitoring_processes.py).

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

import pytest

from hil.cia402 import DISABLE_VOLTAGE, State, statusword_state
from hil.drive.faults import ERROR_CODE, Cause
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_VOLTAGE
from tests.runtime_helpers import (
    ANSWER_S,
    EXIT_S,
    SLOW_2KHZ,
    Children,
    check_recording,
    enable,
    exchange,
    machine_variant,
    terminate,
    until_state,
)

START_MM = 250.0
IQ_A = 0.3
REFUSED = ERROR_CODE[Cause.SETPOINT_REFUSED]
#: 1 mm/s of table speed in motor-encoder increments/s (2**22 per rev, 10 mm lead)
MM_S_COUNTS = 1e-3 / 0.01 * 2**22


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


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
