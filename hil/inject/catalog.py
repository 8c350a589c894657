"""The faults and wear an emulated axis can be given (issue 14 part 6; seed 001 §7 builds
its HIL rig to produce faulty-machine data for condition monitoring).

Each fault is one table of the machine file's ``[inject]`` section, ``[inject.NAME]``:
its *level* (one key, the unit in its name), when it starts (``at_s``, drive time) and
how long it takes to reach the level (``ramp_s``; 0: a step).  The same table, as text
(``hil sim --inject``, ``hil run --inject``) or as a message on the adapter, injects it
at run time (:mod:`hil.inject.schedule`).

==========================  =====================  =============================================
fault                       level key              what changes in the plant
==========================  =====================  =============================================
``friction_growth``         ``growth_pct``         every friction coefficient of the table, nut
                                                   and bearings times (1 + growth/100)
``backlash_growth``         ``growth_m``           the nut's backlash plus this (ball-screw axes)
``preload_loss``            ``loss_pct``           the nut's axial stiffness times (1 - loss/100)
                                                   (a worn preload; ball-screw axes)
``torque_constant_loss``    ``loss_pct``           the magnet flux (torque and back-EMF
                                                   constants) times (1 - loss/100):
                                                   demagnetisation.  The drive keeps its
                                                   commissioned constant, so the torque per
                                                   ampere it commands drops
``encoder_noise``           ``noise_counts``       Gaussian noise on each motor-encoder sample,
                                                   counts rms
``encoder_lost_counts``     ``lost_ppm``           counts the motor encoder misses, per million
                                                   counts travelled (they add up: the encoder
                                                   drifts against the scale)
``current_offset``          ``offset_a``           offset of the phase-a current sensor, A (the
                                                   current loop cancels it: torque ripple at the
                                                   electrical frequency)
``current_gain_error``      ``gain_error_pct``     gain error of the phase-a sensor, % (ripple
                                                   at twice the electrical frequency and a mean
                                                   torque change of about half the error)
``torque_ripple``           ``ripple_pct``         broken-bar-like ripple: the motor's torque
                                                   times 1 + ripple/100 cos(order theta_e +
                                                   phase), growing with the load (cogging does
                                                   not); ``order`` per electrical revolution
==========================  =====================  =============================================

The plant's terms for the last five are in :mod:`plant.effects.faults`.  A fault this
machine cannot have (a nut fault on a linear motor) is refused before start, naming it.
"""

from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np

from plant import layout as L
from plant.config import MachineConfig
from plant.schema import key


@dataclass(frozen=True, kw_only=True)
class _Timed:
    """When a fault acts: the keys every fault's table has besides its level."""
    at_s: float = key("s", "Drive time at which the fault starts (0: from the start).", 0.0,
                      ge=0.0, le=1e7)
    ramp_s: float = key("s", "Time the fault takes to grow linearly from its present level to "
                        "this one (0: a step).", 0.0, ge=0.0, le=1e7)


@dataclass(frozen=True, kw_only=True)
class FrictionGrowth(_Timed):
    """Friction growth (wear, lubrication loss)."""
    growth_pct: float = key("%", "Growth of every friction coefficient (Coulomb, breakaway, "
                            "viscous; table, nut and bearings); negative: less friction.",
                            ge=-90.0, le=1000.0)


@dataclass(frozen=True, kw_only=True)
class BacklashGrowth(_Timed):
    """Backlash growth in the ball-screw nut (ball and raceway wear)."""
    growth_m: float = key("m", "Added to the nut's backlash (total dead-zone width).",
                          ge=0.0, le=1e-3)


@dataclass(frozen=True, kw_only=True)
class PreloadLoss(_Timed):
    """Preload loss of the ball-screw nut: its axial stiffness drops."""
    loss_pct: float = key("%", "Share of the nut's axial stiffness lost.", ge=0.0, le=90.0)


@dataclass(frozen=True, kw_only=True)
class TorqueConstantLoss(_Timed):
    """Demagnetisation: the magnet flux, and with it the torque and back-EMF constants,
    drops; the drive does not know."""
    loss_pct: float = key("%", "Share of the magnet flux lost.", ge=0.0, le=90.0)


@dataclass(frozen=True, kw_only=True)
class EncoderNoise(_Timed):
    """Noise on the motor encoder's samples (a dirty disc, interference on sin/cos)."""
    noise_counts: float = key("1", "Standard deviation of the noise, encoder counts.",
                              ge=0.0, le=1e6)


@dataclass(frozen=True, kw_only=True)
class EncoderLostCounts(_Timed):
    """Counts the motor encoder misses (signal drop-outs)."""
    lost_ppm: float = key("1e-6", "Counts missed per million counts travelled.", ge=0.0,
                          le=1e5)


@dataclass(frozen=True, kw_only=True)
class CurrentOffset(_Timed):
    """Offset of the phase-a current sensor."""
    offset_a: float = key("A", "Offset of the phase-a current measurement.", ge=-1e3, le=1e3)


@dataclass(frozen=True, kw_only=True)
class CurrentGainError(_Timed):
    """Gain error of the phase-a current sensor."""
    gain_error_pct: float = key("%", "Relative gain error of the phase-a current "
                                "measurement (positive: it reads high).", ge=-50.0, le=50.0)


@dataclass(frozen=True, kw_only=True)
class TorqueRipple(_Timed):
    """Broken-bar-like torque ripple, proportional to the motor's torque."""
    ripple_pct: float = key("%", "Ripple amplitude as a share of the motor's torque.",
                            ge=0.0, le=100.0)
    order: float = key("1", "Ripple cycles per electrical revolution (or pole-pair pitch).",
                       1.0, gt=0.0, le=1000.0)
    phase_deg: float = key("deg", "Phase of the ripple against the electrical angle.", 0.0,
                           ge=-360.0, le=360.0)


def _scale(indices: tuple[int, ...], sign: float) -> Callable:
    """Write base * (1 + sign * level/100) at ``indices``."""
    def write(p: np.ndarray, base: np.ndarray, level: float, sec) -> None:
        factor = 1.0 + sign * level / 100.0
        for i in indices:
            p[i] = base[i] * factor
    return write


def _add(index: int, factor: float) -> Callable:
    """Write base + factor * level at ``index``."""
    def write(p: np.ndarray, base: np.ndarray, level: float, sec) -> None:
        p[index] = base[index] + factor * level
    return write


def _ripple(p: np.ndarray, base: np.ndarray, level: float, sec: TorqueRipple) -> None:
    p[L.P_RIPPLE_AMP] = level / 100.0
    p[L.P_RIPPLE_ORDER] = sec.order
    p[L.P_RIPPLE_PHASE] = np.deg2rad(sec.phase_deg)


def _needs_nut(cfg: MachineConfig) -> str:
    if cfg.mechanics.model != "screw":
        return (f"needs a ball-screw nut ([mechanics] model = 'screw'); this machine has "
                f"model = '{cfg.mechanics.model}'")
    return ""


def _anywhere(cfg: MachineConfig) -> str:
    return ""


@dataclass(frozen=True)
class Fault:
    """One fault: its table's declarations, its level key and how it writes the plant's
    parameters.

    Attributes:
        name: the table's name in ``[inject]``.
        section: the dataclass declaring its keys (:func:`plant.schema.key`).
        level_key: the key holding its level.
        write: ``write(p, base, level, section)``: set the parameters it owns in ``p``
            from the healthy values ``base`` (both the plant's params array) at ``level``
            (in the level key's unit).
        wire_per_unit: the level's integer unit on CANopen (object 2F00h): wire value =
            level * this, rounded (0.01 %, nm, 0.001 counts, 0.001 ppm, mA).
        why_not: ``why_not(cfg)``: why this machine cannot have it, "" if it can.
    """
    name: str
    section: type
    level_key: str
    write: Callable
    wire_per_unit: float
    why_not: Callable[[MachineConfig], str] = _anywhere

    @property
    def unit(self) -> str:
        return next(f.metadata["unit"] for f in fields(self.section)
                    if f.name == self.level_key)


_FRICTION = (L.P_FR_VISCOUS, L.P_FR_COULOMB, L.P_FR_STATIC, L.P_FR_VISC_ASYM,
             L.P_BRG_COULOMB, L.P_NUT_COULOMB, L.P_NUT_VISCOUS)

FAULTS: dict[str, Fault] = {f.name: f for f in (
    Fault("friction_growth", FrictionGrowth, "growth_pct", _scale(_FRICTION, 1.0), 100.0),
    Fault("backlash_growth", BacklashGrowth, "growth_m", _add(L.P_NUT_GAP, 1.0), 1e9,
          _needs_nut),
    Fault("preload_loss", PreloadLoss, "loss_pct", _scale((L.P_NUT_K,), -1.0), 100.0,
          _needs_nut),
    Fault("torque_constant_loss", TorqueConstantLoss, "loss_pct",
          _scale((L.P_PSI, L.P_KT, L.P_KE), -1.0), 100.0),
    Fault("encoder_noise", EncoderNoise, "noise_counts", _add(L.P_ENC_NOISE, 1.0), 1e3),
    Fault("encoder_lost_counts", EncoderLostCounts, "lost_ppm", _add(L.P_ENC_LOST, 1e-6),
          1e3),
    Fault("current_offset", CurrentOffset, "offset_a", _add(L.P_I_OFFSET, 1.0), 1e3),
    Fault("current_gain_error", CurrentGainError, "gain_error_pct",
          _add(L.P_I_GAIN_ERR, 0.01), 100.0),
    Fault("torque_ripple", TorqueRipple, "ripple_pct", _ripple, 100.0),
)}
#: the faults in order: sub-index k of the CANopen object 2F00h is ``BY_SUBINDEX[k - 1]``
BY_SUBINDEX = tuple(FAULTS.values())
