"""PMSM in the rotor (d-q) frame with the drive's discrete FOC current loops (seed 000).

Electrical equations (SI; omega_e = pole_pairs * omega_m)::

    L_d di_d/dt = u_d - R i_d + omega_e L_q i_q
    L_q di_q/dt = u_q - R i_q - omega_e L_d i_d - omega_e psi
    T           = 1.5 p (psi i_q + (L_d - L_q) i_d i_q)

The currents are integrated with the exponential (exact-decay) Euler rule over
one sub-step: exact for a locked rotor with the voltage held by the PWM, and
stable for any sub-step.  The current controller runs once per PWM period: it
samples the measured currents, runs two PI loops and limits the voltage
vector to P_U_MAX (U_dc/sqrt(3) with space-vector PWM, U_dc/2 with sine PWM:
:func:`plant.assemble.voltage_limit`; or u_q alone, [motor] voltage_limit = "q"); the
inverter applies that voltage during the
*next* period
(one period of computation/PWM delay, seed 001 eq. 3).
"""

import math

from numba import njit

from plant.layout import (
    P_DECOUPLE,
    P_DT,
    P_EXP_D,
    P_EXP_Q,
    P_I_MAX,
    P_IQ_KICK_NEXT,
    P_IQ_KICK_NOW,
    P_KI_I,
    P_KP_I,
    P_LD,
    P_LQ,
    P_POLE_PAIRS,
    P_PSI,
    P_R,
    P_SUB_PER_PWM,
    P_U_MAX,
    P_U_Q_ONLY,
    S_ID,
    S_ID_MEAS,
    S_INT_D,
    S_INT_Q,
    S_IQ,
    S_IQ_KICK_TAIL,
    S_IQ_MEAS,
    S_UD_NEXT,
    S_UQ_NEXT,
)


@njit(cache=True, error_model="numpy", inline="always")
def clamp(x, lo, hi):
    """``x`` limited to [lo, hi]."""
    return lo if x < lo else (hi if x > hi else x)


@njit(cache=True, error_model="numpy")
def pi_step(err, integ, kp, ki, period, ff, umax):
    """One discrete PI update plus a feed-forward ``ff``, with anti-windup by conditional
    integration.

    Returns (ff + PI output limited to ±umax, new integrator).  The integrator
    only moves when the output is not saturated or the error pulls it back.
    """
    u = ff + kp * err + integ
    if u > umax:
        if err < 0.0:
            integ += ki * period * err
        return umax, integ
    if u < -umax:
        if err > 0.0:
            integ += ki * period * err
        return -umax, integ
    return u, integ + ki * period * err


@njit(cache=True, error_model="numpy")
def dq_current_control(p, s, id_ref, iq_ref, omega_m):
    """Current controller event: PI on the held measured currents -> next voltages.

    With P_DECOUPLE the back-EMF and the d-q cross-coupling are fed forward
    from the speed ``omega_m`` (rad/s; m/s for linear motors), so the PI only
    has to correct what the model of the motor misses.  The voltage vector is
    limited to P_U_MAX with the d axis served first (the flux-producing current
    keeps priority, as drives do); with P_U_Q_ONLY ([motor] voltage_limit = "q") only
    |u_q| is limited to P_U_MAX and u_d is not limited at all (a simulator's q clamp).
    """
    period = p[P_DT] * p[P_SUB_PER_PWM]
    imax = p[P_I_MAX]
    umax = p[P_U_MAX]
    iq_ref = clamp(iq_ref, -imax, imax)
    id_ref = clamp(id_ref, -imax, imax)
    ff_d = 0.0
    ff_q = 0.0
    if p[P_DECOUPLE] > 0.0:
        we = p[P_POLE_PAIRS] * omega_m
        ff_d = -we * p[P_LQ] * s[S_IQ_MEAS]
        ff_q = we * (p[P_PSI] + p[P_LD] * s[S_ID_MEAS])
    q_only = p[P_U_Q_ONLY] > 0.0
    ud, s[S_INT_D] = pi_step(id_ref - s[S_ID_MEAS], s[S_INT_D], p[P_KP_I], p[P_KI_I],
                             period, ff_d, math.inf if q_only else umax)
    uq_max = umax if q_only else math.sqrt(max(umax * umax - ud * ud, 0.0))
    uq, s[S_INT_Q] = pi_step(iq_ref - s[S_IQ_MEAS], s[S_INT_Q], p[P_KP_I], p[P_KI_I],
                             period, ff_q, uq_max)
    s[S_UD_NEXT] = ud
    s[S_UQ_NEXT] = uq


@njit(cache=True, error_model="numpy")
def limit_voltage(ud, uq, umax):
    """Scale the vector (ud, uq) back to magnitude ``umax`` if it is longer."""
    mag = math.sqrt(ud * ud + uq * uq)
    if mag > umax:
        k = umax / mag
        return ud * k, uq * k
    return ud, uq


@njit(cache=True, error_model="numpy", inline="always")
def dq_substep(p, s, ud, uq, omega_m):
    """Advance i_d, i_q over one sub-step with the voltages held; return the torque of the
    currents at the sub-step's start (see :func:`plant.kernel.motor_substep`)."""
    r = p[P_R]
    we = p[P_POLE_PAIRS] * omega_m
    i_d = s[S_ID]
    i_q = s[S_IQ]
    torque = dq_torque(p, i_d, i_q)
    d_inf = (ud + we * p[P_LQ] * i_q) / r
    q_inf = (uq - we * p[P_LD] * i_d - we * p[P_PSI]) / r
    s[S_ID] = d_inf + (i_d - d_inf) * p[P_EXP_D]
    s[S_IQ] = q_inf + (i_q - q_inf) * p[P_EXP_Q]
    return torque


@njit(cache=True, error_model="numpy")
def freewheel(i, u_link, inductance, dt):
    """Current ``i`` (A) one sub-step of ``dt`` (s) later while the inverter's pulses are
    blocked: it flows back through the freewheeling diodes against the link voltage
    ``u_link`` (V) across ``inductance`` (H) and stops at zero (the diodes block the
    reverse direction)."""
    step = u_link / inductance * dt
    if i > 0.0:
        return max(0.0, i - step)
    if i < 0.0:
        return min(0.0, i + step)
    return 0.0


@njit(cache=True, error_model="numpy", inline="always")
def dq_torque(p, i_d, i_q):
    """Electromagnetic torque (N·m; N for linear motors) of the d-q currents."""
    return 1.5 * p[P_POLE_PAIRS] * (p[P_PSI] * i_q + (p[P_LD] - p[P_LQ]) * i_d * i_q)


def first_order_kick_weights(dt: float, t_cl: float) -> tuple[float, float]:
    """(P_IQ_KICK_NOW, P_IQ_KICK_NEXT) of :func:`first_order_substep` for a sub-step of
    ``dt`` s and a lag of ``t_cl`` s, with x = dt / T_cl and a = e^-x: the lag's departure
    from its target weighted by 1 - s/dt over the sub-step after the kick,
    (x - (1 - a)) / x^2, and by s/dt over the one before, ((1 - a) - x a) / x^2, less the
    a / 2 of it that the current at the kick's start already carries (expm1 keeps small x
    exact)."""
    x = dt / t_cl
    a = math.exp(-x)
    rise = -math.expm1(-x)
    return (x - rise) / (x * x), (rise - x * a) / (x * x) - 0.5 * a


@njit(cache=True, error_model="numpy")
def first_order_substep(p, s, iq_ref):
    """Current loop as a first-order lag (seed 004's T_cl): exact over one sub-step.
    Returns the current (A) whose torque is the mechanics' kick of this sub-step.

    The mechanics take kick-drift steps (v += dt F_n / m, then x += dt v): their positions
    meet the true ones at the sub-step boundaries when the kick F_n is the force's average
    over the two sub-steps around t_n weighted by 1 - |s|/dt (x_{n+1} - 2 x_n + x_{n-1}
    is that average of x'' times dt^2).  The lag's current is known exactly between the
    boundaries, i = c + (i_n - c) e^(-s/T) toward the held target c, so the kick takes that
    average: (i_n + c) / 2 + (i_n - c) w_now from this sub-step and, from the one before,
    what its departure from its target adds to i_n / 2 (kept in S_IQ_KICK_TAIL; 0 where
    the current sat at its target, as after a reset or a current set from outside).  The
    current at the sub-step's start alone, as before issue 30, is off by
    (dt^2 / 6 T) di_set/dt: at one sub-step per 250 us PWM period and T = 0.5 ms, a speed
    loop that fights a 120 Hz cogging force moved the position by nm against a generator
    that integrates the lag, and the encoder's count flips turned that into 0.4 floor of
    current error."""
    imax = p[P_I_MAX]
    target = clamp(iq_ref, -imax, imax)
    i_n = s[S_IQ]
    kick = 0.5 * (i_n + target) + (i_n - target) * p[P_IQ_KICK_NOW] + s[S_IQ_KICK_TAIL]
    s[S_IQ_KICK_TAIL] = (i_n - target) * p[P_IQ_KICK_NEXT]
    s[S_IQ] = target + (i_n - target) * p[P_EXP_Q]
    return kick
