"""Fault injection at run time over the adapter, with ``hil run`` in its own process
(issue 14 part 6): an INJECT message on UDP and a write of object 2F00h by canopen's SDO
client on CAN reach the plant, and every injection -- flag, message, SDO, a refused one --
is in the recording's metadata or events and in report.json."""

import time

import numpy as np
import pytest

from hil.inject.catalog import FAULTS
from hil.runtime.record_reader import Recording
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.messages import InjectRequest
from tests.runtime_helpers import (
    SLOW_2KHZ,
    Children,
    enable,
    exchange,
    machine_variant,
    read_run,
    terminate,
)


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


def _events(run) -> list[dict]:
    ev = Recording(run).events()
    return [{k: v[i] for k, v in ev.items()} for i in range(ev["tick"].size)]


def test_an_inject_message_on_udp_changes_the_plant_and_is_recorded(config, tmp_path):
    """hil run with a flag (encoder noise from 0.2 s); the test is the controller: it
    enables the drive holding the current at 0, sends INJECT current_offset 0.5 A and one
    naming a fault the machine does not know.  The measured q current, which the current
    loop holds at its setpoint, shows the offset's ripple in the true current instead; the
    recording's metadata names the flag's injection, its events all three (the refused
    one with its reason), report.json the levels at the end; hil replay, which hands the
    requests on again at their ticks, reproduces the recording; hil export's trace header
    names both injections."""
    run = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, url = children.emulator(config, "udp://127.0.0.1:0", run, "--no-rt",
                                      "--start", 250, "--inject",
                                      "encoder_noise:noise_counts=1.5,at_s=0.2")
        ep = open_endpoint(url, "controller")
        try:
            sp, fb = Setpoint(), Feedback()
            ep.send_setpoint(sp)
            enable(ep, sp, fb)
            exchange(ep, sp, fb, 200)
            ep.send_injection(InjectRequest(0, "current_offset", {"offset_a": 0.5}))
            ep.send_injection(InjectRequest(0, "bearing_seizure", {"level": 1.0}))
            exchange(ep, sp, fb, 400)
        finally:
            ep.close()
        assert terminate(proc) == 0, children.log("emulator")
    report, rec = read_run(run)
    meta = Recording(run).meta
    assert meta["axes"][0]["injections"][0]["fault"] == "encoder_noise"
    events = [e for e in _events(run) if e["source"] == "inject"]
    kinds = [(e["kind"], e["reason"].split()[0]) for e in events]
    assert ("injected", "encoder_noise") in kinds and ("injected", "current_offset") in kinds
    refused = [e for e in events if e["kind"] == "refused"]
    assert len(refused) == 1 and "unknown fault [inject.bearing_seizure]" in refused[0]["reason"]
    offset_tick = next(e["tick"] for e in events if "current_offset" in e["reason"])
    assert report["injections"]["X"]["levels_at_end"] == {"encoder_noise": 1.5,
                                                          "current_offset": 0.5}
    assert report["adapter"]["stats"]["injections"] == 2
    from hil.replay.replay import replay_run
    replayed = replay_run(run)
    assert replayed.matches, replayed.line()
    from hil.runtime.export import export_csv
    from hil.runtime.record_trace import axis_trace
    from hil.trace_file import read_trace
    header = read_trace(export_csv(Recording(run), tmp_path / "trace.csv",
                                   axis_trace(Recording(run)))).metadata
    assert header["injected_1"].endswith("s: current_offset offset_a=0.5 on arrival (adapter)")
    assert header["injected_2"] == "0.2 s: encoder_noise noise_counts=1.5 at 0.2 s (--inject)"
    # the loop regulates the measured current to 0: the true one carries the offset's
    # opposite, a ripple at the electrical frequency (here the axis stands still, so a
    # constant of up to 2/sqrt(3) * 0.5 A in size)
    tick = rec["tick"]
    after = tick > offset_tick + 50
    before = (tick > 100) & (tick < offset_tick)
    true_iq = rec["plant_iq_a"]
    assert np.abs(true_iq[before]).max() < 0.05
    assert 0.05 < np.abs(true_iq[after]).mean() < 2 / np.sqrt(3) * 0.5 + 0.05


def test_an_sdo_write_of_2f00h_injects_and_reads_back(config, tmp_path, multicast_group):
    """hil run as a CANopen node; canopen's SDO client writes the ramp time 2F00h:0A =
    200 ms, then friction growth 2F00h:01 = 5000 (50.00 %): it reads back growing to 5000
    within the ramp.  A level beyond the fault's range is refused with abort 0609 0030 and
    leaves the level as it was; the events hold both."""
    import canopen

    from tests.test_can_cia402 import master_network, master_node
    group, port = multicast_group
    url = f"can://udp_multicast/{group}?node=5&rated_current_ma=28000&port={port}"
    run = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, _ = children.emulator(config, url, run, "--rate", 500, "--start", 250)
        network = master_network()
        try:
            network.connect(interface="udp_multicast", channel=group, port=port)
            node = master_node(network)
            network.sync.start(0.002)
            node.sdo[0x2F00][10].raw = 200
            node.sdo[0x2F00][1].raw = 5000
            levels = []
            end = time.monotonic() + 5.0
            while time.monotonic() < end and (not levels or levels[-1] < 5000):
                levels.append(node.sdo[0x2F00][1].raw)
            assert levels[-1] == 5000 and min(levels) < 5000, levels
            with pytest.raises(canopen.SdoAbortedError) as err:
                node.sdo[0x2F00][1].raw = 2_000_000
            assert err.value.code == 0x06090030
            assert node.sdo[0x2F00][1].raw == 5000
        finally:
            network.sync.stop()
            network.disconnect()
        assert terminate(proc) == 0, children.log("emulator")
    events = [e for e in _events(run) if e["source"] == "inject"]
    assert [e["kind"] for e in events] == ["request", "injected", "reached"]
    assert "friction_growth growth_pct=50 on arrival, ramp 0.2 s (SDO 2F00h)" in \
        events[1]["reason"]


def test_hil_controller_sends_its_injection_over_serial_at_its_program_time(config, tmp_path):
    """hil controller --inject ...,at_s=0.5 and hil run over a socat pty pair: the INJECT
    goes out once, half a second into the program; the emulator takes it from the serial
    link (the adapter's counter), starts it on arrival and ramps it over its 0.2 s.

    Both processes run as the serial loopback's do (SCHED_FIFO, each on a CPU of its own):
    without them, on 2 vCPUs, late setpoints alone moved the axis 1 mm off the contour
    model (alarm 25050) before the injection was due.  An attempt the controller ends on
    an alarm or a silent link is run again; the injection's checks hold on the one that
    completes."""
    from tests.test_loopback import ATTEMPTS, run_pair
    failures = []
    for attempt in range(1, ATTEMPTS + 1):
        folder = tmp_path / f"attempt{attempt}"
        folder.mkdir()
        result = run_pair("serial", config, folder, "--inject",
                          "friction_growth:growth_pct=80,ramp_s=0.2,at_s=0.5")
        if not isinstance(result, str):
            break
        failures.append(f"attempt {attempt}: the controller stopped:\n{result[-600:]}")
    else:
        pytest.fail(f"no completed run in {ATTEMPTS} attempts:\n" + "\n".join(failures))
    summary, report = result
    assert summary["injections_sent"] == [{"at_s": 0.5, "axis": 0, "fault": "friction_growth",
                                          "settings": {"growth_pct": 80.0, "ramp_s": 0.2}}]
    assert report["adapter"]["stats"]["injections"] == 1
    assert report["injections"]["X"]["levels_at_end"] == {"friction_growth": 80.0}
    events = [e for e in _events(folder / "emulator") if e["source"] == "inject"]
    assert [e["kind"] for e in events] == ["request", "injected", "reached"]
    assert events[2]["tick"] - events[1]["tick"] == round(0.2 * 2000)


#: one run-time request per fault of the catalog (levels well inside their ranges)
EVERY_FAULT = {"friction_growth": {"growth_pct": 30.0}, "backlash_growth": {"growth_m": 1e-5},
               "preload_loss": {"loss_pct": 40.0}, "torque_constant_loss": {"loss_pct": 10.0},
               "encoder_noise": {"noise_counts": 3.0}, "encoder_lost_counts": {"lost_ppm": 50.0},
               "current_offset": {"offset_a": 0.2}, "current_gain_error": {"gain_error_pct": 5.0},
               "torque_ripple": {"ripple_pct": 4.0, "order": 3.0}}


def test_every_fault_of_the_catalog_injects_over_udp_and_replays(config, tmp_path):
    """One INJECT per fault, ramped over 0.1 s, while the drive holds the axis in CST: every
    level is in force at the end (report.json), each has its events, and hil replay
    reproduces the run with all nine acting."""
    from hil.inject import FAULT_NAMES
    from hil.replay.replay import replay_run
    assert tuple(EVERY_FAULT) == FAULT_NAMES
    run = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, url = children.emulator(config, "udp://127.0.0.1:0", run, "--no-rt",
                                      "--start", 250)
        ep = open_endpoint(url, "controller")
        try:
            sp, fb = Setpoint(), Feedback()
            ep.send_setpoint(sp)
            enable(ep, sp, fb)
            for fault, table in EVERY_FAULT.items():
                ep.send_injection(InjectRequest(0, fault, {**table, "ramp_s": 0.1}))
            exchange(ep, sp, fb, 400, iq=1.0)
        finally:
            ep.close()
        assert terminate(proc) == 0, children.log("emulator")
    report, _ = read_run(run)
    levels = report["injections"]["X"]["levels_at_end"]
    assert levels == {f: t[FAULTS[f].level_key] for f, t in EVERY_FAULT.items()}
    kinds = [(e["kind"], e["reason"].split()[0]) for e in _events(run)
             if e["source"] == "inject" and e["kind"] != "request"]
    assert sorted(kinds) == sorted([(k, f) for f in FAULT_NAMES for k in ("injected",
                                                                            "reached")])
    replayed = replay_run(run)
    assert replayed.matches, replayed.line()
