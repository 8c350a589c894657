"""The second generator's axis: one rigid body in table units, its constants read from a
machine file's values as the schema documents them (``hil config-keys``).

Equations (x table position in m, rad on a rotary table; v = dx/dt; i the current in A):

* M dv/dt = K_f i + F_cog(x) - B_m v + F_ext - B v - F_C sign(v) while sliding, with
  M = J_motor / r^2 + J_load / r^2 + m_table, K_f = K_t / r, B_m = motor viscous / r^2 and
  r = lead / 2 pi on a screw, 1 on a linear motor or rotary table;
* stuck (v = 0) while |K_f i + F_cog + F_ext| <= F_C, sliding off when it exceeds F_C;
* di/dt = (i_set - i) / T_cl (``[current_loop] time_constant_s``, the ``first_order``
  current loop);
* F_cog(x) = sum_k A_k / r sin(n_k theta_e + phi_k), theta_e = pole pairs x / r (screw,
  rotary) or pi x / pole pitch (linear motor): harmonics of the electrical angle.

The screw is rigid (``[mechanics] model = "rigid"``): the motor encoder and the scale read
one position.  A machine-file feature outside these equations is refused by name.
"""

import math
from typing import NamedTuple

import numpy as np

from plant.config import MachineConfig


class UnsupportedFeature(ValueError):
    """A machine-file key the second generator does not model (the message names it)."""


class AxisConstants(NamedTuple):
    """The equations' constants, SI in table units (module docstring).

    Attributes:
        mass: M, kg (kg m^2 rotary).
        kf: K_f, N/A (N m/A rotary).
        t_cl: T_cl, s.
        i_max: current limit, A.
        viscous: B + B_m, N s/m.
        coulomb: F_C, N.
        f_ext: constant external force, N.
        poles: electrical angle per table unit, rad/m.
    """
    mass: float
    kf: float
    t_cl: float
    i_max: float
    viscous: float
    coulomb: float
    f_ext: float
    poles: float


class Cogging(NamedTuple):
    """Cogging harmonics, shape (k,) each: orders per electrical revolution, amplitudes at
    the table (N; N m rotary), phases (rad)."""
    orders: np.ndarray
    amplitudes: np.ndarray
    phases: np.ndarray


def ratio(cfg: MachineConfig) -> float:
    """r: table travel per motor radian (m/rad on a screw, 1 otherwise)."""
    return cfg.mechanics.lead_m / (2 * math.pi) if cfg.machine.kind == "screw" else 1.0


def axis_constants(cfg: MachineConfig) -> tuple[AxisConstants, Cogging]:
    """The equations' constants of ``cfg``; UnsupportedFeature names a key outside them."""
    _refuse_unmodelled(cfg)
    kind, mo = cfg.machine.kind, cfg.motor
    r = ratio(cfg)
    linear = kind == "linear"
    fr = cfg.friction
    if kind == "rotary":
        b, fc, f_ext = fr.viscous_nms_per_rad, fr.coulomb_nm, cfg.mechanics.external_torque_nm
    else:
        b, fc, f_ext = fr.viscous_ns_per_m, fr.coulomb_n, cfg.table.external_force_n
    table = cfg.table.mass_kg if cfg.table is not None else 0.0
    motor = mo.mass_kg if linear else mo.inertia_kgm2 / r ** 2
    cg = cfg.cogging
    amps = np.array(cg.amplitudes_n if linear else cg.amplitudes_nm, dtype=float) / r
    phases = np.radians(np.array(cg.phases_deg or (0.0,) * len(cg.orders), dtype=float))
    consts = AxisConstants(
        mass=motor + cfg.mechanics.load_inertia_kgm2 / r ** 2 + table,
        kf=mo.force_constant_n_per_a if linear else mo.torque_constant_nm_per_a / r,
        t_cl=cfg.current_loop.time_constant_s, i_max=mo.current_max_a,
        viscous=b + mo.viscous_nms_per_rad / r ** 2, coulomb=fc, f_ext=f_ext,
        poles=math.pi / mo.pole_pitch_m if linear else mo.pole_pairs / r)
    return consts, Cogging(np.array(cg.orders, dtype=float), amps, phases)


def _refuse_unmodelled(cfg: MachineConfig) -> None:
    """UnsupportedFeature for the first key whose value needs another equation."""
    kind, fr = cfg.machine.kind, cfg.friction
    rotary = kind == "rotary"
    checks = {
        "[motor] model": (cfg.motor.model, cfg.motor.model != "first_order"),
        "[mechanics] model": (cfg.mechanics.model, cfg.mechanics.model != "rigid"),
        "[friction] breakaway": (fr.breakaway_nm if rotary else fr.breakaway_n,
                                 (fr.breakaway_nm if rotary else fr.breakaway_n)
                                 > (fr.coulomb_nm if rotary else fr.coulomb_n)),
        "[friction] viscous_asymmetry": (
            fr.viscous_asymmetry_nms_per_rad if rotary else fr.viscous_asymmetry_ns_per_m,
            (fr.viscous_asymmetry_nms_per_rad if rotary else fr.viscous_asymmetry_ns_per_m)
            != 0.0),
        "[presliding] enabled": (cfg.presliding.enabled, cfg.presliding.enabled),
        "[pitch_error]": ("given", cfg.pitch_error is not None and kind == "screw"
                          and bool(cfg.pitch_error.periods_m or cfg.pitch_error.linear_ppm)),
        "[sensors] delay_s": (cfg.sensors.delay_s, cfg.sensors.delay_s != 0.0),
    }
    for key, (value, refused) in checks.items():
        if refused:
            raise UnsupportedFeature(f"{cfg.path}: {key} = {value!r}: not modelled by the "
                                     "second generator (hil.bench.identify_gen2.axis)")
