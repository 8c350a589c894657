"""The controller's conventions a record was taken with, from its ``# key: value`` header.

A servo trace means little without the timing and signal conventions of the controller that
wrote it (``docs/trace-format.md`` of the shared docs, "Conventions in the header").  Most of
them are properties of the controller and have a machine-file key: the header's value, when
given, overrides the machine file's for the replay of that record.  Two describe the recording
alone and live in the header only: ``preroll_s`` and ``vel_set_column``.

=============================== ============================================================
header key                      machine-file key it sets
=============================== ============================================================
``position_loop_sample_time_s`` ``[controller] position_cycle_ratio`` (PWM periods)
``speed_loop_sample_time_s``    ``[controller] speed_cycle_ratio`` (PWM periods)
``current_loop_sample_time_s``  none: must be the plant's PWM period (its current loop's)
``feedforward_interpolation``   ``[controller] feedforward_interpolation``
``velocity_feedforward_factor`` ``[controller] speed_ff_weight`` (and ``speed_ff``)
``speed_actual_filter_s``       ``[controller] speed_actual_filter_s``
``speed_antiwindup``            ``[controller] speed_antiwindup``
``current_delay_cycles``        ``[controller] current_delay_cycles``
``current_adc_bits``,           ``[sensors] current_lsb_a`` = 2 full scale / 2^bits, and
``current_adc_full_scale_a``    ``[sensors] current_full_scale_a`` = full scale (clipping)
``encoder_counts_per_rev``,     ``[sensors]`` keys of the same names
``encoder_resolution_m``,
``scale_resolution_m``,
``encoder_rounding``,
``encoder_zero_at_start``
``voltage_limit``               ``[motor] voltage_limit`` (a ``dq`` motor model only)
``karnopp_reversal``            ``[friction] karnopp_reversal`` (Karnopp friction only)
``preroll_s``                   none: the replay starts this long before t = 0, at rest
``vel_set_column``              none: ``feedforward`` (trace-format.md) or ``speed_command``
=============================== ============================================================

A value the replay cannot honour is a :class:`ConventionError` naming the record, the key,
the value and what would be accepted.
"""

import dataclasses
import math
from dataclasses import dataclass, field

from hil.controller.config import ANTIWINDUP_MODES
from hil.identify.record import Record
from hil.trace_file import TraceFormatError
from plant.config import MachineConfig
from plant.sections import REVERSALS, ROUNDINGS, VOLTAGE_LIMITS

#: relative tolerance of a cycle time against a whole number of PWM periods
CYCLE_TOLERANCE = 1e-3
#: the feed-forward column's meanings: trace-format.md's, and the whole speed command that
#: this project's own trace writers put there before they followed it
VEL_SET_MEANINGS = ("feedforward", "speed_command")
#: ``encoder_zero_at_start``'s values as written, and what they mean
BOOLEANS = {"true": True, "false": False}
#: sources whose ``vel_set_mm_min`` is the whole speed command when the header has no
#: ``vel_set_column``: the traces hil.sim.servo_trace_columns wrote before it followed
#: trace-format.md (it now writes the feed-forward and says so in the header)
SPEED_COMMAND_SOURCES = ("hil sim", "hil controller", "tests (lock-step)")


class ConventionError(TraceFormatError):
    """A record's convention the replay cannot honour (the message names key and value)."""


@dataclass(frozen=True)
class Conventions:
    """What the replay needs to know about how a record was taken.

    Attributes:
        overrides: machine-file keys the header sets, ``{"section": {"key": value}}``.
        preroll_s: s the run stood at rest with zero setpoint before the first sample.
        vel_set_column: what the record's ``vel_set`` is: the speed feed-forward
            ("feedforward") or the whole speed command ("speed_command").
        given: the header keys that were read, as written.
    """
    overrides: dict = field(default_factory=dict)
    preroll_s: float = 0.0
    vel_set_column: str = "feedforward"
    given: dict = field(default_factory=dict)


def _number(rec: Record, key: str, text: str, *, integer: bool = False, lo: float = 0.0,
            hi: float = math.inf, unit: str = "") -> float:
    """``text`` as a finite number within [lo, hi], else ConventionError naming the key."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    ok = math.isfinite(value) and lo <= value <= hi and (not integer or value == int(value))
    if not ok:
        kind = "a whole number" if integer else "a number"
        raise ConventionError(f"{rec.source}: header key {key} = {text!r}: must be {kind} "
                              f">= {lo:g} and <= {hi:g}{' ' + unit if unit else ''}")
    return int(value) if integer else value


def _choice(rec: Record, key: str, text: str, choices: tuple[str, ...]) -> str:
    value = text.strip()
    if value not in choices:
        raise ConventionError(f"{rec.source}: header key {key} = {text!r}: must be one of "
                              + ", ".join(repr(c) for c in choices))
    return value


def _cycles(rec: Record, key: str, text: str, pwm_period_s: float) -> int:
    """A cycle time of the header in whole PWM periods of the machine file."""
    seconds = _number(rec, key, text, lo=1e-7, hi=1.0, unit="s")
    n = round(seconds / pwm_period_s)
    if n < 1 or abs(n * pwm_period_s - seconds) > CYCLE_TOLERANCE * seconds:
        raise ConventionError(f"{rec.source}: header key {key} = {text} s is not a whole "
                              f"number of the machine file's PWM periods ({pwm_period_s:g} s): "
                              "the replay runs the controller on the plant's basic clock")
    return n


def read_conventions(rec: Record, cfg: MachineConfig) -> Conventions:
    """The conventions of ``rec``'s header (``rec.meta``) for a replay through ``cfg``.

    Raises:
        ConventionError: a value that is no number, outside its range, not a whole number
            of PWM periods, a current loop cycle other than the plant's, a word outside its
            choices, or a plant key the machine file cannot take (``voltage_limit = "q"``
            without a ``dq`` motor, ``karnopp_reversal = "stop"`` without Karnopp friction).
    """
    meta = rec.meta
    pwm = 1.0 / cfg.motor.pwm_frequency_hz
    ctrl: dict = {}
    sensors: dict = {}
    given = {}

    def has(key: str) -> bool:
        if key in meta:
            given[key] = meta[key]
            return True
        return False

    if has("position_loop_sample_time_s"):
        n = _cycles(rec, "position_loop_sample_time_s", meta["position_loop_sample_time_s"],
                    pwm)
        ratio = n * pwm / rec.dt
        if not any(abs(r - round(r)) < CYCLE_TOLERANCE * r for r in (ratio, 1.0 / ratio)):
            raise ConventionError(f"{rec.source}: header key position_loop_sample_time_s = "
                                  f"{meta['position_loop_sample_time_s']} s against a sample "
                                  f"time of {rec.dt:g} s: neither is a whole multiple of the "
                                  "other")
        # the replay feeds its own IPO points (the record's setpoints): any multiple will do
        ctrl.update(position_cycle_ratio=n, ipo_cycle_ratio=n)
    if has("speed_loop_sample_time_s"):
        ctrl["speed_cycle_ratio"] = _cycles(rec, "speed_loop_sample_time_s",
                                            meta["speed_loop_sample_time_s"], pwm)
    if has("current_loop_sample_time_s"):
        n = _cycles(rec, "current_loop_sample_time_s", meta["current_loop_sample_time_s"], pwm)
        if n != 1:
            raise ConventionError(f"{rec.source}: header key current_loop_sample_time_s = "
                                  f"{meta['current_loop_sample_time_s']} s: the plant's current "
                                  f"loop runs once per PWM period ({pwm:g} s); set [motor] "
                                  "pwm_frequency_hz to match")
    if has("feedforward_interpolation"):
        ctrl["feedforward_interpolation"] = _choice(rec, "feedforward_interpolation",
                                                    meta["feedforward_interpolation"],
                                                    ("hold", "linear"))
    if has("velocity_feedforward_factor"):
        w = _number(rec, "velocity_feedforward_factor", meta["velocity_feedforward_factor"],
                    hi=2.0)
        ctrl.update(speed_ff=w > 0.0, speed_ff_weight=w)
    if has("speed_actual_filter_s"):
        ctrl["speed_actual_filter_s"] = _number(rec, "speed_actual_filter_s",
                                                meta["speed_actual_filter_s"], hi=1.0, unit="s")
    if has("speed_antiwindup"):
        ctrl["speed_antiwindup"] = _choice(rec, "speed_antiwindup", meta["speed_antiwindup"],
                                           ANTIWINDUP_MODES)
    if has("current_delay_cycles"):
        ctrl["current_delay_cycles"] = _number(rec, "current_delay_cycles",
                                               meta["current_delay_cycles"], integer=True,
                                               hi=64)
    bits, full = has("current_adc_bits"), has("current_adc_full_scale_a")
    if bits != full:
        missing = "current_adc_full_scale_a" if bits else "current_adc_bits"
        raise ConventionError(f"{rec.source}: header key {missing} missing: the current ADC's "
                              "step needs both current_adc_bits and current_adc_full_scale_a")
    if bits:
        n_bits = _number(rec, "current_adc_bits", meta["current_adc_bits"], integer=True,
                         lo=4, hi=32)
        scale = _number(rec, "current_adc_full_scale_a", meta["current_adc_full_scale_a"],
                        lo=0.01, hi=1e4, unit="A")
        sensors.update(current_lsb_a=2.0 * scale / 2.0 ** n_bits, current_full_scale_a=scale)
    if has("encoder_counts_per_rev"):
        sensors["encoder_counts_per_rev"] = _number(rec, "encoder_counts_per_rev",
                                                    meta["encoder_counts_per_rev"],
                                                    integer=True, lo=256, hi=2 ** 32)
    for key in ("encoder_resolution_m", "scale_resolution_m"):
        if has(key):
            sensors[key] = _number(rec, key, meta[key], lo=1e-10, hi=1e-3, unit="m")
    if has("encoder_rounding"):
        sensors["encoder_rounding"] = _choice(rec, "encoder_rounding",
                                              meta["encoder_rounding"], ROUNDINGS)
    if has("encoder_zero_at_start"):
        sensors["encoder_zero_at_start"] = BOOLEANS[_choice(
            rec, "encoder_zero_at_start", meta["encoder_zero_at_start"], tuple(BOOLEANS))]
    motor = _voltage_limit(rec, cfg) if has("voltage_limit") else {}
    friction = _karnopp_reversal(rec, cfg) if has("karnopp_reversal") else {}
    preroll = (_number(rec, "preroll_s", meta["preroll_s"], hi=60.0, unit="s")
               if has("preroll_s") else 0.0)
    if has("vel_set_column"):
        vel_set = _choice(rec, "vel_set_column", meta["vel_set_column"], VEL_SET_MEANINGS)
    else:
        source = str(meta.get("source", ""))
        vel_set = ("speed_command" if source.startswith(SPEED_COMMAND_SOURCES)
                   else "feedforward")
    overrides = {sec: keys for sec, keys in (("controller", ctrl), ("sensors", sensors),
                                             ("motor", motor), ("friction", friction)) if keys}
    return Conventions(overrides, preroll, vel_set, given)


def _voltage_limit(rec: Record, cfg: MachineConfig) -> dict:
    """``{"voltage_limit": ...}`` of the header; ConventionError where the machine file's
    motor has no voltage controller to limit (only the ``dq`` model has)."""
    value = _choice(rec, "voltage_limit", rec.meta["voltage_limit"], VOLTAGE_LIMITS)
    if cfg.motor.model != "dq" and value != "vector":
        raise ConventionError(f"{rec.source}: header key voltage_limit = {value!r}: "
                              f"{cfg.path} has [motor] model = {cfg.motor.model!r}, which "
                              "has no voltage controller; the key needs model = 'dq'")
    return {"voltage_limit": value}


def _karnopp_reversal(rec: Record, cfg: MachineConfig) -> dict:
    """``{"karnopp_reversal": ...}`` of the header; ConventionError where the machine
    file's friction is no Karnopp stick-slip (presliding, or no Coulomb or breakaway
    level), as its loader would refuse the machine-file key."""
    value = _choice(rec, "karnopp_reversal", rec.meta["karnopp_reversal"], REVERSALS)
    fr = cfg.friction
    levels = (fr.coulomb_nm, fr.breakaway_nm) if cfg.machine.kind == "rotary" else \
        (fr.coulomb_n, fr.breakaway_n)
    if value == "stop" and (cfg.presliding.enabled or not max(levels)):
        why = "[presliding] replaces it" if cfg.presliding.enabled else \
            "no Coulomb or breakaway level"
        raise ConventionError(f"{rec.source}: header key karnopp_reversal = 'stop' needs "
                              f"Karnopp stick-slip friction, and {cfg.path} has none ({why})")
    return {"karnopp_reversal": value}


def apply_conventions(cfg: MachineConfig, conv: Conventions) -> MachineConfig:
    """``cfg`` with the header's machine-file keys applied (the ``[controller]`` table
    replaced key by key, the ``[sensors]``, ``[motor]`` and ``[friction]`` values set;
    ranges and applicability are checked where the header is read)."""
    out = cfg
    ctrl = conv.overrides.get("controller")
    if ctrl:
        table = {**out.section("controller"), **ctrl}
        out = dataclasses.replace(out, foreign={**out.foreign, "controller": table})
    for name in ("sensors", "motor", "friction"):
        keys = conv.overrides.get(name)
        if keys:
            out = dataclasses.replace(out, **{name: dataclasses.replace(getattr(out, name),
                                                                        **keys)})
    return out
