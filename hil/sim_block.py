"""The lock-step's steady state compiled end to end: the NC's tick, the drives' cycles and
the plants' PWM periods of every axis, for a block of ticks, in one numba call.

A tick of :class:`hil.sim.LockStep` or :class:`~hil.sim.MachineLockStep` whose NC and
drives are all on their compiled paths (:mod:`hil.controller.compiled_path`,
:mod:`hil.drive.compiled_path`) is their two compiled cycles back to back, with the
setpoint and the feedback passed between them as the Python objects would pass them.
:func:`run_block` runs such ticks one after the other, recording each axis's signals,
until the block's ticks are run, the recording is full, an injection is due, or a cycle
declines; then :class:`Blocks` brings the Python objects (the controllers' signals, the
setpoint and feedback records, the drives' tick counters) to where the per-tick path
would have left them, and the per-tick path runs the tick that declined.  So every tick
is either the compiled cycles' or the Python path's, and the results are the same bits.

The order within a tick is :meth:`hil.sim._Stepper.tick`'s: the NC of every axis (read
the last feedback, write the setpoint), then every drive in axis order.  An NC that
declines leaves the tick untouched (it is run whole in Python); a drive that declines
does so after the NC's tick and the drives before it have run: the per-tick path runs
the drives from that one on (:meth:`hil.sim._Stepper.finish_tick`).

Recording: each axis's rows (:data:`COLUMNS`) go into its array of shape
(len(COLUMNS), n): row r is taken after tick ``first + r * every`` (the controller's
tick count before it).
"""

import math

import numpy as np
from numba import njit

from hil.controller import compiled as N
from hil.drive import compiled as D
from plant import layout as L

#: a recording's columns: the lock-step's signals (:data:`hil.sim.SIGNALS` order), then
#: the table's velocity (m/s or rad/s)
COLUMNS = ("t_s", "x_set", "v_set", "a_set", "x_act", "v_act", "v_cmd", "w_set", "w_act",
           "iq_set", "iq_meas", "iq_true", "table_pos", "motor_pos", "motor_pos_meas",
           "following_error", "contour_deviation", "tick", "table_vel")
#: the block ran every tick asked for, or filled the recording
RAN = 0
#: an injection is due before the next tick (the tick is not begun)
EVENT = 1
#: an axis's NC declined the next tick (the tick is not begun)
NC_DECLINED = 2
#: an axis's drive declined its cycle (the NC's tick and the drives before it ran)
DRIVE_DECLINED = 3
#: ``ctl``: the ticks to run at most; the ticks run; the next recording row; the rows;
#: the first tick recorded and the ticks between rows; the setpoint's seq; why the block
#: ended; the axis that declined
(K_TICKS, K_DONE, K_ROW, K_ROWS, K_FIRST, K_EVERY, K_SEQ, K_STOP, K_AXIS, N_CTL) = range(10)
_U32 = 0xFFFFFFFF


@njit(cache=True, error_model="numpy", inline="always")
def _record(rec, row, nfst, nist, dfbf, out):
    """The axis's signals after a tick into column ``row`` of ``rec``."""
    rec[0, row] = nfst[N.F_T]
    rec[1, row] = nfst[N.F_X_SET]
    rec[2, row] = nfst[N.F_V_SET]
    rec[3, row] = nfst[N.F_A_SET]
    rec[4, row] = nfst[N.F_X_ACT]
    rec[5, row] = nfst[N.F_V_ACT]
    rec[6, row] = nfst[N.F_V_CMD]
    rec[7, row] = nfst[N.F_W_SET]
    rec[8, row] = nfst[N.F_W_ACT]
    rec[9, row] = nfst[N.F_IQ_SET]
    rec[10, row] = dfbf[D.B_IQ]
    rec[11, row] = out[L.O_IQ]
    rec[12, row] = out[L.O_TABLE_POS]
    rec[13, row] = out[L.O_MOTOR_POS]
    rec[14, row] = nfst[N.F_THETA_ACT]
    rec[15, row] = nfst[N.F_FOLLOWING_ERROR]
    rec[16, row] = nfst[N.F_CONTOUR_DEVIATION]
    rec[17, row] = nist[N.J_TICK] - 1
    rec[18, row] = out[L.O_TABLE_VEL]


@njit(cache=True, error_model="numpy", _nrt=False, nogil=True)
def run_block(ctl, t_event, nprm, nfst, nist, npts, nffa, nring, dprm, dfst, dist, dspf,
              dspi, dfbf, dsaved, dring_f, dring_i, pp, ps, pinp, pout, rec):
    """Ticks of every axis (see the module docstring) until ``ctl[K_TICKS]`` are run, the
    recording is full, an axis's plant time reaches its ``t_event`` (s; inf: none), or a
    cycle declines; ``ctl`` says how far it got and why it stopped (``K_*``).  Every other
    argument is a tuple with one array per axis: the NC's (``n*``: :func:`hil.controller.
    compiled.nc_cycle`'s), the drive's (``d*``: :func:`hil.drive.compiled.steady_cycle`'s),
    the plant's (``p*``) and the recording (``rec``).  The NCs' feedback inputs and the
    drives' setpoint arrays hold the last tick's messages when it is called."""
    n_axes = len(nprm)
    seq = ctl[K_SEQ]
    row = ctl[K_ROW]
    ctl[K_DONE] = 0
    ctl[K_STOP] = RAN
    while ctl[K_DONE] < ctl[K_TICKS] and row < ctl[K_ROWS]:
        for a in range(n_axes):
            if ps[a][L.S_TIME] >= t_event[a]:
                ctl[K_STOP], ctl[K_AXIS] = EVENT, a
                ctl[K_ROW] = row
                return
        for a in range(n_axes):
            if N.nc_compute(nprm[a], nfst[a], nist[a], npts[a], nffa[a], nring[a]) != N.DONE:
                ctl[K_STOP], ctl[K_AXIS] = NC_DECLINED, a
                ctl[K_ROW] = row
                return
        k = nist[0][N.J_TICK]
        seq = (seq + 1) & _U32
        for a in range(n_axes):
            nio, spf, spi = nfst[a][N.FIO:], dspf[a], dspi[a]
            spi[D.I_SEQ] = seq
            spi[D.I_CW] = N.CONTROLWORD
            spi[D.I_MODE] = nist[a][N.IIO + N.Y_MODE]
            if nist[a][N.IPM + N.M_VOLTAGE]:
                spf[D.S_UD], spf[D.S_UQ] = nio[N.X_UD], nio[N.X_UQ]
            else:
                spf[D.S_IQ], spf[D.S_ID] = nio[N.X_IQ_REF], nio[N.X_ID_REF]
        for a in range(n_axes):
            if D.steady_cycle(dprm[a], dfst[a], dist[a], dspf[a], dspi[a], pp[a], ps[a],
                              pinp[a], pout[a], dsaved[a], dfbf[a], dring_f[a],
                              dring_i[a]) != D.DONE:
                for b in range(n_axes):
                    N.nc_commit(nfst[b], nist[b], nring[b])
                ctl[K_STOP], ctl[K_AXIS] = DRIVE_DECLINED, a
                ctl[K_SEQ] = seq
                ctl[K_DONE] += 1
                ctl[K_ROW] = row
                return
        record = k >= ctl[K_FIRST] and (k - ctl[K_FIRST]) % ctl[K_EVERY] == 0
        for a in range(n_axes):
            N.nc_commit(nfst[a], nist[a], nring[a])
            fbf, nio = dfbf[a], nfst[a][N.FIO:]
            nio[N.X_ENCODER] = fbf[D.B_ENCODER]
            nio[N.X_SCALE] = fbf[D.B_SCALE]
            nio[N.X_VELOCITY] = fbf[D.B_VELOCITY]
            nio[N.X_IQ] = fbf[D.B_IQ]
            nio[N.X_ID] = fbf[D.B_ID]
            nist[a][N.IIO + N.Y_STATUSWORD] = dist[a][D.J_STATUSWORD]
            if record:
                _record(rec[a], row, nfst[a], nist[a], fbf, pout[a])
        if record:
            row += 1
        ctl[K_DONE] += 1
        ctl[K_SEQ] = seq
    ctl[K_ROW] = row


class Blocks:
    """Blocks of compiled ticks for a lock-step runner (:class:`hil.sim._Stepper`: its
    controllers ``ctrls``, ``drive_list``, ``plants``, records ``sps``/``fbs``, messages
    ``sp``/``fb`` and ``injectors``).

    Args:
        stepper: the runner.
        recs: each axis's recording, float64 of shape (len(COLUMNS), rows).
        first, every: the tick of the first row and the ticks between rows.

    Attributes:
        ticks: ticks run whole in blocks.
        stops: how often a block ended for each reason (index ``RAN``, ``EVENT``, ...).
        row: the next row after the last block.
        stop: why the last block ended; ``axis``: the axis that declined.
    """

    def __init__(self, stepper, recs, first: int, every: int):
        self.st = stepper
        self.ctl = np.zeros(N_CTL, dtype=np.int64)
        self.ctl[K_FIRST], self.ctl[K_EVERY] = first, every
        self.t_event = np.full(len(recs), math.inf)
        self.recs = tuple(recs)
        self.ticks = 0
        self.stops = [0] * 4
        self.row, self.stop, self.axis = 0, RAN, -1
        self.ncs = [c.compiled for c in stepper.ctrls]
        self.dps = [d.compiled for d in stepper.drive_list]
        self.usable = (stepper.feedback_delay_ticks == 0 and all(self.ncs) and all(self.dps))

    def ready(self) -> bool:
        """Every axis is on its compiled paths (the NC's entered now if it can be), and no
        injector's ramp or request needs the ticks one by one."""
        if not self.usable:
            return False
        for d in self.dps:
            dr = d.drive
            if (not d.active or dr.link_causes or dr.faults.latched
                    or dr.params.generation != d._generation):
                return False
        if any(inj.ramps or inj.requests for inj in self.st.injectors):
            return False
        return all(nc.enter() for nc in self.ncs)

    def run(self, ticks: int, row: int, rows: int) -> None:
        """Run at most ``ticks`` ticks compiled, recording rows ``row`` to ``rows - 1`` at
        most: :attr:`row`, :attr:`stop` and :attr:`axis` say how far it got (a drive's
        decline leaves the rest of its tick to :meth:`hil.sim._Stepper.finish_tick`)."""
        st, ctl = self.st, self.ctl
        for i, (nc, f) in enumerate(zip(self.ncs, st.fbs)):
            nc.fst[N.FIO:N.FIO + N.X_IQ_REF] = (f.encoder_counts, f.scale_counts,
                                                f.velocity_counts_s, f.iq_a, f.id_a)
            nc.ist[N.IIO + N.Y_STATUSWORD] = f.statusword
            pending = st.injectors[i].pending
            self.t_event[i] = pending[0].at_s if pending else math.inf
        for d, s in zip(self.dps, st.sps):
            d.spf[:] = (s.iq_ref_a, s.id_ref_a, s.ud_v, s.uq_v, s.target_position_counts,
                        s.target_velocity_counts_s, s.velocity_offset_counts_s)
        ctl[K_TICKS], ctl[K_ROW], ctl[K_ROWS], ctl[K_SEQ] = ticks, row, rows, st.sp.seq
        ncs, dps = self.ncs, self.dps
        locks = [d.drive.lock for d in dps]
        for lock in locks:
            lock.acquire()
        try:
            run_block(ctl, self.t_event, *(tuple(getattr(nc, n) for nc in ncs)
                                           for n in ("prm", "fst", "ist", "pts", "ffa", "ring")),
                      *(tuple(getattr(d, n) for d in dps)
                        for n in ("prm", "fst", "ist", "spf", "spi", "fbf", "saved", "ring_f",
                                  "ring_i")),
                      *(tuple(getattr(p, n) for p in st.plants)
                        for n in ("params", "state", "inp", "out")), self.recs)
        finally:
            for lock in locks:
                lock.release()
        done, self.stop = int(ctl[K_DONE]), int(ctl[K_STOP])
        self.row, self.axis = int(ctl[K_ROW]), int(ctl[K_AXIS])
        self.stops[self.stop] += 1
        declined = self.stop == DRIVE_DECLINED
        if done:
            self._sync(done, declined, self.axis)
        self.ticks += done - declined

    def _sync(self, done: int, declined: bool, axis: int) -> None:
        """The Python objects as the per-tick path leaves them after ``done`` ticks (the
        last one up to the drive ``axis`` when ``declined``): the setpoint records as the
        drives' arrays hold the last tick's, the feedback records as the drives wrote it."""
        st = self.st
        seq = int(self.ctl[K_SEQ])
        for nc, d, s in zip(self.ncs, self.dps, st.sps):
            nc.cycles += done
            nc.write_signals()
            s.seq = seq
            s.controlword, s.mode = int(d.spi[D.I_CW]), int(d.spi[D.I_MODE])
            s.iq_ref_a, s.id_ref_a, s.ud_v, s.uq_v = d.spf[:D.S_POS].tolist()
        st.sp.seq = seq
        for i, (d, f) in enumerate(zip(self.dps, st.fbs)):
            ran = done - (declined and i >= axis)
            if not ran:
                continue
            d.cycles += ran
            d.drive.tick += ran
            f.seq = seq
            f.statusword = int(d.ist[D.J_STATUSWORD])
            (f.time_s, f.encoder_counts, f.scale_counts, f.velocity_counts_s, f.iq_a,
             f.id_a) = d.fbf.tolist()
            f.fault = d.drive.fault
            d.drive.reference_inputs(f)
        if not declined and st.fb is not st.fbs[0]:
            st.fb.seq = seq
            st.fb.time_s = st.fbs[0].time_s
