"""The voltage seed 001's torque motor needs on its torque-speed envelope.

The commutation model (``plant/effects/commutation.py``, seed 001 eq. 1-10) is one
equivalent coil: L dI/dt = U - R I - K omega.  A synchronous machine with that coil's R,
L, K_0 and pole pairs p, its current I at the angle gamma = arccos(K / K_0) ahead of the q
axis that the lowered commutation angle means (K = K_0 sin beta, gamma = 90 deg - beta;
i_d = -|I| sin gamma stays demagnetising for either sign of the torque), takes

    u_d = R i_d - omega_e L i_q
    u_q = R i_q + omega_e L i_d + K_0 omega,    omega_e = p omega,

and |u| must stay within U_Z (eq. 2).  The experiment holds the rotor at the speeds of
:data:`~hil.validate.experiments.electrical.FW_CASES` at full demand, reads the current and
torque constant the kernel settles to, and compares that |u|
(:meth:`~hil.validate.experiments.electrical.SeedOneDrive.dq_voltage`) with U_Z.  Larger
would be a torque the machine could not give: the coil's converter must leave room for
the omega_e L cross term (issue 14 part 5; before, 677 V at 0.9 omega_max).
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.validate import plots
from hil.validate.core import VERIFICATION, Result, SeedRef, experiment
from hil.validate.experiments.electrical import FW_CASES, GEISS, SeedOneDrive, held_speed_run
from plant import Plant

VOLTAGE_SOURCE = SeedRef("001", "§2, eq. 2", None, "The input voltage U for the motor coil is "
                         "limited to the intermediate voltage U_Z")


@dataclass(frozen=True)
class OperatingPoint:
    """Where the kernel settles with the rotor held at ``omega``.

    Attributes:
        omega: rad/s, rotor speed.
        current: A, coil current.
        k: N·m/A, the torque constant it commutates with.
    """
    omega: float
    current: float
    k: float

    def voltages(self, drive: SeedOneDrive) -> tuple[float, float]:
        """(V along the current, R I + K omega, the one coil of eq. 1-4; V the synchronous
        machine needs, |u| of :meth:`~hil.validate.experiments.electrical.SeedOneDrive.
        dq_voltage`)."""
        ud, uq = drive.dq_voltage(self.omega, self.k, self.current)
        return drive.r * self.current + self.k * self.omega, math.hypot(ud, uq)


def settled_point(path: Path, omega: float, iq_ref: float) -> OperatingPoint:
    """Where the kernel settles with the rotor held at ``omega`` (rad/s), field weakening
    on, current setpoint ``iq_ref`` (A) (:func:`~hil.validate.experiments.electrical.
    held_speed_run`)."""
    run = held_speed_run(path, omega, iq_ref, weakening=True)
    return OperatingPoint(omega, run["iq_a"], run["torque"] / run["iq_a"])


@experiment("seed001_voltage_envelope", "001")
def seed001_voltage_envelope(out_dir: Path | None, config: Path = GEISS) -> list[Result]:
    """Full torque demand at the held speeds of the field-weakening experiment: the
    voltage a synchronous machine with the coil's R, L, K_0 and p needs there, against
    U_Z (eq. 2)."""
    cfg = Plant.from_file(config).config
    drive = SeedOneDrive.from_config(cfg)
    uz = cfg.motor.dc_link_v
    label, _, _, speeds = FW_CASES[0]
    omega_max = uz / cfg.motor.torque_constant_nm_per_a  # eq. 6
    rows, points = [], []
    for s in speeds:
        point = settled_point(config, s * omega_max, cfg.motor.current_max_a)
        applied, needed = point.voltages(drive)
        fits = needed <= uz * (1.0 + 1e-6)
        rows.append(Result(
            f"voltage needed at {point.omega:.1f} rad/s ({s:g} omega_max), {label}", uz, needed,
            "V", fits, "U_Z of the machine file, the limit of seed 001 eq. 2; the need: the "
            "coil as a synchronous machine at the kernel's current and commutation angle",
            "<= U_Z", VERIFICATION, VOLTAGE_SOURCE, "" if fits else
            f"disagrees: the coil gets {applied:.0f} V (R I + K omega, seed 001 eq. 9) but the "
            "d-q vector with omega_e L I across the current exceeds U_Z: the converter's limit "
            "in plant/effects/commutation.py (coil_voltage_limit) is not met"))
        points.append((point.omega, applied, needed))
    if out_dir is not None:
        _plot_envelope(out_dir, uz, np.array(points))
    return rows


def _plot_envelope(out_dir: Path, uz: float, points: np.ndarray) -> None:
    fig, ax = plots.new_figure(1, 1, "Seed 001 torque motor at full demand: voltage")
    ax[0, 0].plot(points[:, 0], points[:, 1], "o-", label="applied by the model, R I + K omega")
    ax[0, 0].plot(points[:, 0], points[:, 2], "s-", label="needed with omega_e L I")
    ax[0, 0].axhline(uz, color="r", ls="--", label="U_Z (eq. 2)")
    ax[0, 0].set(xlabel="speed (rad/s)", ylabel="voltage (V)")
    ax[0, 0].legend(fontsize=8)
    plots.save(fig, out_dir, "seed001_voltage_envelope")
