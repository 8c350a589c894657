"""Fuzz properties of the emulator's loop: :class:`hil.runtime.emulator.Emulator` on the
Arrow 500 X (configs/arrow500_x.toml at its 8 kHz, one PWM period per tick), stepped tick
by tick in this process behind a real UDP device endpoint on 127.0.0.1, with a real
controller endpoint sending a hypothesis-drawn sequence: the CiA 402 enable sequence and
valid setpoints, then stretches of bad ones (NaN, +-inf, +-1e308 in any field, mode 42 and
other modes the drive does not take, currents and voltages beyond its bounds), CST at the
current limit for long stretches, silence, and fault resets.

Properties, tick by tick:

* the plant state stays finite;
* the table stays within the stops plus the penetration of the stall force and of an
  arrival at ten times the standstill speed, [-overtravel - d, travel + overtravel + d],
  d = (F + v sqrt(k m)) / k (stops and stiffness k from the built
  plant, F = K_t I_max / ratio): over UDP a master cannot switch the drive's protection
  off, so the axis must be stopped before it hits a stop at speed;
* every refused setpoint, and every runaway (the true motor speed above 1.2 times 6080h,
  beyond the overspeed trip at 1.1, or the table beyond a limit switch moving outward while
  the drive is enabled) is followed, within the longest fault reaction (the braking
  timeout of hil.drive.reaction from the fastest speed), by a feedback reporting CiA 402
  FAULT (statusword_state) with a non-zero 603Fh;
* while the watchdog answers, the controller receives each tick's feedback, with the
  statusword and 603Fh the emulator wrote;
* the device's counters add up (AdapterStats' identity), every datagram the controller
  sent was counted, and each refusal counter holds the number of bad setpoints of its kind
  that were sent;

and at the end a fault reset followed by valid setpoints brings the drive back to
OPERATION ENABLED.
"""

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, Phase, event, example, given, settings
from hypothesis import strategies as st

from hil.cia402 import EnableSequencer, State, statusword_state
from hil.drive.braking import envelope, time_limit, top_speed
from hil.runtime.emulator import Emulator, RuntimeConfig
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_CSV, Feedback, Setpoint
from io_adapters.udp import UdpEndpoint
from plant import layout as L
from plant.config import load_machine
from tests.conftest import CONFIGS
from tests.runtime_helpers import end_stop_reach
from tests.test_adapters import assert_counts_add_up

ARROW = CONFIGS / "arrow500_x.toml"
WAIT_S = 5.0
WATCHDOG_TICKS = 40
#: ticks the recording holds; every example stays below
MAX_TICKS = 60000
#: a runaway: the true motor speed above this many times 6080h (the drive trips at
#: OVERSPEED_FACTOR), or the table beyond a limit switch moving out faster than this
#: many times the drive's standstill speed
RUNAWAY_SPEED_FACTOR = 1.2
RUNAWAY_STANDSTILL_FACTOR = 10.0
NONFINITE = (math.nan, math.inf, -math.inf)
FLOAT_FIELDS = ("target_position_counts", "target_velocity_counts_s",
                "velocity_offset_counts_s", "iq_ref_a", "id_ref_a", "ud_v", "uq_v")
#: (field, value) beyond the Arrow drive's bounds: 28 A, 600 V, 2**53 increments
BEYOND = (("iq_ref_a", 28.001), ("iq_ref_a", -1e6), ("id_ref_a", 29.0), ("uq_v", 600.5),
          ("ud_v", -1e9), ("target_velocity_counts_s", 2.0**54),
          ("target_position_counts", -2.0**60), ("velocity_offset_counts_s", 1e308),
          ("iq_ref_a", -1e308))
FOREIGN_MODES = (42, 0, -128, 127, 7, 11, 1, 6)

SEGMENTS = st.one_of(
    st.tuples(st.just("valid"), st.integers(1, 400),
              st.sampled_from((MODE_CST, MODE_CSV, MODE_CSP)), st.floats(-1.0, 1.0)),
    st.tuples(st.just("non-finite"), st.sampled_from(FLOAT_FIELDS), st.sampled_from(NONFINITE)),
    st.tuples(st.just("beyond"), st.sampled_from(BEYOND)),
    st.tuples(st.just("mode"), st.sampled_from(FOREIGN_MODES)),
    st.tuples(st.just("at the limit"), st.integers(200, 4000), st.sampled_from((1.0, -1.0))),
    st.tuples(st.just("silence"), st.integers(1, 3 * WATCHDOG_TICKS)),
    st.tuples(st.just("reset")))


@dataclass
class Sent:
    """What the controller sent: setpoints by kind, for the device's counters."""
    nonfinite: int = 0
    mode: int = 0
    beyond: int = 0


@dataclass
class Rig:
    """The emulator, its UDP device endpoint, a controller endpoint, and what the
    properties need from the built plant and drive."""
    emu: Emulator
    controller: UdpEndpoint
    seq: EnableSequencer = field(default_factory=lambda: EnableSequencer(timeout_cycles=20000))
    sp: Setpoint = field(default_factory=Setpoint)
    fb: Feedback = field(default_factory=Feedback)
    k: int = 0
    sent: Sent = field(default_factory=Sent)
    due: list = field(default_factory=list)  # (tick by which FAULT must show, what)

    def __post_init__(self):
        plant, drive = self.emu.plant, self.emu.drive
        stops = plant.built.end_stops
        p = drive.params
        self.runaway_speed = RUNAWAY_SPEED_FACTOR * p.max_speed
        self.moving_out = RUNAWAY_STANDSTILL_FACTOR * drive.monitor.standstill()
        # arriving no faster than a table may move out beyond a limit switch
        penetration = end_stop_reach(drive, self.moving_out)
        self.x_range = (stops.stop_neg - penetration, stops.stop_pos + penetration)
        still = drive.monitor.standstill()
        brake_s = max(time_limit(*envelope(p, option, top_speed(p.max_speed), still), still)
                      for option in (1, 2, 3))
        self.react_ticks = math.ceil(brake_s / plant.pwm_period) + WATCHDOG_TICKS

    def tick(self, send: bool = True, mode: int | None = None, **values) -> None:
        """One tick: the controller sends a setpoint (the sequencer's controlword, ``mode``
        and ``values``; the rest as last sent) unless ``send`` is False, the emulator
        steps, the properties are checked."""
        if send:
            self.sp.seq += 1
            self.sp.controlword = self.seq.next_controlword(self.fb.statusword)
            if mode is not None:
                self.sp.mode = mode
            for name, value in values.items():
                setattr(self.sp, name, value)
            assert self.controller.send_setpoint(self.sp)
        emu = self.emu
        emu.step(self.k)
        if emu.watchdog.answering:
            assert self.controller.recv_feedback(self.fb, WAIT_S), f"tick {self.k}: no feedback"
            assert (self.fb.seq, self.fb.statusword, self.fb.fault) == (
                emu.fb.seq, emu.fb.statusword, emu.fb.fault)
        self.check()
        self.k += 1
        assert self.k < MAX_TICKS

    def check(self) -> None:
        emu, k = self.emu, self.k
        out = emu.plant.out
        assert np.isfinite(emu.plant.state).all(), f"tick {k}: plant state not finite"
        x = out[L.O_TABLE_POS]
        assert self.x_range[0] <= x <= self.x_range[1], f"tick {k}: table at {x} m"
        if emu.endpoint.refused_axes:
            self.due.append((k + self.react_ticks, f"refusal at tick {k}"))
        w, v = out[L.O_MOTOR_VEL], out[L.O_TABLE_VEL]
        outward = (out[L.O_LIMIT_POS] > 0.0 and w > self.moving_out) or (
            out[L.O_LIMIT_NEG] > 0.0 and w < -self.moving_out)
        if emu.drive.sm.state == State.OPERATION_ENABLED and (
                abs(w) > self.runaway_speed or outward):
            what = f"runaway at tick {k}: {w} rad/s, table {x} m at {v} m/s"
            self.due.append((k + self.react_ticks, what))
        if statusword_state(emu.fb.statusword) == State.FAULT and emu.fb.fault != 0:
            self.due.clear()
        for deadline, what in self.due:
            assert k <= deadline, f"{what}: no FAULT with 603Fh by tick {deadline}"

    def enable(self) -> None:
        """Fault reset (if faulted) and enable with valid setpoints (CST, no current) until
        this tick's feedback says OPERATION ENABLED.  After silence the sequencer's first
        statusword is stale: when the fresh one contradicts it, it is asked again."""
        self.seq.enable()
        for _ in range(3 * self.react_ticks):
            self.tick(mode=MODE_CST, iq_ref_a=0.0)
            if self.seq.failed:
                self.seq.enable()
            elif self.seq.done and self.fb.seq == self.sp.seq and statusword_state(
                    self.fb.statusword) == State.OPERATION_ENABLED:
                return
        raise AssertionError(f"not enabled by tick {self.k}: {self.seq.reason}")

    def settle(self) -> None:
        """Valid setpoints holding the speed at zero (CSV) until every refusal and runaway
        has met its FAULT and no fault reaction is braking any more."""
        for _ in range(2 * self.react_ticks):
            if not self.due and self.emu.drive.sm.state != State.FAULT_REACTION_ACTIVE:
                return
            self.valid(1, MODE_CSV, 0.0)
        raise AssertionError(f"not settled by tick {self.k}: {self.due}")

    def valid(self, n: int, mode: int, share: float) -> None:
        """``n`` ticks of a valid setpoint: CST at ``share`` of 2 A, CSV at ``share`` of
        10 % of 6080h, CSP at the position actual plus ``share`` of 1 mm."""
        drive = self.emu.drive
        for _ in range(n):
            counts = self.emu.plant.out[L.O_ENCODER]
            if mode == MODE_CST:
                self.tick(mode=mode, iq_ref_a=2.0 * share)
            elif mode == MODE_CSV:
                self.tick(mode=mode, target_velocity_counts_s=0.1 * share
                          * drive.params.max_speed / drive.rad_per_count)
            else:
                self.tick(mode=mode, target_position_counts=counts + share * 1e-3 / (
                    self.emu.plant.built.ratio * drive.rad_per_count),
                    velocity_offset_counts_s=0.0)

    def segment(self, seg: tuple) -> None:
        kind = seg[0]
        if kind == "valid":
            self.valid(*seg[1:])
        elif kind == "non-finite":
            self.sent.nonfinite += 1
            self.tick(**{seg[1]: seg[2]})
            setattr(self.sp, seg[1], 0.0)
        elif kind == "beyond":
            name, value = seg[1]
            self.sent.beyond += 1
            self.tick(**{name: value})
            setattr(self.sp, name, 0.0)
        elif kind == "mode":
            mode, self.sp.mode = self.sp.mode, seg[1]
            self.sent.mode += 1
            self.tick()
            self.sp.mode = mode
        elif kind == "at the limit":
            limit = self.emu.plant.config.motor.current_max_a  # the bound itself: taken
            for _ in range(seg[1]):
                self.tick(mode=MODE_CST, iq_ref_a=seg[2] * limit)
            self.sp.iq_ref_a = 0.0
        elif kind == "silence":
            for _ in range(seg[1]):
                self.tick(send=False)
        else:
            self.enable()


@settings(max_examples=100, deadline=None, database=None,
          phases=(Phase.explicit, Phase.generate),
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
# the minimal runaway: CST at the peak current from 300 mm until the drive stops the axis
@example(start_mm=300.0, segments=[("at the limit", 4000, 1.0)])
@given(start_mm=st.floats(20.0, 490.0), segments=st.lists(SEGMENTS, min_size=1, max_size=6))
def test_the_loop_stays_physical_faults_on_every_refusal_and_recovers(tmp_path, start_mm,
                                                                     segments):
    cfg = load_machine(ARROW)
    rc = RuntimeConfig(machine_file=Path(ARROW), adapter_url="udp://127.0.0.1:0",
                       run_dir=tmp_path, duration_s=MAX_TICKS / cfg.motor.pwm_frequency_hz,
                       watchdog_cycles=WATCHDOG_TICKS, realtime=False, start_cnc=start_mm)
    emu = Emulator(rc, cfg, log=lambda line: None)
    device = UdpEndpoint("device", ("127.0.0.1", 0))
    emu.open(device)
    with device, UdpEndpoint("controller", device.address) as controller:
        rig = Rig(emu, controller)
        rig.enable()
        for seg in segments:
            rig.segment(seg)
        rig.settle()
        rig.enable()  # a fault reset and valid setpoints: back to OPERATION ENABLED
        rig.valid(10, MODE_CSV, 0.0)
        assert emu.drive.sm.state == State.OPERATION_ENABLED and rig.fb.fault == 0
        for e in emu.drive.faults.events:
            event(f"{e.kind} {e.code:04X}h")
        stats = device.stats
        assert_counts_add_up(stats, controller.stats.sent + stats.handshakes)
        assert (stats.refused_nonfinite, stats.refused_mode, stats.refused_range) == (
            rig.sent.nonfinite, rig.sent.mode, rig.sent.beyond)
        assert stats.received == controller.stats.sent - (
            rig.sent.nonfinite + rig.sent.mode + rig.sent.beyond)
