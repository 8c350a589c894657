"""A divergence at run time is a drive fault, never a silent current limit (issue 14 part 2's
last clause, checked here for the plant's side).

The loader chooses the sub-step for the dampers it is given (tests/test_plant_damping.py):
the issue's nut damping of 4e5 N*s/m on the Arrow 500 X builds with more sub-steps and runs
stable; ten times that needs more sub-steps than the plant takes and is refused.  Forced
past that refusal -- the damper written into the params of a plant built without it, a
run-time parameter change -- explicit Euler grows by |1 - dt c/m| > 1 per sub-step on the
axial screw nodes next to the nut, and the kernel reports STATUS_DIVERGED within a few PWM
periods (or STATUS_NONFINITE when the growth overflows within one call); the drive
(hil.drive.core, _step_plant) latches PLANT_DIVERGED (PLANT_NONFINITE), takes the torque off
and restarts the plant at rest.
"""

import math

import numpy as np
import pytest

from hil.drive import Cause
from hil.drive.faults import ERROR_CODE
from plant import Plant
from plant import layout as L
from plant.errors import ConfigError
from tests.test_drive_faults import ARROW, enabled

#: N*s/m, the issue's nut damping, and ten times it
HEAVY_NUT_DAMPING = 4e5
FORCED_NUT_DAMPING = 4e6
#: the kernel's fault statuses: a state beyond P_DIVERGE_LIMIT, or one that overflowed
FAULTS = (L.STATUS_DIVERGED, L.STATUS_NONFINITE)


def test_the_loader_carries_the_heavy_damper_with_more_substeps():
    base = Plant.from_file(ARROW, table_pos=0.25)
    heavy = Plant.from_file(ARROW, table_pos=0.25,
                            overrides={"screw": {"nut_damping_ns_per_m": HEAVY_NUT_DAMPING}})
    assert heavy.sub_per_pwm > base.sub_per_pwm
    heavy.set_input(iq_ref_a=5.0)
    tr = heavy.run(800, heavy.sub_per_pwm)
    assert tr["status"].max() == L.STATUS_OK and np.isfinite(tr["iq_a"]).all()


def test_ten_times_that_is_refused_at_load_time():
    with pytest.raises(ConfigError, match=r"\[screw\] nut_damping_ns_per_m = 4e\+06 N\*s/m"):
        Plant.from_file(ARROW, overrides={"screw": {"nut_damping_ns_per_m": FORCED_NUT_DAMPING}})


def test_forced_in_at_run_time_the_kernel_reports_the_divergence():
    plant = Plant.from_file(ARROW, table_pos=0.25)
    plant.set_input(iq_ref_a=5.0)
    assert plant.run(40, plant.sub_per_pwm)["status"].max() == L.STATUS_OK
    assert plant.dt * FORCED_NUT_DAMPING / plant.built.ax.m.max() > 2.0  # beyond Euler's reach
    plant.params[L.P_NUT_C] = FORCED_NUT_DAMPING
    statuses = [plant.step(plant.sub_per_pwm) for _ in range(5)]
    assert statuses[-1] in FAULTS  # runaway, or past the double range within one call
    assert set(statuses) <= {L.STATUS_OK, *FAULTS}


def test_the_drive_latches_the_plant_fault_and_takes_the_torque_off():
    """Not a current sitting at its limit: a fault with its code, torque off, the plant at
    rest where the table last was valid."""
    b = enabled()
    b.run(400, iq_ref_a=1.0)
    where = b.x
    b.plant.params[L.P_NUT_C] = FORCED_NUT_DAMPING
    n = b.run(10, until=lambda b: b.fb.fault)
    assert n <= 5
    assert b.fb.fault in (ERROR_CODE[Cause.PLANT_DIVERGED], ERROR_CODE[Cause.PLANT_NONFINITE])
    assert not b.torque_on
    assert all(math.isfinite(v) for v in b.plant.state)
    assert abs(b.x - where) < 1e-3
    b.run(10, iq_ref_a=1.0)
    assert not b.torque_on and b.plant.output("status") == L.STATUS_OK
