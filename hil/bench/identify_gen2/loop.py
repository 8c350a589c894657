"""The second generator's closed loop, compiled: the cascade of :mod:`.controller` around
the axis of :mod:`.axis`, integrated with classical fourth-order Runge-Kutta at a fixed
step of a PWM period over ``substeps``.

Stick-slip is handled per step, not by a band around v = 0: a sliding step whose velocity
changes sign is cut where the (linearly interpolated) velocity crosses zero, the axis
sticks there while the force on it stays within F_C and slides on otherwise; a stuck step
integrates the current alone (exactly: it is first order) and, where the force on the
axis reaches F_C within it (interpolated), slides for the rest of the step.

Python decides everything about a run (:mod:`.trace`); this kernel only steps it and
returns 0.
"""

import math

import numpy as np
from numba import njit

#: columns of the kernel's record, one row per trace sample
#: (the screw is rigid: the scale and the motor encoder see one true position)
FB, MOTOR, SPEED, IQ_SET, IQ, POS_TRUE, IQ_TRUE = range(7)
N_COLUMNS = 7


@njit(cache=True)
def _cogging(x, ax, orders, amps, phases):
    f = 0.0
    theta = ax.poles * x
    for k in range(orders.size):
        f += amps[k] * math.sin(orders[k] * theta + phases[k])
    return f


@njit(cache=True)
def _force(x, v, i, ax, orders, amps, phases):
    """The force on the axis besides Coulomb friction, N."""
    return ax.kf * i + _cogging(x, ax, orders, amps, phases) + ax.f_ext - ax.viscous * v


@njit(cache=True)
def _slide_rk4(x, v, i, h, direction, i_set, ax, orders, amps, phases):
    """(x, v, i) after ``h`` s of sliding in ``direction`` (+-1) with ``i_set`` held."""
    fc = direction * ax.coulomb
    k1x = v
    k1v = (_force(x, v, i, ax, orders, amps, phases) - fc) / ax.mass
    k1i = (i_set - i) / ax.t_cl
    x2, v2, i2 = x + 0.5 * h * k1x, v + 0.5 * h * k1v, i + 0.5 * h * k1i
    k2x = v2
    k2v = (_force(x2, v2, i2, ax, orders, amps, phases) - fc) / ax.mass
    k2i = (i_set - i2) / ax.t_cl
    x3, v3, i3 = x + 0.5 * h * k2x, v + 0.5 * h * k2v, i + 0.5 * h * k2i
    k3x = v3
    k3v = (_force(x3, v3, i3, ax, orders, amps, phases) - fc) / ax.mass
    k3i = (i_set - i3) / ax.t_cl
    x4, v4, i4 = x + h * k3x, v + h * k3v, i + h * k3i
    k4x = v4
    k4v = (_force(x4, v4, i4, ax, orders, amps, phases) - fc) / ax.mass
    k4i = (i_set - i4) / ax.t_cl
    return (x + h / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x),
            v + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v),
            i + h / 6.0 * (k1i + 2 * k2i + 2 * k3i + k4i))


@njit(cache=True)
def _step(state, h, i_set, ax, orders, amps, phases):
    """One integration step of ``h`` s; ``state`` = [x, v, i, stuck] updated in place."""
    x, v, i = state[0], state[1], state[2]
    left = h
    for _ in range(3):  # at most a stick and a release within one step
        if left <= 0.0:
            break
        if state[3] != 0.0:
            i_end = i_set + (i - i_set) * math.exp(-left / ax.t_cl)
            g0 = abs(_force(x, 0.0, i, ax, orders, amps, phases)) - ax.coulomb
            g1 = abs(_force(x, 0.0, i_end, ax, orders, amps, phases)) - ax.coulomb
            if g0 <= 0.0 and g1 <= 0.0:
                i = i_end
                break
            # breaks away where the force reaches F_C
            dt = 0.0 if g0 > 0.0 else left * g0 / (g0 - g1)
            i = i_set + (i - i_set) * math.exp(-dt / ax.t_cl)
            left -= dt
            state[3] = 0.0
            continue
        f = _force(x, v, i, ax, orders, amps, phases)
        direction = math.copysign(1.0, v) if v != 0.0 else math.copysign(1.0, f)
        x1, v1, i1 = _slide_rk4(x, v, i, left, direction, i_set, ax, orders, amps, phases)
        if v1 * direction > 0.0:
            x, v, i = x1, v1, i1
            break
        # the velocity reaches zero within the step: cut the step there
        dt = left * (v / (v - v1)) if v != v1 else 0.0
        x, v, i = _slide_rk4(x, v, i, dt, direction, i_set, ax, orders, amps, phases)
        v = 0.0
        left -= dt
        if abs(_force(x, 0.0, i, ax, orders, amps, phases)) <= ax.coulomb:
            state[3] = 1.0
        elif dt <= 0.0:
            # already at rest and pushed beyond F_C: slide the whole rest of the step
            x, v, i = _slide_rk4(x, 0.0, i, left, math.copysign(
                1.0, _force(x, 0.0, i, ax, orders, amps, phases)), i_set, ax, orders, amps,
                phases)
            break
    state[0], state[1], state[2] = x, v, i


@njit(cache=True)
def _count(position, zero, step, rounding):
    """An encoder's reading (table units) of ``position``: whole steps of the travel from
    ``zero``, truncated (rounding 0) or rounded (0.5)."""
    return math.floor((position - zero) / step + rounding) * step


@njit(cache=True)
def run_loop_compiled(ax, lc, orders, amps, phases, x_set, v_rows, noise, x0, out):
    """Run the loop and fill ``out`` (rows x :data:`N_COLUMNS`, table units, A).

    Args:
        ax: AxisConstants; lc: LoopConstants; orders, amps, phases: cogging, shape (k,).
        x_set: the setpoint at each position cycle from the pre-roll's first, m or rad.
        v_rows: the feed-forward of each record row and one past the last, m/s or rad/s.
        noise: the current measurement's noise at each PWM period, A.
        x0: where the axis truly starts, m or rad.
    """
    n_rows = out.shape[0]
    n_ticks = lc.pre_ticks + n_rows * lc.n_rec
    zero = x0 if lc.zero_at_start else 0.0
    state = np.array([x0, 0.0, 0.0, 1.0 if ax.coulomb > 0.0 else 0.0])
    h = lc.pwm_s / lc.substeps
    t_spd = lc.n_spd * lc.pwm_s
    delayed = np.zeros(lc.delay + 1)
    v_p = 0.0
    speed = 0.0
    integral = 0.0
    i_cmd = 0.0
    motor_prev = _count(x0, zero, lc.motor_step, lc.rounding)
    limit = ax.kf * ax.i_max
    for k in range(n_ticks):
        x, i = state[0], state[2]
        motor = _count(x, zero, lc.motor_step, lc.rounding)
        fb = _count(x, zero, lc.scale_step, lc.rounding) if lc.scale_step > 0.0 else motor
        iq = min(lc.full_scale, max(-lc.full_scale,
                                    round((i + noise[k]) / lc.lsb) * lc.lsb))
        if k % lc.n_pos == 0:
            v_p = lc.kv * (x_set[k // lc.n_pos] - fb)
        if k % lc.n_spd == 0:
            raw = (motor - motor_prev) / t_spd
            motor_prev = motor
            speed = raw + (speed - raw) * lc.filter_decay
            v_ff = 0.0
            if k >= lc.pre_ticks:
                row, within = divmod(k - lc.pre_ticks, lc.n_rec)
                v_ff = v_rows[row]
                if lc.ff_linear:
                    v_ff += (v_rows[row + 1] - v_ff) * within / lc.n_rec
            command = min(lc.v_max, max(-lc.v_max, v_p + lc.ff_weight * v_ff))
            e = command - speed
            u = lc.kp * e + integral
            if not ((u > limit and e > 0.0) or (u < -limit and e < 0.0)):
                integral += lc.ki_step * e
            i_cmd = min(ax.i_max, max(-ax.i_max, min(limit, max(-limit, u)) / ax.kf))
        delayed[k % (lc.delay + 1)] = i_cmd
        applied = delayed[(k + 1) % (lc.delay + 1)] if lc.delay > 0 else i_cmd
        if k >= lc.pre_ticks and (k - lc.pre_ticks) % lc.n_rec == 0:
            row = (k - lc.pre_ticks) // lc.n_rec
            out[row, FB] = fb
            out[row, MOTOR] = motor
            out[row, SPEED] = speed
            out[row, IQ_SET] = i_cmd
            out[row, IQ] = iq
            out[row, POS_TRUE] = x - zero
            out[row, IQ_TRUE] = min(lc.full_scale, max(-lc.full_scale, i))
        for _ in range(lc.substeps):
            _step(state, h, applied, ax, orders, amps, phases)
    return 0
