"""The measured motion and force of a record, filtered for the inverse model.

The inverse (IDIM) model needs the table's velocity and acceleration, which are not
measured: they come from the measured position through a zero-phase Butterworth low-pass
and central differences.  The force is filtered by the same low-pass ("parallel
filtering") so that both sides of ``F = M a + ...`` see the same frequency response and
the fit is not biased by the filter.  The first and last ``edge`` samples, where the
zero-phase filter's start-up transients sit, are left out of every fit.

A caveat of servo traces: they sample the current once per position cycle, at the same
phase of it.  Where the speed loop's current ripples in step with that cycle (its speed
setpoint a staircase of the position loop's outputs, without a setpoint filter), the
samples see one phase of the ripple and the fitted mass and viscous friction carry a
bias of a few per cent; a speed-setpoint filter in the drive, or a trace at the speed
cycle, removes it.
"""

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt

from hil.identify.record import Record
from hil.trace_file import TraceFormatError
from plant.assemble import build_chains, reflected_inertia, transmission_ratio
from plant.config import MachineConfig

#: fewest samples a record needs: the filter's start-up edges are left out of every fit
MIN_SAMPLES = 100


@dataclass(frozen=True)
class Drive:
    """What the config says about the drive train, in table units (m or rad at the table).

    Attributes:
        kind: "screw", "linear" or "rotary".
        ratio: table travel per motor rad (m/rad for screws, 1 otherwise).
        force_per_amp: table force per A of iq (N/A; N·m/A on rotary tables).
        pole_pairs: electrical rad per motor-side unit (rad/rad; rad/m for linear motors).
        mass: total moved inertia at the table (kg; kg·m² on rotary tables).
        motor_mass: the motor-side part of it (rotor, coupling, screw), same unit.
        viscous: total viscous coefficient at the table (N·s/m; N·m·s/rad).
        motor_viscous: the part of it on the motor side (bearings), same unit.
    """
    kind: str
    ratio: float
    force_per_amp: float
    pole_pairs: float
    mass: float
    motor_mass: float
    viscous: float
    motor_viscous: float

    @classmethod
    def of(cls, cfg: MachineConfig) -> "Drive":
        ratio = transmission_ratio(cfg)
        rot, _ = build_chains(cfg)
        kind = cfg.machine.kind
        # node 0 of the torsional chain is the motor (with half the coupling)
        motor_mass = float(rot.m[0]) / ratio ** 2 if rot.n > 1 else (
            (cfg.motor.mass_kg if kind == "linear" else cfg.motor.inertia_kgm2) / ratio ** 2)
        motor_viscous = float(np.sum(rot.c_gnd)) / ratio ** 2
        if kind == "linear":
            kf = cfg.motor.force_constant_n_per_a
            pole_pairs = math.pi / cfg.motor.pole_pitch_m
        else:
            kf = cfg.motor.torque_constant_nm_per_a / ratio
            pole_pairs = cfg.motor.pole_pairs
        table_viscous = (cfg.friction.viscous_nms_per_rad if kind == "rotary"
                         else cfg.friction.viscous_ns_per_m)
        return cls(kind, ratio, kf, pole_pairs, reflected_inertia(cfg) / ratio ** 2,
                   motor_mass, motor_viscous + table_viscous, motor_viscous)


@dataclass(frozen=True)
class Motion:
    """Filtered signals of one record, all of shape (n,), SI table units.

    Attributes:
        t: s.
        x: measured table position, low-passed (m or rad).
        v, a: its first and second derivatives.
        force: measured force at the table, low-passed the same way (N or N·m).
        theta_e: electrical angle of the motor (rad), from the motor encoder when recorded.
        dx: (table position - motor position in table units), low-passed, or None when the
            record has no motor encoder column.
        use: boolean mask of the samples a fit may use (filter edges left out).
        cutoff_hz: the low-pass corner.
        noise_force: estimated rms of the measurement noise left in ``force`` after the
            low-pass (N), from the content above the corner.
        noise_dx: the same for ``dx`` (m), or 0.
        sos: the low-pass as second-order sections (for :meth:`lowpass`).
    """
    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    force: np.ndarray
    theta_e: np.ndarray
    dx: np.ndarray | None
    use: np.ndarray
    cutoff_hz: float
    noise_force: float
    noise_dx: float
    sos: np.ndarray

    def lowpass(self, signal: np.ndarray) -> np.ndarray:
        """``signal`` (n,) through the same zero-phase low-pass as the force: a regressor
        built from raw measurements must see the filter the force saw."""
        return sosfiltfilt(self.sos, signal)


def effort_to_force(rec: Record, drive: Drive) -> np.ndarray:
    """The record's effort as force at the table (N, or N·m on rotary tables)."""
    return rec.effort * drive.force_per_amp if rec.effort_kind == "iq" else rec.effort


def _noise_after_lowpass(raw: np.ndarray, low: np.ndarray, frac: float) -> float:
    """rms of white noise left below the corner, estimated from what lies above it.

    ``frac`` is the corner as a fraction of the Nyquist frequency: white noise of variance
    s² has s²(1-frac) above the corner and s²·frac below it."""
    above = float(np.std(raw - low))
    return above * math.sqrt(frac / max(1.0 - frac, 1e-6))


def derivative(x: np.ndarray, dt: float) -> np.ndarray:
    """d/dt of ``x`` (n,) by the five-point central stencil.

    Its gain at w is (8 sin(w dt) - sin(2 w dt)) / (6 w dt): 0.9996 at a twentieth of the
    sample rate (50 Hz in a 1 kHz record), where the three-point difference (np.gradient)
    is already 1.6 % low; that error would go straight into a mass or a cogging
    amplitude."""
    d = np.gradient(x, dt)
    d[2:-2] = (x[:-4] - 8.0 * x[1:-3] + 8.0 * x[3:-1] - x[4:]) / (12.0 * dt)
    return d


def motion(rec: Record, drive: Drive, cutoff_hz: float | None = None) -> Motion:
    """Filter a record for the inverse model.

    Args:
        rec: the record.
        drive: the config's drive train (force constant, ratio, pole pairs).
        cutoff_hz: corner of the 4th-order zero-phase low-pass; default a tenth of the
            sample rate (100 Hz at 1 kHz), well above a servo axis's position bandwidth
            and below the range where quantization noise, differentiated twice, swamps
            the acceleration.
    """
    fs = 1.0 / rec.dt
    fc = cutoff_hz if cutoff_hz is not None else fs / 10.0
    if not 0.0 < fc < fs / 2.0:
        raise ValueError(f"cutoff_hz must lie between 0 and the Nyquist frequency {fs / 2} Hz, "
                         f"got {fc}")
    sos = butter(4, fc / (fs / 2.0), output="sos")
    if rec.n <= MIN_SAMPLES:
        raise TraceFormatError(f"{rec.source}: {rec.n} samples; the inverse model's "
                               f"zero-phase filter needs more than {MIN_SAMPLES}")
    x = sosfiltfilt(sos, rec.pos)
    v = derivative(x, rec.dt)
    a = derivative(v, rec.dt)
    raw_force = effort_to_force(rec, drive)
    force = sosfiltfilt(sos, raw_force)
    frac = fc / (fs / 2.0)
    motor = rec.motor_pos if rec.motor_pos is not None else rec.pos
    theta_e = drive.pole_pairs * motor / drive.ratio
    dx = None
    noise_dx = 0.0
    # a record whose only position sensor is the motor encoder has nothing to compare
    if rec.motor_pos is not None and not np.array_equal(rec.motor_pos, rec.pos):
        raw_dx = rec.pos - rec.motor_pos
        dx = sosfiltfilt(sos, raw_dx)
        noise_dx = _noise_after_lowpass(raw_dx, dx, frac)
    edge = min(rec.n // 10, int(3.0 * fs / fc) + 2)
    use = np.zeros(rec.n, dtype=bool)
    use[edge:rec.n - edge] = True
    return Motion(rec.t, x, v, a, force, theta_e, dx, use, fc,
                  _noise_after_lowpass(raw_force, force, frac), noise_dx, sos)
