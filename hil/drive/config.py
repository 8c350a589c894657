"""The ``[drive]`` section of a machine file: the drive's monitoring and fault-reaction
objects, and :class:`DriveParameters`, the values the drive runs on.

Every key stands for a CiA 402 object (named in its doc).  A key that is absent takes a
default derived from the rest of the machine file (said in its doc); on CAN the same
objects are readable and writable by SDO (:mod:`hil.drive.objects`).  Positions and
accelerations are in table units (m, m/s² on screw and linear axes; deg, deg/s² on rotary
tables), the motor speed in rpm (m/s for linear motors), as a commissioning engineer
reads them; inside, :class:`DriveParameters` holds them in the motor coordinate the drive's
loops use (rad, rad/s, rad/s²; m, m/s, m/s² on linear motors).
"""

import math
from dataclasses import dataclass

from hil.cia402 import AbortConnectionOption, FaultReactionOption, QuickStopOption
from hil.controller.config import ControllerSection, axis_limits, kv_si, motor_constant
from hil.drive.braking import (
    RAMP_TIME_LIMIT_S,
    braking_room,
    min_deceleration,
    reaction_deceleration,
    reaction_time,
    stopping_distance,
    top_speed,
)
from plant.assemble import reflected_inertia, transmission_ratio, voltage_limit
from plant.config import MachineConfig, build_section, check_applies
from plant.errors import ConfigError
from plant.schema import key

DERIVED = None
LINEAR_KINDS = "kind=screw|linear"
#: the share of the room between the travel's ends and the limit switches the derived
#: quick stop deceleration may need (the rest stays for 607Dh's margin beyond the travel)
ROOM_SHARE = 0.8
#: default homing speeds (6099h) as shares of the profile velocity 6081h
HOMING_SWITCH_SHARE = 0.1
HOMING_ZERO_SHARE = 0.01


@dataclass(frozen=True, kw_only=True)
class DriveSection:
    """Drive monitoring and fault reaction (CiA 402 objects); absent keys are derived."""
    following_error_window_m: float = key(
        "m", "6065h following error window (CSP); 0: monitoring off (FFFFFFFFh). Absent: 1.5 "
        "times the following error at the maximum velocity without feed-forward, v_max/K_v "
        "([controller]); off without [controller].", DERIVED, ge=0.0, le=50.0, only=LINEAR_KINDS)
    following_error_window_deg: float = key(
        "deg", "6065h following error window of a rotary table (see the _m key).", DERIVED,
        ge=0.0, le=3600.0, only="kind=rotary")
    following_error_time_s: float = key(
        "s", "6066h following error time out: how long the error may stay beyond the window.",
        0.01, ge=0.0, le=65.535)
    position_window_m: float = key(
        "m", "6067h position window: CSP target reached (statusword bit 10) within it.", 1e-5,
        ge=0.0, le=50.0, only=LINEAR_KINDS)
    position_window_deg: float = key("deg", "6067h position window of a rotary table.", 0.01,
                                     ge=0.0, le=3600.0, only="kind=rotary")
    position_window_time_s: float = key("s", "6068h position window time.", 0.01, ge=0.0,
                                        le=65.535)
    software_limit_min_m: float = key(
        "m", "607Dh:01 minimum software position limit. Absent: halfway from the start of "
        "the travel (0) to the negative limit switch ([table] limit_switch_overtravel_m).",
        DERIVED, ge=-100.0, le=100.0, only=LINEAR_KINDS)
    software_limit_max_m: float = key(
        "m", "607Dh:02 maximum software position limit; equal to the minimum: limits off. "
        "Absent: halfway from the end of [table] travel_m to the positive limit switch.",
        DERIVED, ge=-100.0, le=100.0, only=LINEAR_KINDS)
    software_limit_min_deg: float = key("deg", "607Dh:01 of a rotary table. Absent: off.",
                                        0.0, ge=-3.6e6, le=3.6e6, only="kind=rotary")
    software_limit_max_deg: float = key("deg", "607Dh:02 of a rotary table; equal to the "
                                        "minimum: off (the default).", 0.0, ge=-3.6e6,
                                        le=3.6e6, only="kind=rotary")
    max_motor_speed_rpm: float = key(
        "rpm", "6080h maximum motor speed: speed commands are limited to it, 1.1 times it is "
        "an overspeed fault; 0: off. Absent: 1.2 times the [controller] maximum velocity at "
        "the motor, else the dq motor's no-load speed at the voltage limit, else off.",
        DERIVED, ge=0.0, le=1e5, only="kind=screw|rotary")
    max_motor_speed_m_s: float = key("m/s", "6080h maximum speed of a linear motor (see the "
                                     "rpm key).", DERIVED, ge=0.0, le=100.0, only="kind=linear")
    max_current_a: float = key(
        "A", "6072h maximum torque, as the q-current limit the drive applies to every current "
        "setpoint (<= [motor] current_max_a). Absent: [motor] current_max_a.", DERIVED, gt=0.0,
        le=5000.0)
    quick_stop_deceleration_m_s2: float = key(
        "m/s^2", "6085h quick stop deceleration. Absent: half the acceleration the motor gives "
        "the axis at [motor] current_max_a, or more (up to what max_current_a gives) where "
        "the fault reaction from 1.1 x 6080h would need more than 80 % of the room from the "
        "travel's ends to the limit switches.", DERIVED, gt=0.0, le=1e4, only=LINEAR_KINDS)
    quick_stop_deceleration_deg_s2: float = key(
        "deg/s^2", "6085h quick stop deceleration of a rotary table.", DERIVED, gt=0.0,
        le=1e7, only="kind=rotary")
    profile_deceleration_m_s2: float = key(
        "m/s^2", "6084h profile deceleration, the slow down ramp. Absent: the [controller] "
        "maximum acceleration, else the quick stop deceleration.", DERIVED, gt=0.0, le=1e4,
        only=LINEAR_KINDS)
    profile_deceleration_deg_s2: float = key("deg/s^2", "6084h of a rotary table.", DERIVED,
                                             gt=0.0, le=1e7, only="kind=rotary")
    quick_stop_option: int = key("1", "605Ah quick stop option code, 1-8.", 2, ge=1, le=8)
    fault_reaction_option: int = key(
        "1", "605Eh fault reaction option code: 0 torque off, 1 slow down ramp, 2 quick stop "
        "ramp, 3 current limit, 4 voltage limit (here: current limit).", 2, ge=0, le=4)
    abort_connection_option: int = key(
        "1", "6007h abort connection option code: what setpoint silence, a lost heartbeat or "
        "an NMT stop/reset does: 0 nothing, 1 fault, 2 disable voltage, 3 quick stop.", 1,
        ge=0, le=3)
    continuous_current_a: float = key(
        "A", "I2t: the current the drive carries without end (< [motor] current_max_a). "
        "Absent: half of [motor] current_max_a.", DERIVED, gt=0.0, le=5000.0)
    overload_time_s: float = key(
        "s", "I2t: how long [motor] current_max_a may flow from cold before the over-current "
        "fault (2310h).", 1.0, gt=0.0, le=3600.0)
    communication_cycle_s: float = key(
        "s", "1006h communication cycle period on CANopen: the SYNC period the drive takes its "
        "setpoints at and interpolates them over (60C2h), in whole PWM periods.", 0.001,
        ge=0.00025, le=0.01)
    interpolation_time_period_s: float = key(
        "s", "60C2h interpolation time period: the drive moves each cyclic target (CSP, CSV) "
        "to the next one linearly over this time, in whole PWM periods; set it to the "
        "controller's cycle when that is longer than a PWM period (a LinuxCNC servo period "
        "over UDP). 0: each target taken as it comes. On CANopen the master writes 60C2h.",
        0.0, ge=0.0, le=0.255)


@dataclass
class DriveParameters:
    """What the drive runs on, in the motor coordinate (rad; m on linear motors).

    Mutable: a master writes these objects by SDO while the drive runs (each write is one
    attribute; the loop reads them every cycle).  ``inf`` bounds mean "off".  Every write
    raises ``generation`` (an int, not a field).

    Attributes:
        fe_window: 6065h, inf: off.
        fe_time_s: 6066h.
        position_window: 6067h.
        position_window_time_s: 6068h.
        limit_min, limit_max: 607Dh (-inf/inf: off).
        max_speed: 6080h, motor units/s (inf: off).
        max_current_a: 6072h as a q-current limit.
        quick_stop_decel: 6085h, motor units/s².
        profile_decel: 6084h, motor units/s².
        quick_stop_option, fault_reaction_option, abort_connection_option: 605Ah, 605Eh,
            6007h.
        continuous_current_a, overload_time_s: the I²t model (the peak current may flow
            for overload_time_s from cold).
        current_max_a: the power stage's peak current ([motor] current_max_a), the bound of
            max_current_a.
        communication_cycle_s: 1006h, s.
        interpolation_value, interpolation_index: 60C2h, the interpolation time period
            value * 10**index s; 0: each cyclic setpoint is taken as it comes (a link that
            delivers one every drive cycle).
        profile_velocity: 6081h, motor units/s.
        profile_acceleration: 6083h, motor units/s².
        homing_method: 6098h.
        homing_speed_switch, homing_speed_zero: 6099h:01 and :02, motor units/s.
        homing_acceleration: 609Ah, motor units/s².
        home_offset: 607Ch, motor units: the position actual value at the home position.
        accel_per_amp: the motor's acceleration per ampere of q-current, motor units/s²/A
            (K_t over the inertia it moves, the table's reflected): with 6072h, the
            deceleration braking at the current limit reaches.
        coast_decel: the deceleration the table's Coulomb friction alone gives, less any
            constant external force, motor units/s² (>= 0): braking with torque off.
        switch_min, switch_max: the limit switches, motor units (-inf/inf: none).
        stop_min, stop_max: the mechanical end stops, motor units (-inf/inf: none).
        reaction_time_s: from a fault's cause to full braking current, s
            (:func:`hil.drive.braking.reaction_time` of the plant's current loop).
    """
    fe_window: float
    fe_time_s: float
    position_window: float
    position_window_time_s: float
    limit_min: float
    limit_max: float
    max_speed: float
    max_current_a: float
    quick_stop_decel: float
    profile_decel: float
    quick_stop_option: int
    fault_reaction_option: int
    abort_connection_option: int
    continuous_current_a: float
    overload_time_s: float
    current_max_a: float
    communication_cycle_s: float
    interpolation_value: int
    interpolation_index: int
    profile_velocity: float
    profile_acceleration: float
    homing_method: int
    homing_speed_switch: float
    homing_speed_zero: float
    homing_acceleration: float
    home_offset: float
    accel_per_amp: float
    coast_decel: float
    switch_min: float
    switch_max: float
    stop_min: float
    stop_max: float
    reaction_time_s: float

    def __setattr__(self, name: str, value) -> None:
        # every write counts, so a copy of these values (the compiled path's) knows it is old
        object.__setattr__(self, name, value)
        object.__setattr__(self, "generation", self.__dict__.get("generation", 0) + 1)

    @property
    def interpolation_period_s(self) -> float:
        """60C2h in s (0: no interpolation)."""
        return self.interpolation_value * 10.0 ** self.interpolation_index

    @property
    def i2t_trip_a2s(self) -> float:
        """The I²t integral of (i² - continuous²) that trips the over-current fault: the
        power stage's peak current for ``overload_time_s`` from cold, A²·s."""
        return (self.current_max_a ** 2 - self.continuous_current_a ** 2) * self.overload_time_s


def _per_motor_unit(cfg: MachineConfig) -> tuple[float, float]:
    """(table unit of the keys per motor unit, motor unit per rpm-or-m/s key unit)."""
    kind = cfg.machine.kind
    table_per_motor = transmission_ratio(cfg)
    if kind == "rotary":
        table_per_motor = 180.0 / math.pi  # deg per rad (direct drive)
    speed = 1.0 if kind == "linear" else 2.0 * math.pi / 60.0  # rad/s per rpm
    return table_per_motor, speed


def _motor_acceleration(cfg: MachineConfig) -> float:
    """The motor's acceleration at [motor] current_max_a, motor units/s²."""
    return cfg.motor.current_max_a * motor_constant(cfg) / reflected_inertia(cfg)


def _coast_deceleration(cfg: MachineConfig) -> float:
    """The deceleration of the table's Coulomb friction less a constant external force,
    with torque off, motor units/s² (>= 0)."""
    fr = cfg.friction
    if cfg.table is None:
        force, push = fr.coulomb_nm, abs(cfg.mechanics.external_torque_nm)
    else:
        force, push = fr.coulomb_n, abs(cfg.table.external_force_n)
    return max(force - push, 0.0) * transmission_ratio(cfg) / reflected_inertia(cfg)


def _current_loop_time_constant(cfg: MachineConfig) -> float:
    """The closed current loop's time constant, s: [current_loop] time_constant_s of a
    first-order model; L_q / K_p of a PI loop whose zero cancels the winding's pole."""
    cl = cfg.current_loop
    if cfg.motor.model == "first_order":
        return cl.time_constant_s
    return cfg.motor.inductance_q_h / cl.kp_v_per_a


def _barriers(cfg: MachineConfig, per: float) -> tuple[float, float, float, float]:
    """(negative, positive limit switch, negative, positive end stop), motor units; none
    (-inf/inf) without a table (a rotary table)."""
    if cfg.table is None:
        return -math.inf, math.inf, -math.inf, math.inf
    t = cfg.table
    switch, stop = t.limit_switch_overtravel_m, t.end_stop_overtravel_m
    return -switch / per, (t.travel_m + switch) / per, -stop / per, (t.travel_m + stop) / per


def _no_load_speed(cfg: MachineConfig) -> float:
    """The dq motor's speed at which the back-EMF takes the whole voltage vector
    (U_dc/sqrt(3) with SVPWM, U_dc/2 with sine PWM: :func:`plant.assemble.voltage_limit`),
    motor units/s (inf for other motor models: they state no voltage limit)."""
    if cfg.motor.model != "dq":
        return math.inf
    return 1.5 * voltage_limit(cfg) / motor_constant(cfg)  # omega = U / (p psi), K_t = 1.5 p psi


def current_limit_a(cfg: MachineConfig) -> float:
    """6072h as the q-current limit, A: ``[drive] max_current_a``, absent [motor]
    current_max_a (the bound :func:`load_drive` checks it against)."""
    sec = build_section(DriveSection, cfg.section("drive"), cfg.path, "drive")
    return sec.max_current_a or cfg.motor.current_max_a


def load_drive(cfg: MachineConfig, controller: ControllerSection | None) -> DriveParameters:
    """The drive's parameters from ``cfg``'s ``[drive]`` section (absent keys derived);
    ConfigError names the file, the key and the unit."""
    raw = cfg.section("drive")
    sec = build_section(DriveSection, raw, cfg.path, "drive")
    check_applies(sec, raw, {"kind": cfg.machine.kind, "model": cfg.motor.model}, cfg.path,
                  "drive")
    kind = cfg.machine.kind
    rotary, linear = kind == "rotary", kind == "linear"
    pos_sfx, acc_sfx = ("_deg", "_deg_s2") if rotary else ("_m", "_m_s2")
    per, rpm = _per_motor_unit(cfg)

    def given(name: str):
        return getattr(sec, name)

    v_max = kv = None
    if controller is not None:
        v_max = axis_limits(cfg, controller).velocity  # table SI units/s (m or rad)
        kv = kv_si(controller)
    table_si_per_motor = transmission_ratio(cfg)  # m (or rad) per motor unit

    fe = given("following_error_window" + pos_sfx)
    if fe is None:
        fe_window = (1.5 * v_max / kv / table_si_per_motor if v_max else math.inf)
    else:
        fe_window = fe / per if fe > 0.0 else math.inf
    lo, hi = given("software_limit_min" + pos_sfx), given("software_limit_max" + pos_sfx)
    if lo is not None and hi is not None and lo > hi:
        raise ConfigError(f"{cfg.path}: [drive] software_limit_min{pos_sfx} = {lo:g} must be "
                          f"<= software_limit_max{pos_sfx} = {hi:g} ({pos_sfx[1:]})")
    speed_key = "max_motor_speed_m_s" if linear else "max_motor_speed_rpm"
    speed = given(speed_key)
    if speed is None:
        max_speed = 1.2 * v_max / table_si_per_motor if v_max else _no_load_speed(cfg)
    else:
        max_speed = speed * rpm if speed > 0.0 else math.inf
    i_peak = cfg.motor.current_max_a
    max_current = current_limit_a(cfg)
    if max_current > i_peak:
        raise ConfigError(f"{cfg.path}: [drive] max_current_a = {max_current:g} A must be <= "
                          f"[motor] current_max_a = {i_peak:g} A (the power stage's peak)")
    continuous = given("continuous_current_a") or 0.5 * i_peak
    if continuous >= i_peak:
        raise ConfigError(f"{cfg.path}: [drive] continuous_current_a = {continuous:g} A must "
                          f"be < [motor] current_max_a = {i_peak:g} A")
    qs = given("quick_stop_deceleration" + acc_sfx)
    quick_stop = qs / per if qs is not None else 0.5 * _motor_acceleration(cfg)
    pd = given("profile_deceleration" + acc_sfx)
    if pd is not None:
        profile = pd / per
    elif controller is not None:
        profile = axis_limits(cfg, controller).acceleration / table_si_per_motor
    else:
        profile = quick_stop
    cycle = sec.communication_cycle_s
    for name, period in (("communication_cycle_s", cycle),
                         ("interpolation_time_period_s", sec.interpolation_time_period_s)):
        pwm_periods = period * cfg.motor.pwm_frequency_hz
        if abs(pwm_periods - round(pwm_periods)) > 1e-6:
            raise ConfigError(f"{cfg.path}: [drive] {name} = {period:g} s must be a whole "
                              f"number of PWM periods (1/{cfg.motor.pwm_frequency_hz:g} s)")
    interpolation_value, interpolation_index = interpolation_time_period(
        cfg, sec.interpolation_time_period_s)
    profile_velocity = (v_max / table_si_per_motor if v_max
                        else max_speed if math.isfinite(max_speed) else 0.0)
    switch_min, switch_max, stop_min, stop_max = _barriers(cfg, per)
    params = DriveParameters(
        fe_window=fe_window, fe_time_s=sec.following_error_time_s,
        position_window=given("position_window" + pos_sfx) / per,
        position_window_time_s=sec.position_window_time_s,
        limit_min=-math.inf, limit_max=math.inf, max_speed=max_speed,
        max_current_a=max_current, quick_stop_decel=quick_stop, profile_decel=profile,
        quick_stop_option=int(QuickStopOption(sec.quick_stop_option)),
        fault_reaction_option=int(FaultReactionOption(sec.fault_reaction_option)),
        abort_connection_option=int(AbortConnectionOption(sec.abort_connection_option)),
        continuous_current_a=continuous, overload_time_s=sec.overload_time_s,
        current_max_a=i_peak, communication_cycle_s=cycle,
        interpolation_value=interpolation_value, interpolation_index=interpolation_index,
        profile_velocity=profile_velocity,
        profile_acceleration=profile, homing_method=0,
        homing_speed_switch=HOMING_SWITCH_SHARE * profile_velocity,
        homing_speed_zero=HOMING_ZERO_SHARE * profile_velocity,
        homing_acceleration=profile, home_offset=0.0,
        accel_per_amp=motor_constant(cfg) / reflected_inertia(cfg),
        coast_decel=_coast_deceleration(cfg), switch_min=switch_min, switch_max=switch_max,
        stop_min=stop_min, stop_max=stop_max,
        reaction_time_s=reaction_time(_current_loop_time_constant(cfg)))
    braking = controller is not None
    if qs is None and lo is None and hi is None and braking:
        params.quick_stop_decel = _quick_stop_for_room(cfg, params)
    _check_ramps(cfg, params, {"quick_stop_deceleration": qs, "profile_deceleration": pd})
    params.limit_min, params.limit_max = _software_limits(cfg, params, lo, hi, braking)
    short = braking_room(params, braking)
    if short:
        raise ConfigError(_room_text(cfg, params, short))
    return params


def interpolation_time_period(cfg: MachineConfig, period_s: float) -> tuple[int, int]:
    """60C2h (:01 value, u8; :02 index, the power of ten of the unit) for ``period_s``:
    the coarsest unit from 1 ms to 1 µs that gives a whole value; (0, -3) for 0."""
    for index in (-3, -4, -5, -6):
        value = period_s * 10.0 ** -index
        if abs(value - round(value)) < 1e-6 and round(value) <= 0xFF:
            return round(value), index
    raise ConfigError(f"{cfg.path}: [drive] interpolation_time_period_s = {period_s:g} s is "
                      f"not a value of 60C2h (a whole 1-255 ms, 100 µs, 10 µs or µs)")


def _quick_stop_for_room(cfg: MachineConfig, p: DriveParameters) -> float:
    """6085h when the file gives none (nor 607Dh): half the motor's acceleration at
    [motor] current_max_a, raised where the quick stop reaction (605Eh = 2) from 1.1 x
    6080h would need more than :data:`ROOM_SHARE` of the room between the travel's ends
    and the limit switches, up to the deceleration 6072h gives (a heavier table, a weaker
    motor: what a commissioning engineer sets); motor units/s²."""
    top = top_speed(p.max_speed)
    if cfg.table is None or p.fault_reaction_option != 2 or not math.isfinite(top):
        return p.quick_stop_decel
    room = min(p.switch_max - cfg.table.travel_m / _units(cfg)[0], -p.switch_min)
    budget = ROOM_SHARE * room - top * p.reaction_time_s
    if budget <= 0.0:
        return p.quick_stop_decel  # no deceleration fits: the room check refuses the file
    needed = top * top / (2.0 * budget)
    return max(p.quick_stop_decel, min(needed, p.max_current_a * p.accel_per_amp))


def _units(cfg: MachineConfig) -> tuple[float, str]:
    """(the keys' table unit per motor unit, that unit's name: m or deg)."""
    return _per_motor_unit(cfg)[0], "deg" if cfg.machine.kind == "rotary" else "m"


def _check_ramps(cfg: MachineConfig, p: DriveParameters, given: dict) -> None:
    """Refuse a slow down (6084h) or quick stop (6085h) ramp below
    :func:`~hil.drive.braking.min_deceleration`, given or derived."""
    per, unit = _units(cfg)
    bound = min_deceleration(p.max_speed)
    for name, value in (("quick_stop_deceleration", p.quick_stop_decel),
                        ("profile_deceleration", p.profile_decel)):
        if value < bound:
            origin = ("" if given[name] is not None
                      else " (derived: give it in the [drive] section)")
            raise ConfigError(
                f"{cfg.path}: [drive] {name}_{unit}_s2 = {value * per:.4g} {unit}/s^2{origin} "
                f"is below {bound * per:.4g} {unit}/s^2, the least that stops the axis from "
                f"its top speed {top_speed(p.max_speed) * per:.4g} {unit}/s (1.1 x 6080h) "
                f"within {RAMP_TIME_LIMIT_S:g} s")


def _software_limits(cfg: MachineConfig, p: DriveParameters, lo: float | None,
                     hi: float | None, braking: bool) -> tuple[float, float]:
    """607Dh in motor units, (-inf, inf) when off (min = max).  An absent limit of a table
    with a stroke is derived (:mod:`hil.drive.braking`): halfway between the end of the
    travel and the last point from which the fault reaction stops the axis at its top
    speed before the limit switch (halfway to the switch when 6080h is off, or on a drive
    that cannot brake: its controller owns the braking); refused when even the end of the
    travel leaves no such room."""
    per, unit = _units(cfg)
    if cfg.table is not None and (lo is None or hi is None):
        travel = cfg.table.travel_m / per
        top = top_speed(p.max_speed)
        need = (stopping_distance(p, top, p.fault_reaction_option)
                if braking and math.isfinite(top) else 0.0)
        farthest = (p.switch_min + need, p.switch_max - need)
        if farthest[0] > 0.0 or farthest[1] < travel:
            raise ConfigError(_room_text(cfg, p, [], derive=True))
        lo = 0.5 * farthest[0] * per if lo is None else lo
        hi = (travel + 0.5 * (farthest[1] - travel)) * per if hi is None else hi
        if lo > hi:
            raise ConfigError(f"{cfg.path}: [drive] software_limit_min_{unit} = {lo:g} must "
                              f"be <= software_limit_max_{unit} = {hi:g} ({unit})")
    return (lo / per, hi / per) if lo < hi else (-math.inf, math.inf)


_REACTION = {0: "torque off, coasting on the friction", 1: "the slow down ramp 6084h",
             2: "the quick stop ramp 6085h", 3: "the current limit", 4: "the current limit"}


def _room_text(cfg: MachineConfig, p: DriveParameters, short: list,
               derive: bool = False) -> str:
    """Why an axis at its top speed would not stop before its limit switch (or end stop),
    with the numbers in the keys' units and what would make room."""
    per, unit = _units(cfg)
    option = p.fault_reaction_option
    top = top_speed(p.max_speed)
    need = stopping_distance(p, top, option)
    how = (f"from its top speed {top * per:.4g} {unit}/s (1.1 x 6080h) the fault reaction "
           f"(605Eh = {p.fault_reaction_option}: {_REACTION[option]}, "
           f"{reaction_deceleration(p, option) * per:.4g} {unit}/s^2, after "
           f"{p.reaction_time_s * 1e3:.3g} ms) runs {need * per:.4g} {unit}")
    fix = ("raise the reaction's deceleration, lower max_motor_speed"
           f"{'_m_s' if cfg.machine.kind == 'linear' else '_rpm'}, or move the limit "
           "switches out ([table] limit_switch_overtravel_m)")
    if derive:
        return (f"{cfg.path}: [drive] software_limit_min/max_{unit} cannot be derived: [table] "
                f"limit_switch_overtravel_m = {cfg.table.limit_switch_overtravel_m:g} m leaves "
                f"no room beyond the travel to stop before the limit switches: {how}; {fix}")
    limits_on = math.isfinite(p.limit_min)
    side, room, _ = short[0]
    start = f"software_limit_{side}_{unit} = {getattr(p, 'limit_' + side) * per:.4g} {unit}"
    barrier = "limit switch" if limits_on else "end stop"
    if not limits_on:
        start = f"the {side} limit switch (the software limits are off)"
    return (f"{cfg.path}: [drive] {start} leaves {room * per:.4g} {unit} to the {barrier}, "
            f"too little: {how}; {fix}")

