"""Seed 002's position-domain analysis of the LD386 linear motor's force.

The axis runs at constant velocity under a stiff velocity loop; the force the
motor has to produce (K_f * i_q, as the drive reports it) is resampled on
equally spaced positions and Fourier-transformed against position.  Seed 002
§5 found, in cycles per electrical revolution, 1.39 N at 1, 2.62 N at 2 and
1.52 N at 4 (cogging), and a DC part of 18.76 N, the friction (Fig. 9).
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.validate import plots
from hil.validate.core import CONFIGS, Result, experiment, within
from plant import Plant

LD386 = CONFIGS / "ld386_linear.toml"
PAPER_HARMONICS = {1: 1.39, 2: 2.62, 4: 1.52}  # N, seed 002 Fig. 9
PAPER_DC_N = 18.76  # N, seed 002 §5


@dataclass(frozen=True)
class PositionSpectrum:
    """Force spectrum against position.

    Attributes:
        orders: cycles per electrical revolution, shape (k,).
        amplitudes: N, shape (k,); entry 0 is the mean (DC) force.
        position: m, the uniform grid, shape (n,).
        force: N, the resampled force, shape (n,).
    """
    orders: np.ndarray
    amplitudes: np.ndarray
    position: np.ndarray
    force: np.ndarray


def position_spectrum(position, force, period_m: float, n_periods: int) -> PositionSpectrum:
    """Resample ``force`` (N) on a uniform grid of ``n_periods`` electrical periods of
    ``period_m`` starting at the first sample, and take the one-sided amplitude spectrum."""
    n = 512 * n_periods
    grid = position[0] + np.arange(n) * (n_periods * period_m / n)
    f = np.interp(grid, position, force)
    spec = np.fft.rfft(f) / n
    amp = 2.0 * np.abs(spec)
    amp[0] = spec[0].real
    return PositionSpectrum(np.arange(amp.size) / n_periods, amp, grid, f)


def constant_velocity_run(plant: Plant, velocity: float, distance: float):
    """Drive ``plant`` at ``velocity`` (m/s) over ``distance`` (m) under a PI velocity loop
    (40 Hz crossover, integral corner a tenth of it: stiff enough that the cogging
    frequencies, 0.6-2.2 Hz here, are rejected with little closed-loop peaking), run once
    per PWM period; returns (position, force K_f*i_q) after the start-up transient."""
    kf = plant.config.motor.force_constant_n_per_a
    mass = plant.config.motor.mass_kg + plant.config.table.mass_kg
    wc = 2 * math.pi * 40.0
    kp = mass * wc / kf  # A per m/s
    ki = kp * wc / 10.0  # A per m
    dt = plant.pwm_period
    n = int((distance / velocity + 0.5) / dt)
    pos = np.empty(n)
    force = np.empty(n)
    integ = 0.0
    for k in range(n):
        err = velocity - plant.output("table_vel")
        integ += ki * err * dt
        plant.set_input(iq_ref_a=kp * err + integ)
        plant.step(plant.sub_per_pwm)
        pos[k] = plant.output("table_pos")
        force[k] = kf * plant.output("iq_meas_a")
    settled = int(0.5 / dt)
    return pos[settled:], force[settled:]


@experiment("cogging_spectrum", "002")
def cogging_spectrum(out_dir: Path | None) -> list[Result]:
    """Constant velocity on the LD386 config; position-domain FFT of the motor force."""
    plant = Plant.from_file(LD386)
    period = 2.0 * plant.config.motor.pole_pitch_m  # one electrical revolution
    n_periods = 4
    velocity = 2.0 / 60.0  # m/s: the 2000 mm/min of the friction figure (see ld386_linear.toml)
    pos, force = constant_velocity_run(plant, velocity, (n_periods + 0.2) * period)
    sp = position_spectrum(pos, force, period, n_periods)
    rows = [Result("cogging DC (friction)", PAPER_DC_N, float(sp.amplitudes[0]), "N",
                   within(sp.amplitudes[0], PAPER_DC_N, rel=0.03), "seed 002 §5", "±3 %")]
    for order, paper in PAPER_HARMONICS.items():
        idx = int(round(order * n_periods))
        model = float(sp.amplitudes[idx])
        rows.append(Result(f"cogging {order} cycle/rev", paper, model, "N",
                           within(model, paper, rel=0.05), "seed 002 Fig. 9", "±5 %"))
    if out_dir is not None:
        fig, ax = plots.new_figure(2, 1, "LD386 at constant velocity (seed 002 method)")
        ax[0, 0].plot(sp.position * 1e3, sp.force)
        ax[0, 0].set(xlabel="position (mm)", ylabel="motor force K_f i_q (N)")
        ax[1, 0].bar(sp.orders[1:33], sp.amplitudes[1:33], width=0.2, label="model")
        ax[1, 0].plot(list(PAPER_HARMONICS), list(PAPER_HARMONICS.values()), "rx", ms=10,
                      label="seed 002 Fig. 9")
        ax[1, 0].set(xlabel="position frequency (cycles / electrical revolution)",
                     ylabel="amplitude (N)")
        ax[1, 0].legend()
        plots.save(fig, out_dir, "cogging_spectrum")
    return rows
