"""The lock-step simulation compiled (``hil.sim``, the default: the NC's and the drives'
compiled steady-state paths, :mod:`hil.controller.compiled_path` and
:mod:`hil.drive.compiled_path`, in compiled blocks, :mod:`hil.sim_block`) against the same
run with every tick in Python (``compiled=False``), the reference the compiled paths were
written to equal: every recorded signal bit for bit, and the alarms, on each shipped
machine file and program, each ``[controller]`` convention, a plant fed by voltage,
alarms with their stop reactions, a drive fault, fault injections and a feedback delay
(the compiled tick without the blocks).  Each run also checks that the compiled paths
ran most of the ticks it should (a run that never took them would compare Python with
Python)."""

import math

import numpy as np
import pytest

from hil.controller.compiled import MONITORING
from hil.controller.config import axis_limits, clamp_codes, load_controller
from hil.controller.interpolator import plan
from hil.controller.path import parse_path_program, read_path_program
from hil.controller.program import parse_program
from hil.sim import SIGNALS, LockStep, MachineLockStep
from io_adapters.messages import axis_records
from plant.config import load_machine
from plant.machines import load_machine_set
from tests.conftest import CONFIGS, ROOT

ARROW = CONFIGS / "arrow500_x.toml"
ARROW_XY = CONFIGS / "machines" / "arrow500_xy.toml"
PROGRAMS = ROOT / "programs"
#: every shipped program on its machine (as tests/test_nc_monitoring.py runs them)
SHIPPED = [("arrow500_x.toml", "demo_moves.nc"), ("arrow500_x.toml", "seed000_moves.nc"),
           ("tlm_rig.toml", "seed003_trapezoid.nc"),
           ("machines/arrow500_xy.toml", "xy_moves.nc"),
           ("machines/geiss_5axis.toml", "geiss_5axis_moves.nc")]
MOVES = "G1 X252 F3000\nG1 X250.5 F1500"
#: each [controller] convention away from the Arrow 500 X's own value, and the NC's
#: current loop (the plant fed by voltage, tests/test_voltage_plant.py's gains)
CONVENTIONS = {
    "feedforward_interpolation": {"feedforward_interpolation": "linear"},
    "speed_actual_filter_s": {"speed_actual_filter_s": 0.0008},
    "speed_antiwindup=torque_setpoint": {"speed_antiwindup": "torque_setpoint"},
    "speed_antiwindup=clamp": {"speed_antiwindup": "clamp"},
    "speed_antiwindup=none": {"speed_antiwindup": "none"},
    "current_delay_cycles": {"current_delay_cycles": 2},
    "filters_and_torque_ff": {"torque_ff": True, "speed_setpoint_lowpass_hz": 800.0,
                              "current_setpoint_lowpass_hz": 1500.0, "notch_hz": 600.0,
                              "notch_bandwidth_hz": 200.0, "notch_depth_db": -20.0,
                              "speed_kd_nms2_per_rad": 1e-4},
    "plant_input=voltage": {"plant_input": "voltage", "current_kp_v_per_a": 7.2,
                            "current_ti_s": 0.0125},
}


def assert_same(fast: dict, ref: dict) -> None:
    """Every signal of every axis bit for bit (NaN where NaN)."""
    for axis, res in ref.items():
        assert set(res.signals) == set(SIGNALS)
        for name, signal in res.signals.items():
            assert np.array_equal(fast[axis][name], signal, equal_nan=True), (axis, name)
        assert fast[axis].alarms == res.alarms, axis


def single(cfg, program: str, x0: float, seconds: float, compiled: bool, **kwargs):
    """A lock-step session on ``program`` (text) from ``x0``, ``seconds`` recorded."""
    sec = load_controller(cfg)
    profile = plan(parse_program(program, start=x0, clamp=clamp_codes(sec)),
                   axis_limits(cfg, sec))
    ls = LockStep(cfg, x0, compiled=compiled, **kwargs)
    ls.enable()
    ls.ctrl.run_profile(profile)
    return ls, {"X": ls.run(seconds)}


#: the feedback's fields the drive writes every cycle, and the setpoint's the NC writes
FEEDBACK = ("seq", "statusword", "time_s", "encoder_counts", "scale_counts",
            "velocity_counts_s", "iq_a", "id_a", "fault")
SETPOINT = ("seq", "controlword", "mode", "iq_ref_a", "id_ref_a", "ud_v", "uq_v")


def messages(ls) -> list:
    """The last setpoint and feedback of every axis, and the messages' seq and time."""
    return ([[getattr(s, n) for n in SETPOINT] for s in axis_records(ls.sp)]
            + [[getattr(f, n) for n in FEEDBACK] for f in axis_records(ls.fb)]
            + [ls.sp.seq, ls.fb.seq, ls.fb.time_s])


def both(run, *args, **kwargs):
    """``run(..., compiled)`` compiled and in Python: the compiled session and both
    results (axis -> SimResult); the last messages the same too."""
    ls, fast = run(*args, compiled=True, **kwargs)
    py, ref = run(*args, compiled=False, **kwargs)
    assert_same(fast, ref)
    assert messages(ls) == messages(py)
    return ls, fast


def shipped(machine: str, program: str, compiled: bool, seconds: float = 0.25):
    m = load_machine_set(CONFIGS / machine)
    ls = MachineLockStep(m, compiled=compiled)
    ls.enable()
    ls.ctrl.run_profiles(ls.ctrl.plan(read_path_program(PROGRAMS / program, m.names,
                                                        clamp=ls.ctrl.clamp_codes)))
    return ls, ls.run(seconds)


@pytest.mark.parametrize("machine, program", SHIPPED)
def test_every_shipped_program_is_the_python_nc_bit_for_bit(machine, program):
    """The first 0.25 s of each shipped program on its machine (one, two and five axes):
    every tick in one compiled block."""
    ls, fast = both(shipped, machine, program)
    n = fast[ls.machine.names[0]]["t_s"].size
    assert ls.blocks.ticks == n
    assert all(c.compiled.cycles == n for c in ls.ctrl.ctrls)


@pytest.mark.parametrize("over", CONVENTIONS.values(), ids=CONVENTIONS.keys())
def test_every_convention_is_the_python_nc_bit_for_bit(over):
    """The Arrow 500 X on two moves with each convention (0.25 s)."""
    ls, fast = both(single, load_machine(ARROW, {"controller": over}), MOVES, 0.25, 0.25)
    assert ls.blocks.ticks >= fast["X"]["t_s"].size - 1  # voltage: the drive's mode change


def test_a_runaway_axis_its_alarm_and_its_stop_are_the_python_nc_bit_for_bit():
    """The position feedback reversed (MD32110 = -1): alarm 25050 after a few position
    cycles, the braking at the current limit and the drive disabled, as in Python."""
    cfg = load_machine(ARROW, {"controller": {"encoder_feedback_polarity": -1}})
    ls, fast = both(single, cfg, MOVES, 0.25, 0.15)
    assert [a.number for a in fast["X"].alarms] == [25050] and ls.ctrl.stopped
    assert ls.ctrl.compiled.exits == {25050: 1} and ls.blocks.stops[2] == 1  # NC_DECLINED


def push(ls, force_n: float, seconds: float, rest_s: float):
    ls.run(rest_s)
    ls.plant.set_input(load=force_n)
    first = ls.run(seconds)
    ls.plant.set_input(load=0.0)
    return first, ls.run(0.1)


def clamped(force_n: float, program: str, rest_s: float, compiled: bool):
    ls, _ = single(load_machine(ARROW), program, 0.25, 0.0, compiled)
    first, then = push(ls, force_n, 0.01, rest_s)
    return ls, {"X": first, "Y": then}


@pytest.mark.parametrize("force_n, program, rest_s, alarm", [
    (25000.0, "G1 X250.2 F600\nM10\nG4 F2", 0.3, 26000),
    (20000.0, "G1 X250.2 F600\nG4 F2", 0.65, 25040)])
def test_clamping_and_standstill_monitoring_are_the_python_nc_bit_for_bit(force_n, program,
                                                                          rest_s, alarm):
    """A push on the axis at rest (tests/test_nc_monitoring.py's): clamped by M10 (a clamp
    block: the compiled tick hands it to Python) 0.66 mm, beyond MD36050 (26000); not
    clamped 0.43 mm after MD36040, beyond MD36030 (25040)."""
    ls, fast = both(clamped, force_n, program, rest_s)
    assert [a.number for a in fast["X"].alarms] == [alarm] and alarm in MONITORING
    assert ls.ctrl.compiled.exits[alarm] == 1


def drive_fault(compiled: bool):
    cfg = load_machine(ARROW, {"table": {"external_force_n": -20000.0},
                               "drive": {"overload_time_s": 0.1}})
    return single(cfg, "G4 F1", 0.25, 0.3, compiled)


def test_a_drive_fault_and_its_alarm_are_the_python_nc_bit_for_bit():
    """The drive's I2t trips holding 20 kN (overload time 0.1 s: at about 0.16 s) in a
    compiled block: its cycle is handed to Python mid-tick, the NC raises 25201 on the
    next one, as in Python."""
    ls, fast = both(drive_fault)
    assert [a.number for a in fast["X"].alarms] == [25201]
    assert ls.blocks.stops[3] == 1 and ls.drive.compiled.exits[3] == 1  # DRIVE_DECLINED, cause


def non_finite(compiled: bool):
    ls, first = single(load_machine(ARROW), "G1 X260 F6000", 0.25, 0.05, compiled)
    names = ("t", "x_set", "x_act", "v_act", "w_act", "w_set", "iq_set", "tick_count")
    ticks = []
    for _ in range(50):
        ls.fb.scale_counts = math.nan
        ls.tick()
        ticks.append([getattr(ls.ctrl, name) for name in names])
    return ls, {"X": first["X"], "ticks": np.array(ticks), "Z": ls.run(0.1)}


def test_a_non_finite_feedback_value_is_the_python_nc_bit_for_bit():
    """A NaN scale count every tick for 50 ticks from the middle of a move: the compiled
    tick hands each to Python (alarm 25000, the drive disabled at once), then the
    follow-up."""
    ls, fast = non_finite(True)
    _, ref = non_finite(False)
    assert np.array_equal(fast.pop("ticks"), ref.pop("ticks"), equal_nan=True)
    assert_same(fast, ref)
    assert [a.number for a in fast["Z"].alarms] == [25000]
    assert ls.ctrl.compiled.exits == {1: 1}  # EXIT_FEEDBACK, then no steady tick


def xy(compiled: bool, **kwargs):
    m = load_machine_set(ARROW_XY)
    ms = MachineLockStep(m, (0.25, 0.25), compiled=compiled, **kwargs)
    ms.enable()
    ms.ctrl.run_profiles(ms.ctrl.plan(parse_path_program(
        "G90 G01 X252 Y251 F3000\nM30\n", m.names)))
    return ms, ms.run(0.2)


def test_two_axes_with_a_fault_injected_on_one_are_the_python_nc_bit_for_bit():
    """Friction on Y grows by 300 % over 50 ms from 0.1 s (hil.inject): the blocks stop
    where the ramp starts, its ticks run one by one, the blocks resume after it."""
    ms, fast = both(xy, inject=["Y/friction_growth:growth_pct=300,at_s=0.1,ramp_s=0.05"])
    n = fast["X"]["t_s"].size
    assert ms.injectors[1].events[0].kind == "injected"
    assert ms.blocks.stops[1] == 1 and 0.6 * n < ms.blocks.ticks < 0.9 * n  # EVENT


def test_a_feedback_delay_runs_the_compiled_tick_without_blocks_bit_for_bit():
    """With a feedback delay (CANopen's one tick) no block runs, but every tick's NC and
    drives are still compiled."""
    ms, fast = both(xy, feedback_delay_ticks=1)
    n = fast["X"]["t_s"].size
    assert ms.blocks.ticks == 0
    for c, d in zip(ms.ctrl.ctrls, ms.drives.drives):
        assert c.compiled.cycles > 0.9 * n and d.compiled.cycles > 0.9 * n
