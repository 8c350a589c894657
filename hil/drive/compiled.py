"""The drive cycle in steady state, compiled: one numba call from the speed actual value to
the feedback.

In OPERATION ENABLED in a cyclic mode (CSP, CSV, CST) with nothing to react to, a drive
cycle of :class:`hil.drive.core.EmulatedDrive` is arithmetic on a few dozen numbers: the
speed actual value, the mode's command and its interpolation (60C2h), the software-limit
clamp, the monitor's checks and statusword flags, the position and speed loops, the
current limit, the plant's sub-steps (the plant's own numba entry
:func:`plant.kernel.axis_step_nb`) and the feedback.  :func:`steady_cycle` does exactly
that on flat arrays, in the same floating-point order as the Python path (no fused
multiply-add; ``x ** 2`` through libm's ``pow`` as numpy does it, the exponent a run-time
value so that LLVM does not turn it into ``x * x``, which differs in the last bit for some
``x``), so both give the same bits.

It computes the whole cycle into local variables first.  The moment anything falls
outside the steady state -- a fault cause present, a changed controlword or mode, a
refused setpoint, a non-finite loop output, a plant status not OK -- it returns a
non-zero ``EXIT_*`` code *before* it has changed any state (a plant step that failed is
undone from a copy), and the Python path runs that cycle: it stays the one owner of the
state machine, the faults and their reactions.  :mod:`hil.drive.compiled_path` packs the
drive's state into these arrays and back.

Array layouts (module constants, compile-time indices):

* ``prm`` float64[:data:`N_PRM`]: parameters and loop coefficients (``R_*``), SI units;
* ``fst`` float64[:data:`N_FST`]: the float state (``F_*``);
* ``ist`` int64[:data:`N_IST`]: the integer state and cycle ratios (``J_*``);
* ``spf`` float64[:data:`N_SPF`]: the setpoint's floats in :data:`SP_FLOATS` order;
  ``spi`` int64[3]: seq, controlword, mode;
* ``fbf`` float64[:data:`N_FBF`]: the feedback's floats (``B_*``); the statusword is
  ``ist[J_STATUSWORD]``;
* ``ring_f`` float64[n_floats, slots], ``ring_i`` int64[n_ints, slots]: this axis's
  planes of the recording's ring (:mod:`hil.runtime.recording`); a cycle that ran writes
  its row into column ``ist[J_ROW]`` (-1: none): the setpoint's floats, the plant's
  outputs, and the words in :data:`RING_INTS` order.
"""

import math

from numba import njit

from hil.cia402 import (
    STATUS_PATTERNS,
    SW_CALLER_BITS,
    SW_FOLLOWING_ERROR,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT_ACTIVE,
    SW_REMOTE,
    SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
    SW_WARNING,
    State,
)
from hil.drive.interpolation import EXTRAPOLATE
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_CSV
from plant import layout as L
from plant.kernel import axis_step_nb

#: the statusword of OPERATION ENABLED without the cycle's flags (hil.cia402's table)
SW_OPERATION_ENABLED_BASE = (STATUS_PATTERNS[State.OPERATION_ENABLED].value | SW_REMOTE
                             | SW_VOLTAGE_ENABLED)
_MODE_BITS = SW_TARGET_REACHED | SW_FOLLOWS_COMMAND | SW_FOLLOWING_ERROR

#: the cycle ran compiled
DONE = 0
#: another mode or controlword than the steady state's (the Python path takes the edge)
EXIT_COMMAND = 1
#: the setpoint is refused (the Python path latches the fault)
EXIT_REFUSED = 2
#: a fault cause is present (following error, limits, overspeed, I²t)
EXIT_CAUSE = 3
#: the loops gave a non-finite current
EXIT_LOOP = 4
#: the plant's status is not OK (the step was undone)
EXIT_PLANT = 5

#: the recording's integer row of an axis (hil.runtime.recording.AXIS_INTS)
RING_INTS = ("sp_controlword", "sp_mode", "fb_statusword", "fb_fault", "drive_state",
             "drive_enable")
#: the setpoint's float fields, in ``spf`` order (and the recording's)
SP_FLOATS = ("iq_ref_a", "id_ref_a", "ud_v", "uq_v", "target_position_counts",
             "target_velocity_counts_s", "velocity_offset_counts_s")
S_IQ, S_ID, S_UD, S_UQ, S_POS, S_VEL, S_VOFF = range(7)
N_SPF = 7
I_SEQ, I_CW, I_MODE = range(3)

(R_RPC, R_SPEED_PERIOD, R_CYCLE, R_LIMIT_MIN, R_LIMIT_MAX, R_MAX_SPEED, R_MAX_CURRENT,
 R_FE_WINDOW, R_FE_TIME, R_POS_WINDOW, R_POS_WINDOW_TIME, R_I2T_TRIP, R_I2T_COOLED,
 R_I2T_WARNING, R_CONTINUOUS2, R_OVERSPEED, R_STANDSTILL, R_INTERP_PERIOD, R_SHIFT, R_TWO,
 R_B_POSITION, R_B_VELOCITY, R_B_CURRENT, R_B_VOLTAGE,
 R_KV, R_FF, R_SYM_A, R_V_LIM, R_KD_T, R_KP, R_KI_T, R_PI_LIMIT, R_INV_KT, R_I_MAX, R_KT,
 R_STOP_ON_TOTAL,
 R_SET_B0, R_SET_B1, R_SET_B2, R_SET_A1, R_SET_A2,
 R_CUR_B0, R_CUR_B1, R_CUR_B2, R_CUR_A1, R_CUR_A2,
 R_NOTCH_B0, R_NOTCH_B1, R_NOTCH_B2, R_NOTCH_A1, R_NOTCH_A2, N_PRM) = range(52)
(F_COUNTS_PREV, F_VELOCITY, F_I2T, F_FE_TIME, F_IN_WINDOW, F_SWITCH_NEG, F_SWITCH_POS,
 F_FOLLOWING_ERROR, F_DEMAND, F_SPEED, F_START_A, F_START_B, F_END_A, F_END_B,
 F_SYM_Y, F_POS_ERROR, F_INTEG, F_SET_Z1, F_SET_Z2, F_CUR_Z1, F_CUR_Z2, F_NOTCH_Z1,
 F_NOTCH_Z2, F_E_PREV, F_W_CMD, F_IQ, F_LAST_GOOD_X, N_FST) = range(28)
(J_TICK, J_LIMITED, J_HOT, J_MONITOR_FLAGS, J_STATUSWORD, J_INTERP_SEQ, J_CYCLES, J_LENGTH,
 J_SPEED_RATIO, J_POSITION_RATIO, J_N_SUB, J_MODE, J_CONTROLWORD, J_ROW, N_IST) = range(15)
B_TIME, B_ENCODER, B_SCALE, B_VELOCITY, B_IQ, B_ID = range(6)
N_FBF = 6



@njit(cache=True, error_model="numpy", inline="always")
def _py_max(a, b):
    """Python's ``max(a, b)``: ``a`` unless ``b`` is strictly greater (signed zeros and
    NaN as Python has them)."""
    return b if b > a else a


@njit(cache=True, error_model="numpy", inline="always")
def _py_min(a, b):
    """Python's ``min(a, b)``: ``a`` unless ``b`` is strictly smaller."""
    return b if b < a else a


@njit(cache=True, error_model="numpy", inline="always")
def _biquad(prm, base, fst, z, x):
    """:meth:`hil.controller.blocks.Biquad.step` on coefficients ``prm[base:base + 5]``
    and the delay line ``fst[z:z + 2]``; returns (y, z1, z2) without storing them."""
    y = prm[base] * x + fst[z]
    z1 = prm[base + 1] * x - prm[base + 3] * y + fst[z + 1]
    z2 = prm[base + 2] * x - prm[base + 4] * y
    return y, z1, z2


@njit(cache=True, error_model="numpy", inline="always")
def _refused(prm, spf, mode):
    """:meth:`io_adapters.messages.SetpointBounds.refusal` != 0 for a cyclic mode."""
    if (spf[S_POS] * 0.0 + spf[S_VEL] * 0.0 + spf[S_VOFF] * 0.0 + spf[S_IQ] * 0.0
            + spf[S_ID] * 0.0 + spf[S_UD] * 0.0 + spf[S_UQ] * 0.0) != 0.0:
        return True
    if mode != MODE_CSP and mode != MODE_CSV and mode != MODE_CST:
        return True
    return (abs(spf[S_POS]) > prm[R_B_POSITION] or abs(spf[S_VEL]) > prm[R_B_VELOCITY]
            or abs(spf[S_VOFF]) > prm[R_B_VELOCITY] or abs(spf[S_IQ]) > prm[R_B_CURRENT]
            or abs(spf[S_ID]) > prm[R_B_CURRENT] or abs(spf[S_UD]) > prm[R_B_VOLTAGE]
            or abs(spf[S_UQ]) > prm[R_B_VOLTAGE])


@njit(cache=True, error_model="numpy", _nrt=False)
def steady_cycle(prm, fst, ist, spf, spi, p, s, inp, out, saved, fbf, ring_f, ring_i):
    """One drive cycle in steady state (see the module docstring); returns :data:`DONE` or
    an ``EXIT_*`` code with nothing changed (the ring's row included).  ``p``, ``s``, ``inp``, ``out``: the plant's
    arrays (:mod:`plant.layout`); ``saved``: float64 scratch of at least
    ``len(s) + len(inp) + len(out)``, for undoing a failed plant step."""
    mode, cw = spi[I_MODE], spi[I_CW]
    if mode != ist[J_MODE] or cw != ist[J_CONTROLWORD]:
        return EXIT_COMMAND
    if _refused(prm, spf, mode):
        return EXIT_REFUSED
    tick = ist[J_TICK]
    rpc = prm[R_RPC]
    # the speed actual value (EmulatedDrive._speed_actual)
    counts = out[L.O_ENCODER]
    counts_prev, velocity = fst[F_COUNTS_PREV], fst[F_VELOCITY]
    if tick % ist[J_SPEED_RATIO] == 0:
        if counts_prev == counts_prev:
            velocity = (counts - counts_prev) / prm[R_SPEED_PERIOD]
        counts_prev = counts
    theta = counts * rpc
    w_act = velocity * rpc
    # the mode's command (ModeControl.command, Interpolator.step)
    interp_seq, cycles, length = ist[J_INTERP_SEQ], ist[J_CYCLES], ist[J_LENGTH]
    a0, b0, a1, b1 = fst[F_START_A], fst[F_START_B], fst[F_END_A], fst[F_END_B]
    target, w_cmd = math.nan, 0.0
    if mode == MODE_CST:
        demand, speed = theta, 0.0
    else:
        if mode == MODE_CSP:
            a = (spf[S_POS] - prm[R_SHIFT]) * rpc
            b = spf[S_VOFF] * rpc
        else:
            a = spf[S_VEL] * rpc
            b = 0.0
        period = prm[R_INTERP_PERIOD]
        if period < prm[R_CYCLE]:
            interp_seq, a0, b0, a1, b1, cycles, length = -1, a, b, a, b, 1, 1
            x, ff = a, b
        else:
            if spi[I_SEQ] != interp_seq:
                interp_seq = spi[I_SEQ]
                a0, b0, a1, b1 = a1, b1, a, b
                cycles = 0
                length = max(1, round(period / prm[R_CYCLE]))
            cycles += 1
            f = _py_min(cycles / length, EXTRAPOLATE)
            x, ff = a0 + (a1 - a0) * f, b0 + (b1 - b0) * f
        if mode == MODE_CSP:
            target, w_cmd = x, ff
            demand = x if x == x else math.nan
            speed = ff
            target = _py_min(_py_max(target, prm[R_LIMIT_MIN]), prm[R_LIMIT_MAX])
        else:
            w_cmd = x
            demand, speed = theta, x
    # the monitor (Monitor.check, operating)
    two = prm[R_TWO]
    currents_a2 = math.pow(out[L.O_IQ_MEAS], two) + math.pow(out[L.O_ID_MEAS], two)
    heat = fst[F_I2T] + (currents_a2 - prm[R_CONTINUOUS2]) * prm[R_CYCLE]
    i2t = heat if heat > 0.0 else 0.0
    hot = ist[J_HOT]
    if i2t >= prm[R_I2T_TRIP]:
        hot = 1
    elif i2t <= prm[R_I2T_COOLED]:
        hot = 0
    if hot:
        return EXIT_CAUSE
    flags = SW_WARNING if i2t >= prm[R_I2T_WARNING] else 0
    if abs(w_act) > prm[R_OVERSPEED]:
        return EXIT_CAUSE
    sw_neg, sw_pos = out[L.O_LIMIT_NEG], out[L.O_LIMIT_POS]
    reached_neg = sw_neg > 0.0 and fst[F_SWITCH_NEG] <= 0.0
    reached_pos = sw_pos > 0.0 and fst[F_SWITCH_POS] <= 0.0
    if sw_neg > 0.0 or sw_pos > 0.0:
        flags |= SW_INTERNAL_LIMIT_ACTIVE
    standstill = prm[R_STANDSTILL]
    if (sw_neg > 0.0 and (reached_neg or w_act < -standstill)) or (
            sw_pos > 0.0 and (reached_pos or w_act > standstill)):
        return EXIT_CAUSE
    csp = target == target
    if not csp and ((theta < prm[R_LIMIT_MIN] and w_act < -standstill)
                    or (theta > prm[R_LIMIT_MAX] and w_act > standstill)):
        return EXIT_CAUSE
    following_error, fe_time, in_window = (fst[F_FOLLOWING_ERROR], fst[F_FE_TIME],
                                           fst[F_IN_WINDOW])
    if csp:
        following_error = target - theta
        if abs(following_error) > prm[R_FE_WINDOW]:
            fe_time += prm[R_CYCLE]
            if fe_time > prm[R_FE_TIME]:
                return EXIT_CAUSE
        else:
            fe_time = 0.0
        if abs(following_error) <= prm[R_POS_WINDOW]:
            in_window += prm[R_CYCLE]
        else:
            in_window = 0.0
        if in_window >= prm[R_POS_WINDOW_TIME]:
            flags |= SW_TARGET_REACHED
    monitor_flags = flags | (SW_FOLLOWING_ERROR if abs(following_error) > prm[R_FE_WINDOW]
                             else 0)
    # the statusword (EmulatedDrive._flags, DriveStateMachine.update without a transition:
    # the controlword is enable operation and no fault is latched)
    word_flags = (monitor_flags & ~_MODE_BITS | monitor_flags | SW_FOLLOWS_COMMAND
                  | ist[J_LIMITED])
    statusword = SW_OPERATION_ENABLED_BASE | (word_flags & SW_CALLER_BITS)
    # the loops and limits (EmulatedDrive._current)
    limited = 0
    sym_y, pos_error, w_loop = fst[F_SYM_Y], fst[F_POS_ERROR], fst[F_W_CMD]
    integ, e_prev, iq_loop = fst[F_INTEG], fst[F_E_PREV], fst[F_IQ]
    set_z1, set_z2 = fst[F_SET_Z1], fst[F_SET_Z2]
    cur_z1, cur_z2 = fst[F_CUR_Z1], fst[F_CUR_Z2]
    notch_z1, notch_z2 = fst[F_NOTCH_Z1], fst[F_NOTCH_Z2]
    max_speed = prm[R_MAX_SPEED]
    if mode == MODE_CST:
        iq = spf[S_IQ]
    else:
        if csp:
            held = target != demand
            if held:
                limited = SW_INTERNAL_LIMIT_ACTIVE
            if tick % ist[J_POSITION_RATIO] == 0:
                sym_y = target + (sym_y - target) * prm[R_SYM_A]
                pos_error = sym_y - theta
                v = prm[R_KV] * pos_error + prm[R_FF] * (0.0 if held else w_cmd)
                w_loop = _py_max(-prm[R_V_LIM], _py_min(prm[R_V_LIM], v))
            w = w_loop
            if abs(w) > max_speed:
                limited = SW_INTERNAL_LIMIT_ACTIVE
                w = math.copysign(max_speed, w)
        else:
            w = w_cmd
            if abs(w) > max_speed:
                limited = SW_INTERNAL_LIMIT_ACTIVE
                w = math.copysign(max_speed, w)
            if (w > 0.0 and theta >= prm[R_LIMIT_MAX]) or (
                    w < 0.0 and theta <= prm[R_LIMIT_MIN]):
                w = 0.0
                limited = SW_INTERNAL_LIMIT_ACTIVE
        if tick % ist[J_SPEED_RATIO] == 0:
            # SpeedLoop.step
            e, set_z1, set_z2 = _biquad(prm, R_SET_B0, fst, F_SET_Z1, w)
            e = e - w_act
            d_part = prm[R_KD_T] * (e - e_prev)
            i_ff = spf[S_IQ]
            outer = d_part + i_ff * prm[R_KT] if prm[R_STOP_ON_TOTAL] != 0.0 else 0.0
            # PI.step_within
            u = prm[R_KP] * e + integ
            total = u + outer
            pi_limit = prm[R_PI_LIMIT]
            if total > pi_limit:
                if e < 0.0:
                    integ += prm[R_KI_T] * e
                u = _py_min(u, pi_limit)
            elif total < -pi_limit:
                if e > 0.0:
                    integ += prm[R_KI_T] * e
                u = _py_max(u, -pi_limit)
            else:
                integ += prm[R_KI_T] * e
            torque = u + d_part
            e_prev = e
            c, cur_z1, cur_z2 = _biquad(prm, R_CUR_B0, fst, F_CUR_Z1,
                                        torque * prm[R_INV_KT] + i_ff)
            i, notch_z1, notch_z2 = _biquad(prm, R_NOTCH_B0, fst, F_NOTCH_Z1, c)
            iq_loop = _py_max(-prm[R_I_MAX], _py_min(prm[R_I_MAX], i))
        iq = iq_loop
    if iq != iq or abs(iq) == math.inf:
        return EXIT_LOOP
    limit = prm[R_MAX_CURRENT]
    if abs(iq) > limit:
        limited = SW_INTERNAL_LIMIT_ACTIVE
        iq = math.copysign(limit, iq)
    # the plant, undone if its status is not OK
    n_s, n_i = s.size, inp.size
    for k in range(n_s):
        saved[k] = s[k]
    for k in range(n_i):
        saved[n_s + k] = inp[k]
    for k in range(out.size):
        saved[n_s + n_i + k] = out[k]
    inp[L.I_ENABLE] = 1.0
    inp[L.I_MODE] = L.INPUT_CURRENT
    inp[L.I_IQ_REF] = iq
    inp[L.I_ID_REF] = _py_min(_py_max(spf[S_ID], -limit), limit)
    inp[L.I_UD] = 0.0
    inp[L.I_UQ] = 0.0
    status = axis_step_nb(p, s, inp, out, ist[J_N_SUB])
    if status != L.STATUS_OK:
        for k in range(n_s):
            s[k] = saved[k]
        for k in range(n_i):
            inp[k] = saved[n_s + k]
        for k in range(out.size):
            out[k] = saved[n_s + n_i + k]
        return EXIT_PLANT
    # commit
    fst[F_COUNTS_PREV], fst[F_VELOCITY] = counts_prev, velocity
    fst[F_I2T], fst[F_FE_TIME], fst[F_IN_WINDOW] = i2t, fe_time, in_window
    fst[F_SWITCH_NEG], fst[F_SWITCH_POS] = sw_neg, sw_pos
    fst[F_FOLLOWING_ERROR], fst[F_DEMAND], fst[F_SPEED] = following_error, demand, speed
    fst[F_START_A], fst[F_START_B], fst[F_END_A], fst[F_END_B] = a0, b0, a1, b1
    fst[F_SYM_Y], fst[F_POS_ERROR], fst[F_W_CMD] = sym_y, pos_error, w_loop
    fst[F_INTEG], fst[F_E_PREV], fst[F_IQ] = integ, e_prev, iq_loop
    fst[F_SET_Z1], fst[F_SET_Z2], fst[F_CUR_Z1], fst[F_CUR_Z2] = set_z1, set_z2, cur_z1, cur_z2
    fst[F_NOTCH_Z1], fst[F_NOTCH_Z2] = notch_z1, notch_z2
    fst[F_LAST_GOOD_X] = out[L.O_TABLE_POS]
    ist[J_TICK] = tick + 1
    ist[J_LIMITED], ist[J_HOT], ist[J_MONITOR_FLAGS] = limited, hot, monitor_flags
    ist[J_STATUSWORD] = statusword
    ist[J_INTERP_SEQ], ist[J_CYCLES], ist[J_LENGTH] = interp_seq, cycles, length
    fbf[B_TIME] = out[L.O_TIME]
    fbf[B_ENCODER] = out[L.O_ENCODER] + prm[R_SHIFT]
    fbf[B_SCALE] = out[L.O_SCALE]
    fbf[B_VELOCITY] = velocity
    fbf[B_IQ] = out[L.O_IQ_MEAS]
    fbf[B_ID] = out[L.O_ID_MEAS]
    j = ist[J_ROW]
    if j >= 0:
        for k in range(N_SPF):
            ring_f[k, j] = spf[k]
        for k in range(out.size):
            ring_f[N_SPF + k, j] = out[k]
        ring_i[0, j] = cw
        ring_i[1, j] = mode
        ring_i[2, j] = statusword
        ring_i[3, j] = 0  # 603Fh: no fault is latched in steady state
        ring_i[4, j] = State.OPERATION_ENABLED
        ring_i[5, j] = 1  # the power stage on
    return DONE
