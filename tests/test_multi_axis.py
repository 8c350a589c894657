"""Machines of several axes: the manifest loader, wire version 2, multi-axis programs, the
lock-step simulation of a whole machine and the emulator stepping every axis.

References: the manifest's own text (names, files, overrides) and the rules of
:mod:`plant.machines`; the msgpack layout written out by hand from the codec's docstring;
the straight line and the limits themselves (every sample of every axis checked against
them, and the closed-form duration of a trapezoid); the single-axis planner and the
single-axis lock-step simulation, which a one-axis path and each axis of an uncoupled
machine must reproduce exactly.
"""

import math
from pathlib import Path

import msgpack
import numpy as np
import pytest

from hil.cia402 import State
from hil.commands import SETTLE_S
from hil.controller.config import AxisLimits
from hil.controller.interpolator import plan
from hil.controller.machine import MachineController
from hil.controller.path import (
    parse_path_program,
    path_limits,
    plan_path,
    read_path_program,
)
from hil.controller.program import ProgramError, parse_program
from hil.runtime.common import RuntimeInputError, StopFlag, check_link
from hil.runtime.controller_proc import (
    START_WINDOW_CNC,
    ControllerProcess,
    ControllerRunConfig,
)
from hil.runtime.emulator import Emulator, RuntimeConfig
from hil.runtime.recording import units
from hil.runtime.watchdog import FAULT_WATCHDOG
from hil.sim import LockStep, MachineLockStep
from io_adapters import FrameError, codec, codec_fixed
from io_adapters.messages import FeedbackGroup, Setpoint, SetpointGroup, message_pair
from io_adapters.serial_link import MAX_AXES, MAX_AXES_BY_WIRE, MAX_PAYLOAD
from io_adapters.udp import UdpEndpoint
from plant import layout as L
from plant.config import load_machine
from plant.errors import ConfigError
from plant.machines import load_machine_set
from tests.conftest import CONFIGS

XY = CONFIGS / "machines" / "arrow500_xy.toml"
ARROW = CONFIGS / "arrow500_x.toml"
GEISS = CONFIGS / "geiss_c_axis.toml"
#: the Arrow 500 X at 2 kHz (tests/runtime_helpers.SLOW_2KHZ) as manifest overrides
SLOW = {"motor": {"pwm_frequency_hz": 2000.0}, "current_loop": {"kp_v_per_a": 3.0},
        "controller": {"position_cycle_ratio": 4, "ipo_cycle_ratio": 8,
                       "speed_kp_nms_per_rad": 0.6}}


def _toml(value) -> str:
    return f'"{value}"' if isinstance(value, str) else repr(value)


def write_manifest(path: Path, axes: list[tuple[str, Path, dict]], machine: dict | None = None,
                   extra: str = "") -> Path:
    """A manifest with ``axes`` = [(name, file, {section: {key: value}})]."""
    machine = machine if machine is not None else {"name": "test machine", "source": "test"}
    lines = ["[machine]"] + [f"{k} = {_toml(v)}" for k, v in machine.items()]
    for name, file, overrides in axes:
        lines += ["[[axis]]", f'name = "{name}"', f'file = "{file}"']
        for sec, values in overrides.items():
            lines.append(f"[axis.overrides.{sec}]")
            lines += [f"{k} = {_toml(v)}" for k, v in values.items()]
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


@pytest.fixture(scope="module")
def slow_xy(tmp_path_factory) -> Path:
    """The Arrow 500 XY at 2 kHz: Y a copy of X with a 550 kg slide."""
    return write_manifest(tmp_path_factory.mktemp("cfg") / "xy.toml", [
        ("X", ARROW, SLOW), ("Y", ARROW, {**SLOW, "table": {"mass_kg": 550.0}})])


# -- manifests ---------------------------------------------------------------------------------

def test_the_xy_manifest_loads_two_named_axes_with_their_overrides():
    m = load_machine_set(XY)
    assert m.manifest and m.multi_axis and m.names == ("X", "Y")
    assert [c.table.mass_kg for c in m.configs] == [350.0, 550.0]
    assert m.configs[1].machine.name.startswith("Cincinnati Arrow 500 Y axis")
    assert m.pwm_frequency_hz == 8000.0


def test_a_single_machine_file_is_a_machine_of_one_axis():
    m = load_machine_set(ARROW)
    assert not m.manifest and m.names == ("X",) and m.configs[0].path == str(ARROW)
    assert load_machine_set(GEISS).names == ("C",)
    assert load_machine_set(ARROW, "Y").names == ("Y",)


@pytest.mark.parametrize("axes, machine, extra, message", [
    ([("X", ARROW, {}), ("X", ARROW, {})], None, "", "axis name 'X' given twice"),
    ([("C", ARROW, {})], None, "", "A, B and C are rotary"),
    ([("X", GEISS, {})], None, "", "kind = 'rotary'"),
    ([("Q", ARROW, {})], None, "", "must be one letter"),
    ([("X", ARROW, {}), ("Y", ARROW, {"motor": {"pwm_frequency_hz": 4000.0}})], None, "",
     "pwm_frequency_hz = 4000 Hz"),
    ([("X", ARROW, {"table": {"mass_kgs": 1.0}})], None, "", "axis X: "),
    ([("X", ARROW, {"table": {"mass_kg": -1.0}})], None, "", "mass_kg"),
    ([("X", Path("/nonexistent.toml"), {})], None, "", "no such machine file"),
    ([("X", ARROW, {})], {"name": "m"}, "", "'source' is missing"),
    ([("X", ARROW, {})], {"name": "m", "source": "s", "speed": 1}, "", "unknown key 'speed'"),
    ([("X", ARROW, {})], None, "[spindle]\nrpm = 1\n", "unknown key 'spindle'"),
])
def test_a_bad_manifest_is_refused_naming_file_axis_and_key(tmp_path, axes, machine, extra,
                                                            message):
    path = write_manifest(tmp_path / "m.toml", axes, machine, extra)
    with pytest.raises(ConfigError) as e:
        load_machine_set(path)
    assert message in str(e.value) and str(path) in str(e.value)


# -- wire version 2 ----------------------------------------------------------------------------

def test_group_messages_round_trip_every_axis_field():
    sp, fb = message_pair(3)
    sp.seq, sp.t_ns, sp.controlword = 7, 123, 0x0F
    for i, s in enumerate(sp.axes):
        s.mode, s.target_position_counts, s.iq_ref_a = 8, 1e6 * (i + 1), -0.5 * i
        s.seq, s.t_ns = 7, 123  # what decoding copies into every axis
    fb.seq, fb.time_s, fb.sp_t_ns, fb.sp_rx_ns, fb.t_ns, fb.tick_ns = 7, 0.25, 1, 2, 3, 4
    for i, f in enumerate(fb.axes):
        f.statusword, f.encoder_counts, f.fault, f.id_a = 0x237, 10.0 * i, i, math.nan
    sp2, fb2 = message_pair(3)
    codec.fill(sp2, codec.decode(codec.encode(sp, 1, 2), SetpointGroup, 3))
    codec.fill(fb2, codec.decode(codec.encode(fb, 1, 2), FeedbackGroup, 3))
    assert sp2 == sp
    for a, b in zip(fb.axes, fb2.axes):
        assert (b.statusword, b.encoder_counts, b.fault, b.seq, b.time_s) == (
            a.statusword, a.encoder_counts, a.fault, 7, 0.25) and math.isnan(b.id_a)
    assert (fb2.seq, fb2.time_s, fb2.sp_t_ns, fb2.sp_rx_ns, fb2.t_ns, fb2.tick_ns) == (
        7, 0.25, 1, 2, 3, 4)


def test_version_1_is_unchanged_and_the_versions_do_not_mix():
    """A plain Setpoint is still the documented version-1 array; a version-2 message is not
    taken for a plain record nor the reverse; a group of other size is refused."""
    sp = Setpoint(seq=3, controlword=6, mode=10, iq_ref_a=1.5, t_ns=9)
    wire = codec.encode(sp, 5, 4)
    assert msgpack.unpackb(wire) == [1, 1, 5, 4, 3, 6, 10, 0.0, 0.0, 0.0, 1.5, 0.0, 0.0,
                                     0.0, 9]
    out = Setpoint()
    codec.fill(out, codec.decode(wire, Setpoint))
    assert out == sp
    group = codec.encode(message_pair(2)[0], 5, 4)
    assert msgpack.unpackb(group)[:6] == [2, 1, 5, 4, 0, 0]
    with pytest.raises(FrameError, match="version 2, expected 1"):
        codec.decode(group, Setpoint)
    with pytest.raises(FrameError, match="version 1, expected 2"):
        codec.decode(wire, SetpointGroup, 2)
    with pytest.raises(FrameError, match="2 axes, expected 3"):
        codec.decode(group, SetpointGroup, 3)
    bad = msgpack.packb([2, 2, 0, 0, 0, 0.0, 0, 0, 0, 0, [[0, 0, 0.0, 0.0, 0.0, 0.0, "x"]]])
    with pytest.raises(FrameError, match=r"axes\[0\] id_a='x'"):
        codec.decode(bad, FeedbackGroup, 1)


def test_a_group_crosses_udp_and_a_wrong_axis_count_is_counted_as_malformed():
    with UdpEndpoint("device", ("127.0.0.1", 0)) as dev, \
            UdpEndpoint("controller", dev.address[:2]) as ctl:
        sp, _ = message_pair(2)
        sp.seq, sp.axes[1].target_position_counts = 11, 42.0
        ctl.send_setpoint(sp)
        got, fb = message_pair(2)
        assert dev.recv_setpoint(got, 1.0)
        assert got.seq == 11 and got.axes[1].target_position_counts == 42.0
        fb.axes[0].encoder_counts = 5.0
        dev.send_feedback(fb)
        back = message_pair(2)[1]
        assert ctl.recv_feedback(back, 1.0) and back.axes[0].encoder_counts == 5.0
        assert back.sp_t_ns == got.t_ns and back.round_trip_ns() > 0
        ctl.send_setpoint(message_pair(3)[0])
        assert not dev.recv_setpoint(got, 0.2) and dev.stats.malformed == 1


# -- multi-axis programs -----------------------------------------------------------------------

LIMITS = (AxisLimits(0.5, 2.0, 40.0), AxisLimits(0.25, 1.0, 10.0), AxisLimits(1.0, 3.0, 0.0))


def _samples(profiles, n=20001):
    t = np.linspace(0.0, profiles[0].duration_s, n)
    return t, [p.sample_array(t) for p in profiles]


def test_a_g1_block_moves_every_axis_on_the_line_within_its_own_limits():
    prog = parse_path_program("G1 X10 Y5 Z-20 F6000\nM30", "XYZ")
    profiles = plan_path(prog, LIMITS)
    assert len({p.duration_s for p in profiles}) == 1 and all(
        np.array_equal(p.knots_s, profiles[0].knots_s) for p in profiles)
    _, s = _samples(profiles)
    d = np.array([0.010, 0.005, -0.020])
    length = np.linalg.norm(d)
    path = s[0].pos / d[0] * length
    for i in range(3):  # on the straight line: x_i = d_i s / L for one s
        assert np.allclose(s[i].pos, d[i] / length * path, rtol=0, atol=1e-12)
    for i, lim in enumerate(LIMITS):
        assert np.abs(s[i].vel).max() <= lim.velocity * (1 + 1e-9)
        assert np.abs(s[i].acc).max() <= lim.acceleration * (1 + 1e-9)
        if lim.jerk:
            assert np.abs(profiles[i].jerk).max() <= lim.jerk * (1 + 1e-9)
    assert [p.sample(p.duration_s).pos for p in profiles] == pytest.approx(list(d), abs=1e-12)
    # the feed along the path: 6000 mm/min unless an axis's own limit is lower
    lim = path_limits(d / length, LIMITS)
    v_path = np.linalg.norm([x.vel for x in s], axis=0)
    assert v_path.max() == pytest.approx(min(0.1, lim.velocity), rel=1e-9)
    assert lim.velocity == pytest.approx(0.25 / (0.005 / length))  # Y limits the path


def test_a_trapezoid_path_takes_the_closed_form_time():
    """No jerk limit on the moving axes: t = L/v + v/a with the path's limits."""
    prog = parse_path_program("G1 Z30 F3000\nM30", "XYZ")
    (_, _, pz) = plan_path(prog, LIMITS)
    v, a = 0.05, 3.0
    assert pz.duration_s == pytest.approx(0.030 / v + v / a, rel=1e-12)


def test_a_one_axis_path_is_the_single_axis_plan_exactly():
    text = (CONFIGS.parent / "programs" / "demo_moves.nc").read_text()
    single = plan(parse_program(text), LIMITS[0])
    (path,) = plan_path(parse_path_program(text, "X"), LIMITS[:1])
    for name in ("knots_s", "pos0", "vel0", "acc0", "jerk"):
        assert np.array_equal(getattr(single, name), getattr(path, name)), name


def test_rapid_dwell_hold_and_rotary_feeds():
    prog = parse_path_program("G0 X200 Y200\nG4 F0.5\nG91 G1 Y-10 F600\nG1 C90 F3600\nM30",
                              ("X", "Y", "C"))
    rapid, dwell, hold, rot = prog.blocks
    assert rapid.rapid and rapid.target == pytest.approx((0.2, 0.2, 0.0))
    assert dwell.dwell_s == 0.5 and dwell.start == dwell.target
    assert hold.target == pytest.approx((0.2, 0.19, 0.0)) and hold.feed == pytest.approx(0.01)
    assert rot.feed == pytest.approx(math.radians(60.0))  # deg/min when only C moves
    px, py, pc = plan_path(prog, LIMITS)
    t, (sx, sy, _) = _samples((px, py, pc))
    in_rapid = t < px.knots_s[np.flatnonzero(px.vel0 == 0.0)[1]]
    # the rapid runs at Y's maximum velocity (Y limits it), X as fast on the diagonal
    assert np.abs(sy.vel[in_rapid]).max() == pytest.approx(0.25, rel=1e-9)
    assert np.array_equal(sx.vel[in_rapid], sy.vel[in_rapid])
    assert np.all(sx.vel[~in_rapid] == 0.0)  # X holds after the rapid


@pytest.mark.parametrize("text, message", [
    ("G1 X1 A5 F100", "this machine has the axes X, Y"),
    ("G1 X1 X2 F100", "appears twice"),
    ("G4 F1 X2", "G4 must stand in its own block"),
    ("X1 Y2", "without a motion mode"),
])
def test_bad_multi_axis_blocks_are_refused(text, message):
    with pytest.raises(ProgramError, match=message):
        parse_path_program(text, "XY")


# -- the whole machine in lock step and in the emulator ----------------------------------------

PROGRAM = "G1 X10 Y5 F6000\nG4 F0.05\nG0 X0 Y0\nM30"


def test_each_axis_of_a_machine_runs_as_that_axis_alone(slow_xy):
    """The axes are not coupled: axis i of the machine's lock-step simulation is the
    single-axis LockStep of axis i following its own profile, tick for tick."""
    m = load_machine_set(slow_xy)
    ms = MachineLockStep(m)
    ms.enable()
    profiles = ms.ctrl.plan(parse_path_program(PROGRAM, m.names))
    ms.ctrl.run_profiles(profiles)
    res = ms.run(profiles[0].duration_s + 0.05)
    for axis, profile in zip(m.axes, profiles):
        ls = LockStep(axis.config)
        ls.enable()
        ls.ctrl.run_profile(profile)
        ref = ls.run(profiles[0].duration_s + 0.05)
        for name in ("x_set", "x_act", "following_error", "iq_set", "table_pos"):
            assert np.array_equal(res[axis.name][name], ref[name]), (axis.name, name)
    assert res["X"]["x_set"].max() == pytest.approx(0.010)
    assert res["Y"]["x_set"].max() == pytest.approx(0.005)


def test_the_emulator_steps_every_axis_and_its_watchdog_faults_both(slow_xy, tmp_path):
    """In process over UDP: the machine's controller enables both drives through wire
    version 2; a silent controller then faults both (each its own CiA 402 FAULT)."""
    m = load_machine_set(slow_xy)
    rc = RuntimeConfig(machine_file=slow_xy, adapter_url="udp://127.0.0.1:0", run_dir=tmp_path,
                       duration_s=1.0, watchdog_cycles=10, realtime=False,
                       start_cnc={"X": 100.0, "Y": 50.0})
    emu = Emulator(rc, m, log=lambda line: None)
    url = emu.open()
    assert [p.output("table_pos") for p in emu.plants] == pytest.approx([0.1, 0.05])
    ctrl = MachineController(m, emu.plant.pwm_period, (0.1, 0.05))
    sp, fb = message_pair(2)
    with UdpEndpoint.from_url(url, "controller") as ep:
        k = 0
        while not ctrl.enabled and k < 200:
            ctrl.tick(fb, sp)
            ep.send_setpoint(sp)
            emu.step(k)
            emu.recorder.end_tick(k, 0, 0)  # as the loop does after each step
            assert ep.recv_feedback(fb, 1.0)
            k += 1
        assert ctrl.enabled and [d.sm.state for d in emu.drives.drives] == [
            State.OPERATION_ENABLED] * 2
        assert fb.seq == sp.seq and all(f.seq == sp.seq for f in fb.axes)
        for j in range(30):  # 10 silent ticks trip it; the axes at rest stop braking at once
            emu.step(k + j)
            emu.recorder.end_tick(k + j, 0, 0)
    assert [d.fault for d in emu.drives.drives] == [FAULT_WATCHDOG] * 2
    assert [d.sm.state for d in emu.drives.drives] == [State.FAULT] * 2
    assert all(p.inp[L.I_ENABLE] == 0.0 for p in emu.plants)
    assert emu.watchdog.n_events == 1
    cols = emu.recorder.columns(0, emu.recorder.committed)
    assert cols["tick"].tolist() == list(range(k + 30))
    assert set(cols) == set(units(("screw", "screw"), ("X", "Y")))
    assert cols["Y_drive_enable"][k - 1] == 1 and cols["Y_drive_enable"][-1] == 0
    assert cols["X_plant_table_pos"][0] == pytest.approx(0.1, abs=1e-6)


def test_the_controller_refuses_axis_letters_with_a_manifest_and_start_of_unknown_axes(
        slow_xy, tmp_path):
    prog = tmp_path / "p.nc"
    prog.write_text(PROGRAM)
    base = {"machine_file": slow_xy, "adapter_url": "udp://127.0.0.1:1", "program_file": prog}
    with pytest.raises(RuntimeInputError, match="--axis"):
        ControllerProcess(ControllerRunConfig(**base, axis="X"), StopFlag())
    with pytest.raises(RuntimeInputError, match="--start names axes Z"):
        ControllerProcess(ControllerRunConfig(**base, start_cnc={"Z": 1.0}), StopFlag())


@pytest.mark.parametrize("url, n_axes, refused", [
    ("can://virtual/x?node=1&rated_current_ma=28000&axes=3", 2, "axes=3, but the machine"),
    ("can://virtual/x?node=1&rated_current_ma=28000&axes=2", 1, "axes=2, but the machine"),
    ("can://virtual/x?node=1&rated_current_ma=28000", 2, None),
    ("can://virtual/x?node=1&rated_current_ma=28000", 1, None),
    ("serial:///dev/null", 4, "3 axes per message at most"),
    ("serial:///dev/null", 3, None),
    ("serial:///dev/null?wire=fixed", 3, "2 axes per message at most on the fixed wire"),
    ("serial:///dev/null?baud=9600&wire=fixed", 2, None),
    ("udp://127.0.0.1:0", 9, None),
])
def test_links_that_cannot_carry_the_axes_are_refused_before_start(url, n_axes, refused):
    if refused is None:
        check_link(url, n_axes)
    else:
        with pytest.raises(RuntimeInputError, match=refused):
            check_link(url, n_axes)


def test_serial_frames_hold_max_axes_at_their_widest():
    """serial_link.MAX_AXES against the codec: every integer at its widest, the group of
    MAX_AXES fits a 255-byte frame and one axis more does not."""
    def widest(n):
        sp, fb = message_pair(n)
        sp.seq, sp.t_ns, fb.seq = 2**32 - 1, 2**63 - 1, 2**32 - 1
        fb.sp_t_ns = fb.sp_rx_ns = fb.t_ns = fb.tick_ns = 2**63 - 1
        for s, f in zip(sp.axes, fb.axes):
            s.controlword, s.mode = 0xFFFF, -128
            f.statusword, f.fault = 0xFFFF, -2**31
        return max(len(codec.encode(m, 2**32 - 1, 2**32 - 1)) for m in (sp, fb))

    assert widest(MAX_AXES) <= MAX_PAYLOAD < widest(MAX_AXES + 1)


def test_serial_frames_hold_the_fixed_wires_max_axes():
    """MAX_AXES_BY_WIRE's fixed entry against the fixed codec's own bytes: the feedback of
    2 axes (192 bytes) fits a 255-byte frame, of 3 (256) does not; the setpoint is
    shorter."""
    most = MAX_AXES_BY_WIRE["fixed"]
    sizes = [max(len(codec_fixed.encode(m, 1, 1)) for m in message_pair(n))
             for n in (most, most + 1)]
    assert (most, sizes) == (2, [192, 256])
    assert sizes[0] <= MAX_PAYLOAD < sizes[1]


# -- the five-axis machine of seed 001 ----------------------------------------------------------

GEISS_5 = CONFIGS / "machines" / "geiss_5axis.toml"
FIVE_AXIS_PROGRAM = CONFIGS.parent / "programs" / "geiss_5axis_moves.nc"


def test_the_geiss_manifest_loads_five_axes_at_one_pwm_frequency():
    """The manifest's own text: five letters, the overrides it states, C the seed-001 file
    unchanged but for its [controller], one PWM frequency without any override."""
    m = load_machine_set(GEISS_5)
    assert m.names == ("X", "Y", "Z", "B", "C")
    assert [c.machine.kind for c in m.configs] == ["screw"] * 3 + ["rotary"] * 2
    assert [c.table.mass_kg for c in m.configs[:3]] == [350.0, 550.0, 250.0]
    geiss = load_machine(GEISS)
    assert [c.mechanics.load_inertia_kgm2 for c in m.configs[3:]] == [
        6.0, geiss.mechanics.load_inertia_kgm2]
    c = m.configs[4]
    for sec in ("machine", "motor", "current_loop", "field_weakening", "cogging", "mechanics",
                "friction", "sensors"):
        assert getattr(c, sec) == getattr(geiss, sec), sec
    assert {cfg.motor.pwm_frequency_hz for cfg in m.configs} == {8000.0}
    assert len(MachineController(m, 1 / m.pwm_frequency_hz)) == 5  # every [controller] checks


def test_the_machine_lockstep_steps_all_five_axes_through_the_program():
    """programs/geiss_5axis_moves.nc on the five-axis machine: every axis's setpoint
    reaches the program's positions, block N30 keeps all five on its straight line (the
    program's geometry: B and C follow the linear path in the same time), block N40 moves C
    alone, and every plant follows its setpoint and is home after the settling time
    (SINUMERIK exact stop coarse, MD36000: 0.04 mm or deg)."""
    m = load_machine_set(GEISS_5)
    ls = MachineLockStep(m)
    ls.enable()
    profiles = ls.ctrl.plan(read_path_program(FIVE_AXIS_PROGRAM, m.names))
    ls.ctrl.run_profiles(profiles)
    res = ls.run(profiles[0].duration_s + SETTLE_S)
    cnc = {a.name: 180.0 / math.pi if a.rotary else 1e3 for a in m.axes}
    x = {n: res[n]["x_set"] * cnc[n] for n in m.names}
    assert {n: (x[n].min(), x[n].max()) for n in m.names} == {
        "X": (0.0, pytest.approx(20.0)), "Y": (0.0, pytest.approx(5.0)),
        "Z": (0.0, pytest.approx(4.0)), "B": (0.0, pytest.approx(5.0)),
        "C": (0.0, pytest.approx(60.0))}
    n30_end = np.argmax(x["C"] >= 30.0 - 1e-9)  # the IPO points straddle the block ends
    n30 = np.flatnonzero(x["X"][:n30_end] > 10.0 + 1e-6)
    assert n30.size > 100
    u = (x["X"][n30] - 10.0) / 10.0
    for name, start, end in (("Y", 5.0, 0.0), ("Z", 4.0, 0.0), ("B", 0.0, 5.0),
                             ("C", 0.0, 30.0)):
        assert x[name][n30] == pytest.approx(start + (end - start) * u, abs=1e-9), name
    n40_end = np.argmax(x["C"] >= 60.0 - 1e-9)
    n40 = n30_end + np.flatnonzero(x["C"][n30_end:n40_end] > 30.01)
    assert n40.size > 100
    for name, held in (("X", 20.0), ("Y", 0.0), ("Z", 0.0), ("B", 5.0)):
        assert x[name][n40] == pytest.approx(held, abs=1e-9), name
    for name in m.names:
        act = res[name]["x_act"] * cnc[name]
        assert np.ptp(act) > 0.9 * np.ptp(x[name]), name    # the plant moved with its setpoint
        assert abs(act[-1]) <= START_WINDOW_CNC, name   # and came home
