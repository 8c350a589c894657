"""Programmed moves of the seed machines: seed 003's trapezoid at 6000 mm/min on the TLM
test rig and seed 002's 1 m move of the LD386 linear motor."""

from pathlib import Path

import numpy as np

from hil.controller.config import axis_limits, kv_si, load_controller
from hil.controller.interpolator import plan
from hil.controller.program import read_program
from hil.measure.runs import position_step
from hil.sim import LockStep, SimResult
from hil.validate import plots
from hil.validate.core import CONFIGS, PROGRAMS, Result, experiment, within
from plant.config import MachineConfig, load_machine

TLM_RIG = CONFIGS / "tlm_rig.toml"
LD386 = CONFIGS / "ld386_linear.toml"
TRAPEZOID = PROGRAMS / "seed003_trapezoid.nc"
MM_MIN = 60000.0  # (mm/min) per (m/s)

# --- seed 003: trapezoid on the TLM rig ------------------------------------------------

PAPER_FEED_MM_MIN = 6000.0  # seed 003 §5
PAPER_POSITION_CYCLE_S = 0.003  # seed 003 eq. 5
PAPER_SPEED_CYCLE_S = 0.0006  # seed 003 §3
PAPER_VELOCITY_ERROR_MM_MIN = 10.0  # seed 003 §5 Fig. 8: simulated vs measured, mean
TRAPEZOID_X0 = 0.05  # m, the program's start point (its G0 X50 is then empty)
NO_FF = {"controller": {"speed_ff": False, "torque_ff": False}}
SETTLE_S = 0.2
CRUISE_SETTLE_S = 0.5  # s skipped at the start of the constant phase: 8 / K_v, the
                       # following error has settled to 3e-4 of its change


def run_program(cfg: MachineConfig, program: Path, x0: float) -> SimResult:
    """Plan ``program`` (axis X) with the machine's limits and run it in lock-step from
    table position ``x0`` (m), plus SETTLE_S."""
    limits = axis_limits(cfg, load_controller(cfg))
    profile = plan(read_program(program, axis="X", start=x0), limits)
    ls = LockStep(cfg, x0)
    ls.enable()
    ls.ctrl.run_profile(profile)
    return ls.run(profile.duration_s + SETTLE_S)


def run_trapezoid(overrides: dict | None = None) -> SimResult:
    """programs/seed003_trapezoid.nc on the TLM rig (``overrides`` as for load_machine)."""
    return run_program(load_machine(TLM_RIG, overrides=overrides), TRAPEZOID, TRAPEZOID_X0)


def cruise(res: SimResult, feed: float, sign: float) -> np.ndarray:
    """Mask of the constant-velocity phase: the ticks where the interpolator commands
    ``sign`` * ``feed`` (m/s), from CRUISE_SETTLE_S after it first does."""
    at_feed = np.abs(res["v_set"] - sign * feed) <= 1e-9 * feed
    start = res["t_s"][np.argmax(at_feed)] + CRUISE_SETTLE_S
    return at_feed & (res["t_s"] >= start)


def table_velocity(res: SimResult) -> np.ndarray:
    """True table velocity (m/s) per tick: backward difference of the table position."""
    return np.concatenate([[0.0], np.diff(res["table_pos"]) / res.period_s])


def _cycle_rows(cfg: MachineConfig) -> list[Result]:
    sec, period = load_controller(cfg), 1.0 / cfg.motor.pwm_frequency_hz
    return [
        Result("TLM rig: position-control cycle", PAPER_POSITION_CYCLE_S * 1e3,
               sec.position_cycle_ratio * period * 1e3, "ms",
               within(sec.position_cycle_ratio * period, PAPER_POSITION_CYCLE_S, rel=1e-9),
               "seed 003 eq. 5 (Delta t = 3 ms)", "exact (whole PWM periods)"),
        Result("TLM rig: speed-control cycle", PAPER_SPEED_CYCLE_S * 1e3,
               sec.speed_cycle_ratio * period * 1e3, "ms",
               within(sec.speed_cycle_ratio * period, PAPER_SPEED_CYCLE_S, rel=1e-9),
               "seed 003 §3 (0.6 ms)", "exact (whole PWM periods)"),
    ]


def _direction_rows(cfg, ff: SimResult, no_ff: SimResult, sign: float) -> list[Result]:
    """Rows of one constant-velocity phase (``sign`` +1 out, -1 back)."""
    feed = PAPER_FEED_MM_MIN / MM_MIN
    on, off = cruise(ff, feed, sign), cruise(no_ff, feed, sign)
    v_mean = float(ff["v_act"][on].mean() * MM_MIN)
    v_err = float(np.abs(ff["v_set"] - table_velocity(ff))[on].mean() * MM_MIN)
    fe_ff = float(ff["following_error"][on].mean())
    fe_off = float(no_ff["following_error"][off].mean())
    fe_kv = sign * feed / kv_si(load_controller(cfg))
    res_m = cfg.sensors.scale_resolution_m
    d = f"{sign * PAPER_FEED_MM_MIN:+g} mm/min"
    return [
        Result(f"trapezoid {d}: mean velocity, constant phase", sign * PAPER_FEED_MM_MIN,
               v_mean, "mm/min", within(v_mean, sign * PAPER_FEED_MM_MIN, rel=0.01),
               "seed 003 §5 (programmed F6000)", "±1 %"),
        Result(f"trapezoid {d}: following error, feed-forward", 0.0, fe_ff * 1e6, "µm",
               within(fe_ff, 0.0, abs_=res_m),
               "K_v e + v_ff = v with unit feed-forward weight and no symmetrising delay "
               "(seed 003 eq. 5)", f"±1 scale count ({res_m * 1e6:g} µm)"),
        Result(f"trapezoid {d}: following error, no feed-forward", fe_kv * 1e3, fe_off * 1e3,
               "mm", within(fe_off, fe_kv, rel=1e-3), "v / K_v (P position loop)", "±0.1 %"),
        Result(f"trapezoid {d}: mean abs(v_set - v_table), constant phase",
               PAPER_VELOCITY_ERROR_MM_MIN, v_err, "mm/min", v_err <= 0.01 * PAPER_FEED_MM_MIN,
               "model only: seed 003 Fig. 8's ~10 mm/min is simulated vs measured nut "
               "velocity, not comparable; constant phase from 0.5 s after reaching the feed",
               "<= 1 % of the feed"),
    ]


@experiment("seed003_trapezoid", "003")
def seed003_trapezoid(out_dir: Path | None) -> list[Result]:
    """programs/seed003_trapezoid.nc (400 mm out and back at 6000 mm/min) on the TLM rig,
    with the feed-forward of seed 003 eq. 5-8 and without it."""
    ff, no_ff = run_trapezoid(), run_trapezoid(NO_FF)
    cfg = load_machine(TLM_RIG)
    rows = _cycle_rows(cfg)
    for sign in (1.0, -1.0):
        rows += _direction_rows(cfg, ff, no_ff, sign)
    _plot_trapezoid(ff, no_ff, out_dir)
    return rows


def _plot_trapezoid(ff: SimResult, no_ff: SimResult, out_dir: Path | None) -> None:
    fig, ax = plots.new_figure(3, 1, "Trapezoid at 6000 mm/min, TLM rig\n"
                               "(seed 003 §5, Fig. 8)")
    t = ff["t_s"]
    v_tab = table_velocity(ff)
    ax[0, 0].plot(t, ff["v_set"] * MM_MIN, label="interpolator v_set")
    ax[0, 0].plot(t[1:], v_tab[1:] * MM_MIN, "--", label="table (true)")
    ax[0, 0].set(ylabel="velocity (mm/min)")
    ax[1, 0].plot(t, (ff["v_set"] - ff["v_act"]) * MM_MIN, lw=0.4, alpha=0.6,
                  label="v_set - v_act (controller's speed, motor encoder)")
    ax[1, 0].plot(t[1:], (ff["v_set"] - v_tab)[1:] * MM_MIN, label="v_set - v_table (true)")
    ax[1, 0].axhline(PAPER_VELOCITY_ERROR_MM_MIN, color="r", ls=":",
                     label="seed 003 Fig. 8: ~10 mm/min (sim vs measured)")
    ax[1, 0].set(ylabel="velocity error (mm/min)", ylim=(-600, 600))
    ax[2, 0].plot(t, ff["following_error"] * 1e3, label="feed-forward (eq. 5-8)")
    ax[2, 0].plot(no_ff["t_s"], no_ff["following_error"] * 1e3, label="no feed-forward")
    ax[2, 0].set(xlabel="time (s)", ylabel="following error (mm)")
    for a in ax[:, 0]:
        a.legend(fontsize=7)
    plots.save(fig, out_dir, "seed003_trapezoid")


# --- seed 002: 1 m move of the linear motor --------------------------------------------

PAPER_MOVE_M = 1.0  # seed 002 §4: step of 1 m
PAPER_MOVE_TIME_S = 0.65  # seed 002 §4 Fig. 5: "approximately .65s" (printed without the 0)
PAPER_PEAK_VELOCITY = 2.5  # m/s, seed 002 §4: the velocity limit, peak 2.5 m/s
LD386_X0 = 0.25  # m, assumed: room for 1 m in the 1.5 m travel
ARRIVAL_M = 0.001  # "reached": within 1 mm of the target


def time_to_target(t: np.ndarray, x: np.ndarray, target: float, band: float) -> float:
    """First time (s) after which |x - target| stays within ``band`` (m)."""
    outside = np.flatnonzero(np.abs(x - target) > band)
    return float(t[outside[-1] + 1]) if outside.size else float(t[0])


@experiment("seed002_linear_move", "002")
def seed002_linear_move(out_dir: Path | None) -> list[Result]:
    """A 1 m position step into the P position loop with the 2.5 m/s velocity limit (seed
    002 Fig. 4: no interpolator), on the LD386 linear motor."""
    cfg = load_machine(LD386)
    res = position_step(cfg, LD386_X0, PAPER_MOVE_M, duration_s=1.2)
    target = LD386_X0 + PAPER_MOVE_M
    t_arr = time_to_target(res.t_s, res.response, target, ARRIVAL_M)
    v_peak = float(res.sim["v_act"].max())
    rows = [
        Result("linear motor 1 m step: time to within 1 mm", PAPER_MOVE_TIME_S, t_arr, "s",
               within(t_arr, PAPER_MOVE_TIME_S, rel=0.15),
               "seed 002 §4 Fig. 5 (simulated; Fig. 6 measured alike)", "±15 %"),
        Result("linear motor 1 m step: peak velocity", PAPER_PEAK_VELOCITY, v_peak, "m/s",
               within(v_peak, PAPER_PEAK_VELOCITY, rel=0.1),
               "seed 002 §4 (velocity limit); the 7.2 ms current loop carries the speed past "
               "the limit", "±10 %"),
    ]
    fig, ax = plots.new_figure(1, 2, "LD386: 1 m step at a 2.5 m/s velocity limit "
                               "(seed 002 §4, Fig. 5/6)")
    ax[0, 0].plot(res.t_s, res.response - LD386_X0, label="model")
    ax[0, 0].axvline(PAPER_MOVE_TIME_S, color="r", ls="--", label="paper: ~0.65 s")
    ax[0, 0].plot(t_arr, res.response[np.searchsorted(res.t_s, t_arr)] - LD386_X0, "ko",
                  mfc="none", label=f"model: within 1 mm at {t_arr:.3f} s")
    ax[0, 0].set(xlabel="time (s)", ylabel="distance (m)")
    ax[0, 1].plot(res.t_s, res.sim["v_act"], label="model: encoder velocity")
    ax[0, 1].plot(res.t_s, res.sim["v_cmd"], ":", label="speed command (limited)")
    ax[0, 1].axhline(PAPER_PEAK_VELOCITY, color="r", ls="--", label="paper: peak 2.5 m/s")
    ax[0, 1].set(xlabel="time (s)", ylabel="velocity (m/s)")
    for a in ax[0]:
        a.legend(fontsize=8)
    plots.save(fig, out_dir, "seed002_linear_move")
    return rows
