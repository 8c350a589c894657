"""The emulator daemon (``hil run``): stop on a signal, the watchdog, bad input.

In-process tests step :class:`~hil.runtime.emulator.Emulator` tick by tick through an
in-memory endpoint, so the watchdog's timing is checked to the tick.  Process tests start
``python -m hil.runtime.emulator`` on the Arrow 500 X at 2 kHz (``runtime_helpers``) with the
test as the controller over UDP on 127.0.0.1; the references are the CiA 402 state machine's
table (statusword patterns, the fault-reset edge) and the emulator's own recording and
report.  No wall-clock duration is asserted; every wait is bounded; children are reaped.
"""

import socket
from collections import deque
from dataclasses import fields, replace

import numpy as np
import pytest

from hil.cia402 import (
    DISABLE_VOLTAGE,
    ENABLE_OPERATION,
    EnableSequencer,
    State,
    statusword_state,
)
from hil.runtime.emulator import Emulator, RuntimeConfig
from hil.runtime.watchdog import FAULT_WATCHDOG
from io_adapters import Endpoint, Feedback, Setpoint, open_endpoint
from plant import layout as L
from plant.config import load_machine
from tests.runtime_helpers import (
    SLOW_2KHZ,
    Children,
    enable,
    exchange,
    machine_variant,
    python_module,
    read_run,
    terminate,
)

WAIT_S = 5.0
LIMIT = 20          # watchdog cycles used below
IQ_A = 0.3          # current setpoint: above breakaway, small enough to stay in travel
START_MM = 250.0    # mid travel


@pytest.fixture(scope="module")
def slow_config(tmp_path_factory):
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


# -- in process: the watchdog to the tick --------------------------------------------------

class QueueEndpoint(Endpoint):
    """A device endpoint in memory: the test queues setpoints, the feedback sent is kept."""

    def __init__(self):
        super().__init__("device")
        self.inbox: deque[Setpoint] = deque()
        self.sent: list[Feedback] = []

    @classmethod
    def from_url(cls, url, role):
        raise NotImplementedError("in-memory test endpoint")

    def _write(self, record):
        self.sent.append(replace(record))
        return True

    def _read(self, into, timeout_s):
        if not self.inbox:
            return False
        sp = self.inbox.popleft()
        for f in fields(Setpoint):
            setattr(into, f.name, getattr(sp, f.name))
        self.stats.received += 1
        return True

    def _close(self):
        pass


class Master:
    """The controller side of the in-process tests: one setpoint per tick."""

    def __init__(self, emulator: Emulator, ep: QueueEndpoint):
        self.emu, self.ep, self.k = emulator, ep, 0
        self.seq = EnableSequencer(timeout_cycles=50)
        self.sp = Setpoint()

    def tick(self, send: bool = True, iq: float = 0.0) -> None:
        """Queue the next setpoint (unless ``send`` is False), then one emulator tick."""
        if send:
            last = self.ep.sent[-1].statusword if self.ep.sent else 0
            self.sp.seq += 1
            self.sp.controlword = self.seq.next_controlword(last)
            self.sp.iq_ref_a = iq
            self.ep.inbox.append(replace(self.sp))
        self.emu.step(self.k)
        self.k += 1

    def enable(self) -> None:
        self.seq.enable()
        for _ in range(50):
            self.tick()
            if self.seq.done:
                return
        raise AssertionError(f"not enabled: {self.seq.reason}")


@pytest.fixture
def stepped(slow_config, tmp_path):
    """An emulator stepped by hand with LIMIT watchdog cycles, its log lines, a master."""
    rc = RuntimeConfig(machine_file=slow_config, adapter_url="memory", run_dir=tmp_path,
                       duration_s=1.0, watchdog_cycles=LIMIT, realtime=False,
                       start_cnc=START_MM)
    lines = []
    emu = Emulator(rc, load_machine(slow_config), log=lines.append)
    ep = QueueEndpoint()
    emu.open(ep)
    return emu, ep, lines, Master(emu, ep)


def test_watchdog_trips_exactly_limit_ticks_after_the_last_setpoint(stepped):
    emu, ep, lines, master = stepped
    master.enable()
    for _ in range(5):
        master.tick(iq=IQ_A)
    last = master.k - 1
    answered = len(ep.sent)
    for _ in range(LIMIT - 1):
        master.tick(send=False)
        assert emu.plant.inp[L.I_ENABLE] == 1.0 and not emu.watchdog.tripped
    master.tick(send=False)  # tick last + LIMIT
    # 6007h = 1: a fault, 605Eh = 2: brake on the quick stop ramp with torque on, then FAULT
    assert emu.watchdog.tripped and emu.drive.fault == FAULT_WATCHDOG == 0x8250
    assert emu.drive.sm.state == State.FAULT_REACTION_ACTIVE
    assert len(ep.sent) - answered == LIMIT - 1, "feedback only while silent < limit"
    event = emu.watchdog.events[0]
    assert (event.kind, event.tick, event.silent_ticks) == ("tripped", last + LIMIT, LIMIT)
    assert len(lines) == 1 and f"no setpoint for {LIMIT} cycles" in lines[0]
    for _ in range(2000):
        master.tick(send=False)
        if emu.drive.sm.state == State.FAULT:
            break
    assert emu.drive.sm.state == State.FAULT and emu.plant.inp[L.I_ENABLE] == 0.0
    assert len(emu.watchdog.events) == 1


def test_after_a_trip_a_fault_reset_and_re_enable_resume_the_axis(stepped):
    emu, ep, _, master = stepped
    master.enable()
    for _ in range(LIMIT + 2):
        master.tick(send=False)
    for _ in range(2000):
        master.tick(send=False)
        if emu.drive.sm.state == State.FAULT:
            break
    master.tick(iq=IQ_A)  # the controller is back: the cause is gone, the fault stays
    fb = ep.sent[-1]
    assert statusword_state(fb.statusword) == State.FAULT and fb.fault == FAULT_WATCHDOG
    assert emu.watchdog.events[-1].kind == "recovered"
    master.tick(iq=IQ_A)
    assert master.seq.failed, "the sequencer saw the drive leave OPERATION ENABLED"
    master.enable()  # fault reset (bit 7 edge: 15), then 2, 3, 4
    assert emu.drive.sm.log.recent()[-4:] == (15, 2, 3, 4) and ep.sent[-1].fault == 0
    for _ in range(20):
        master.tick(iq=IQ_A)
    iq = np.mean([f.iq_a for f in ep.sent[-10:]])
    assert iq == pytest.approx(IQ_A, abs=0.05)


def test_a_silent_controller_with_the_drive_disabled_is_no_event(stepped):
    emu, _, lines, master = stepped
    master.tick()  # controlword 0: the drive stays disabled
    for _ in range(3 * LIMIT):
        master.tick(send=False)
    assert not emu.watchdog.events and not lines and emu.drive.fault == 0


def test_a_rate_below_the_pwm_frequency_runs_whole_pwm_periods_per_tick(slow_config, tmp_path):
    """At a quarter of the PWM rate every tick advances the plant four PWM periods."""
    cfg = load_machine(slow_config)
    rc = RuntimeConfig(machine_file=slow_config, adapter_url="memory", run_dir=tmp_path,
                       duration_s=0.01, rate_hz=cfg.motor.pwm_frequency_hz / 4, realtime=False)
    emu = Emulator(rc, cfg, log=lambda line: None)
    emu.open(QueueEndpoint())
    assert (emu.timing.cycles_per_tick, emu.timing.period_ns) == (4, 2_000_000)
    t0 = emu.plant.out[L.O_TIME]
    emu.step(0)
    assert emu.plant.out[L.O_TIME] - t0 == pytest.approx(4 / cfg.motor.pwm_frequency_hz, rel=1e-9)


# -- processes -------------------------------------------------------------------------------

def test_sigterm_stops_the_daemon_with_report_and_recording_complete(slow_config, tmp_path):
    run_dir = tmp_path / "run"
    with Children(tmp_path) as children:
        proc, url = children.emulator(slow_config, "udp://127.0.0.1:0", run_dir)
        with open_endpoint(url, "controller") as ep:  # the loop is running once it answers
            ep.send_setpoint(Setpoint())
            assert ep.recv_feedback(Feedback(), WAIT_S)
        assert terminate(proc) == 0, children.log("emulator")
    report, rec = read_run(run_dir)
    loop = report["loop"]
    assert loop["stopped_by"] == "stop_flag" and loop["skipped"] == 0 and loop["ticks"] > 0
    assert report["recording"]["rows"] == loop["ticks"]
    assert {len(v) for v in rec.values()} == {loop["ticks"]}
    assert report["safe_state"] == {"state": "SWITCH_ON_DISABLED", "statusword": "0x0250",
                                    "plant_enable": 0.0, "error_code": "0x0000",
                                    "cycle": loop["ticks"]}
    assert report["adapter"]["name"] == url and report["host"]["kernel_release"]


def test_watchdog_over_udp_torque_off_then_fault_reset_resumes(slow_config, tmp_path):
    run_dir = tmp_path / "run"
    sp, fb = Setpoint(), Feedback()
    with Children(tmp_path) as children:
        proc, url = children.emulator(slow_config, "udp://127.0.0.1:0", run_dir,
                                      "--watchdog-cycles", LIMIT, "--start", START_MM)
        with open_endpoint(url, "controller") as ep:
            ep.send_setpoint(sp)
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 40, seq, IQ_A)
            assert fb.iq_a == pytest.approx(IQ_A, abs=0.1)
            # silence: the drive answers what it heard, then stops.  Only answers to the
            # last setpoint count: answers to earlier ones may still be queued when this
            # process fell behind the drive's ticks on a loaded machine
            late = 0
            while ep.recv_feedback(fb, 0.5):
                late += fb.seq == sp.seq
                assert late <= LIMIT + 1, "the drive kept answering a silent controller"
            sp.controlword = ENABLE_OPERATION.value
            ep.send_setpoint(sp)  # back: the drive is in FAULT until reset
            exchange(ep, sp, fb, 1)
            assert statusword_state(fb.statusword) == State.FAULT
            seq = enable(ep, sp, fb)
            exchange(ep, sp, fb, 40, seq, IQ_A)
            assert fb.iq_a == pytest.approx(IQ_A, abs=0.1), "torque again after re-enable"
            sp.controlword = DISABLE_VOLTAGE.value
            exchange(ep, sp, fb, 3)
        assert terminate(proc) == 0
        log = children.log("emulator")
    assert f"watchdog: no setpoint for {LIMIT} cycles" in log
    report, rec = read_run(run_dir)
    tripped, recovered = report["watchdog"]["events"]
    assert (tripped["kind"], recovered["kind"]) == ("tripped", "recovered")
    # rows, not tick numbers: a stall of this process on a loaded machine drops deadlines
    # (hil.rt.loop), and the watchdog counts the ticks that ran
    assert report["recording"]["rows"] == report["loop"]["ticks"]  # every tick recorded
    k = int(np.searchsorted(rec["tick"], tripped["tick"]))
    heard = np.flatnonzero(rec["sp_new"][:k])
    assert k - heard[-1] == LIMIT, "tripped LIMIT ticks after the last setpoint"
    # the fault reaction (605Eh = 2) brakes with torque on, then FAULT takes it off
    assert rec["fb_fault"][k] == FAULT_WATCHDOG
    assert rec["drive_state"][k] == State.FAULT_REACTION_ACTIVE
    off = k + np.flatnonzero(rec["drive_enable"][k:] == 0)[0]
    assert rec["drive_state"][off] == State.FAULT
    assert rec["drive_state"][np.searchsorted(rec["tick"], recovered["tick"])] == State.FAULT


def test_bad_config_is_refused_before_the_adapter_opens(tmp_path):
    """Exit 2 naming the file, key and unit; the adapter's port (held here) is never
    tried, or the message would be about binding it."""
    bad = tmp_path / "bad.toml"
    machine_variant(bad, {"pwm_frequency_hz": "-5.0"})
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as held:
        held.bind(("127.0.0.1", 0))
        url = f"udp://127.0.0.1:{held.getsockname()[1]}"
        with Children(tmp_path) as children:
            proc = children.start("emulator", python_module(
                "hil.runtime.emulator", bad, "--adapter", url, "--record", tmp_path / "run"))
            assert proc.wait(timeout=60) == 2
            log = children.log("emulator")
    assert str(bad) in log and "pwm_frequency_hz" in log and "Hz" in log
    assert "bind" not in log and not (tmp_path / "run").exists()


def test_datagrams_from_another_sender_are_counted_and_the_run_goes_on(slow_config, tmp_path):
    """Junk from a socket other than the controller's (the pinned peer) is dropped as
    foreign whatever it holds; the controller's setpoints all arrive."""
    run_dir = tmp_path / "run"
    sp, fb = Setpoint(), Feedback()
    with Children(tmp_path) as children:
        proc, url = children.emulator(slow_config, "udp://127.0.0.1:0", run_dir)
        port = int(url.rsplit(":", 1)[1])
        with open_endpoint(url, "controller") as ep, \
                socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
            ep.send_setpoint(sp)
            exchange(ep, sp, fb, 10)
            for junk in (b"\x00", b"not msgpack \xff\xfe", b"\x95\x01\x01\x00\x00\x00"):
                raw.sendto(junk, ("127.0.0.1", port))
            exchange(ep, sp, fb, 10)
        assert terminate(proc) == 0
    report, rec = read_run(run_dir)
    stats = report["adapter"]["stats"]
    assert (stats["foreign"], stats["received"]) == (3, 21), "every good setpoint taken"
    assert report["loop"]["stopped_by"] == "stop_flag" and rec["sp_new"].sum() > 0


def test_a_controller_without_a_drive_names_the_drive_it_waited_for():
    """No emulator at the URL: the alignment gives up after its timeout and says which
    drive address it waited for (not only its own port)."""
    from hil.runtime.sync import DriveNotAnswering, align

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a port nobody serves
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with open_endpoint(f"udp://127.0.0.1:{port}", "controller") as ep:
        with pytest.raises(DriveNotAnswering, match=rf"drive 127\.0\.0\.1:{port}\b"):
            align(ep, Setpoint(), Feedback(), 125_000, 0.2)
