"""The NC replay's closed loop compiled: the trace controller and the drive in lock step
with the plant kernel, one numba call for the whole record.

The identification replays a record tens of times (every proposal, every refinement
iteration); :func:`hil.identify.replay._replay_nc`'s Python loop of
:class:`~hil.identify.trace_controller.TraceController` and
:class:`~hil.drive.EmulatedDrive` takes about 20 µs per PWM period, 5 s for a minute at
4 kHz.  Once the drive is enabled (in Python: a few periods), what the loop does each
period in position control, the pre-roll at rest included, is a few lines:
read the encoders, the position cycle (fine interpolator, position loop with its
symmetrising PT1 and feed-forward, or the linear fine interpolation of the feed-forward
between position cycles), the speed cycle (speed from the encoder difference, the actual
speed filter, setpoint PT2, PI with the record's anti-windup, D part, current filters,
limit), the current delay, the drive's current limit and the plant's PWM period.  That is
:func:`nc_loop`, fed with the Python objects' coefficients and states by
:class:`CompiledLoop`, and checked sample for sample against the Python loop
(``tests/test_identify_replay.py``).

What it leaves out, because a replay of a recorded run never meets it: the drive's
monitoring (i²t, overspeed, limit switches, software limits) and the NC's axis monitoring
and alarm reactions.  A non-finite loop state or plant fault ends the replay with a status.
Plants fed by voltage (``[controller] plant_input = "voltage"``, the NC's current loop)
keep the Python loop.
"""

import math

import numpy as np
from numba import njit

from hil.controller.blocks import Biquad
from hil.identify.trace_controller import TraceController
from plant import Plant
from plant import layout as L
from plant.kernel import axis_step_nb

# -- coefficients, array c ---------------------------------------------------------------
C_N_POS, C_N_SPEED, C_EVERY, C_N_SUB, C_FINE_RATIO = 0, 1, 2, 3, 4
C_PERIOD, C_RATIO, C_RAD_PER_COUNT, C_SCALE_RES, C_POLARITY = 5, 6, 7, 8, 9
C_KV, C_FF, C_SYM_A, C_V_LIM, C_I_FF_GAIN = 10, 11, 12, 13, 14
C_KP, C_KI_T, C_PI_LIMIT, C_PI_MODE, C_KD_T = 15, 16, 17, 18, 19
C_INV_KT, C_KT, C_I_MAX, C_STOP_ON_TOTAL, C_DRIVE_I_MAX = 20, 21, 22, 23, 24
C_FILTER_A, C_FILTER_ON, C_FF_LINEAR, C_PER_AMP = 25, 26, 27, 28
C_SET_FILTER, C_CUR_FILTER, C_NOTCH = 29, 34, 39  # five biquad coefficients each
C_COUNT = 44
#: the speed PI's anti-windup (C_PI_MODE): conditional (on the PI's output or, with
#: C_STOP_ON_TOTAL, on the whole torque setpoint), integrator clamped, none
PI_CONDITIONAL, PI_CLAMP, PI_NONE = 0.0, 1.0, 2.0
_PI_MODES = {"clamp": PI_CLAMP, "none": PI_NONE}

# -- loop state, array s -----------------------------------------------------------------
S_K, S_X_ACT, S_THETA_ACT, S_W_ACT, S_THETA_PREV = 0, 1, 2, 3, 4
S_X_SET, S_V_SET, S_A_SET, S_I_FF, S_V_CMD, S_W_SET, S_IQ_SET = 5, 6, 7, 8, 9, 10, 11
S_SYM_Y, S_POS_ERROR, S_INTEG, S_E_PREV, S_FILTER_Y = 12, 13, 14, 15, 16
S_SET_Z, S_CUR_Z, S_NOTCH_Z = 17, 19, 21  # two delay-line values each
S_FINE_K, S_FINE_M, S_DELAY_HEAD = 23, 24, 25
S_COUNT = 26
#: status of a non-finite loop state (the plant's are plant.layout.STATUS_*)
STATUS_LOOP_NONFINITE = 101


def _biquad(c: np.ndarray, s: np.ndarray, ci: int, si: int, f: Biquad) -> None:
    c[ci:ci + 5] = (f.b0, f.b1, f.b2, f.a1, f.a2)
    s[si:si + 2] = (f.z1, f.z2)


def pack(ctrl: TraceController, plant: Plant, drive_i_max: float, every: int,
         per_amp: float) -> tuple[np.ndarray, np.ndarray]:
    """The controller's coefficients and states as the kernel's arrays (c, s)."""
    sec, sl, pl = ctrl.sec, ctrl.speed_loop, ctrl.pos_loop
    c = np.zeros(C_COUNT)
    s = np.zeros(S_COUNT)
    c[C_N_POS], c[C_N_SPEED] = sec.position_cycle_ratio, sec.speed_cycle_ratio
    c[C_EVERY], c[C_N_SUB] = every, plant.sub_per_pwm
    c[C_FINE_RATIO] = sec.ipo_cycle_ratio // sec.position_cycle_ratio
    c[C_PERIOD], c[C_RATIO] = ctrl.period, ctrl.ratio
    c[C_RAD_PER_COUNT], c[C_SCALE_RES], c[C_POLARITY] = (ctrl.rad_per_count, ctrl.scale_res,
                                                         ctrl.polarity)
    c[C_KV], c[C_FF], c[C_SYM_A], c[C_V_LIM] = pl.kv, pl.ff, pl.sym.a, pl.v_lim
    c[C_I_FF_GAIN] = ctrl.i_ff_gain
    c[C_KP], c[C_KI_T], c[C_PI_LIMIT] = sl.pi.kp, sl.pi.ki_t, sl.pi.limit
    c[C_PI_MODE], c[C_KD_T] = _PI_MODES.get(sl.antiwindup, PI_CONDITIONAL), sl.kd_t
    c[C_INV_KT], c[C_KT], c[C_I_MAX] = sl.inv_kt, sl.kt, sl.i_max
    c[C_STOP_ON_TOTAL], c[C_DRIVE_I_MAX] = float(sl.stop_on_total), drive_i_max
    c[C_FILTER_A], c[C_FILTER_ON] = ctrl.speed_filter.a, float(sec.speed_actual_filter_s > 0)
    c[C_FF_LINEAR], c[C_PER_AMP] = float(bool(ctrl.ff_linear)), per_amp
    _biquad(c, s, C_SET_FILTER, S_SET_Z, sl.set_filter)
    _biquad(c, s, C_CUR_FILTER, S_CUR_Z, sl.cur_filter)
    _biquad(c, s, C_NOTCH, S_NOTCH_Z, sl.notch)
    s[S_K], s[S_X_ACT], s[S_THETA_ACT], s[S_W_ACT] = (ctrl.tick_count, ctrl.x_act,
                                                      ctrl.theta_act, ctrl.w_act)
    s[S_THETA_PREV] = math.nan if ctrl.theta_prev is None else ctrl.theta_prev
    s[S_X_SET], s[S_V_SET], s[S_A_SET], s[S_I_FF] = ctrl.x_set, ctrl.v_set, ctrl.a_set, ctrl.i_ff
    s[S_V_CMD], s[S_W_SET], s[S_IQ_SET] = ctrl.v_cmd, ctrl.w_set, ctrl.iq_set
    s[S_SYM_Y], s[S_POS_ERROR] = pl.sym.y, pl.error
    s[S_INTEG], s[S_E_PREV], s[S_FILTER_Y] = sl.pi.integ, sl.e_prev, ctrl.speed_filter.y
    s[S_DELAY_HEAD] = ctrl.iq_delay.head
    return c, s


class CompiledLoop:
    """The trace controller, drive and plant from their present state on (the drive
    enabled), run by :func:`nc_loop`.

    Args:
        ctrl: the controller, enabled; its coefficients and states are copied.
        plant: the plant, whose arrays the loop advances in place.
        drive_i_max: the drive's current limit (6072h), A.
        every: PWM periods per record sample.
        per_amp: effort per q-current ampere (1, or N/A when the record has forces).
    """

    def __init__(self, ctrl: TraceController, plant: Plant, drive_i_max: float, every: int,
                 per_amp: float):
        self.c, self.s = pack(ctrl, plant, drive_i_max, every, per_amp)
        self.delay = np.array(ctrl.iq_delay.ring, dtype=np.float64)
        self.plant = plant

    def run(self, fine: tuple[np.ndarray, np.ndarray, np.ndarray], v_pos: np.ndarray,
            n: int, ticks: int = 0) -> tuple[np.ndarray, int]:
        """Follow the setpoints ``fine`` = (pos, vel, acc), shape (m,) each, at the IPO
        cycle (``ctrl.run_points``'s, the fine interpolator restarted), with ``v_pos`` the
        feed-forward at every position cycle from the first on; record ``n`` samples, or
        with ``n`` = 0 run ``ticks`` PWM periods (the pre-roll).

        Returns (rec, status): rec shape (4, n), rows table position, effort, motor
        position in table units, table velocity (NaN after a fault)."""
        self.s[S_FINE_K] = self.s[S_FINE_M] = 0.0
        rec = np.full((4, n), math.nan)
        p = self.plant
        status = nc_loop(self.c, self.s, p.params, p.state, p.inp, p.out,
                         *(np.ascontiguousarray(a, dtype=np.float64) for a in fine),
                         np.ascontiguousarray(v_pos, dtype=np.float64), self.delay, rec,
                         ticks)
        return rec, int(status)


@njit(cache=True)
def _biquad_step(c, ci, s, si, x):
    y = c[ci] * x + s[si]
    s[si] = c[ci + 1] * x - c[ci + 3] * y + s[si + 1]
    s[si + 1] = c[ci + 2] * x - c[ci + 4] * y
    return y


@njit(cache=True)
def _speed_pi(c, s, e, outer):
    """The speed PI's output (PI.step_within; ClampPI.step, WindupPI.step of
    hil.controller.blocks)."""
    u = c[C_KP] * e + s[S_INTEG]
    lim = c[C_PI_LIMIT]
    mode = c[C_PI_MODE]
    if mode == PI_CLAMP:
        s[S_INTEG] = max(-lim, min(lim, s[S_INTEG] + c[C_KI_T] * e))
        return max(-lim, min(lim, u))
    if mode == PI_NONE:
        s[S_INTEG] += c[C_KI_T] * e
        return max(-lim, min(lim, u))
    total = u + outer
    if total > lim:
        if e < 0.0:
            s[S_INTEG] += c[C_KI_T] * e
        return min(u, lim)
    if total < -lim:
        if e > 0.0:
            s[S_INTEG] += c[C_KI_T] * e
        return max(u, -lim)
    s[S_INTEG] += c[C_KI_T] * e
    return u


@njit(cache=True)
def _speed_step(c, s):
    """SpeedLoop.step: the q-current setpoint (A) of this speed cycle."""
    e = _biquad_step(c, C_SET_FILTER, s, S_SET_Z, s[S_W_SET]) - s[S_W_ACT]
    d_part = c[C_KD_T] * (e - s[S_E_PREV])
    outer = d_part + s[S_I_FF] * c[C_KT] if c[C_STOP_ON_TOTAL] != 0.0 else 0.0
    torque = _speed_pi(c, s, e, outer) + d_part
    s[S_E_PREV] = e
    i = _biquad_step(c, C_CUR_FILTER, s, S_CUR_Z, torque * c[C_INV_KT] + s[S_I_FF])
    i = _biquad_step(c, C_NOTCH, s, S_NOTCH_Z, i)
    return max(-c[C_I_MAX], min(c[C_I_MAX], i))


@njit(cache=True)
def _position_cycle(c, s, fine_pos, fine_vel, fine_acc):
    """FineInterpolator.step and the position loop (Controller._position_cycle without
    the monitoring a replay does not run)."""
    k = int(s[S_FINE_K])
    last = fine_pos.size - 1
    if k >= last:
        s[S_X_SET], s[S_V_SET], s[S_A_SET] = fine_pos[last], fine_vel[last], fine_acc[last]
    else:
        m = s[S_FINE_M]
        f = m / c[C_FINE_RATIO]
        s[S_X_SET] = fine_pos[k] + (fine_pos[k + 1] - fine_pos[k]) * f
        s[S_V_SET] = fine_vel[k] + (fine_vel[k + 1] - fine_vel[k]) * f
        s[S_A_SET] = fine_acc[k] + (fine_acc[k + 1] - fine_acc[k]) * f
        m += 1.0
        if m == c[C_FINE_RATIO]:
            m = 0.0
            s[S_FINE_K] = k + 1
        s[S_FINE_M] = m
    s[S_I_FF] = c[C_I_FF_GAIN] * s[S_A_SET]
    x_set = s[S_X_SET]
    s[S_SYM_Y] = x_set + (s[S_SYM_Y] - x_set) * c[C_SYM_A]
    s[S_POS_ERROR] = s[S_SYM_Y] - s[S_X_ACT]
    v = c[C_KV] * s[S_POS_ERROR] + c[C_FF] * s[S_V_SET]
    s[S_V_CMD] = max(-c[C_V_LIM], min(c[C_V_LIM], v))
    s[S_W_SET] = s[S_V_CMD] / c[C_RATIO]


@njit(cache=True)
def _measure(c, s, out, k, n_speed):
    """Controller._measure, its actual-speed filter included."""
    theta = out[L.O_ENCODER] * c[C_RAD_PER_COUNT]
    if k % n_speed == 0:
        if s[S_THETA_PREV] == s[S_THETA_PREV]:
            s[S_W_ACT] = (theta - s[S_THETA_PREV]) / (c[C_PERIOD] * n_speed)
        s[S_THETA_PREV] = theta
        if c[C_FILTER_ON] != 0.0:
            w = s[S_W_ACT]
            s[S_FILTER_Y] = w + (s[S_FILTER_Y] - w) * c[C_FILTER_A]
            s[S_W_ACT] = s[S_FILTER_Y]
    s[S_THETA_ACT] = theta
    if c[C_SCALE_RES] != 0.0:
        x = out[L.O_SCALE] * c[C_SCALE_RES]
    else:
        x = theta * c[C_RATIO]
    s[S_X_ACT] = c[C_POLARITY] * x


@njit(cache=True, error_model="numpy")
def nc_loop(c, s, p, ps, inp, out, fine_pos, fine_vel, fine_acc, v_pos, delay, rec, ticks):
    """The replay's ticks until ``rec`` (4, n) is full: rows table position, effort,
    motor position (table units), table velocity, one column per record sample; with n = 0,
    ``ticks`` ticks.

    ``c``/``s`` from :func:`pack`; ``p, ps, inp, out`` the plant's arrays; ``delay`` the
    current setpoints still in the computation delay (a ring, the oldest at
    ``s[S_DELAY_HEAD]``), shape (d,);
    ``v_pos`` the feed-forward at each position cycle from the first on.  Returns
    STATUS_OK, a plant status, or STATUS_LOOP_NONFINITE."""
    n_pos = int(c[C_N_POS])
    n_speed = int(c[C_N_SPEED])
    every = int(c[C_EVERY])
    n_sub = int(c[C_N_SUB])
    n = rec.shape[1]
    n_delay = delay.size
    head = int(s[S_DELAY_HEAD])
    first = -1
    tick_end = int(s[S_K]) + ticks
    row = 0
    ff_next = 0.0
    inp[L.I_ENABLE] = 1.0
    inp[L.I_MODE] = L.INPUT_CURRENT
    inp[L.I_ID_REF] = 0.0
    inp[L.I_UD] = 0.0
    inp[L.I_UQ] = 0.0
    while row < n or (n == 0 and int(s[S_K]) < tick_end):
        k = int(s[S_K])
        s[S_K] = k + 1
        if k % n_pos == 0:
            if first < 0:
                first = k
            ff_next = v_pos[(k - first) // n_pos + 1]
        _measure(c, s, out, k, n_speed)
        if c[C_FF_LINEAR] != 0.0 and k % n_pos != 0 and k % n_speed == 0:
            # between position cycles: the P part held, the feed-forward interpolated
            frac = (k % n_pos) / n_pos
            v_ff = s[S_V_SET] + (ff_next - s[S_V_SET]) * frac
            v = c[C_KV] * s[S_POS_ERROR] + c[C_FF] * v_ff
            s[S_V_CMD] = max(-c[C_V_LIM], min(c[C_V_LIM], v))
            s[S_W_SET] = s[S_V_CMD] / c[C_RATIO]
        if k % n_pos == 0:
            _position_cycle(c, s, fine_pos, fine_vel, fine_acc)
        if k % n_speed == 0:
            s[S_IQ_SET] = _speed_step(c, s)
        iq = s[S_IQ_SET]
        if (iq * 0.0 + s[S_INTEG] * 0.0 + s[S_W_SET] * 0.0 + s[S_SYM_Y] * 0.0) != 0.0:
            return STATUS_LOOP_NONFINITE
        if n_delay > 0:
            delayed = delay[head]
            delay[head] = iq
            head = (head + 1) % n_delay
            s[S_DELAY_HEAD] = head
            iq = delayed
        lim = c[C_DRIVE_I_MAX]
        inp[L.I_IQ_REF] = max(-lim, min(lim, iq))
        status = axis_step_nb(p, ps, inp, out, n_sub)
        if status != L.STATUS_OK:
            return status
        if n > 0 and first >= 0 and (k - first) % every == 0:
            rec[0, row] = s[S_X_ACT]
            rec[1, row] = out[L.O_IQ_MEAS] * c[C_PER_AMP]
            rec[2, row] = s[S_THETA_ACT] * c[C_RATIO]
            rec[3, row] = out[L.O_TABLE_VEL]
            row += 1
    return L.STATUS_OK

