"""How hard, how far and how long the drive brakes: the bounds every braking reaction is
held to, and the room a linear axis needs to stop before its limit switch.

A braking reaction (a quick stop, 605Ah, or a fault reaction, 605Eh) is bounded three
ways, as a commercial drive's safe stop (SS1 with its brake ramp monitoring) bounds it:

* **its ramp is steep enough**: 6084h and 6085h must stop the axis from its top speed
  (:func:`top_speed`) within :data:`RAMP_TIME_LIMIT_S` (:func:`min_deceleration`); the
  machine file and an SDO write are refused below that;
* **the speed actually falls**: after the drive's reaction time (``reaction_time_s``,
  :func:`reaction_time`) the speed actual must stay under an envelope that falls from the
  speed at the reaction's start (plus a tolerance: :data:`SPEED_TOLERANCE_SHARE` of it,
  at least the standstill speed, and what the axis gains at the current limit within the
  reaction time) at 1/:data:`RAMP_TIME_FACTOR` of the deceleration the axis is expected
  to reach (:func:`reaction_deceleration`), down to the standstill speed
  (:class:`hil.drive.reaction.BrakeRamp`);
* **in time**: so the envelope reaches the standstill speed at the latest after the
  reaction time plus :data:`RAMP_TIME_FACTOR` times the ideal braking time from the start
  speed and its tolerance; a reaction that has not stopped the axis by then has failed.

A failed reaction is the cause ``REACTION_FAILED`` (FF04h): pulses inhibited at once
(torque off) and the holding brake closed where the machine has one.

**Room to brake** (:func:`braking_room`): from the last position the drive monitors (the
software position limit 607Dh, or the limit switch where 607Dh is off), an axis at its top
speed must stop, on the fault reaction 605Eh selects, before the next barrier (the limit
switch, or the mechanical end stop).  The distance is the speed times
the reaction time (the fault's detection and the current's reversal) plus the braking
distance at :func:`reaction_deceleration`.  The derived 607Dh of a screw or linear
axis sits halfway between the end of the programmable travel and the last point that
leaves that room (:mod:`hil.drive.config`).
"""

import math

from hil.drive.faults import OVERSPEED_FACTOR

#: a reaction ramp (6084h, 6085h) stops the axis from its top speed within this time, s:
#: a lower bound of the deceleration (refused below it)
RAMP_TIME_LIMIT_S = 2.0
#: a braking reaction may take this many times its ideal braking time (after the
#: reaction time)
RAMP_TIME_FACTOR = 1.5
#: the speed envelope's tolerance: this share of the speed at the reaction's start
SPEED_TOLERANCE_SHARE = 0.1
#: the reaction time's part before the current loop: the cycle that detects a cause, the
#: speed cycle that answers it, s
DETECTION_TIME_S = 0.003
#: the current loop's part of the reaction time: this many of its time constants (the
#: current from +peak to -peak: 95 % of the step after three)
CURRENT_TIME_CONSTANTS = 3.0


def reaction_time(current_loop_time_constant_s: float) -> float:
    """From a fault's cause to full braking current, s: :data:`DETECTION_TIME_S` plus
    :data:`CURRENT_TIME_CONSTANTS` time constants of the closed current loop (``s``).
    The axis runs this long at full speed, and may still gain speed, before the braking
    deceleration acts."""
    return DETECTION_TIME_S + CURRENT_TIME_CONSTANTS * current_loop_time_constant_s


def top_speed(max_speed: float) -> float:
    """The fastest the axis runs without an overspeed fault, motor units/s: 6080h times
    :data:`~hil.drive.faults.OVERSPEED_FACTOR` (inf when 6080h is off)."""
    return OVERSPEED_FACTOR * max_speed


def min_deceleration(max_speed: float) -> float:
    """The lower bound of 6084h and 6085h: a stop from :func:`top_speed` within
    :data:`RAMP_TIME_LIMIT_S`, motor units/s² (0 when 6080h is off: no top speed)."""
    top = top_speed(max_speed)
    return top / RAMP_TIME_LIMIT_S if math.isfinite(top) else 0.0


def reaction_deceleration(params, option: int) -> float:
    """The deceleration a braking reaction reaches at least, motor units/s²: the ramp of
    option code ``option`` (605Ah reduced to 1-4, or 605Eh: 1 slow down ramp 6084h, 2 quick
    stop ramp 6085h, 3 and 4 the current limit), no more than the current limit 6072h
    gives; coasting on the friction alone for code 0."""
    if option == 0:
        return params.coast_decel
    ramp = {1: params.profile_decel, 2: params.quick_stop_decel}.get(option, math.inf)
    return min(ramp, params.max_current_a * params.accel_per_amp)


def envelope(params, option: int, speed: float, standstill: float) -> tuple[float, float,
                                                                           float]:
    """The speed envelope of a braking reaction of option code ``option`` that starts at
    ``speed`` (motor units/s): (its ceiling, motor units/s: the speed plus the tolerance;
    its slope, motor units/s²: the expected deceleration over :data:`RAMP_TIME_FACTOR`;
    its delay, s: the drive's reaction time), ``standstill`` the standstill speed."""
    t_r = params.reaction_time_s
    gain = params.max_current_a * params.accel_per_amp * t_r
    ceiling = abs(speed) + max(SPEED_TOLERANCE_SHARE * abs(speed), standstill) + gain
    return ceiling, reaction_deceleration(params, option) / RAMP_TIME_FACTOR, t_r


def time_limit(ceiling: float, slope: float, delay_s: float, standstill: float) -> float:
    """When an :func:`envelope` has fallen to the standstill speed, s after the reaction's
    start: the longest a braking reaction may take (inf: a slope of 0)."""
    return delay_s + (ceiling - standstill) / slope if slope > 0.0 else math.inf


def stopping_distance(params, speed: float, option: int) -> float:
    """The distance the axis runs from ``speed`` (motor units/s) until it stands, on
    option code ``option`` (:func:`reaction_deceleration`): ``speed`` for the drive's
    ``reaction_time_s``, then the braking distance; motor units (inf: it does not
    stop)."""
    a = reaction_deceleration(params, option)
    speed = abs(speed)
    if a <= 0.0:
        return math.inf if speed > 0.0 else 0.0
    return speed * params.reaction_time_s + speed * speed / (2.0 * a)


def braking_room(params, braking: bool) -> list[tuple[str, float, float]]:
    """The sides where an axis at :func:`top_speed` would not stop on 605Eh before its
    next barrier: (side "min" or "max", room, distance needed), motor units; empty when
    every side has room, or the axis has no barriers, no top speed, or a drive that cannot
    brake (``braking`` False: no speed loop, its controller owns the braking)."""
    top = top_speed(params.max_speed)
    if not braking or not math.isfinite(top):
        return []
    need = stopping_distance(params, top, params.fault_reaction_option)
    limits_on = math.isfinite(params.limit_min) or math.isfinite(params.limit_max)
    sides = (("min", params.limit_min, params.switch_min, params.stop_min),
             ("max", params.limit_max, params.switch_max, params.stop_max))
    short = []
    for side, limit, switch, stop in sides:
        start, barrier = (limit, switch) if limits_on else (switch, stop)
        room = barrier - start if side == "max" else start - barrier
        if not math.isnan(room) and room < need:  # NaN: neither switch nor stop
            short.append((side, room, need))
    return short
