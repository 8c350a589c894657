"""Seed 000's validation of the Arrow 500 X loops with the controller's own measuring
functions: current steps and current-loop bandwidth, velocity steps, the 0.5 mm
position step, and the speed loop's frequency response."""

import math
from pathlib import Path

import numpy as np
import scipy.signal

from hil.controller.config import kv_si, load_controller
from hil.measure.frequency_response import bandwidth_hz, peaks
from hil.measure.runs import bode, current_step, position_step, speed_step
from hil.validate import plots
from hil.validate.core import CONFIGS, Result, experiment, within
from hil.validate.experiments.electrical import (
    STEP_FRACTIONS,
    analytic_current_step,
    rise_and_overshoot,
)
from plant.assemble import natural_frequencies, reflected_inertia, transmission_ratio
from plant.config import MachineConfig, load_machine

ARROW = CONFIGS / "arrow500_x.toml"
MM_MIN = 60000.0  # (mm/min) per (m/s)
ARROW_X0 = 0.25  # m, seed 000 §5: steps from 250 mm, the nut at mid travel

# --- seed 000: current loop ------------------------------------------------------------

PAPER_CURRENT_BW_HZ = 800.0  # seed 000 §5: model and measurement agree up to 800 Hz
CURRENT_PRBS_A = 1.0  # assumed: PRBS amplitude, 3.6 % of I_max, zero offset


def _current_step_rows(cfg: MachineConfig, i_ref: float, frac: float, res) -> list[Result]:
    """Final value, rise time and overshoot of one current step (``res``: StepResponse)."""
    post = res.t_s >= 0.0
    t, true = res.t_s[post], res.sim["iq_true"][post]
    rise, over = rise_and_overshoot(t, true, i_ref)
    f_pwm = cfg.motor.pwm_frequency_hz
    ref = analytic_current_step(cfg, i_ref, round(t[-1] * f_pwm))
    tr_a, os_a = rise_and_overshoot(np.arange(ref.size) / f_pwm, ref, i_ref)
    label = f"current step {i_ref:g} A ({frac:.0%} I_max)"
    analytic = "analytic discrete loop, locked rotor (electrical.py)"
    return [
        Result(f"{label}: final measured current", i_ref, res.final, "A",
               within(res.final, i_ref, rel=0.02), "setpoint", "±2 %"),
        Result(f"{label}: rise time 10-90 %", tr_a * 1e6, rise * 1e6, "us",
               within(rise, tr_a, rel=0.05), f"{analytic}; seed 000 §5 gives no number",
               "±5 %"),
        Result(f"{label}: overshoot", "slight", over, "%", 0.0 < over <= 10.0,
               f"seed 000 §5 (text); {analytic}: {os_a:.2f} %", "'slight': > 0 and <= 10 %"),
    ]


@experiment("seed000_current_steps", "000")
def seed000_current_steps(out_dir: Path | None) -> list[Result]:
    """The controller's current-loop measurement on the Arrow 500 X axis: q-current steps of
    3 % and 10 % of I_max (free rotor, speed loop off) and the PRBS frequency response."""
    cfg = load_machine(ARROW)
    rows: list[Result] = []
    fig, ax = plots.new_figure(1, 3, "Current loop, controller's measuring function "
                               "(seed 000 §5)")
    for col, (i_ref, frac) in enumerate(STEP_FRACTIONS.items()):
        res = current_step(cfg, i_ref, x0=ARROW_X0)
        rows += _current_step_rows(cfg, i_ref, frac, res)
        ref = analytic_current_step(cfg, i_ref, 24)
        a = ax[0, col]
        a.step(res.t_s * 1e3, res.response, where="post", label="measured i_q (drive)")
        a.plot(res.t_s * 1e3, res.sim["iq_true"], label="true i_q")
        a.plot(np.arange(ref.size) * 1e3 / cfg.motor.pwm_frequency_hz, ref, "k--",
               label="analytic, locked rotor")
        a.plot(res.t_s * 1e3, res.setpoint, ":", label="setpoint")
        a.set(xlabel="time from the step (ms)", ylabel="i_q (A)",
              title=f"step {i_ref:g} A ({frac:.0%} of I_max)")
        a.legend(fontsize=7)
    fr = bode(cfg, "current", CURRENT_PRBS_A, order=10, x0=ARROW_X0).response
    bw = bandwidth_hz(fr)
    rows.append(Result("current loop: -3 dB bandwidth (PRBS, 1 A)", PAPER_CURRENT_BW_HZ,
                       bw if bw is not None else "none", "Hz",
                       bw is None or bw >= PAPER_CURRENT_BW_HZ,
                       "seed 000 §5: model matches the measured response up to 800 Hz",
                       ">= 800 Hz"))
    a = ax[0, 2]
    a.semilogx(fr.freq_hz, fr.magnitude_db, label="model (PRBS, H1)")
    a.axvline(PAPER_CURRENT_BW_HZ, ls=":", color="k", label="800 Hz (seed 000 §5)")
    a.axhline(-3.0, ls="--", color="grey", lw=0.8)
    a.set(xlabel="frequency (Hz)", ylabel="|i_q / i_q,set| (dB)", ylim=(-20, 6),
          title=f"closed current loop, -3 dB at {bw:.0f} Hz" if bw else "closed current loop")
    a.legend(fontsize=7)
    plots.save(fig, out_dir, "seed000_current_steps")
    return rows


# --- seed 000: speed loop --------------------------------------------------------------

PAPER_PEAK_S = 0.004  # seed 000 §5: "the peak at approximately 4 ms"
PEAK_WINDOW_S = (0.002, 0.006)
SPEED_STEPS_MM_MIN = (200.0, 500.0)  # seed 000 §5
PEAK_PROMINENCE = 0.05  # a peak must stand 5 % of the step above its surroundings
FINAL_FROM_S = 0.04  # s, the final velocity is the mean from here to 0.12 s: a whole
                     # period of the 6th cogging harmonic at 500 mm/min (67 ms)


def first_peak(t: np.ndarray, v: np.ndarray, step: float) -> tuple[float, float]:
    """(time s, value) of the first local maximum of ``v`` after t = 0 that stands at least
    5 % of ``step`` above the minima around it (encoder ripple is far smaller)."""
    post = t >= 0.0
    index, _ = scipy.signal.find_peaks(v[post], prominence=PEAK_PROMINENCE * step)
    if index.size == 0:
        return math.nan, math.nan
    return float(t[post][index[0]]), float(v[post][index[0]])


@experiment("seed000_velocity_steps", "000")
def seed000_velocity_steps(out_dir: Path | None) -> list[Result]:
    """Speed-loop steps of 200 and 500 mm/min at 250 mm (position loop off), table velocity
    from the motor encoder as the drive's trace shows it."""
    cfg = load_machine(ARROW)
    rows: list[Result] = []
    fig, ax = plots.new_figure(1, 2, "Speed-loop steps at 250 mm (seed 000 §5, Fig. 9)")
    for a, step_mm_min in zip(ax[0], SPEED_STEPS_MM_MIN):
        res = speed_step(cfg, step_mm_min / MM_MIN, duration_s=0.12, x0=ARROW_X0)
        v = res.response * MM_MIN
        final = float(v[res.t_s >= FINAL_FROM_S].mean())
        t_pk, v_pk = first_peak(res.t_s, v, step_mm_min)
        t_max = float(res.t_s[int(np.argmax(v))])
        label = f"speed step {step_mm_min:g} mm/min"
        rows += [
            Result(f"{label}: final velocity (mean 40-120 ms)", step_mm_min, final, "mm/min",
                   within(final, step_mm_min, rel=0.02), "setpoint", "±2 %"),
            Result(f"{label}: time of the first velocity peak", PAPER_PEAK_S * 1e3,
                   t_pk * 1e3, "ms", PEAK_WINDOW_S[0] <= t_pk <= PEAK_WINDOW_S[1],
                   "seed 000 §5 ('peak at approximately 4 ms', read as static friction); "
                   "model: first local maximum, a ripple of the elastic drive train (gone "
                   "with a 10x stiffer coupling; the breakaway force does not move it); the "
                   f"highest peak, the loop's overshoot ({res.overshoot_pct:.0f} %), is at "
                   f"{t_max * 1e3:.1f} ms", "2..6 ms"),
        ]
        a.plot(res.t_s * 1e3, v, label="model: velocity from the motor encoder")
        a.plot(res.t_s * 1e3, res.setpoint * MM_MIN, "k:", label="setpoint")
        a.plot(t_pk * 1e3, v_pk, "ro", mfc="none", label="model: first peak")
        a.axvline(PAPER_PEAK_S * 1e3, color="r", ls="--", lw=0.8, label="paper: peak ~4 ms")
        a.set(xlabel="time from the step (ms)", ylabel="table velocity (mm/min)",
              title=f"{label}: rise {res.rise_time_s * 1e3:.1f} ms, overshoot "
              f"{res.overshoot_pct:.0f} %")
        a.legend(fontsize=7)
    plots.save(fig, out_dir, "seed000_velocity_steps")
    return rows


# --- seed 000: position loop -----------------------------------------------------------

POSITION_STEP_M = 0.0005  # seed 000 §5: 0.5 mm from 250 mm


def position_loop_polynomials(cfg: MachineConfig) -> tuple[np.ndarray, np.ndarray]:
    """(numerator, denominator) in s of x / x_set for the P position loop (K_v, 1/s) around
    the PI speed loop (K_p, T_n) on the rigid reflected inertia J, continuous time, no
    current loop, sampling or elasticity:  K_v K_p (s + 1/T_n) /
    (s (J s^2 + K_p s + K_p/T_n) + K_v K_p (s + 1/T_n)), in motor and table units alike
    (the lead cancels); the symmetrising lag is left out."""
    sec = load_controller(cfg)
    kv, kp, tn = kv_si(sec), sec.speed_kp_nms_per_rad, sec.speed_tn_s
    num = kv * kp * np.array([1.0, 1.0 / tn])
    den = np.polyadd(np.polymul([1.0, 0.0], [reflected_inertia(cfg), kp, kp / tn]), num)
    return num, den


def position_loop_reference(cfg: MachineConfig) -> scipy.signal.lti:
    """x / x_set of :func:`position_loop_polynomials` behind the symmetrising lag
    1 / (T_e s + 1) (MD32810) that the position loop puts on its setpoint when feed-forward
    is on."""
    sec = load_controller(cfg)
    num, den = position_loop_polynomials(cfg)
    t_sym = sec.speedctrl_equiv_time_s if sec.speed_ff else 0.0
    return scipy.signal.lti(num, np.polymul(den, [t_sym, 1.0]))


def _rise_overshoot(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(10-90 % rise time s, overshoot %) of a unit step response sampled densely."""
    return float(t[np.argmax(y >= 0.9)] - t[np.argmax(y >= 0.1)]), float(100 * (y.max() - 1))


@experiment("seed000_position_step", "000")
def seed000_position_step(out_dir: Path | None) -> list[Result]:
    """A 0.5 mm position step from 250 mm past the interpolator, linear-scale feedback."""
    cfg = load_machine(ARROW)
    res = position_step(cfg, ARROW_X0, POSITION_STEP_M, duration_s=0.3)
    target = ARROW_X0 + POSITION_STEP_M
    resolution = cfg.sensors.scale_resolution_m
    t_ref = np.linspace(0.0, 0.3, 30001)
    _, y_ref = scipy.signal.step(position_loop_reference(cfg), T=t_ref)
    rise_ref, over_ref = _rise_overshoot(t_ref, y_ref)
    linear = ("linear analysis: K_v around the PI speed loop on the rigid inertia "
              "(scipy.signal)")
    rows = [
        Result("position step 0.5 mm: final position", target * 1e3, res.final * 1e3, "mm",
               within(res.final, target, abs_=resolution), "step target",
               f"±1 scale count ({resolution * 1e6:g} µm)"),
        Result("position step 0.5 mm: rise time 10-90 %", rise_ref * 1e3,
               res.rise_time_s * 1e3, "ms", within(res.rise_time_s, rise_ref, rel=0.1),
               f"{linear}; seed 000 §5 gives no number", "±10 %"),
        Result("position step 0.5 mm: overshoot", "measured: overshoot; simulated: undershoot",
               res.overshoot_pct, "%", res.overshoot_pct <= max(over_ref, 0.0) + 1.0,
               f"seed 000 §5 Fig. 10 (text, second-order-like); {linear}: {over_ref:.2f} %",
               "<= linear analysis + 1 %-point"),
    ]
    fig, ax = plots.new_figure(1, 1, "Position step 0.5 mm from 250 mm\n(seed 000 §5, Fig. 10)")
    a = ax[0, 0]
    t_step = res.t_s[np.argmax(res.setpoint > ARROW_X0 + 0.5 * POSITION_STEP_M)]
    a.plot(res.t_s * 1e3, res.response * 1e3, label="model: linear scale")
    a.plot((t_ref + t_step) * 1e3, (ARROW_X0 + POSITION_STEP_M * y_ref) * 1e3, "k--",
           label="linear analysis")
    a.plot(res.t_s * 1e3, res.setpoint * 1e3, ":", label="setpoint")
    a.set(xlabel="time from the step (ms)", ylabel="table position (mm)",
          title=f"rise {res.rise_time_s * 1e3:.1f} ms, overshoot {res.overshoot_pct:.2f} %")
    a.legend(fontsize=8)
    plots.save(fig, out_dir, "seed000_position_step")
    return rows


# --- seed 000: speed-loop frequency response -------------------------------------------

PAPER_RESONANCE_HZ = 400.0  # seed 000 §5: the first resonance peak of the speed loop
SPEED_PRBS_OFFSET_MM_MIN = 1000.0  # assumed: keeps the axis moving one way (v > 0)
SPEED_PRBS_AMPLITUDE_MM_MIN = 250.0  # assumed: a quarter of the offset
MODE_BAND_HZ = 1000.0  # modes and peaks below this are compared (coherent, not noise)


def _prbs_rows(cfg: MachineConfig, m) -> list[Result]:
    """The PRBS run kept the current below I_max and the axis moving one way."""
    run = m.sim["t_s"] >= 0.05  # the offset has settled, the PRBS runs
    i_peak = float(np.abs(m.sim["iq_set"][run]).max())
    v_min = float(m.sim["v_act"][run].min() * MM_MIN)
    i_max = cfg.motor.current_max_a
    return [
        Result("speed PRBS: peak current setpoint", i_max, i_peak, "A", i_peak < i_max,
               "drive current limit I_max", "< I_max"),
        Result("speed PRBS: lowest table velocity", "> 0", v_min, "mm/min", v_min > 0.0,
               "one direction of motion (no friction reversal)", "> 0"),
    ]


def _mode_rows(fr, modes_hz: np.ndarray) -> list[Result]:
    """Each linearised mode below MODE_BAND_HZ against the nearest closed-loop peak."""
    found = np.array([p.freq_hz for p in peaks(fr) if p.freq_hz < MODE_BAND_HZ])
    rows = []
    for f in modes_hz:
        near = float(found[np.argmin(np.abs(found - f))]) if found.size else math.nan
        note = ("; seed 000 §5 reports no peak below ~400 Hz: this mode (table on the axial "
                "chain, assumed mass and stiffnesses) is not in the paper's measurement"
                if f < 0.5 * PAPER_RESONANCE_HZ else "")
        rows.append(Result(f"speed loop: resonance peak near the {f:.0f} Hz mode", f, near,
                           "Hz", within(near, f, rel=0.1),
                           f"linearised mechanics, natural_frequencies at mid run{note}",
                           "±10 %"))
    return rows


@experiment("seed000_speed_loop_bode", "000")
def seed000_speed_loop_bode(out_dir: Path | None) -> list[Result]:
    """Speed-loop frequency response with a PRBS of ±250 mm/min on 1000 mm/min from 250 mm:
    bandwidth, resonance peaks, the linearised plant's modes."""
    cfg = load_machine(ARROW)
    ratio = transmission_ratio(cfg)
    m = bode(cfg, "speed", SPEED_PRBS_AMPLITUDE_MM_MIN / MM_MIN / ratio,
             SPEED_PRBS_OFFSET_MM_MIN / MM_MIN / ratio, order=12, x0=ARROW_X0)
    fr = m.response
    bw = bandwidth_hz(fr)
    t_e = load_controller(cfg).speedctrl_equiv_time_s
    bw_md = 1.0 / (2.0 * math.pi * t_e)
    mid = 0.5 * (m.sim["table_pos"][0] + m.sim["table_pos"][-1])
    modes = natural_frequencies(cfg, mid) / (2.0 * math.pi)
    modes = modes[(modes > 1.0) & (modes < MODE_BAND_HZ)]
    found = [p.freq_hz for p in peaks(fr) if p.freq_hz < MODE_BAND_HZ]
    near_400 = min(found, key=lambda f: abs(f - PAPER_RESONANCE_HZ)) if found else math.nan
    rows = _prbs_rows(cfg, m) + [
        Result("speed loop: -3 dB bandwidth", bw_md, bw if bw is not None else "none", "Hz",
               bw is not None and within(bw, bw_md, rel=0.25),
               f"config: 1 / (2 pi speedctrl_equiv_time_s = {t_e * 1e3:g} ms), the closed "
               "speed loop the NC's symmetrising filter assumes; seed 000 gives no number",
               "±25 %"),
        Result("speed loop: resonance peak near 400 Hz", PAPER_RESONANCE_HZ, near_400, "Hz",
               within(near_400, PAPER_RESONANCE_HZ, rel=0.15),
               "seed 000 §5 (its first peak); the coupling stiffness was chosen to put the "
               "torsional mode there (config comment): the row checks the closed loop shows "
               "it, it is not an independent prediction; the model's first peak is at "
               f"{found[0] if found else math.nan:.0f} Hz (next rows)", "±15 %"),
    ] + _mode_rows(fr, modes)
    _plot_speed_bode(fr, modes, bw, out_dir)
    return rows


def _plot_speed_bode(fr, modes: np.ndarray, bw: float | None, out_dir: Path | None) -> None:
    fig, ax = plots.new_figure(2, 1, "Speed loop, PRBS ±250 on 1000 mm/min\n"
                               "(seed 000 §5, Fig. 9)")
    ax[0, 0].semilogx(fr.freq_hz, fr.magnitude_db, label="model (H1 over PRBS periods)")
    ax[1, 0].semilogx(fr.freq_hz, fr.phase_deg)
    ax[0, 0].axvline(PAPER_RESONANCE_HZ, color="r", ls="--", lw=0.9,
                     label="paper: first peak ~400 Hz")
    for f in modes:
        ax[0, 0].axvline(f, color="k", ls=":", lw=0.9)
    if bw is not None:
        ax[0, 0].plot(bw, fr.magnitude_db[0] - 3.0, "ko", mfc="none",
                      label=f"-3 dB at {bw:.0f} Hz")
    ax[0, 0].set(ylabel="|v / v_set| (dB)", ylim=(-40, 10),
                 title="dotted: modes of the linearised mechanics", xlim=(1.0, 4000.0))
    ax[1, 0].set_xlim(1.0, 4000.0)
    ax[1, 0].set(xlabel="frequency (Hz)", ylabel="phase (deg)")
    ax[0, 0].legend(fontsize=8)
    plots.save(fig, out_dir, "seed000_speed_loop_bode")
