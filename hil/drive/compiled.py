"""The drive cycle in steady state, compiled: one numba call from the speed actual value to
the feedback.

In OPERATION ENABLED in a cyclic mode (CSP, CSV, CST, voltage) with nothing to react to, a drive
cycle of :class:`hil.drive.core.EmulatedDrive` is arithmetic on a few dozen numbers: the
speed actual value, the mode's command and its interpolation (60C2h), the software-limit
clamp, the monitor's checks and statusword flags, the position and speed loops, the
current limit, the plant's sub-steps (the plant's own numba entry
:func:`plant.kernel.axis_step_nb`) and the feedback.  :func:`steady_cycle` does exactly
that on flat arrays, in the same floating-point order as the Python path (no fused
multiply-add; ``x ** 2`` through libm's ``pow`` as numpy does it, the exponent a run-time
value so that LLVM does not turn it into ``x * x``, which differs in the last bit for some
``x``), so both give the same bits.

It computes the cycle on a working copy of its state and copies it back at the end.  The
moment anything falls outside the steady state -- a fault cause present, a changed
controlword or mode, a refused setpoint, a non-finite loop output, a plant status not OK
-- it returns a non-zero ``EXIT_*`` code *before* it has changed any state (a plant step
that failed is undone from a copy), and the Python path runs that cycle: it stays the one
owner of the state machine, the faults and their reactions.
:mod:`hil.drive.compiled_path` packs the drive's state into these arrays and back.

Array layouts (module constants, compile-time indices):

* ``prm`` float64[:data:`N_PRM`]: parameters and loop coefficients (``R_*``), SI units;
* ``fst`` float64[2 * :data:`N_FST`]: the float state (``F_*``), then the cycle's working
  copy of it;
* ``ist`` int64[2 * :data:`N_IST`]: the integer state and cycle ratios (``J_*``), then
  its working copy;
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
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_CSV, MODE_VOLTAGE
from plant import layout as L
from plant.kernel import axis_step_nb

#: the statusword of OPERATION ENABLED without the cycle's flags (hil.cia402's table)
SW_OPERATION_ENABLED_BASE = (STATUS_PATTERNS[State.OPERATION_ENABLED].value | SW_REMOTE
                             | SW_VOLTAGE_ENABLED)

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
#: the exit codes' names (reports)
EXIT_NAMES = {EXIT_COMMAND: "command", EXIT_REFUSED: "refused", EXIT_CAUSE: "cause",
              EXIT_LOOP: "loop", EXIT_PLANT: "plant"}

#: the recording's integer row of an axis (hil.runtime.recording.AXIS_INTS)
RING_INTS = ("sp_controlword", "sp_mode", "fb_statusword", "fb_fault", "drive_state",
             "drive_enable")
#: the setpoint's float fields, in ``spf`` order (and the recording's)
SP_FLOATS = ("iq_ref_a", "id_ref_a", "ud_v", "uq_v", "target_position_counts",
             "target_velocity_counts_s", "velocity_offset_counts_s")
S_IQ, S_ID, S_UD, S_UQ, S_POS, S_VEL, S_VOFF = range(7)
N_SPF = 7
I_SEQ, I_CW, I_MODE = range(3)

#: ``prm`` (the last two: the holding brake's presence, 1.0, and closing time, s):
#: motor units per increment; the speed cycle, the drive cycle (s); 607Dh, 6080h,
#: 6072h, 6065h-6068h, the I²t levels, the overspeed and standstill speeds, 60C2h (s), the
#: home shift (increments), 2.0 (``pow``'s exponent); the adapter's bounds (wire units);
#: the position loop (K_v 1/s, feed-forward weight, symmetrising PT1 factor, speed limit),
#: the speed loop (K_d/T, K_p, K_i T, the PI's limit, 1/K_t, I_max, K_t, the anti-windup's
#: :data:`ANTIWINDUP_CODES`) and its three biquads (b0, b1, b2, a1, a2 each); the voltage
#: mode's peak-current trip (6072h squared, the trip level squared, the time allowed above
#: 6072h), 1.0 when the drive takes voltage mode: motor units, s, A
(R_RPC, R_SPEED_PERIOD, R_CYCLE, R_LIMIT_MIN, R_LIMIT_MAX, R_MAX_SPEED, R_MAX_CURRENT,
 R_FE_WINDOW, R_FE_TIME, R_POS_WINDOW, R_POS_WINDOW_TIME, R_I2T_TRIP, R_I2T_COOLED,
 R_I2T_WARNING, R_CONTINUOUS2, R_OVERSPEED, R_STANDSTILL, R_INTERP_PERIOD, R_SHIFT, R_TWO,
 R_B_POSITION, R_B_VELOCITY, R_B_CURRENT, R_B_VOLTAGE,
 R_KV, R_FF, R_SYM_A, R_V_LIM, R_KD_T, R_KP, R_KI_T, R_PI_LIMIT, R_INV_KT, R_I_MAX, R_KT,
 R_ANTIWINDUP,
 R_SET_B0, R_SET_B1, R_SET_B2, R_SET_A1, R_SET_A2,
 R_CUR_B0, R_CUR_B1, R_CUR_B2, R_CUR_A1, R_CUR_A2,
 R_NOTCH_B0, R_NOTCH_B1, R_NOTCH_B2, R_NOTCH_A1, R_NOTCH_A2, R_MAX_CURRENT2, R_PEAK_TRIP2,
 R_PEAK_TIME, R_VOLTAGE_OK, R_BRAKE_PRESENT, R_BRAKE_CLOSING, N_PRM) = range(58)
#: ``fst``: the drive's, the monitor's, the modes' and interpolator's and the loops' floats;
#: the holding brake's time since the pulses went off (s); the power-off cycle's last
#: position and speed actual and the last setpoint's 607Ah and 60B1h (NaN: none ran since
#: the state was packed)
(F_COUNTS_PREV, F_VELOCITY, F_I2T, F_FE_TIME, F_IN_WINDOW, F_SWITCH_NEG, F_SWITCH_POS,
 F_FOLLOWING_ERROR, F_DEMAND, F_SPEED, F_START_A, F_START_B, F_END_A, F_END_B,
 F_SYM_Y, F_POS_ERROR, F_INTEG, F_SET_Z1, F_SET_Z2, F_CUR_Z1, F_CUR_Z2, F_NOTCH_Z1,
 F_NOTCH_Z2, F_E_PREV, F_W_CMD, F_IQ, F_LAST_GOOD_X, F_PEAK_TIME, F_BRAKE_OFF, F_IDLE_THETA,
 F_IDLE_W, F_IDLE_POS, F_IDLE_VOFF, N_FST) = range(34)
#: ``ist``: the drive cycle, statusword bits, the interpolator's segment, the cycle ratios,
#: sub-steps per cycle, the steady state's mode and controlword, the ring's column; 1 when
#: the steady state is a power-off one (:func:`steady_cycle` runs the power-off cycle), its
#: CiA 402 state and that state's statusword without the cycle's flags
(J_TICK, J_LIMITED, J_HOT, J_MONITOR_FLAGS, J_STATUSWORD, J_INTERP_SEQ, J_CYCLES, J_LENGTH,
 J_SPEED_RATIO, J_POSITION_RATIO, J_N_SUB, J_MODE, J_CONTROLWORD, J_ROW, J_IDLE, J_STATE,
 J_BASE_STATUSWORD, N_IST) = range(18)
B_TIME, B_ENCODER, B_SCALE, B_VELOCITY, B_IQ, B_ID = range(6)
#: ``[controller] speed_antiwindup`` in ``prm[R_ANTIWINDUP]``
AW_CONDITIONAL, AW_TORQUE_SETPOINT, AW_CLAMP, AW_NONE = 0.0, 1.0, 2.0, 3.0
ANTIWINDUP_CODES = {"conditional": AW_CONDITIONAL, "torque_setpoint": AW_TORQUE_SETPOINT,
                    "clamp": AW_CLAMP, "none": AW_NONE}
N_FBF = 6


@njit(cache=True, error_model="numpy", inline="always")
def _py_max(a, b):
    """Python's ``max(a, b)``: ``a`` unless ``b`` is strictly greater (signed zeros and
    NaN as Python has them)."""
    return b if b > a else a  # noqa: FURB136 (numba's max orders NaN and -0.0 otherwise)


@njit(cache=True, error_model="numpy", inline="always")
def _py_min(a, b):
    """Python's ``min(a, b)``: ``a`` unless ``b`` is strictly smaller."""
    return b if b < a else a  # noqa: FURB136 (as _py_max)


@njit(cache=True, error_model="numpy", inline="always")
def _copy(src, dst, n):
    """``dst[:n] = src[:n]`` (a slice assignment would allocate a temporary)."""
    for k in range(n):
        dst[k] = src[k]


@njit(cache=True, error_model="numpy", inline="always")
def _biquad(prm, base, w, z, x):
    """:meth:`hil.controller.blocks.Biquad.step` on coefficients ``prm[base:base + 5]``
    and the delay line ``w[z:z + 2]``."""
    y = prm[base] * x + w[z]
    w[z] = prm[base + 1] * x - prm[base + 3] * y + w[z + 1]
    w[z + 1] = prm[base + 2] * x - prm[base + 4] * y
    return y


@njit(cache=True, error_model="numpy", inline="always")
def _refused(prm, spf, mode):
    """:meth:`io_adapters.messages.SetpointBounds.refusal` != 0 for a cyclic mode."""
    if (spf[S_POS] * 0.0 + spf[S_VEL] * 0.0 + spf[S_VOFF] * 0.0 + spf[S_IQ] * 0.0
            + spf[S_ID] * 0.0 + spf[S_UD] * 0.0 + spf[S_UQ] * 0.0) != 0.0:
        return True
    if mode != MODE_CSP and mode != MODE_CSV and mode != MODE_CST and (
            mode != MODE_VOLTAGE or prm[R_VOLTAGE_OK] == 0.0):
        return True
    return (abs(spf[S_POS]) > prm[R_B_POSITION] or abs(spf[S_VEL]) > prm[R_B_VELOCITY]
            or abs(spf[S_VOFF]) > prm[R_B_VELOCITY] or abs(spf[S_IQ]) > prm[R_B_CURRENT]
            or abs(spf[S_ID]) > prm[R_B_CURRENT] or abs(spf[S_UD]) > prm[R_B_VOLTAGE]
            or abs(spf[S_UQ]) > prm[R_B_VOLTAGE])


@njit(cache=True, error_model="numpy", inline="always")
def _speed_actual(prm, w, wi, counts):
    """EmulatedDrive._speed_actual: the encoder difference over the speed cycle."""
    if wi[J_TICK] % wi[J_SPEED_RATIO] == 0:
        previous = w[F_COUNTS_PREV]
        if previous == previous:  # not NaN: a previous sample exists
            w[F_VELOCITY] = (counts - previous) / prm[R_SPEED_PERIOD]
        w[F_COUNTS_PREV] = counts


@njit(cache=True, error_model="numpy", inline="always")
def _interpolated(prm, w, wi, seq, a, b):
    """Interpolator.step: this cycle's (a, b) for the newest setpoint ``seq``."""
    period = prm[R_INTERP_PERIOD]
    if period < prm[R_CYCLE]:
        wi[J_INTERP_SEQ], wi[J_CYCLES], wi[J_LENGTH] = -1, 1, 1
        w[F_START_A], w[F_START_B], w[F_END_A], w[F_END_B] = a, b, a, b
        return a, b
    if seq != wi[J_INTERP_SEQ]:
        wi[J_INTERP_SEQ] = seq
        w[F_START_A], w[F_START_B] = w[F_END_A], w[F_END_B]
        w[F_END_A], w[F_END_B] = a, b
        wi[J_CYCLES] = 0
        wi[J_LENGTH] = max(1, round(period / prm[R_CYCLE]))
    wi[J_CYCLES] += 1
    f = _py_min(wi[J_CYCLES] / wi[J_LENGTH], EXTRAPOLATE)
    a0, b0 = w[F_START_A], w[F_START_B]
    held = wi[J_CYCLES] > EXTRAPOLATE * wi[J_LENGTH]
    return a0 + (w[F_END_A] - a0) * f, 0.0 if held else b0 + (w[F_END_B] - b0) * f


@njit(cache=True, error_model="numpy", inline="always")
def _command(prm, w, wi, spf, spi, theta):
    """ModeControl.command and the CSP target held inside 607Dh: (position target or
    NaN, speed command or feed-forward)."""
    mode, rpc = spi[I_MODE], prm[R_RPC]
    if mode == MODE_CST or mode == MODE_VOLTAGE:
        w[F_DEMAND], w[F_SPEED] = theta, 0.0
        return math.nan, 0.0
    if mode == MODE_CSV:
        v, _ = _interpolated(prm, w, wi, spi[I_SEQ], spf[S_VEL] * rpc, 0.0)
        w[F_DEMAND], w[F_SPEED] = theta, v
        return math.nan, v
    x, ff = _interpolated(prm, w, wi, spi[I_SEQ], (spf[S_POS] - prm[R_SHIFT]) * rpc,
                          spf[S_VOFF] * rpc)
    w[F_DEMAND] = x if x == x else math.nan
    w[F_SPEED] = ff
    return _py_min(_py_max(x, prm[R_LIMIT_MIN]), prm[R_LIMIT_MAX]), ff


@njit(cache=True, error_model="numpy", inline="always")
def _i2t(prm, w, wi, out):
    """Monitor._i2t on the sampled currents: True when hot (the cause OVERCURRENT)."""
    currents_a2 = math.pow(out[L.O_IQ_MEAS], prm[R_TWO]) + math.pow(out[L.O_ID_MEAS],
                                                                     prm[R_TWO])
    heat = w[F_I2T] + (currents_a2 - prm[R_CONTINUOUS2]) * prm[R_CYCLE]
    w[F_I2T] = heat if heat > 0.0 else 0.0  # noqa: FURB136 (a NaN current counts as cold)
    if w[F_I2T] >= prm[R_I2T_TRIP]:
        wi[J_HOT] = 1
    elif w[F_I2T] <= prm[R_I2T_COOLED]:
        wi[J_HOT] = 0
    return currents_a2, wi[J_HOT] != 0


@njit(cache=True, error_model="numpy", inline="always")
def _monitor(prm, w, wi, out, target, theta, w_act, voltage):
    """Monitor.check in OPERATION ENABLED (``voltage``: in voltage mode): its statusword
    flags, or -1 when a fault cause is present (then the cycle is the Python path's)."""
    currents_a2, hot = _i2t(prm, w, wi, out)
    if hot or abs(w_act) > prm[R_OVERSPEED]:
        return -1
    if voltage:  # Monitor._peak
        if currents_a2 > prm[R_MAX_CURRENT2]:
            w[F_PEAK_TIME] += prm[R_CYCLE]
            if w[F_PEAK_TIME] > prm[R_PEAK_TIME] or currents_a2 > prm[R_PEAK_TRIP2]:
                return -1
        else:
            w[F_PEAK_TIME] = 0.0
    flags = SW_WARNING if w[F_I2T] >= prm[R_I2T_WARNING] else 0
    neg, pos = out[L.O_LIMIT_NEG], out[L.O_LIMIT_POS]
    reached_neg = neg > 0.0 and w[F_SWITCH_NEG] <= 0.0
    reached_pos = pos > 0.0 and w[F_SWITCH_POS] <= 0.0
    w[F_SWITCH_NEG], w[F_SWITCH_POS] = neg, pos
    if neg > 0.0 or pos > 0.0:
        flags |= SW_INTERNAL_LIMIT_ACTIVE
    still = prm[R_STANDSTILL]
    if (neg > 0.0 and (reached_neg or w_act < -still)) or (
            pos > 0.0 and (reached_pos or w_act > still)):
        return -1
    if target != target:
        if (theta < prm[R_LIMIT_MIN] and w_act < -still) or (
                theta > prm[R_LIMIT_MAX] and w_act > still):
            return -1
    else:
        error = target - theta
        w[F_FOLLOWING_ERROR] = error
        if abs(error) > prm[R_FE_WINDOW]:
            w[F_FE_TIME] += prm[R_CYCLE]
            if w[F_FE_TIME] > prm[R_FE_TIME]:
                return -1
        else:
            w[F_FE_TIME] = 0.0
        if abs(error) <= prm[R_POS_WINDOW]:
            w[F_IN_WINDOW] += prm[R_CYCLE]
        else:
            w[F_IN_WINDOW] = 0.0
        if w[F_IN_WINDOW] >= prm[R_POS_WINDOW_TIME]:
            flags |= SW_TARGET_REACHED
    if abs(w[F_FOLLOWING_ERROR]) > prm[R_FE_WINDOW]:
        flags |= SW_FOLLOWING_ERROR
    return flags


@njit(cache=True, error_model="numpy", inline="always")
def _speed_limited(prm, wi, v):
    """EmulatedDrive._speed_limited: ``v`` inside 6080h (bit 11 when it was not)."""
    limit = prm[R_MAX_SPEED]
    if abs(v) > limit:
        wi[J_LIMITED] = SW_INTERNAL_LIMIT_ACTIVE
        return math.copysign(limit, v)
    return v


@njit(cache=True, error_model="numpy", inline="always")
def _speed_loop(prm, w, wi, w_set, w_act, i_ff):
    """DriveLoops.current: SpeedLoop.step on speed cycles, held in between; A."""
    if wi[J_TICK] % wi[J_SPEED_RATIO] != 0:
        return w[F_IQ]
    e = _biquad(prm, R_SET_B0, w, F_SET_Z1, w_set) - w_act
    d_part = prm[R_KD_T] * (e - w[F_E_PREV])
    mode = prm[R_ANTIWINDUP]
    outer = d_part + i_ff * prm[R_KT] if mode == AW_TORQUE_SETPOINT else 0.0
    u = prm[R_KP] * e + w[F_INTEG]  # PI.step_within
    total = u + outer
    limit = prm[R_PI_LIMIT]
    if mode >= AW_CLAMP:  # ClampPI.step, WindupPI.step
        integ = w[F_INTEG] + prm[R_KI_T] * e
        w[F_INTEG] = _py_max(-limit, _py_min(limit, integ)) if mode == AW_CLAMP else integ
        u = _py_max(-limit, _py_min(limit, u))
    elif total > limit:
        if e < 0.0:
            w[F_INTEG] += prm[R_KI_T] * e
        u = _py_min(u, limit)
    elif total < -limit:
        if e > 0.0:
            w[F_INTEG] += prm[R_KI_T] * e
        u = _py_max(u, -limit)
    else:
        w[F_INTEG] += prm[R_KI_T] * e
    w[F_E_PREV] = e
    c = _biquad(prm, R_CUR_B0, w, F_CUR_Z1, (u + d_part) * prm[R_INV_KT] + i_ff)
    i = _biquad(prm, R_NOTCH_B0, w, F_NOTCH_Z1, c)
    w[F_IQ] = _py_max(-prm[R_I_MAX], _py_min(prm[R_I_MAX], i))
    return w[F_IQ]


@njit(cache=True, error_model="numpy", inline="always")
def _current(prm, w, wi, spf, mode, target, w_cmd, theta, w_act):
    """EmulatedDrive._current in OPERATION ENABLED, before the current limit: the
    q-current setpoint, A (voltage mode: the q-current field as the Python path passes it
    on, unused by the plant)."""
    if mode == MODE_CST or mode == MODE_VOLTAGE:
        return spf[S_IQ]
    if target == target:
        held = target != w[F_DEMAND]  # at a software limit: no speed feed-forward
        if held:
            wi[J_LIMITED] = SW_INTERNAL_LIMIT_ACTIVE
        if wi[J_TICK] % wi[J_POSITION_RATIO] == 0:  # PositionLoop.step
            w[F_SYM_Y] = target + (w[F_SYM_Y] - target) * prm[R_SYM_A]
            w[F_POS_ERROR] = w[F_SYM_Y] - theta
            v = prm[R_KV] * w[F_POS_ERROR] + prm[R_FF] * (0.0 if held else w_cmd)
            w[F_W_CMD] = _py_max(-prm[R_V_LIM], _py_min(prm[R_V_LIM], v))
        return _speed_loop(prm, w, wi, _speed_limited(prm, wi, w[F_W_CMD]), w_act, spf[S_IQ])
    v = _speed_limited(prm, wi, w_cmd)
    if (v > 0.0 and theta >= prm[R_LIMIT_MAX]) or (v < 0.0 and theta <= prm[R_LIMIT_MIN]):
        v = 0.0  # at a software limit: no further out
        wi[J_LIMITED] = SW_INTERNAL_LIMIT_ACTIVE
    return _speed_loop(prm, w, wi, v, w_act, spf[S_IQ])


@njit(cache=True, error_model="numpy", inline="always")
def _step_plant(p, s, inp, out, saved, n_sub, iq, i_d, voltage, ud, uq, enable, brake):
    """The plant's PWM period on the q- and d-current setpoints ``iq``, ``i_d`` (A), or
    with ``voltage`` on the d- and q-voltages ``ud``, ``uq`` (V), the pulses on or off
    (``enable`` 1.0 or 0.0) and the holding brake's input ``brake``; a status not OK is
    undone from ``saved`` (the arrays as they were), and returned."""
    n_s, n_i = s.size, inp.size
    for k in range(n_s):
        saved[k] = s[k]
    for k in range(n_i):
        saved[n_s + k] = inp[k]
    for k in range(out.size):
        saved[n_s + n_i + k] = out[k]
    inp[L.I_ENABLE] = enable
    inp[L.I_BRAKE] = brake
    inp[L.I_MODE] = L.INPUT_VOLTAGE if voltage else L.INPUT_CURRENT
    inp[L.I_IQ_REF] = iq
    inp[L.I_ID_REF] = i_d
    inp[L.I_UD] = ud
    inp[L.I_UQ] = uq
    status = axis_step_nb(p, s, inp, out, n_sub)
    if status != L.STATUS_OK:
        for k in range(n_s):
            s[k] = saved[k]
        for k in range(n_i):
            inp[k] = saved[n_s + k]
        for k in range(out.size):
            out[k] = saved[n_s + n_i + k]
    return status


@njit(cache=True, error_model="numpy", inline="always")
def _write_row(ring_f, ring_i, j, spf, out, spi, statusword, state, enable):
    """The axis's recording row in column ``j`` of its ring planes (``state``: the CiA 402
    state, ``enable``: 1 with the power stage on)."""
    for k in range(N_SPF):
        ring_f[k, j] = spf[k]
    for k in range(out.size):
        ring_f[N_SPF + k, j] = out[k]
    ring_i[0, j] = spi[I_CW]
    ring_i[1, j] = spi[I_MODE]
    ring_i[2, j] = statusword
    ring_i[3, j] = 0  # 603Fh: no fault is latched in steady state
    ring_i[4, j] = state
    ring_i[5, j] = enable


@njit(cache=True, error_model="numpy", inline="always")
def _idle_cycle(prm, fst, ist, spf, spi, p, s, inp, out, saved, fbf, ring_f, ring_i, w, wi,
                theta, w_act):
    """A drive cycle with the power stage off, in SWITCH ON DISABLED, READY TO SWITCH ON
    or SWITCHED ON under a controlword that takes no transition there (see
    :func:`steady_cycle`): EmulatedDrive._cycle's path when not operating -- the speed
    actual value, the monitor's I²t, overspeed and limit-switch flags, the statusword,
    the holding brake, the plant's PWM period with the pulses off, the feedback.  The
    modes' hold and the loops' reset, which change nothing but their own state on inputs
    this cycle leaves in ``fst``, are :meth:`hil.drive.compiled_path.CompiledPath.leave`'s
    to replay.  ``w``, ``wi``: the working copies, ``theta``, ``w_act``: the position and
    speed actual values, as :func:`steady_cycle` began the cycle."""
    # Monitor.check, not operating: overcurrent and overspeed are latched even so
    _, hot = _i2t(prm, w, wi, out)
    if hot or abs(w_act) > prm[R_OVERSPEED]:
        return EXIT_CAUSE
    flags = SW_WARNING if w[F_I2T] >= prm[R_I2T_WARNING] else 0
    neg, pos = out[L.O_LIMIT_NEG], out[L.O_LIMIT_POS]
    w[F_SWITCH_NEG], w[F_SWITCH_POS] = neg, pos
    if neg > 0.0 or pos > 0.0:
        flags |= SW_INTERNAL_LIMIT_ACTIVE
    wi[J_MONITOR_FLAGS] = flags
    # DriveStateMachine.update without a transition; EmulatedDrive._flags out of
    # OPERATION ENABLED: the monitor's flags (no limit met: the power stage is off)
    wi[J_STATUSWORD] = wi[J_BASE_STATUSWORD] | (flags & SW_CALLER_BITS)
    w[F_IDLE_THETA], w[F_IDLE_W] = theta, w_act
    w[F_IDLE_POS], w[F_IDLE_VOFF] = spf[S_POS], spf[S_VOFF]
    # HoldingBrake.update with the pulses off
    w[F_BRAKE_OFF] += prm[R_CYCLE]
    brake = 1.0 if prm[R_BRAKE_PRESENT] != 0.0 and w[F_BRAKE_OFF] >= prm[R_BRAKE_CLOSING] \
        else 0.0
    return _end_cycle(prm, fst, ist, spf, spi, p, s, inp, out, saved, fbf, ring_f, ring_i,
                      0.0, 0.0, False, 0.0, 0.0, 0.0, brake, ist[J_STATE])


@njit(cache=True, error_model="numpy", inline="always")
def _end_cycle(prm, fst, ist, spf, spi, p, s, inp, out, saved, fbf, ring_f, ring_i, iq, i_d,
               voltage, ud, uq, enable, brake, state):
    """Both cycles' end: the plant's PWM period (:func:`_step_plant`), the working copy
    made the state, the feedback's floats, the recording row (``state``: the CiA 402
    state, the power stage on with ``enable`` 1.0); :data:`DONE`, or EXIT_PLANT with the
    plant's step undone and the state as it was."""
    w, wi = fst[N_FST:], ist[N_IST:]
    if _step_plant(p, s, inp, out, saved, wi[J_N_SUB], iq, i_d, voltage, ud, uq, enable,
                   brake) != L.STATUS_OK:
        return EXIT_PLANT
    w[F_LAST_GOOD_X] = out[L.O_TABLE_POS]
    wi[J_TICK] += 1
    _copy(w, fst, N_FST)
    _copy(wi, ist, N_IST)
    fbf[B_TIME] = out[L.O_TIME]
    fbf[B_ENCODER] = out[L.O_ENCODER] + prm[R_SHIFT]
    fbf[B_SCALE] = out[L.O_SCALE]
    fbf[B_VELOCITY] = w[F_VELOCITY]
    fbf[B_IQ] = out[L.O_IQ_MEAS]
    fbf[B_ID] = out[L.O_ID_MEAS]
    if ist[J_ROW] >= 0:
        _write_row(ring_f, ring_i, ist[J_ROW], spf, out, spi, ist[J_STATUSWORD], state,
                   1 if enable else 0)
    return DONE


@njit(cache=True, error_model="numpy", _nrt=False)
def steady_cycle(prm, fst, ist, spf, spi, p, s, inp, out, saved, fbf, ring_f, ring_i):
    """One drive cycle in steady state (see the module docstring); returns :data:`DONE` or
    an ``EXIT_*`` code with nothing changed (the ring's row included).  ``p``, ``s``,
    ``inp``, ``out``: the plant's arrays (:mod:`plant.layout`); ``saved``: float64 scratch
    of at least ``len(s) + len(inp) + len(out)``, for undoing a failed plant step.  The
    cycle works on the second halves of ``fst`` and ``ist`` (a copy of the first) and
    copies them back once it is done."""
    mode = spi[I_MODE]
    if mode != ist[J_MODE] or spi[I_CW] != ist[J_CONTROLWORD]:
        return EXIT_COMMAND
    if _refused(prm, spf, mode):
        return EXIT_REFUSED
    w, wi = fst[N_FST:], ist[N_IST:]
    _copy(fst, w, N_FST)
    _copy(ist, wi, N_IST)
    counts = out[L.O_ENCODER]
    _speed_actual(prm, w, wi, counts)
    theta = counts * prm[R_RPC]
    w_act = w[F_VELOCITY] * prm[R_RPC]
    if ist[J_IDLE]:
        return _idle_cycle(prm, fst, ist, spf, spi, p, s, inp, out, saved, fbf, ring_f,
                           ring_i, w, wi, theta, w_act)
    target, w_cmd = _command(prm, w, wi, spf, spi, theta)
    voltage = mode == MODE_VOLTAGE
    flags = _monitor(prm, w, wi, out, target, theta, w_act, voltage)
    if flags < 0:
        return EXIT_CAUSE
    # EmulatedDrive._flags (in CSP, CSV and CST the mode's bits 10 and 13 are the
    # monitor's, bit 12 is set, in voltage mode not; bit 11 of the last cycle's limits)
    # and DriveStateMachine.update without a transition (the controlword is enable
    # operation, no fault is latched)
    word = flags | (0 if voltage else SW_FOLLOWS_COMMAND) | wi[J_LIMITED]
    wi[J_MONITOR_FLAGS] = flags
    wi[J_STATUSWORD] = SW_OPERATION_ENABLED_BASE | (word & SW_CALLER_BITS)
    wi[J_LIMITED] = 0
    iq = _current(prm, w, wi, spf, mode, target, w_cmd, theta, w_act)
    if iq != iq or abs(iq) == math.inf:
        return EXIT_LOOP
    limit = prm[R_MAX_CURRENT]
    if abs(iq) > limit:
        wi[J_LIMITED] = SW_INTERNAL_LIMIT_ACTIVE
        iq = math.copysign(limit, iq)
    i_d = 0.0 if voltage else _py_min(_py_max(spf[S_ID], -limit), limit)
    ud, uq = (spf[S_UD], spf[S_UQ]) if voltage else (0.0, 0.0)
    # the holding brake opens with the pulses (HoldingBrake.update)
    w[F_BRAKE_OFF] = 0.0
    return _end_cycle(prm, fst, ist, spf, spi, p, s, inp, out, saved, fbf, ring_f, ring_i,
                      iq, i_d, voltage, ud, uq, 1.0, 0.0, State.OPERATION_ENABLED)
