"""Seed 002's position-domain analysis of the LD386 linear motor's force.

The axis runs at constant velocity under a stiff velocity loop; the force the
motor has to produce (K_f * i_q, as the drive reports it) is resampled on
equally spaced positions and Fourier-transformed against position.  Seed 002
§5 found, in cycles per electrical revolution, 1.39 N at 1, 2.62 N at 2 and
1.52 N at 4 (cogging), and a DC part of 18.76 N, the friction (Fig. 9).

ld386_linear.toml copied those numbers into [cogging] and [friction], so the rows verify
the configuration and the method (a velocity loop passes a position-periodic force to the
motor force with its complementary sensitivity |T(j omega)|), they reproduce nothing.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.validate import plots
from hil.validate.core import CONFIGS, VERIFICATION, Result, SeedRef, experiment, within
from plant import Plant

LD386 = CONFIGS / "ld386_linear.toml"
PAPER_HARMONICS = {1: 1.39, 2: 2.62, 4: 1.52}  # N, seed 002 Fig. 9
HARMONICS_SOURCE = SeedRef("002", "§5, Fig. 9", 8, "largest component was found at 2 "
                           "cycles/revolution (2.62N), which along with the components at "
                           "1 cycle/revolution (1.39N) and 4 cycles/revolution (1.52N)")
DC_SOURCE = SeedRef("002", "§5", 7, "The DC component (friction) was found to be 18.76N")
#: acceptance of the spectrum against |T| times the configured amplitude: the position
#: grid of a run whose velocity ripples leaves a few 0.1 % (order 1: 0.4 %)
SPECTRUM_REL_TOL = 0.01


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


def velocity_loop_gains(plant: Plant) -> tuple[float, float]:
    """(K_p in A per m/s, K_i in A per m) of the PI velocity loop of the constant-velocity
    run: 40 Hz crossover on the moving mass, integral corner a tenth of it, stiff enough
    that the cogging frequencies, 0.6-2.2 Hz here, are rejected with little peaking."""
    kf = plant.config.motor.force_constant_n_per_a
    mass = plant.config.motor.mass_kg + plant.config.table.mass_kg
    wc = 2 * math.pi * 40.0
    kp = mass * wc / kf
    return kp, kp * wc / 10.0


def force_transmission(plant: Plant, freq_hz: float) -> float:
    """|T(j 2 pi f)| = |L / (1 + L)|: the share of a position-periodic force of ``freq_hz``
    (Hz) the velocity loop puts into the motor force, L = C(z) K_f G_cl(s) / (M s + B)
    with the loop's discrete PI at the PWM period, the first-order current loop G_cl and
    the viscous friction B."""
    cfg = plant.config
    kp, ki = velocity_loop_gains(plant)
    s = 2j * math.pi * freq_hz
    z = np.exp(s * plant.pwm_period)
    pi = kp + ki * plant.pwm_period * z / (z - 1.0)  # integral updated before the output
    lag = 1.0 / (cfg.current_loop.time_constant_s * s + 1.0)
    mass = cfg.motor.mass_kg + cfg.table.mass_kg
    loop = pi * cfg.motor.force_constant_n_per_a * lag / (mass * s + cfg.friction.viscous_ns_per_m)
    return float(abs(loop / (1.0 + loop)))


def constant_velocity_run(plant: Plant, velocity: float, distance: float):
    """Drive ``plant`` at ``velocity`` (m/s) over ``distance`` (m) under the PI velocity loop
    of :func:`velocity_loop_gains`, run once per PWM period; returns (position, force
    K_f*i_q) after the start-up transient."""
    kf = plant.config.motor.force_constant_n_per_a
    kp, ki = velocity_loop_gains(plant)
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
    fr = plant.config.friction
    dc_ref = fr.coulomb_n + fr.viscous_ns_per_m * velocity
    tol = f"±{SPECTRUM_REL_TOL * 100:g} % (position grid of a rippling velocity)"
    rows = [Result("cogging DC (friction)", dc_ref, float(sp.amplitudes[0]), "N",
                   within(sp.amplitudes[0], dc_ref, rel=SPECTRUM_REL_TOL),
                   "configuration: coulomb_n + viscous_ns_per_m v, set from seed 002's 18.76 N "
                   "(the row verifies the configuration)", tol, VERIFICATION, DC_SOURCE)]
    amplitudes = dict(zip(plant.config.cogging.orders, plant.config.cogging.amplitudes_n))
    for order in PAPER_HARMONICS:
        idx = int(round(order * n_periods))
        model = float(sp.amplitudes[idx])
        gain = force_transmission(plant, order * velocity / period)
        ref = amplitudes[order] * gain
        rows.append(Result(f"cogging {order} cycle/rev", ref, model, "N",
                           within(model, ref, rel=SPECTRUM_REL_TOL),
                           f"configuration: amplitudes_n (copied from seed 002) x |T| = "
                           f"{gain:.4f} of the velocity loop (the row verifies the "
                           "configuration and the method, it reproduces nothing)", tol,
                           VERIFICATION, HARMONICS_SOURCE))
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
