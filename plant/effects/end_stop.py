"""Mechanical end stops and limit switches of a table with a stroke (screw and linear axes).

The hard stops sit at ``P_STOP_NEG`` and ``P_STOP_POS`` (m).  Beyond one, the table
penetrates the stop by ``pen`` and feels a Kelvin-Voigt contact, spring ``P_STOP_K`` in
parallel with damper ``P_STOP_C``, that is unilateral: it only ever pushes the table back
out.  A damper alone would pull the table into the wall while it leaves (``c v`` larger
than ``k pen`` near the surface); that pull is clamped to zero, so the table separates
where the contact force reaches zero, slightly inside the stop, and leaves faster than
the bilateral model's ``e = exp(-zeta pi / sqrt(1 - zeta^2))`` says.

The limit switches are on while the table is beyond ``P_LIMIT_NEG`` or ``P_LIMIT_POS``
(strictly).  A table without a stroke (``P_STROKE`` = 0: a rotary table) has neither.
"""

from numba import njit

from plant.layout import (
    P_LIMIT_NEG,
    P_LIMIT_POS,
    P_STOP_C,
    P_STOP_K,
    P_STOP_NEG,
    P_STOP_POS,
    P_STROKE,
)


@njit(cache=True, error_model="numpy", inline="always")
def end_stop_force(p, x, v):
    """Force of the end stops on the table at position ``x`` (m) and velocity ``v`` (m/s):
    N, + pushing toward +x; 0 inside the stroke."""
    if p[P_STROKE] <= 0.0:
        return 0.0
    if x > p[P_STOP_POS]:
        f = -p[P_STOP_K] * (x - p[P_STOP_POS]) - p[P_STOP_C] * v
        return f if f < 0.0 else 0.0
    if x < p[P_STOP_NEG]:
        f = p[P_STOP_K] * (p[P_STOP_NEG] - x) - p[P_STOP_C] * v
        return f if f > 0.0 else 0.0
    return 0.0


@njit(cache=True, error_model="numpy")
def limit_switches(p, x):
    """(negative, positive) limit-switch signals at table position ``x`` (m): 1.0 while
    the table is beyond that switch, else 0.0."""
    if p[P_STROKE] <= 0.0:
        return 0.0, 0.0
    return (1.0 if x < p[P_LIMIT_NEG] else 0.0), (1.0 if x > p[P_LIMIT_POS] else 0.0)
