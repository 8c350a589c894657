"""The NC's cycle in steady state, compiled: one numba call from the feedback to the
setpoint.

In position control with the drive enabled, no alarm and no test mode, a tick of
:class:`hil.controller.nc.Controller` is arithmetic on some hundred numbers: the feedback
checked and measured (the speed every speed cycle through ``speed_actual_filter_s``), the
drive's state watched, the enable sequence holding, the feed-forward finely interpolated
between position cycles (``feedforward_interpolation = "linear"``) or a trace's given at
every speed cycle, every position cycle the fine interpolator, the axis monitoring
(contour model, standstill and clamping checks) and the position loop, every speed cycle
the speed loop (its filters, ``speed_antiwindup``, D part) and the contour model's, the
current setpoint delayed by ``current_delay_cycles``, with ``plant_input = "voltage"``
the current loop, and the loop state checked finite.  :func:`nc_cycle` does exactly that on flat arrays, in the same
floating-point order as the Python path (no fused multiply-add; Python's ``max`` and
``min`` with their order of NaN and signed zeros), so both give the same bits.

It computes the tick on a working copy of its state (:func:`nc_compute`) and commits it
at the end (:func:`nc_commit`).  The moment anything falls outside the steady state -- a
non-finite feedback value, the drive out of OPERATION ENABLED, a clamp block reached, a
monitoring limit exceeded, a non-finite loop state -- it returns a non-zero code
*before* it has changed any state, and the Python path runs that tick: it stays the one
owner of the alarms, their stop reaction and everything rare.  A monitoring limit's
code is its alarm's number (:data:`MONITORING`): the monitoring raises a status, never an
exception.  :mod:`hil.controller.compiled_path` packs the controller's state into these
arrays and back.

Array layouts (module constants, compile-time indices):

* ``prm`` float64[:data:`N_PRM`]: parameters and loop coefficients (``R_*``; the loops'
  as blocks: a position loop ``POS_*`` at :data:`R_POS` and the contour model's at
  :data:`R_MODEL_POS`, a speed loop ``SP_*`` at :data:`R_SPEED` and
  :data:`R_MODEL_SPEED`), SI units;
* ``fst`` float64[2 * :data:`N_FST` + :data:`N_FIO`]: the float state (``F_*``; the
  signals first, in :data:`SIGNALS` order), its working copy, then the tick's inputs and
  outputs (``X_*``: the feedback's values, the setpoint's currents and voltages);
* ``ist`` int64[2 * :data:`N_IST` + :data:`N_IPM` + :data:`N_IIO`]: the integer state
  (``J_*``), its working copy, the integer parameters (``M_*``), the statusword read and
  the mode sent (``Y_*``);
* ``pts`` float64[3, n]: the fine interpolator's IPO points (position, velocity,
  acceleration);
* ``ffa`` float64[m]: a trace-fed controller's speed feed-forward of every speed cycle
  from the first position cycle of its points (:mod:`hil.identify.trace_controller`;
  unused with ``M_TRACE_FF`` 0);
* ``ring`` float64[max(1, d)]: the current setpoints in the computation delay (d =
  ``current_delay_cycles``), the oldest at ``ist[J_DELAY_HEAD]``.
"""

import math

from numba import njit

from hil.cia402 import ENABLE_OPERATION, STATUS_PATTERNS, State
from hil.controller.alarms import AlarmNumber
from hil.drive.compiled import (
    AW_CLAMP,
    AW_CONDITIONAL,
    AW_TORQUE_SETPOINT,
    _biquad,
    _copy,
    _py_max,
    _py_min,
)
from io_adapters.messages import MODE_CST, MODE_VOLTAGE

#: the tick ran compiled
DONE = 0
#: a feedback value is not finite (the Python path raises alarm 25000)
EXIT_FEEDBACK = 1
#: the drive is not in OPERATION ENABLED (alarm 25201)
EXIT_DRIVE = 2
#: a clamp or unclamp block is reached (the Python path clamps or unclamps)
EXIT_CLAMP = 3
#: the trace's feed-forward ends before the speed cycle (the Python path's IndexError)
EXIT_FEED_FORWARD = 4
#: a loop state or output is not finite (alarm 1000)
EXIT_NONFINITE = 5
#: the monitoring's statuses: the number of the alarm a limit exceeded raises
MONITORING = (int(AlarmNumber.CONTOUR), int(AlarmNumber.STANDSTILL),
              int(AlarmNumber.CLAMPING))
CONTOUR, STANDSTILL, CLAMPING = MONITORING
#: the statusword pattern of OPERATION ENABLED, and the controlword that holds it
_OE_MASK = STATUS_PATTERNS[State.OPERATION_ENABLED].mask
_OE_VALUE = STATUS_PATTERNS[State.OPERATION_ENABLED].value
CONTROLWORD = ENABLE_OPERATION.value

#: a position loop's coefficients (relative to its block): K_v (1/s), feed-forward weight,
#: symmetrising PT1 factor, speed-command limit
POS_KV, POS_FF, POS_SYM_A, POS_V_LIM, POS_SIZE = range(5)
#: a speed loop's coefficients: K_d/T, K_p, K_i T, the PI's limit, 1/K_t, I_max, K_t, the
#: anti-windup (:data:`hil.drive.compiled.ANTIWINDUP_CODES`), the setpoint filter's, the
#: current filter's and the notch's (b0, b1, b2, a1, a2) each
(SP_KD_T, SP_KP, SP_KI_T, SP_LIMIT, SP_INV_KT, SP_I_MAX, SP_KT, SP_ANTIWINDUP) = range(8)
SP_SET, SP_CUR, SP_NOTCH, SP_SIZE = 8, 13, 18, 23
#: a position loop's state: the symmetrising PT1's output, the error
PS_SYM_Y, PS_ERROR, PS_SIZE = range(3)
#: a speed loop's state: the integrator, the last error, the three filters' delay lines
SS_INTEG, SS_E_PREV, SS_SET, SS_CUR, SS_NOTCH, SS_SIZE = 0, 1, 2, 4, 6, 8

#: ``prm``: motor units per encoder count, the basic clock (s), the speed cycle (s), table
#: units per motor unit, m per scale count (0: the motor encoder), the feedback's sign,
#: the actual-speed PT1 factor, the current feed-forward's gain (A per table unit/s²),
#: the next clamp block's time (s, inf: none), the contour, clamping and standstill
#: tolerances (table units), the contour model's speed cycle (s), acceleration per ampere
#: and table units per motor unit, the current loop's voltage limit (V), pole pairs (or
#: pi / pole pitch), flux (V s), L_d and L_q (H), its d and q PI's K_p, K_i T and limit;
#: then the loops' blocks
(R_RPC, R_PERIOD, R_SPEED_DT, R_RATIO, R_SCALE_RES, R_POLARITY, R_FILTER_A, R_I_FF_GAIN,
 R_NEXT_CLAMP_S, R_CONTOUR_TOL, R_CLAMP_TOL, R_STANDSTILL_TOL, R_MODEL_DT,
 R_ACCEL_PER_AMP, R_MODEL_RATIO, R_U_MAX, R_POLES, R_PSI, R_LD, R_LQ,
 R_D_KP, R_D_KI_T, R_D_LIMIT, R_Q_KP, R_Q_KI_T, R_Q_LIMIT, R_POS) = range(27)
R_MODEL_POS = R_POS + POS_SIZE
R_SPEED = R_MODEL_POS + POS_SIZE
R_MODEL_SPEED = R_SPEED + SP_SIZE
N_PRM = R_MODEL_SPEED + SP_SIZE

#: the controller's signals, the first floats of ``fst`` in this order (its attributes)
SIGNALS = ("t", "x_set", "v_set", "a_set", "x_act", "theta_act", "v_act", "v_cmd", "w_set",
           "w_act", "iq_set", "following_error", "contour_deviation", "i_ff", "id_meas",
           "iq_meas")
(F_T, F_X_SET, F_V_SET, F_A_SET, F_X_ACT, F_THETA_ACT, F_V_ACT, F_V_CMD, F_W_SET, F_W_ACT,
 F_IQ_SET, F_FOLLOWING_ERROR, F_CONTOUR_DEVIATION, F_I_FF, F_ID_MEAS, F_IQ_MEAS) = range(16)
#: ``fst`` beyond the signals: the last speed cycle's motor position (NaN: none), the
#: actual-speed PT1's output, the monitor's deviation, last setpoint and clamp position,
#: the fine interpolator's setpoint, the contour model's motor position, speed, speed
#: command, current feed-forward and last position, the current loop's two integrators;
#: then the loops' states
(F_THETA_PREV, F_FILTER_Y, F_DEVIATION, F_X_SET_PREV, F_CLAMP_POSITION, F_FINE_POS,
 F_FINE_VEL, F_FINE_ACC, F_MODEL_THETA, F_MODEL_W, F_MODEL_W_CMD, F_MODEL_I_FF,
 F_MODEL_THETA_PREV, F_D_INTEG, F_Q_INTEG, F_POS) = range(16, 32)
F_MODEL_POS = F_POS + PS_SIZE
F_SPEED = F_MODEL_POS + PS_SIZE
F_MODEL_SPEED = F_SPEED + SS_SIZE
N_FST = F_MODEL_SPEED + SS_SIZE
#: ``fst[2 N_FST:]``: the feedback's encoder and scale counts, speed (counts/s), q and d
#: currents (A); the setpoint's q and d currents (A), d and q voltages (V)
X_ENCODER, X_SCALE, X_VELOCITY, X_IQ, X_ID, X_IQ_REF, X_ID_REF, X_UD, X_UQ, N_FIO = range(10)

#: ``ist``: the tick, the fine interpolator's position cycles, IPO point, step within it
#: and whether it reached the last point, the delay ring's head, the position cycles the
#: setpoint stood still, the enable sequence's cycles, the monitoring running, the axis
#: clamped
(J_TICK, J_FINE_CYCLES, J_FINE_K, J_FINE_M, J_FINE_DONE, J_DELAY_HEAD, J_STILL,
 J_ENABLE_CYCLES, J_MONITOR_ACTIVE, J_CLAMPED, N_IST) = range(11)
#: ``ist[2 N_IST:]``: the speed and position cycles (ticks), position cycles per IPO
#: cycle, the current delay (ticks), the linear feed-forward interpolation, the
#: actual-speed filter, position control monitored, a fine interpolator (0: the setpoint
#: stands), the current loop (the plant takes voltage), the standstill delay (position
#: cycles), the feed-forward is the trace's (``ffa``)
(M_N_SPEED, M_N_POS, M_FINE_RATIO, M_N_DELAY, M_FF_LINEAR, M_FILTER, M_MONITORED, M_FINE,
 M_VOLTAGE, M_STILL_DELAY, M_TRACE_FF, N_IPM) = range(12)
#: ``ist[2 N_IST + N_IPM:]``: the feedback's statusword, the setpoint's mode
Y_STATUSWORD, Y_MODE, N_IIO = range(3)
#: offsets of the sections of ``fst`` and ``ist``
FIO = 2 * N_FST
IPM = 2 * N_IST
IIO = IPM + N_IPM


@njit(cache=True, error_model="numpy", inline="always")
def _pi(prm, c, w, s, e, outer):
    """PI.step_within: the output for the error ``e``, the integrator ``w[s]`` stopped by
    the limit on output + ``outer``; coefficients K_p, K_i T, limit at ``prm[c:c + 3]``."""
    u = prm[c] * e + w[s]
    total = u + outer
    limit = prm[c + 2]
    if total > limit:
        if e < 0.0:
            w[s] += prm[c + 1] * e
        return _py_min(u, limit)
    if total < -limit:
        if e > 0.0:
            w[s] += prm[c + 1] * e
        return _py_max(u, -limit)
    w[s] += prm[c + 1] * e
    return u


@njit(cache=True, error_model="numpy", inline="always")
def _position_command(prm, c, w, s, v_ff):
    """PositionLoop.command: the speed command of the held P part with ``v_ff``."""
    v = prm[c + POS_KV] * w[s + PS_ERROR] + prm[c + POS_FF] * v_ff
    return _py_max(-prm[c + POS_V_LIM], _py_min(prm[c + POS_V_LIM], v))


@njit(cache=True, error_model="numpy", inline="always")
def _position_step(prm, c, w, s, x_set, v_set, x_act):
    """PositionLoop.step: the symmetrising PT1, the error, the speed command."""
    y = w[s + PS_SYM_Y]
    w[s + PS_SYM_Y] = x_set + (y - x_set) * prm[c + POS_SYM_A]
    w[s + PS_ERROR] = w[s + PS_SYM_Y] - x_act
    return _position_command(prm, c, w, s, v_set)


@njit(cache=True, error_model="numpy", inline="always")
def _speed_step(prm, c, w, s, w_set, w_act, i_ff):
    """SpeedLoop.step (its PI by ``speed_antiwindup``: PI, ClampPI, WindupPI of
    :mod:`hil.controller.blocks`): the q-current setpoint, A."""
    e = _biquad(prm, c + SP_SET, w, s + SS_SET, w_set) - w_act
    d_part = prm[c + SP_KD_T] * (e - w[s + SS_E_PREV])
    mode = prm[c + SP_ANTIWINDUP]
    if mode == AW_TORQUE_SETPOINT:
        torque = _pi(prm, c + SP_KP, w, s + SS_INTEG, e, d_part + i_ff * prm[c + SP_KT]) + d_part
    elif mode == AW_CONDITIONAL:
        torque = _pi(prm, c + SP_KP, w, s + SS_INTEG, e, 0.0) + d_part
    else:
        limit = prm[c + SP_LIMIT]
        u = prm[c + SP_KP] * e + w[s + SS_INTEG]
        integ = w[s + SS_INTEG] + prm[c + SP_KI_T] * e
        w[s + SS_INTEG] = _py_max(-limit, _py_min(limit, integ)) if mode == AW_CLAMP else integ
        torque = _py_max(-limit, _py_min(limit, u)) + d_part
    w[s + SS_E_PREV] = e
    i = _biquad(prm, c + SP_NOTCH, w, s + SS_NOTCH,
                _biquad(prm, c + SP_CUR, w, s + SS_CUR, torque * prm[c + SP_INV_KT] + i_ff))
    return _py_max(-prm[c + SP_I_MAX], _py_min(prm[c + SP_I_MAX], i))


@njit(cache=True, error_model="numpy", inline="always")
def _speed_finite(w, s):
    """SpeedLoop.finite."""
    return (w[s + SS_E_PREV] * 0.0 == 0.0 and w[s + SS_INTEG] * 0.0 == 0.0
            and w[s + SS_SET] * 0.0 + w[s + SS_SET + 1] * 0.0 == 0.0
            and w[s + SS_CUR] * 0.0 + w[s + SS_CUR + 1] * 0.0 == 0.0
            and w[s + SS_NOTCH] * 0.0 + w[s + SS_NOTCH + 1] * 0.0 == 0.0)


@njit(cache=True, error_model="numpy", inline="always")
def _measure(prm, w, wi, m, fio, k):
    """Controller._measure: the actual values of tick ``k``."""
    theta = fio[X_ENCODER] * prm[R_RPC]
    if k % m[M_N_SPEED] == 0:
        previous = w[F_THETA_PREV]
        if not math.isnan(previous):  # a previous sample exists
            w[F_W_ACT] = (theta - previous) / prm[R_SPEED_DT]
        w[F_THETA_PREV] = theta
        if m[M_FILTER]:
            u = w[F_W_ACT]
            w[F_FILTER_Y] = u + (w[F_FILTER_Y] - u) * prm[R_FILTER_A]
            w[F_W_ACT] = w[F_FILTER_Y]
        w[F_V_ACT] = w[F_W_ACT] * prm[R_RATIO]
    w[F_THETA_ACT] = theta
    if prm[R_SCALE_RES] != 0.0:
        x = fio[X_SCALE] * prm[R_SCALE_RES]
    else:
        x = theta * prm[R_RATIO]
    w[F_X_ACT] = prm[R_POLARITY] * x
    w[F_ID_MEAS] = fio[X_ID]
    w[F_IQ_MEAS] = fio[X_IQ]


@njit(cache=True, error_model="numpy", inline="always")
def _next_feed_forward(w, wi, m, pts):
    """The next position cycle's feed-forward (Controller._next_feed_forward)."""
    if not m[M_FINE]:
        return w[F_V_SET]
    k, last = wi[J_FINE_K], pts.shape[1] - 1
    if k >= last:
        return pts[1, last]
    return pts[1, k] + (pts[1, k + 1] - pts[1, k]) * (wi[J_FINE_M] / m[M_FINE_RATIO])


@njit(cache=True, error_model="numpy", inline="always")
def _fine_step(w, wi, m, pts):
    """FineInterpolator.step: this position cycle's setpoint."""
    k, last = wi[J_FINE_K], pts.shape[1] - 1
    if k >= last:
        w[F_FINE_POS], w[F_FINE_VEL], w[F_FINE_ACC] = pts[0, last], pts[1, last], pts[2, last]
        wi[J_FINE_DONE] = 1
        return
    f = wi[J_FINE_M] / m[M_FINE_RATIO]
    w[F_FINE_POS] = pts[0, k] + (pts[0, k + 1] - pts[0, k]) * f
    w[F_FINE_VEL] = pts[1, k] + (pts[1, k + 1] - pts[1, k]) * f
    w[F_FINE_ACC] = pts[2, k] + (pts[2, k + 1] - pts[2, k]) * f
    wi[J_FINE_M] += 1
    if wi[J_FINE_M] == m[M_FINE_RATIO]:
        wi[J_FINE_M] = 0
        wi[J_FINE_K] = k + 1


@njit(cache=True, error_model="numpy", inline="always")
def _monitor_start(prm, w, wi):
    """AxisMonitor.start at the actual position, speed and symmetrised setpoint."""
    w[F_MODEL_THETA] = w[F_MODEL_THETA_PREV] = w[F_X_ACT] / prm[R_MODEL_RATIO]
    w[F_MODEL_W] = w[F_MODEL_W_CMD] = w[F_W_ACT]
    w[F_MODEL_I_FF] = 0.0
    w[F_MODEL_POS + PS_SYM_Y] = w[F_POS + PS_SYM_Y]
    w[F_MODEL_POS + PS_ERROR] = 0.0
    for j in range(SS_SIZE):
        w[F_MODEL_SPEED + j] = 0.0
    wi[J_MONITOR_ACTIVE] = 1
    w[F_DEVIATION] = 0.0
    w[F_X_SET_PREV] = math.nan
    wi[J_STILL] = 0


@njit(cache=True, error_model="numpy", inline="always")
def _monitor_check(prm, w, wi, m):
    """AxisMonitor.check on this position cycle's setpoint: 0, or the status of the limit
    exceeded (:data:`MONITORING`)."""
    x_set, x_act = w[F_X_SET], w[F_X_ACT]
    w[F_DEVIATION] = x_act - w[F_MODEL_THETA] * prm[R_MODEL_RATIO]
    # ContourModel.position_cycle
    v = _position_step(prm, R_MODEL_POS, w, F_MODEL_POS, x_set, w[F_V_SET],
                       w[F_MODEL_THETA] * prm[R_MODEL_RATIO])
    w[F_MODEL_W_CMD] = v / prm[R_MODEL_RATIO]
    w[F_MODEL_I_FF] = w[F_I_FF]
    if x_set == w[F_X_SET_PREV]:
        wi[J_STILL] += 1
    else:
        wi[J_STILL] = 0
    w[F_X_SET_PREV] = x_set
    if abs(w[F_DEVIATION]) > prm[R_CONTOUR_TOL]:
        return CONTOUR
    if wi[J_CLAMPED]:
        if abs(x_act - w[F_CLAMP_POSITION]) > prm[R_CLAMP_TOL]:
            return CLAMPING
    elif wi[J_STILL] >= m[M_STILL_DELAY] and abs(x_set - x_act) > prm[R_STANDSTILL_TOL]:
        return STANDSTILL
    return DONE


@njit(cache=True, error_model="numpy", inline="always")
def _model_speed_cycle(prm, w):
    """ContourModel.speed_cycle: the model's speed loop, then its rigid axis."""
    dt = prm[R_MODEL_DT]
    w_measured = (w[F_MODEL_THETA] - w[F_MODEL_THETA_PREV]) / dt
    w[F_MODEL_THETA_PREV] = w[F_MODEL_THETA]
    accel = prm[R_ACCEL_PER_AMP] * _speed_step(prm, R_MODEL_SPEED, w, F_MODEL_SPEED,
                                               w[F_MODEL_W_CMD], w_measured,
                                               w[F_MODEL_I_FF])
    w[F_MODEL_THETA] += dt * (w[F_MODEL_W] + 0.5 * accel * dt)
    w[F_MODEL_W] += accel * dt


@njit(cache=True, error_model="numpy", inline="always")
def _position_cycle(prm, w, wi, m, pts):
    """Controller._position_cycle in position control: 0, or a status to decline with."""
    if m[M_MONITORED] and not wi[J_MONITOR_ACTIVE]:
        _monitor_start(prm, w, wi)
    if m[M_FINE]:
        # Controller._clamp_events: the clamp blocks are the Python path's
        t_fine = wi[J_FINE_CYCLES] * prm[R_PERIOD] * m[M_N_POS]
        if prm[R_NEXT_CLAMP_S] <= t_fine:
            return EXIT_CLAMP
        wi[J_FINE_CYCLES] += 1
        _fine_step(w, wi, m, pts)
        w[F_X_SET], w[F_V_SET], w[F_A_SET] = w[F_FINE_POS], w[F_FINE_VEL], w[F_FINE_ACC]
    w[F_FOLLOWING_ERROR] = w[F_X_SET] - w[F_X_ACT]
    w[F_I_FF] = prm[R_I_FF_GAIN] * w[F_A_SET]
    if wi[J_MONITOR_ACTIVE]:
        status = _monitor_check(prm, w, wi, m)
        w[F_CONTOUR_DEVIATION] = w[F_DEVIATION]
        if status != DONE:
            return status
    w[F_V_CMD] = _position_step(prm, R_POS, w, F_POS, w[F_X_SET], w[F_V_SET], w[F_X_ACT])
    w[F_W_SET] = w[F_V_CMD] / prm[R_RATIO]
    return DONE


@njit(cache=True, error_model="numpy", inline="always")
def _current_loop(prm, w, iq_ref):
    """CurrentLoop.step(0, iq_ref, ...) on the measured currents and speed: (u_d, u_q), V."""
    we = prm[R_POLES] * w[F_W_ACT]
    iq_act, id_act = w[F_IQ_MEAS], w[F_ID_MEAS]
    u_max = prm[R_U_MAX]
    ud = _py_max(-u_max, _py_min(u_max, _pi(prm, R_D_KP, w, F_D_INTEG, 0.0 - id_act, 0.0)
                                 - we * prm[R_LQ] * iq_act))
    uq_max = math.sqrt(_py_max(u_max * u_max - ud * ud, 0.0))
    uq = (_pi(prm, R_Q_KP, w, F_Q_INTEG, iq_ref - iq_act, 0.0)
          + we * (prm[R_PSI] + prm[R_LD] * id_act))
    return ud, _py_max(-uq_max, _py_min(uq_max, uq))


@njit(cache=True, error_model="numpy", inline="always")
def _finite(w, ud, uq):
    """Controller._state_finite on the working copy."""
    return (w[F_POS + PS_ERROR] * 0.0 == 0.0 and w[F_POS + PS_SYM_Y] * 0.0 == 0.0
            and _speed_finite(w, F_SPEED)
            and (w[F_MODEL_THETA] * 0.0 + w[F_MODEL_W] * 0.0 + w[F_MODEL_W_CMD] * 0.0) == 0.0
            and w[F_MODEL_POS + PS_ERROR] * 0.0 == 0.0
            and w[F_MODEL_POS + PS_SYM_Y] * 0.0 == 0.0 and _speed_finite(w, F_MODEL_SPEED)
            and w[F_D_INTEG] * 0.0 == 0.0 and w[F_Q_INTEG] * 0.0 == 0.0
            and (w[F_IQ_SET] * 0.0 + w[F_W_SET] * 0.0 + w[F_V_CMD] * 0.0 + ud * 0.0
                 + uq * 0.0) == 0.0)


@njit(cache=True, error_model="numpy", _nrt=False)
def nc_compute(prm, fst, ist, pts, ffa, ring):
    """One tick of the NC in steady state (see the module docstring) on the working copy of
    the state, the setpoint written into ``fst[FIO + X_IQ_REF:]`` and ``ist[IIO +
    Y_MODE]``; returns :data:`DONE` (then :func:`nc_commit` makes it the state) or a status
    with the state unchanged."""
    fio = fst[FIO:]
    if (fio[X_ENCODER] * 0.0 + fio[X_SCALE] * 0.0 + fio[X_VELOCITY] * 0.0 + fio[X_IQ] * 0.0
            + fio[X_ID] * 0.0) != 0.0:
        return EXIT_FEEDBACK
    if ist[IIO + Y_STATUSWORD] & _OE_MASK != _OE_VALUE:
        return EXIT_DRIVE
    w, wi, m = fst[N_FST:FIO], ist[N_IST:IPM], ist[IPM:IIO]
    _copy(fst, w, N_FST)
    _copy(ist, wi, N_IST)
    k = wi[J_TICK]
    wi[J_TICK] = k + 1
    _measure(prm, w, wi, m, fio, k)
    wi[J_ENABLE_CYCLES] += 1
    n_pos, n_speed = m[M_N_POS], m[M_N_SPEED]
    if m[M_FF_LINEAR] and not m[M_TRACE_FF] and k % n_pos and k % n_speed == 0:
        # Controller._interpolate_feed_forward: the P part held, the feed-forward on the
        # line towards the next position cycle's
        v_next = _next_feed_forward(w, wi, m, pts)
        v_ff = w[F_V_SET] + (v_next - w[F_V_SET]) * ((k % n_pos) / n_pos)
        w[F_V_CMD] = _position_command(prm, R_POS, w, F_POS, v_ff)
        w[F_W_SET] = w[F_V_CMD] / prm[R_RATIO]
    if k % n_pos == 0:
        status = _position_cycle(prm, w, wi, m, pts)
        if status != DONE:
            return status
    if k % n_speed == 0:
        if m[M_TRACE_FF]:
            # Controller._given_feed_forward: the trace's feed-forward of this speed cycle
            j = (wi[J_FINE_CYCLES] - 1) * (n_pos // n_speed) + (k % n_pos) // n_speed
            if j >= ffa.size:
                return EXIT_FEED_FORWARD
            if j >= 0:
                w[F_V_CMD] = _position_command(prm, R_POS, w, F_POS, ffa[j])
                w[F_W_SET] = w[F_V_CMD] / prm[R_RATIO]
        w[F_IQ_SET] = _speed_step(prm, R_SPEED, w, F_SPEED, w[F_W_SET], w[F_W_ACT], w[F_I_FF])
        if wi[J_MONITOR_ACTIVE]:
            _model_speed_cycle(prm, w)
    iq_ref = ring[wi[J_DELAY_HEAD]] if m[M_N_DELAY] else w[F_IQ_SET]
    ud = uq = 0.0
    if m[M_VOLTAGE]:
        ud, uq = _current_loop(prm, w, iq_ref)
    if not _finite(w, ud, uq):
        return EXIT_NONFINITE
    if m[M_VOLTAGE]:
        ist[IIO + Y_MODE] = MODE_VOLTAGE
        fio[X_UD], fio[X_UQ] = ud, uq
    else:
        ist[IIO + Y_MODE] = MODE_CST
        fio[X_IQ_REF], fio[X_ID_REF] = iq_ref, 0.0
    w[F_T] += prm[R_PERIOD]
    return DONE


@njit(cache=True, error_model="numpy", _nrt=False)
def nc_commit(fst, ist, ring):
    """Make the working copy of a tick :func:`nc_compute` ran the state: the current
    setpoint into the delay ring (Delay.step), the copies back."""
    n = ist[IPM + M_N_DELAY]
    if n:
        head = ist[N_IST + J_DELAY_HEAD]
        ring[head] = fst[N_FST + F_IQ_SET]
        ist[N_IST + J_DELAY_HEAD] = (head + 1) % n
    _copy(fst[N_FST:FIO], fst, N_FST)
    _copy(ist[N_IST:IPM], ist, N_IST)


@njit(cache=True, error_model="numpy", _nrt=False)
def nc_cycle(prm, fst, ist, pts, ffa, ring):
    """:func:`nc_compute`, then :func:`nc_commit` when it ran: one tick; returns
    :data:`DONE` or the status it declined with (nothing changed)."""
    status = nc_compute(prm, fst, ist, pts, ffa, ring)
    if status == DONE:
        nc_commit(fst, ist, ring)
    return status
