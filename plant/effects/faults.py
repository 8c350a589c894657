"""Fault terms of a damaged axis (issue 14 part 6): encoder noise and lost counts, an
offset and gain error of the phase-a current sensor, a load-proportional torque ripple.

All of them are 0 after assembly; the run-time injector writes them (``P_ENC_NOISE`` ..
``P_RIPPLE_PHASE``, units in :mod:`plant.layout`) between drive cycles and sets
``P_FAULTS`` to :func:`faults_active`, so a healthy kernel pays one test per sub-step and
gives the same bits as without them.

* **Encoder noise**: each encoder sample (at the end of a PWM period, where the measured
  signals are sampled) reads ``floor(theta cpr + sigma N(0,1))``: a noisy analogue
  reading (sin/cos interpolation) floored to whole counts.  The draw is held in
  ``S_ENC_NOISE`` until the next sample.
* **Lost counts**: over each PWM period the counter misses one edge with probability
  ``min(1, P_ENC_LOST dn)``, dn the whole counts travelled in the period; a miss moves
  ``S_ENC_LOST`` by one count against the motion, and it stays (an incremental counter
  never gets it back until re-referenced).  The reading is the true count plus
  ``S_ENC_LOST``.
* **Current sensor on phase a** (two sensors, a and b; c = -a-b): the sensor reads
  ``(1 + g) i_a + offset``.  The error ``e = g i_a + offset`` enters the Clarke
  transform (alpha = a, beta = (a + 2 b)/sqrt(3)) as ``(e, e/sqrt(3))`` and the Park
  transform rotates it by -theta_e into d-q (:func:`two_sensor_dq`).  The current loop
  regulates the measurement, so the true current carries the error's opposite: an
  offset gives a q ripple at 1x the electrical frequency of amplitude 2 offset/sqrt(3),
  a gain error one at 2x (g i_q/sqrt(3)) and a mean of about -g/2 i_q.
* **Torque ripple**: the motor's electromagnetic torque (before cogging) times
  ``1 + a cos(k theta_e + phi)``, proportional to the load as the ripple of a broken
  bar or a shorted turn is (cogging is not).

The electrical angle is ``theta_e = pole_pairs * motor angle`` as for cogging, with the
Park transform ``i_a = i_d cos(theta_e) - i_q sin(theta_e)``.
"""

import math

from numba import njit

from plant.effects.pmsm import clamp
from plant.effects.rng import gaussian, uniform
from plant.effects.sensors import counts, whole_counts
from plant.layout import (
    MOTOR_COMMUTATION,
    P_ENC_COUNTS_PER_RAD,
    P_ENC_LOST,
    P_ENC_NOISE,
    P_ENC_ORIGIN,
    P_ENC_ROUND,
    P_I_GAIN_ERR,
    P_I_MAX,
    P_I_OFFSET,
    P_KT,
    P_MOTOR_MODEL,
    P_POLE_PAIRS,
    P_RIPPLE_AMP,
    P_RIPPLE_ORDER,
    P_RIPPLE_PHASE,
    P_SEED,
    P_SOFF_ROT,
    S_ENC_LOST,
    S_ENC_NOISE,
    S_ENC_PREV,
    S_ID,
    S_IQ,
    S_KM,
    S_RNG_COUNTER,
)

SQRT3 = math.sqrt(3.0)


@njit(cache=True, error_model="numpy")
def faults_active(p):
    """1.0 when a fault term acts (encoder noise or lost counts, current-sensor offset or
    gain error, torque ripple amplitude non-zero), else 0.0: the value of ``P_FAULTS``.
    A ripple order or phase without an amplitude changes nothing and does not count."""
    active = (p[P_ENC_NOISE] != 0.0 or p[P_ENC_LOST] != 0.0 or p[P_I_OFFSET] != 0.0
              or p[P_I_GAIN_ERR] != 0.0 or p[P_RIPPLE_AMP] != 0.0)
    return 1.0 if active else 0.0


@njit(cache=True, error_model="numpy")
def two_sensor_dq(i_d, i_q, theta_e, offset_a, gain_err):
    """Measured (i_d, i_q) in A of the true ``i_d``, ``i_q`` (A) at the electrical angle
    ``theta_e`` (rad) when the phase-a sensor reads ``(1 + gain_err) i_a + offset_a``
    (``offset_a`` A, ``gain_err`` 1) and phase b is exact; no error gives back the
    true currents exactly."""
    c = math.cos(theta_e)
    sn = math.sin(theta_e)
    e = gain_err * (i_d * c - i_q * sn) + offset_a
    return i_d + e * (c + sn / SQRT3), i_q + e * (c / SQRT3 - sn)


@njit(cache=True, error_model="numpy")
def electrical_angle(p, s):
    """theta_e (rad): pole pairs times the motor angle (rad, or m on linear motors)."""
    return p[P_POLE_PAIRS] * s[int(p[P_SOFF_ROT])]


@njit(cache=True, error_model="numpy")
def sensed_current(p, s):
    """The current sensors' (i_d, i_q) in A at a PWM event, before noise and quantization.

    The commutation model's coil current I flows at gamma ahead of the q axis (cos gamma =
    K / K_0, :mod:`plant.effects.commutation`): it is measured as the projection of the
    measured d-q vector onto its direction (i_d is returned 0, that model has none)."""
    theta_e = electrical_angle(p, s)
    offset_a = p[P_I_OFFSET]
    gain_err = p[P_I_GAIN_ERR]
    if int(p[P_MOTOR_MODEL]) != MOTOR_COMMUTATION:
        return two_sensor_dq(s[S_ID], s[S_IQ], theta_e, offset_a, gain_err)
    i = s[S_IQ]
    cos_g = s[S_KM] / p[P_KT]
    sin_g = math.sqrt(max(1.0 - cos_g * cos_g, 0.0))
    u_d = -sin_g if i >= 0.0 else sin_g
    d, q = two_sensor_dq(i * u_d, i * cos_g, theta_e, offset_a, gain_err)
    return 0.0, u_d * d + cos_g * q


@njit(cache=True, error_model="numpy")
def first_order_target(p, iq_ref, theta_e):
    """True q current (A) whose measurement equals ``iq_ref`` (A, limited to the current
    limit) at ``theta_e`` (rad), i_d = 0: the first-order model's lag stands for a closed
    loop that regulates its measurement, ``i_q + (offset - g i_q sin) (cos/sqrt(3) - sin)``.

    The denominator stays above 0.07 for gain errors in (-0.93, 0.93)."""
    ref = clamp(iq_ref, -p[P_I_MAX], p[P_I_MAX])
    c = math.cos(theta_e)
    sn = math.sin(theta_e)
    c_q = c / SQRT3 - sn
    return (ref - p[P_I_OFFSET] * c_q) / (1.0 - p[P_I_GAIN_ERR] * sn * c_q)


@njit(cache=True, error_model="numpy")
def ripple_factor(p, theta_e):
    """Factor (1) on the electromagnetic torque at ``theta_e`` (rad)."""
    return 1.0 + p[P_RIPPLE_AMP] * math.cos(p[P_RIPPLE_ORDER] * theta_e + p[P_RIPPLE_PHASE])


@njit(cache=True, error_model="numpy")
def encoder_mark(p, s):
    """PWM event: the true encoder count the period's lost-count draw measures from."""
    s[S_ENC_PREV] = counts(s[int(p[P_SOFF_ROT])] - p[P_ENC_ORIGIN],
                           p[P_ENC_COUNTS_PER_RAD], p[P_ENC_ROUND])


@njit(cache=True, error_model="numpy")
def encoder_sample(p, s):
    """End of a PWM period: the lost-count draw over the counts travelled in it and the
    noise of this sample (each from the axis's noise stream, only when configured)."""
    dn = (counts(s[int(p[P_SOFF_ROT])] - p[P_ENC_ORIGIN], p[P_ENC_COUNTS_PER_RAD],
                 p[P_ENC_ROUND]) - s[S_ENC_PREV])
    if p[P_ENC_LOST] > 0.0 and dn != 0.0:
        u = uniform(p[P_SEED], s[S_RNG_COUNTER])
        s[S_RNG_COUNTER] += 1.0
        if u < min(1.0, p[P_ENC_LOST] * abs(dn)):
            s[S_ENC_LOST] -= 1.0 if dn > 0.0 else -1.0
    if p[P_ENC_NOISE] > 0.0:
        s[S_ENC_NOISE] = p[P_ENC_NOISE] * gaussian(p[P_SEED], s[S_RNG_COUNTER])
        s[S_RNG_COUNTER] += 2.0
    else:
        s[S_ENC_NOISE] = 0.0


@njit(cache=True, error_model="numpy")
def encoder_reading(p, s, position):
    """Counts the faulty encoder shows at ``position`` (rad, or m on linear motors, from its
    count 0): the held noise before the floor (or rounding), the lost counts after it."""
    per_unit = p[P_ENC_COUNTS_PER_RAD]
    if per_unit <= 0.0:
        return 0.0
    return whole_counts(position * per_unit + s[S_ENC_NOISE], p[P_ENC_ROUND]) + s[S_ENC_LOST]
