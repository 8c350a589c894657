"""Seed 002's stiffness test of the LD386: a 225 N force suddenly applied to the table in
steady-state position control (§5.1, Fig. 7), the largest position error it causes.

No machine-file value was set from Fig. 7: the LD386's gains follow stated rules (K_v the
MD32200 default, the speed PI a symmetric optimum on the current loop) and its masses are
assumed, so the row is a prediction.
"""

from pathlib import Path

import numpy as np

from hil.controller.interpolator import ProfileSamples
from hil.sim import LockStep, SimResult
from hil.validate import plots
from hil.validate.core import PREDICTION, Result, SeedRef, experiment, within
from hil.validate.experiments.moves import CURRENT_LOOP_ZEROS_S, LD386
from plant.config import MachineConfig, load_machine

PAPER_FORCE_N = 225.0  # seed 002 §5.1
PAPER_ERROR_M = 1.5e-3  # seed 002 §5.1 Fig. 7: "approximately 1.5mm"
PAPER_ERROR_PM_M = 0.1e-3  # "approximately": one unit of the last printed digit
HOLD_X0 = 0.75  # m, assumed: mid travel
SETTLE_S = 0.3  # s of standstill before the force
AFTER_S = 0.6  # s recorded after it
ERROR_SOURCE = SeedRef("002", "§5.1, Fig. 7", 6, "A maximum position error of approximately "
                       "1.5mm can be seen in the response of the linear motor")


def disturbance_run(cfg: MachineConfig) -> SimResult:
    """Hold ``HOLD_X0`` in position control, then apply the 225 N table force; the
    recording after the force (time from the start of the hold)."""
    ls = LockStep(cfg, HOLD_X0)
    ls.enable()
    hold = np.full(2, HOLD_X0)
    zero = np.zeros(2)
    ls.ctrl.run_points(ProfileSamples(np.array([0.0, ls.ctrl.ipo_period_s]), hold, zero, zero))
    ls.run(SETTLE_S)
    ls.plant.set_input(load=PAPER_FORCE_N)
    return ls.run(AFTER_S)


def largest_error(sim: SimResult) -> float:
    """m: the largest |x_act - x0| of a :func:`disturbance_run`."""
    return float(np.abs(sim["x_act"] - HOLD_X0).max())


@experiment("seed002_disturbance", "002")
def seed002_disturbance(out_dir: Path | None) -> list[Result]:
    """The LD386 under a 225 N step force at standstill: its largest position error against
    seed 002's ~1.5 mm, as configured and with the current loop read as 1350/(s+1380)."""
    as_is = disturbance_run(load_machine(LD386))
    fast = disturbance_run(load_machine(LD386, overrides={
        "current_loop": {"time_constant_s": CURRENT_LOOP_ZEROS_S}}))
    error, error_fast = largest_error(as_is), largest_error(fast)
    agrees = within(error, PAPER_ERROR_M, abs_=PAPER_ERROR_PM_M)
    row = Result("linear motor: largest position error under a 225 N step force",
                 PAPER_ERROR_M * 1e3, error * 1e3, "mm", agrees,
                 'seed 002 §5.1: "approximately 1.5mm" (test bed)',
                 f"±{PAPER_ERROR_PM_M * 1e3:g} mm ('approximately')", PREDICTION,
                 ERROR_SOURCE, ("" if agrees else
                                f"disagrees: the model yields {error / PAPER_ERROR_M:.1f} "
                                "times the paper's error: its assumed gains are softer than "
                                "the test bed's (the paper prints none); with the current "
                                f"loop read as 1350/(s+1380) it is {error_fast * 1e3:.1f} mm.  ")
                 + "Not tuned to it: ld386_linear.toml sets K_v to the MD32200 default, the "
                 "speed PI by the symmetric optimum on the current loop and assumes the masses; "
                 "no value comes from Fig. 7", PAPER_ERROR_PM_M * 1e3)
    if out_dir is not None:
        fig, ax = plots.new_figure(1, 1, "LD386: 225 N step force at standstill "
                                   "(seed 002 §5.1, Fig. 7)")
        for sim, label in ((as_is, "model"), (fast, "model, current loop 1350/(s+1380)")):
            ax[0, 0].plot(sim["t_s"], (sim["x_act"] - HOLD_X0) * 1e3, label=label)
        ax[0, 0].axhline(PAPER_ERROR_M * 1e3, color="r", ls="--", label="paper: ~1.5 mm")
        ax[0, 0].set(xlabel="time (s)", ylabel="position error (mm)")
        ax[0, 0].legend(fontsize=8)
        plots.save(fig, out_dir, "seed002_disturbance")
    return [row]
