"""The lock-step simulation on the drives' compiled steady-state path (``hil.sim``, the
default) against the same run with every drive cycle in Python (``compiled=False``), the
reference the compiled path was written to equal: every recorded signal bit for bit, on
one axis with a fault injected halfway and on the two-axis Arrow 500 XY, and the compiled
path ran most of the cycles (a run that never took it would compare Python with Python)."""

import numpy as np

from hil.controller.config import axis_limits, load_controller
from hil.controller.interpolator import plan
from hil.controller.path import parse_path_program
from hil.controller.program import parse_program
from hil.sim import LockStep, MachineLockStep
from plant.config import load_machine
from plant.machines import load_machine_set
from tests.conftest import ROOT

ARROW = ROOT / "configs" / "arrow500_x.toml"
ARROW_XY = ROOT / "configs" / "machines" / "arrow500_xy.toml"


def _single(compiled: bool):
    cfg = load_machine(ARROW)
    profile = plan(parse_program("G1 X252 F3000\nG1 X250.5 F1500", start=0.25),
                   axis_limits(cfg, load_controller(cfg)))
    ls = LockStep(cfg, 0.25, compiled=compiled,
                  inject=["friction_growth:growth_pct=100,at_s=0.15"])
    ls.enable()
    ls.ctrl.run_profile(profile)
    return ls, ls.run(0.3)


def test_one_axis_with_a_fault_is_the_python_drive_bit_for_bit():
    ls, fast = _single(True)
    _, ref = _single(False)
    for name, signal in ref.signals.items():
        assert np.array_equal(fast[name], signal, equal_nan=True), name
    assert ls.drive.compiled.cycles > 0.8 * fast["t_s"].size
    assert ls.injectors[0].events[0].kind == "injected"


def _xy(compiled: bool):
    m = load_machine_set(ARROW_XY)
    ms = MachineLockStep(m, (0.25, 0.25), compiled=compiled)
    ms.enable()
    ms.ctrl.run_profiles(ms.ctrl.plan(parse_path_program(
        "G90 G01 X252 Y251 F3000\nM30\n", m.names)))
    return ms, ms.run(0.2)


def test_two_axes_are_the_python_drives_bit_for_bit():
    ms, fast = _xy(True)
    _, ref = _xy(False)
    for axis, res in ref.items():
        for name, signal in res.signals.items():
            assert np.array_equal(fast[axis][name], signal, equal_nan=True), (axis, name)
    for drive in ms.drives.drives:
        assert drive.compiled.cycles > 0.8 * fast["X"]["t_s"].size
