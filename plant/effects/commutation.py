"""Direct-drive torque motor with commutation-angle field weakening (seed 001 eq. 1-10).

The motor is one equivalent coil: L dI/dt = U - R I - K_S(beta) omega, torque
M = K_M(beta) I, with K_M = K_S = K (SI units make them equal) and
|U| <= U_Z (eq. 2; U_Z is the link voltage itself, P_U_MAX = [motor] dc_link_v, which
[motor] modulation does not change: plant.assemble.voltage_limit).  Without field
weakening K = K_0 (beta = 90 deg).  Above omega_Mmax = U_Z/K_0 - M_max R / K_0^2 (eq. 8)
the converter lowers the commutation angle so that the torque asked for stays reachable;
solving eq. 9,
M = (U_Z - omega K) K / R, for K gives eq. 10:

    K(omega, M) = U_Z / (2 omega) + sqrt((U_Z / (2 omega))^2 - R M / omega)

(the paper prints the square root's argument garbled; this is the root of
eq. 9 that tends to U_Z/omega, the larger one).  Where the torque asked for is
beyond the curve, K = U_Z / (2 omega) gives the most torque there is.  The
current setpoint is scaled as I_set = M_set / K (eq. 5).

The coil is the current's direction of a synchronous machine (L_d = L_q = L, omega_e =
pole_pairs omega): with the current I at the angle gamma = arccos(K / K_0) ahead of the
q axis (i_d = -|I| sin gamma, i_q = I cos gamma) the d-q voltage equations split into

    along I:   L dI/dt = U - R I - K omega                          (the coil, eq. 1-4)
    across I:  U_perp  = omega (K_0 sin gamma - p L |I|)           (the omega_e L cross term)

and the converter has to apply both within its limit, U^2 + U_perp^2 <= U_Z^2.  The
coil's PI therefore gets what U_perp leaves of U_Z (:func:`coil_voltage_limit`); without
it the envelope of eq. 8-10 is optimistic by omega_e L I (issue 14 part 5).  Where U_perp
alone exceeds U_Z (beyond omega_max without field weakening, the current braking) the coil
gets 0 V and its current, -K omega / R, is no longer one the converter holds at its angle:
the one-coil model leaves its validity there (a drive would trip on overcurrent).
"""

import math

from numba import njit

from plant.effects.pmsm import clamp, pi_step
from plant.layout import (
    P_DT,
    P_EXP_D,
    P_FW_ENABLED,
    P_FW_M_MAX,
    P_I_MAX,
    P_KI_I,
    P_KP_I,
    P_KT,
    P_LD,
    P_POLE_PAIRS,
    P_R,
    P_SUB_PER_PWM,
    P_U_MAX,
    S_INT_Q,
    S_IQ,
    S_IQ_MEAS,
    S_KM,
    S_UQ_NEXT,
)


@njit(cache=True, error_model="numpy")
def field_weakening_k(k0, r, uz, m_max, omega, m_set):
    """Torque constant K (N·m/A) the converter commutes with at speed ``omega`` (rad/s)
    for a torque demand ``m_set`` (N·m); seed 001 eq. 8 and 10."""
    w = abs(omega)
    w_mmax = uz / k0 - m_max * r / (k0 * k0)
    if w <= w_mmax or w == 0.0:
        return k0
    half = uz / (2.0 * w)
    disc = half * half - r * abs(m_set) / w
    if disc <= 0.0:
        return min(k0, half)
    return min(k0, half + math.sqrt(disc))


@njit(cache=True, error_model="numpy")
def coil_voltage_limit(uz, k0, k, pole_pairs, inductance, omega, current):
    """Largest |U| (V) the coil may get when the converter also applies the voltage across
    the current, U_perp = omega (K_0 sin gamma - p L |I|) with cos gamma = K / K_0, within
    |u| <= U_Z: sqrt(U_Z^2 - U_perp^2), 0 where U_perp alone exceeds U_Z.

    ``uz`` V, ``k0`` and ``k`` N·m/A (N/A), ``pole_pairs`` 1 (1/m), ``inductance`` H,
    ``omega`` rad/s (m/s), ``current`` A."""
    c = k / k0
    sin_gamma = math.sqrt(max(1.0 - c * c, 0.0))
    u_perp = omega * (k0 * sin_gamma - pole_pairs * inductance * abs(current))
    return math.sqrt(max(uz * uz - u_perp * u_perp, 0.0))


@njit(cache=True, error_model="numpy")
def commutation_control(p, s, iq_ref, omega):
    """Converter event: commutation angle, current setpoint (eq. 5), PI on the coil current
    within what the voltage across the current leaves of U_Z (the measured current stands
    for I there, as in a drive)."""
    k0 = p[P_KT]
    m_set = k0 * clamp(iq_ref, -p[P_I_MAX], p[P_I_MAX])
    k = k0
    if p[P_FW_ENABLED] > 0.0:
        k = field_weakening_k(k0, p[P_R], p[P_U_MAX], p[P_FW_M_MAX], omega, m_set)
    s[S_KM] = k
    i_set = clamp(m_set / k, -p[P_I_MAX], p[P_I_MAX])
    period = p[P_DT] * p[P_SUB_PER_PWM]
    umax = coil_voltage_limit(p[P_U_MAX], k0, k, p[P_POLE_PAIRS], p[P_LD], omega, s[S_IQ_MEAS])
    u, s[S_INT_Q] = pi_step(i_set - s[S_IQ_MEAS], s[S_INT_Q], p[P_KP_I], p[P_KI_I], period,
                            0.0, umax)
    s[S_UQ_NEXT] = u


@njit(cache=True, error_model="numpy")
def commutation_substep(p, s, u, omega):
    """Advance the coil current one sub-step (exact decay); return the torque (N·m) of the
    current at the sub-step's start (see :func:`plant.kernel.motor_substep`)."""
    k = s[S_KM]
    torque = k * s[S_IQ]
    i_inf = (u - k * omega) / p[P_R]
    s[S_IQ] = i_inf + (s[S_IQ] - i_inf) * p[P_EXP_D]
    return torque
