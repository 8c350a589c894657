"""The second generator's controller settings: the conventions of trace-format.md's header
(chosen per case) and the gains of the declared machine file's ``[controller]`` table, read
as data (``MachineConfig.section``), turned into the compiled loop's constants.

The cascade (run by :func:`~.loop.run_loop_compiled`), per PWM period k of ``pwm_s``:

* measure: motor encoder and scale counts (floor or round, of the travel since the start
  when zeroed at the start), the current with its noise, rounded to the ADC step
  2 full scale / 2^bits and clipped at +- full scale;
* every position cycle: v_P = K_v (x_set - x_fb), x_fb the scale or the motor encoder
  (``feedback``), K_v = ``kv_m_min_per_mm`` x 1000/60 in 1/s;
* every speed cycle: the measured speed, the motor encoder's difference over the cycle
  through the first-order filter e^(-T/T_f) (exact for a held input); the feed-forward of
  the record row the sample falls in, held, or interpolated linearly toward the next
  row's (trace-format.md: ``vel_set`` is the feed-forward, per record sample); the speed
  command v_P + w_ff v_ff limited to the axis's top speed; a PI on its error, in force at
  the table, that stops integrating while its output is beyond K_f I_max and the error
  would drive it further ("conditional"); the current setpoint its output over K_f;
* that setpoint applied ``current_delay_cycles`` periods later and held for the period.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

from plant.config import MachineConfig

from .axis import UnsupportedFeature, ratio

#: ``[controller]`` keys that need a part of the cascade this generator does not have, with
#: the value that leaves the part out
UNMODELLED = {"plant_input": "current", "torque_ff": False, "speedctrl_equiv_time_s": 0.0,
              "speed_kd_nms2_per_rad": 0.0, "speed_kd_ns2_per_m": 0.0,
              "speed_setpoint_lowpass_hz": 0.0, "current_setpoint_lowpass_hz": 0.0,
              "notch_hz": 0.0, "encoder_feedback_polarity": 1}


@dataclass(frozen=True)
class Conventions:
    """How the trace's controller and sensors work (trace-format.md's header keys).

    Attributes:
        position_cycle_s: position-loop cycle, s (a whole number of PWM periods).
        speed_cycle_s: speed-loop cycle, s.
        feedforward: "hold" or "linear" (feed-forward between record rows).
        ff_weight: weight of the feed-forward in the speed command, 1.
        speed_filter_s: time constant of the filter on the measured speed, s (0: none).
        current_delay_cycles: PWM periods between the speed loop's output and its use.
        adc_bits: current ADC bits.
        adc_full_scale_a: where the ADC clips, A (0: the declared step x 2^(bits-1)).
        encoder_rounding: "floor" or "round".
        encoder_zero_at_start: the encoders count the travel since the start.
    """
    position_cycle_s: float = 0.001
    speed_cycle_s: float = 0.00025
    feedforward: str = "hold"
    ff_weight: float = 1.0
    speed_filter_s: float = 0.0
    current_delay_cycles: int = 0
    adc_bits: int = 12
    adc_full_scale_a: float = 0.0
    encoder_rounding: str = "floor"
    encoder_zero_at_start: bool = False


class LoopConstants(NamedTuple):
    """The compiled loop's settings, SI in table units (module docstring)."""
    pwm_s: float
    substeps: int
    n_pos: int
    n_spd: int
    n_rec: int
    pre_ticks: int
    delay: int
    kv: float
    ff_weight: float
    ff_linear: bool
    filter_decay: float
    kp: float
    ki_step: float
    v_max: float
    motor_step: float
    scale_step: float
    rounding: float
    zero_at_start: bool
    lsb: float
    full_scale: float


def full_scale_a(cfg: MachineConfig, conv: Conventions) -> float:
    """Where the trace's ADC clips, A."""
    return conv.adc_full_scale_a or cfg.sensors.current_lsb_a * 2 ** (conv.adc_bits - 1)


def loop_constants(cfg: MachineConfig, conv: Conventions, record_s: float, preroll_s: float,
                   substeps: int) -> LoopConstants:
    """The loop's constants for ``cfg``'s gains with ``conv``; ``record_s``: the trace's
    sample time, s; ``preroll_s``: s at rest before it; ``substeps``: integration steps per
    PWM period.  UnsupportedFeature for a ``[controller]`` key of :data:`UNMODELLED`, or
    cycles that are no whole number of PWM periods."""
    raw = cfg.section("controller")
    for key, neutral in UNMODELLED.items():
        if raw.get(key, neutral) != neutral:
            raise UnsupportedFeature(f"{cfg.path}: [controller] {key} = {raw[key]!r}: not "
                                     "modelled by the second generator")
    pwm = 1.0 / cfg.motor.pwm_frequency_hz
    n_pos, n_spd, n_rec = (_periods(cfg, s, pwm) for s in
                           (conv.position_cycle_s, conv.speed_cycle_s, record_s))
    kind, sen = cfg.machine.kind, cfg.sensors
    r = ratio(cfg)
    if kind == "linear":
        kp, motor_step = raw["speed_kp_ns_per_m"], sen.encoder_resolution_m
        v_max = raw["max_velocity_mm_min"] / 60000.0
    else:
        # N m s/rad on the motor's speed, as force at the table per table speed: / r^2
        kp, motor_step = raw["speed_kp_nms_per_rad"] / r ** 2, 2 * math.pi * r / \
            sen.encoder_counts_per_rev
        v_max = (raw["max_velocity_deg_min"] * math.pi / 180.0 / 60.0 if kind == "rotary"
                 else raw["max_velocity_mm_min"] / 60000.0)
    tn = raw.get("speed_tn_s", 0.0)
    scale = sen.scale_resolution_m if raw.get("feedback") == "scale" else 0.0
    # the pre-roll a whole number of position cycles and record rows: t = 0 starts both
    block = n_pos * n_rec // math.gcd(n_pos, n_rec)
    full = full_scale_a(cfg, conv)
    return LoopConstants(
        pwm_s=pwm, substeps=substeps, n_pos=n_pos, n_spd=n_spd, n_rec=n_rec,
        pre_ticks=round(preroll_s / (block * pwm)) * block, delay=conv.current_delay_cycles,
        kv=raw["kv_m_min_per_mm"] * 1000.0 / 60.0, ff_weight=conv.ff_weight,
        ff_linear=conv.feedforward == "linear",
        filter_decay=math.exp(-n_spd * pwm / conv.speed_filter_s) if conv.speed_filter_s
        else 0.0,
        kp=kp, ki_step=kp * n_spd * pwm / tn if tn > 0 else 0.0, v_max=v_max,
        motor_step=motor_step, scale_step=scale,
        rounding=0.5 if conv.encoder_rounding == "round" else 0.0,
        zero_at_start=conv.encoder_zero_at_start,
        lsb=2.0 * full / 2 ** conv.adc_bits, full_scale=full)


def _periods(cfg: MachineConfig, seconds: float, pwm: float) -> int:
    n = round(seconds / pwm)
    if n < 1 or abs(n * pwm - seconds) > 1e-9 * seconds:
        raise UnsupportedFeature(f"{cfg.path}: a cycle of {seconds:g} s is no whole number of "
                                 f"PWM periods ({pwm:g} s)")
    return n


def header(cfg: MachineConfig, conv: Conventions, record_s: float,
           preroll_s: float) -> dict:
    """The trace header's convention keys (trace-format.md) for this controller."""
    sen = cfg.sensors
    meta = {
        "sample_time_s": repr(record_s),
        "position_loop_sample_time_s": repr(conv.position_cycle_s),
        "speed_loop_sample_time_s": repr(conv.speed_cycle_s),
        "current_loop_sample_time_s": repr(1.0 / cfg.motor.pwm_frequency_hz),
        "feedforward_interpolation": conv.feedforward,
        "velocity_feedforward_factor": repr(conv.ff_weight),
        "speed_actual_filter_s": repr(conv.speed_filter_s),
        "speed_antiwindup": "conditional",
        "current_delay_cycles": str(conv.current_delay_cycles),
        "current_adc_bits": str(conv.adc_bits),
        "current_adc_full_scale_a": repr(full_scale_a(cfg, conv)),
        "encoder_rounding": conv.encoder_rounding,
        "encoder_zero_at_start": "true" if conv.encoder_zero_at_start else "false",
        "preroll_s": repr(preroll_s),
        "vel_set_column": "feedforward",
    }
    if cfg.machine.kind == "linear":
        meta["encoder_resolution_m"] = repr(sen.encoder_resolution_m)
    else:
        meta["encoder_counts_per_rev"] = str(sen.encoder_counts_per_rev)
    if cfg.section("controller").get("feedback") == "scale":
        meta["scale_resolution_m"] = repr(sen.scale_resolution_m)
    return meta
