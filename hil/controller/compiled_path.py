"""The compiled steady-state path of the NC's axis: when it is taken, and the controller's
state packed into the arrays of :mod:`hil.controller.compiled` and back.

The Python objects of :class:`~hil.controller.nc.Controller` (its loops, filters, fine
interpolator, monitor, delay and enable sequence) own the axis's state.  On the first
tick of a steady state (:meth:`CompiledAxis.run`: the drive enabled, no alarm's stop
reaction, position control, valid feedback) their state is copied into flat arrays, and
from then on each tick is one call of :func:`hil.controller.compiled.nc_cycle`.  The
first tick it declines copies the state back (:meth:`CompiledAxis.leave`) and the Python
path runs that tick from the same state, so the Python path stays the only one that
raises alarms, stops, clamps or changes mode.  Every tick the compiled path runs writes
the controller's signals (:data:`hil.controller.compiled.SIGNALS`, ``tick_count``) back
into its attributes; its deeper state (loops, filters, monitor, interpolator) stays in
the arrays: a reader of it from outside the tick calls
:meth:`~hil.controller.nc.Controller.settle` first, and every method that changes what
the controller does (a program, a test mode, a stop, a RESET) settles it itself.
"""

import math

import numpy as np

from hil.controller import compiled as C
from hil.controller.blocks import PI, PT1, Biquad, ClampPI, WindupPI
from hil.controller.loops import PositionLoop, SpeedLoop
from hil.controller.stop import Phase
from hil.drive.compiled import ANTIWINDUP_CODES
from io_adapters.messages import MODE_CST, MODE_VOLTAGE

#: no trace feed-forward (``ffa``)
_NO_FEED_FORWARD = np.zeros(1)
#: the IPO points of a controller without a fine interpolator
_NO_POINTS = np.zeros((3, 1))
#: the speed PI's classes the compiled tick computes (by ``speed_antiwindup``)
_SPEED_PIS = {"conditional": PI, "torque_setpoint": PI, "clamp": ClampPI, "none": WindupPI}


def _standard(ctrl) -> bool:
    """The controller's loops are the classes the compiled tick computes (a caller may
    replace one, as a validation experiment replaces the speed PI; then every tick is the
    Python path's)."""
    pos, speed = ctrl.pos_loop, ctrl.speed_loop
    return (type(pos) is PositionLoop and type(pos.sym) is PT1 and type(speed) is SpeedLoop
            and type(speed.pi) is _SPEED_PIS[speed.antiwindup]
            and all(type(f) is Biquad for f in (speed.set_filter, speed.cur_filter,
                                                  speed.notch)))


def _pack_position(prm, c, fst, s, loop) -> None:
    """A PositionLoop's coefficients at ``prm[c:]`` and state at ``fst[s:]``."""
    prm[c:c + C.POS_SIZE] = loop.kv, loop.ff, loop.sym.a, loop.v_lim
    fst[s + C.PS_SYM_Y], fst[s + C.PS_ERROR] = loop.sym.y, loop.error


def _pack_speed(prm, c, fst, s, loop) -> None:
    """A SpeedLoop's coefficients at ``prm[c:]`` and state at ``fst[s:]``."""
    pi = loop.pi
    prm[c:c + C.SP_SET] = (loop.kd_t, pi.kp, pi.ki_t, pi.limit, loop.inv_kt, loop.i_max,
                           loop.kt, ANTIWINDUP_CODES[loop.antiwindup])
    fst[s + C.SS_INTEG], fst[s + C.SS_E_PREV] = pi.integ, loop.e_prev
    for cb, sb, f in ((C.SP_SET, C.SS_SET, loop.set_filter), (C.SP_CUR, C.SS_CUR, loop.cur_filter),
                      (C.SP_NOTCH, C.SS_NOTCH, loop.notch)):
        prm[c + cb:c + cb + 5] = f.b0, f.b1, f.b2, f.a1, f.a2
        fst[s + sb], fst[s + sb + 1] = f.z1, f.z2


def _leave_position(f: list, s: int, loop) -> None:
    loop.sym.y, loop.error = f[s + C.PS_SYM_Y], f[s + C.PS_ERROR]


def _leave_speed(f: list, s: int, loop) -> None:
    loop.pi.integ, loop.e_prev = f[s + C.SS_INTEG], f[s + C.SS_E_PREV]
    for sb, filt in ((C.SS_SET, loop.set_filter), (C.SS_CUR, loop.cur_filter),
                     (C.SS_NOTCH, loop.notch)):
        filt.z1, filt.z2 = f[s + sb], f[s + sb + 1]


class CompiledAxis:
    """The compiled path of the controller ``ctrl`` (see the module docstring).

    Attributes:
        active: the arrays hold the controller's state.
        cycles: ticks run compiled since the controller was built.
        exits: how often each status of :mod:`hil.controller.compiled` handed a tick back
            to Python (status -> count).
        prm, fst, ist, pts, ffa, ring: the arrays of :func:`~hil.controller.compiled.
            nc_cycle` (``pts`` and ``ffa`` those of the program the path was entered with).
    """

    def __init__(self, ctrl):
        self.ctrl = ctrl
        self.prm = np.zeros(C.N_PRM)
        self.fst = np.zeros(2 * C.N_FST + C.N_FIO)
        self.ist = np.zeros(2 * C.N_IST + C.N_IPM + C.N_IIO, dtype=np.int64)
        self.pts = _NO_POINTS
        self.ffa = _NO_FEED_FORWARD
        self.ring = np.zeros(max(1, len(ctrl.iq_delay.ring)))
        self.active = False
        self.cycles = 0
        self.exits: dict[int, int] = {}

    def steady(self) -> bool:
        """The controller is in the state the compiled tick runs (or runs it already)."""
        c = self.ctrl
        return self.active or (c.phase is Phase.RUN and c.mode == "position" and c.feedback_ok
                               and c.enabled and _standard(c))

    def enter(self) -> bool:
        """Pack the state if the controller is in its steady state; whether it is."""
        if not self.active:
            if not self.steady():
                return False
            self._pack()
            self.active = True
        return True

    def run(self, fb, sp) -> bool:
        """Run this tick compiled if the controller is in its steady state; False: the
        Python path must run it (the state is back in the controller's objects)."""
        if not self.enter():
            return False
        fst, ist = self.fst, self.ist
        fst[C.FIO:C.FIO + C.X_IQ_REF] = (fb.encoder_counts, fb.scale_counts,
                                         fb.velocity_counts_s, fb.iq_a, fb.id_a)
        ist[C.IIO + C.Y_STATUSWORD] = fb.statusword
        status = C.nc_cycle(self.prm, fst, ist, self.pts, self.ffa, self.ring)
        if status:
            self.exits[status] = self.exits.get(status, 0) + 1
            self.leave()
            return False
        self.cycles += 1
        self.write_signals()
        sp.seq = (sp.seq + 1) & 0xFFFFFFFF
        self.write_setpoint(sp)
        return True

    def write_signals(self) -> None:
        """The signals of the last tick into the controller's attributes."""
        c = self.ctrl
        (c.t, c.x_set, c.v_set, c.a_set, c.x_act, c.theta_act, c.v_act, c.v_cmd, c.w_set,
         c.w_act, c.iq_set, c.following_error, c.contour_deviation, c.i_ff, c.id_meas,
         c.iq_meas) = self.fst[:len(C.SIGNALS)].tolist()
        c.tick_count = int(self.ist[C.J_TICK])

    def write_setpoint(self, sp) -> None:
        """The last tick's setpoint into ``sp`` (its seq aside), as the Python tick writes
        it."""
        sp.controlword = C.CONTROLWORD
        fio = self.fst[C.FIO:].tolist()
        if self.ist[C.IPM + C.M_VOLTAGE]:
            sp.mode = MODE_VOLTAGE
            sp.ud_v, sp.uq_v = fio[C.X_UD], fio[C.X_UQ]
        else:
            sp.mode = MODE_CST
            sp.iq_ref_a, sp.id_ref_a = fio[C.X_IQ_REF], fio[C.X_ID_REF]

    def _pack(self) -> None:
        c = self.ctrl
        sec, mon, model, fine = c.sec, c.monitor, c.monitor.model, c.fine
        lim = mon.limits
        prm = self.prm
        prm[[C.R_RPC, C.R_PERIOD, C.R_SPEED_DT, C.R_RATIO, C.R_SCALE_RES, C.R_POLARITY]] = (
            c.rad_per_count, c.period, c.period * sec.speed_cycle_ratio, c.ratio, c.scale_res,
            c.polarity)
        prm[[C.R_FILTER_A, C.R_I_FF_GAIN, C.R_NEXT_CLAMP_S]] = (
            c.speed_filter.a, c.i_ff_gain, c.clamps[0].t_s if c.clamps else math.inf)
        prm[[C.R_CONTOUR_TOL, C.R_CLAMP_TOL, C.R_STANDSTILL_TOL]] = (
            lim.contour_tol, lim.clamp_tol, lim.standstill_tol)
        prm[[C.R_MODEL_DT, C.R_ACCEL_PER_AMP, C.R_MODEL_RATIO]] = (
            model.speed_period, model.accel_per_amp, model.ratio)
        fst = self.fst
        fst[:len(C.SIGNALS)] = [getattr(c, name) for name in C.SIGNALS]
        theta_prev = math.nan if c.theta_prev is None else c.theta_prev
        fst[[C.F_THETA_PREV, C.F_FILTER_Y]] = theta_prev, c.speed_filter.y
        fst[[C.F_DEVIATION, C.F_X_SET_PREV, C.F_CLAMP_POSITION]] = (
            mon.deviation, mon._x_set_prev, mon.clamp_position)
        fst[[C.F_MODEL_THETA, C.F_MODEL_W, C.F_MODEL_W_CMD, C.F_MODEL_I_FF,
             C.F_MODEL_THETA_PREV]] = (model.theta, model.w, model.w_cmd, model.i_ff,
                                       model.theta_prev)
        cur = c.cur_loop
        if cur is not None:
            prm[[C.R_U_MAX, C.R_POLES, C.R_PSI, C.R_LD, C.R_LQ]] = (
                cur.u_max, cur.poles, cur.psi, cur.ld, cur.lq)
            prm[C.R_D_KP:C.R_D_KP + 3] = cur.d.kp, cur.d.ki_t, cur.d.limit
            prm[C.R_Q_KP:C.R_Q_KP + 3] = cur.q.kp, cur.q.ki_t, cur.q.limit
            fst[[C.F_D_INTEG, C.F_Q_INTEG]] = cur.d.integ, cur.q.integ
        _pack_position(prm, C.R_POS, fst, C.F_POS, c.pos_loop)
        _pack_position(prm, C.R_MODEL_POS, fst, C.F_MODEL_POS, model.pos)
        _pack_speed(prm, C.R_SPEED, fst, C.F_SPEED, c.speed_loop)
        _pack_speed(prm, C.R_MODEL_SPEED, fst, C.F_MODEL_SPEED, model.speed)
        ist = self.ist
        ist[[C.J_TICK, C.J_FINE_CYCLES, C.J_DELAY_HEAD, C.J_STILL, C.J_ENABLE_CYCLES,
             C.J_MONITOR_ACTIVE, C.J_CLAMPED]] = (
            c.tick_count, c._fine_cycles, c.iq_delay.head, mon._still_cycles,
            c.enable.cycles, int(mon.active), int(mon.clamped))
        m = C.IPM
        ist[[m + C.M_N_SPEED, m + C.M_N_POS, m + C.M_N_DELAY, m + C.M_FF_LINEAR,
             m + C.M_FILTER, m + C.M_MONITORED, m + C.M_VOLTAGE, m + C.M_STILL_DELAY]] = (
            sec.speed_cycle_ratio, sec.position_cycle_ratio, len(c.iq_delay.ring),
            int(bool(c.ff_linear)), int(c.filter_speed), int(c.monitored), int(cur is not None),
            mon.delay_cycles)
        if fine is None:
            self.pts = _NO_POINTS
            ist[[m + C.M_FINE, m + C.M_FINE_RATIO]] = 0, 1
        else:
            self.pts = fine.points
            fst[[C.F_FINE_POS, C.F_FINE_VEL, C.F_FINE_ACC]] = fine.pos, fine.vel, fine.acc
            ist[[C.J_FINE_K, C.J_FINE_M, C.J_FINE_DONE]] = fine._k, fine._m, int(fine.done)
            ist[[m + C.M_FINE, m + C.M_FINE_RATIO]] = 1, fine._ratio
        trace = c.trace_feed_forward()
        self.ffa = _NO_FEED_FORWARD if trace is None else trace
        ist[m + C.M_TRACE_FF] = int(trace is not None)
        self.ring[:len(c.iq_delay.ring)] = c.iq_delay.ring

    def leave(self) -> None:
        """Copy the state back into the controller's objects (nothing when not active)."""
        if not self.active:
            return
        self.active = False
        c = self.ctrl
        mon, model, fine = c.monitor, c.monitor.model, c.fine
        f = self.fst.tolist()
        i = self.ist.tolist()
        c.theta_prev = None if math.isnan(f[C.F_THETA_PREV]) else f[C.F_THETA_PREV]
        c.speed_filter.y = f[C.F_FILTER_Y]
        mon.deviation, mon._x_set_prev = f[C.F_DEVIATION], f[C.F_X_SET_PREV]
        mon.clamp_position = f[C.F_CLAMP_POSITION]
        mon.active, mon.clamped = bool(i[C.J_MONITOR_ACTIVE]), bool(i[C.J_CLAMPED])
        mon._still_cycles = i[C.J_STILL]
        (model.theta, model.w, model.w_cmd, model.i_ff, model.theta_prev) = (
            f[C.F_MODEL_THETA], f[C.F_MODEL_W], f[C.F_MODEL_W_CMD], f[C.F_MODEL_I_FF],
            f[C.F_MODEL_THETA_PREV])
        if c.cur_loop is not None:
            c.cur_loop.d.integ, c.cur_loop.q.integ = f[C.F_D_INTEG], f[C.F_Q_INTEG]
        _leave_position(f, C.F_POS, c.pos_loop)
        _leave_position(f, C.F_MODEL_POS, model.pos)
        _leave_speed(f, C.F_SPEED, c.speed_loop)
        _leave_speed(f, C.F_MODEL_SPEED, model.speed)
        c._fine_cycles = i[C.J_FINE_CYCLES]
        c.iq_delay.head = i[C.J_DELAY_HEAD]
        c.enable.cycles = i[C.J_ENABLE_CYCLES]
        n = len(c.iq_delay.ring)
        c.iq_delay.ring[:] = self.ring[:n].tolist()
        if fine is not None:
            fine.pos, fine.vel, fine.acc = f[C.F_FINE_POS], f[C.F_FINE_VEL], f[C.F_FINE_ACC]
            fine._k, fine._m, fine.done = i[C.J_FINE_K], i[C.J_FINE_M], bool(i[C.J_FINE_DONE])


def warm() -> None:
    """Compile, or load from numba's cache, the compiled tick's kernel now, before a
    real-time loop starts (its first call does it: a stall of a tenth of a second to
    seconds in the loop otherwise): one call that declines at once (no drive enabled)."""
    C.nc_cycle(np.zeros(C.N_PRM), np.zeros(2 * C.N_FST + C.N_FIO),
               np.zeros(2 * C.N_IST + C.N_IPM + C.N_IIO, dtype=np.int64), _NO_POINTS,
               _NO_FEED_FORWARD, np.zeros(1))
