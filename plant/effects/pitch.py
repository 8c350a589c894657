"""Ball-screw pitch (lead) error: the table is not exactly where the screw angle says.

With u = lead/2pi * theta the nominal table position of the screw angle theta at the
nut, the nut (and with it the table) stands at

    x = u + e(u),   e(u) = sum_k A_k sin(2 pi u / P_k + phi_k) + c u

(periodic thread error of periods P_k, plus a cumulative lead error c in m/m).  The
error is a function of the screw angle, so the transmission from screw angle to table
stays a holonomic constraint with the local ratio dx/dtheta = lead/2pi (1 + e'(u)).
The kernel maps forces with that ratio (virtual work, exact) and gives the table the
acceleration term e''(u) u_dot^2 the curved kinematics asks for; see plant.kernel.
"""

import math

from numba import njit

from plant.layout import P_PITCH_AMP, P_PITCH_LINEAR, P_PITCH_N, P_PITCH_PHASE, P_PITCH_WAVENUMBER


@njit(cache=True, error_model="numpy", inline="always")
def pitch_error(p, u):
    """(e, de/du, d2e/du2) at nominal table position ``u`` (m): the error in m, its
    slope (m/m) and its curvature (1/m)."""
    e = p[P_PITCH_LINEAR] * u
    e1 = p[P_PITCH_LINEAR]
    e2 = 0.0
    for k in range(int(p[P_PITCH_N])):
        a = p[P_PITCH_AMP + k]
        kw = p[P_PITCH_WAVENUMBER + k]
        arg = kw * u + p[P_PITCH_PHASE + k]
        sn = math.sin(arg)
        e += a * sn
        e1 += a * kw * math.cos(arg)
        e2 -= a * kw * kw * sn
    return e, e1, e2


def nominal_position(p, x: float, tol: float = 1e-15) -> float:
    """The nominal position u (m) with u + e(u) = x: where the screw angle must stand for
    the table to be at ``x`` (m).  Fixed-point iteration, converging since |e'| < 1 (the
    loader bounds the slope)."""
    u = x
    for _ in range(100):
        u_next = x - pitch_error(p, u)[0]
        if abs(u_next - u) <= tol * max(1.0, abs(x)):
            return u_next
        u = u_next
    return u
