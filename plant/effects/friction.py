"""Table friction: viscous, Coulomb, Stribeck, Karnopp stick-slip (seed 003 §4.1) and the
presliding nonlinear spring of seed 004 eq. 1.

Sign convention: every function returns the force (N; N·m for rotary tables)
that friction exerts *on* the body, opposing its motion or its applied force.
"""

import math

from numba import njit

from plant.layout import (
    P_FR_COULOMB,
    P_FR_DV,
    P_FR_REVERSAL_STOP,
    P_FR_STATIC,
    P_FR_STRIBECK_V,
    P_FR_VISC_ASYM,
    P_FR_VISCOUS,
    P_PRE_A,
    P_PRE_ENABLED,
    P_PRE_K1,
    P_PRE_X1,
    S_PRE_DIR,
    S_PRE_F,
    S_PRE_XREV,
)

#: (v/v_s)^2 at and above which the Stribeck term is skipped: exp(-x) underflows to exactly
#: 0.0 in double precision beyond x = 745.13, so skipping it changes no bit, and it spares
#: libm's underflow path (a range error, errno) on every sub-step of a table sliding faster
#: than 27 v_s (0.03 m/s on the Arrow 500 X)
STRIBECK_CUTOFF = 746.0


@njit(cache=True, error_model="numpy", inline="always")
def viscous_friction(p, v):
    """Viscous friction at velocity ``v``: -(B + dB sign(v)) v, the coefficient B + dB
    moving toward + and B - dB moving toward - (seals and preload that differ by
    direction: EMPS shows 167 against 240 N·s/m)."""
    return -p[P_FR_VISCOUS] * v - p[P_FR_VISC_ASYM] * abs(v)


@njit(cache=True, error_model="numpy", inline="always")
def sliding_friction(p, v):
    """Friction while sliding at velocity ``v``: viscous (:func:`viscous_friction`) and
    -sign(v) (F_C + (F_H - F_C) exp(-(v/v_s)^2)); without a Stribeck velocity the level
    is F_C (and beyond :data:`STRIBECK_CUTOFF`, where the exponential is 0.0)."""
    level = p[P_FR_COULOMB]
    vs = p[P_FR_STRIBECK_V]
    if vs > 0.0:
        x = (v / vs) ** 2
        if x < STRIBECK_CUTOFF:
            level += (p[P_FR_STATIC] - p[P_FR_COULOMB]) * math.exp(-x)
    if v > 0.0:
        return viscous_friction(p, v) - level
    if v < 0.0:
        return viscous_friction(p, v) + level
    return 0.0


@njit(cache=True, error_model="numpy", inline="always")
def karnopp_friction(p, v, f_app, mass, dt):
    """Karnopp stick-slip friction on a body of ``mass`` moving at ``v`` under the other
    forces ``f_app``, for one sub-step of ``dt``.

    Returns (friction force, stuck).  Inside the zero-velocity band, or when
    the velocity would cross zero within this sub-step, the body sticks while
    |f_app| <= F_H: friction cancels f_app and the caller sets v = 0.  Above
    F_H it breaks away against F_H (in the band) or reverses within the step (a crossing);
    with P_FR_REVERSAL_STOP ([friction] karnopp_reversal = "stop") a crossing stops it
    whatever f_app, and the next sub-step, in the band at v = 0, decides on breakaway.
    Outside the band it slides.
    """
    f_h = p[P_FR_STATIC]
    if abs(v) <= p[P_FR_DV]:
        if abs(f_app) <= f_h:
            return -f_app, True
        return (-f_h if f_app > 0.0 else f_h), False
    ff = sliding_friction(p, v)
    v_new = v + dt * (f_app + ff) / mass
    if v_new * v <= 0.0 and (abs(f_app) <= f_h or p[P_FR_REVERSAL_STOP] > 0.0):
        return -f_app, True
    return ff, False


@njit(cache=True, error_model="numpy", inline="always")
def presliding_force(p, s, v):
    """Friction with the presliding spring on: the spring force plus viscous friction."""
    return -s[S_PRE_F] + viscous_friction(p, v)


@njit(cache=True, error_model="numpy")
def presliding_update(p, s, x_old, x_new):
    """Integrate dF/dx = k1 / (|(x - x_rev)/x1|^a + 1) from x_old to x_new (midpoint rule).

    x_rev is the position of the last reversal of motion: the law starts
    again from there (seed 004).  Beyond the Coulomb level F_C (when given)
    the force saturates: the contact slides.
    """
    dx = x_new - x_old
    if dx == 0.0:
        return
    direction = 1.0 if dx > 0.0 else -1.0
    if direction != s[S_PRE_DIR]:
        s[S_PRE_DIR] = direction
        s[S_PRE_XREV] = x_old
    u = abs(0.5 * (x_old + x_new) - s[S_PRE_XREV]) / p[P_PRE_X1]
    f = s[S_PRE_F] + p[P_PRE_K1] / (u ** p[P_PRE_A] + 1.0) * dx
    fc = p[P_FR_COULOMB]
    if fc > 0.0:
        f = min(fc, max(-fc, f))
    s[S_PRE_F] = f


@njit(cache=True, error_model="numpy", inline="always")
def table_friction(p, s, v, f_app, mass, dt):
    """Friction on the table for one sub-step: the presliding law when enabled, else
    Karnopp stick-slip with Stribeck sliding.  Returns (force, stuck)."""
    if p[P_PRE_ENABLED] > 0.0:
        return presliding_force(p, s, v), False
    if p[P_FR_STATIC] <= 0.0:
        return viscous_friction(p, v), False
    return karnopp_friction(p, v, f_app, mass, dt)
