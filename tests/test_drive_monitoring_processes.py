"""The drive's own monitoring (following error, software limit, overspeed, I2t) and a
CANopen master lost in every way (heartbeat, NMT stop, SYNC and RPDOs, a refused mode),
with the emulator (``hil run``) in its own process: the other half of
test_drive_safety_processes.py (its references hold here too)."""

import signal
import time
from pathlib import Path

import numpy as np
import pytest

from hil.cia402 import DISABLE_VOLTAGE, State, statusword_state
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.messages import MODE_CSP, MODE_CST
from tests.runtime_helpers import (
    SLOW_2KHZ,
    Children,
    check_recording,
    enable,
    exchange,
    machine_variant,
    terminate,
)

START_MM = 250.0


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


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
    CSP at a 2 ms SYNC with its heartbeat consumed (1016h, 100 ms; the master sends it
    every 20 ms).  First the emulator's process is stopped (SIGSTOP) for 300 ms while the
    master's heartbeat and SYNC go on: the frames queue in its socket with the kernel's
    arrival stamps, and the heartbeat is judged on them (CiA 301: the consumer time is the
    bus's, not the late thread's): no EMCY 8130h, the drive still in OPERATION ENABLED.
    Then, each followed by a fault reset: the heartbeat stops (8130h), NMT stop (8100h),
    SYNC and RPDOs stop (the watchdog: 8250h; the drive's own cycles are not heard), and a
    mode 42 in RPDO1 (FF10h).  Every fault is the drive's FAULT with its EMCY and 603Fh;
    the recording holds them in order."""
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

            proc.send_signal(signal.SIGSTOP)  # 0: the emulator starved, the master healthy
            time.sleep(0.3)
            proc.send_signal(signal.SIGCONT)
            time.sleep(0.5)
            assert 0x8130 not in emcy_codes(node), [hex(c) for c in emcy_codes(node)]
            assert node.state == "OPERATION ENABLED"

            heartbeat.stop()  # 1: the master's heartbeat stops
            wait_until(lambda: 0x8130 in emcy_codes(node), "EMCY 8130h")
            wait_until(lambda: node.state == "FAULT", "FAULT")
            assert node.sdo[0x603F].raw == 0x8130
            heartbeat = network.send_periodic(MASTER_HEARTBEAT, [0x05], 0.02)
            recover(network, node)

            node.nmt.state = "STOPPED"  # 2: NMT stop (no SDO, PDO or EMCY while STOPPED)
            time.sleep(0.2)  # the drive's ticks see it within one; nothing to poll
            node.nmt.state = "OPERATIONAL"
            wait_until(lambda: 0x8100 in emcy_codes(node), "EMCY 8100h after NMT stop")
            wait_until(lambda: node.state == "FAULT", "FAULT after NMT stop")
            assert node.sdo[0x603F].raw == 0x8100
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


# -- the drive's own monitoring, through hil run ------------------------------------------

MONITORING = [  # what, [drive] keys, setpoint fields while enabled (iq_ref_a: a function
    # of the exchange), 603Fh expected
    ("following error", "", {"mode": MODE_CSP, "target_position_counts": 1.68e7}, 0x8611),
    ("software limit", "", {"mode": MODE_CST, "iq_ref_a": lambda k: 28.0}, 0x8612),
    ("overspeed", "max_motor_speed_rpm = 300.0\nsoftware_limit_min_m = 0.0\n"
     "software_limit_max_m = 0.0\n", {"mode": MODE_CST, "iq_ref_a": lambda k: 5.0}, 0x8400),
    ("over-current", "continuous_current_a = 2.0\noverload_time_s = 0.01\n",
     {"mode": MODE_CST, "iq_ref_a": lambda k: 5.0 if k // 40 % 2 else -5.0}, 0x2310),
]


@pytest.mark.parametrize("what, keys, fields, code", MONITORING, ids=[m[0] for m in MONITORING])
def test_the_drives_monitoring_faults_it_in_a_separate_process(config, tmp_path, what, keys,
                                                               fields, code):
    """Over UDP against ``hil run``: a CSP target 40 mm away, beyond the 22.5 mm window
    (8611h), CST at the current limit toward the end of travel (the software limit,
    8612h), CST with 6080h at 300 rpm and the software limits off (8400h), CST
    chattering at +-5 A every 20 ms (the axis stays put) with an I2t of 2 A continuous
    and 10 ms at the peak (2310h after about 0.4 s; cooled to 90 % 0.2 s later).  Each
    ends in FAULT with its code and a fault reset brings the drive back."""
    machine = tmp_path / "machine.toml"
    machine.write_text(config.read_text() + (f"\n[drive]\n{keys}" if keys else ""))
    run_dir = tmp_path / "run"
    sp, fb = Setpoint(mode=MODE_CST), Feedback()
    with Children(tmp_path) as children:
        proc, url = children.emulator(machine, "udp://127.0.0.1:0", run_dir,
                                      "--start", START_MM)
        with open_endpoint(url, "controller") as ep:
            ep.send_setpoint(sp)
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 5, seq)
            sp.target_position_counts = fb.encoder_counts + fields.get(
                "target_position_counts", 0.0)
            sp.mode = fields["mode"]
            current = fields.get("iq_ref_a", lambda k: 0.0)
            for k in range(20000):
                exchange(ep, sp, fb, 1, seq, current(k))
                if statusword_state(fb.statusword) == State.FAULT:
                    break
            assert statusword_state(fb.statusword) == State.FAULT and fb.fault == code, what
            sp.mode, sp.target_position_counts = MODE_CST, 0.0
            exchange(ep, sp, fb, 1000)  # the table comes to rest; the I2t model cools
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 5, seq)
            assert fb.fault == 0 and statusword_state(fb.statusword) == State.OPERATION_ENABLED
            sp.controlword = DISABLE_VOLTAGE.value
            exchange(ep, sp, fb, 3)
        assert terminate(proc) == 0, children.log("emulator")
    report, _ = check_recording(run_dir)
    assert report["faults"]["X"]["events"][0]["code"] == code


# -- a CAN run's bus frames beside its recording ------------------------------------------

def test_an_export_places_the_bus_frames_on_the_runs_time(config, tmp_path, multicast_group):
    """hil run on udp_multicast with ``log=bus.asc``, driven in CSP by our master along a
    ramp (5 mm/s); ``hil export --to mdf4 --bus bus.asc`` holds the recording and the
    frames as MDF4 bus logging, which hil eds's DBC decodes: every position actual value
    (6064h, TPDO2) on the ramp is an encoder reading the recording has, typically (the
    median) within 1.5 ms of the recording's time for it (a frame answers the newest tick
    before its SYNC: a tick or two, 0.5-1 ms, and the bus's latency) and each within 15 ms
    (a frame held up by one of the machine's CPU stops, up to 7 ms on the 2-vCPU VM,
    docs/benchmarks.md: a suite run here had one frame 5.5 ms off, the median 0.3 ms).
    Clocks placed wrongly would be seconds off."""
    from asammdf import MDF

    from hil.bench.can import Program, master
    from hil.cli import main as hil
    from hil.dbc import pdo_frames, write_dbc
    from hil.eds import device_values
    from hil.runtime.record_reader import Recording
    group, port = multicast_group
    log = tmp_path / "bus.asc"
    url = (f"can://udp_multicast/{group}?node={CAN_NODE}&rated_current_ma={CAN_RATED_MA}"
           f"&port={port}")
    run_dir = tmp_path / "run"
    counts_per_ms = 4194304 / 10 * 5 / 1000  # 5 mm/s at 1 ms SYNC
    program = Program(START_MM, np.arange(1, 301) * counts_per_ms, 1e-3, 2)
    with Children(tmp_path) as children:
        proc, _ = children.emulator(config, f"{url}&log={log}", run_dir, "--rate", 2000,
                                    "--start", START_MM)
        with open_endpoint(url, "controller") as ep:
            ep.drain = True
            master(ep, program)
        assert terminate(proc) == 0, children.log("emulator")
    dbc = write_dbc(pdo_frames(CAN_NODE, device_values(config, url)[0].values),
                    tmp_path / "nodes.dbc")
    out = tmp_path / "run.mf4"
    assert hil(["export", str(run_dir), "--to", "mdf4", "--bus", str(log), "--out",
                str(out)]) == 0
    rec = Recording(run_dir).read(["tick", "plant_encoder_counts"])
    t_rec = rec["tick"] * 0.5e-3
    with MDF(out) as mdf:
        assert "plant_encoder_counts" in mdf.channels_db
        decoded = mdf.extract_bus_logging({"CAN": [(str(dbc), 0)]})
        position = decoded.get("Position_actual_value_6064")
    # on the ramp: at rest the encoder dithers over a few counts, each seen at many times
    moving = np.flatnonzero(np.abs(position.samples - position.samples[0]) > 10_000)
    assert moving.size > 200
    offsets_s = []
    for t, p in zip(position.timestamps[moving], position.samples[moving]):
        rows = np.flatnonzero(np.round(rec["plant_encoder_counts"]) == p)
        assert rows.size, p
        offsets_s.append(np.abs(t_rec[rows] - t).min())
    offsets_s = np.array(offsets_s)
    assert np.median(offsets_s) < 1.5e-3, np.percentile(offsets_s, [50, 99, 100])
    assert offsets_s.max() < 15e-3, np.percentile(offsets_s, [50, 99, 100])
