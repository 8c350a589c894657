"""The compiled steady-state path of one drive: when it is taken, and the drive's state
packed into the arrays of :mod:`hil.drive.compiled` and back.

The Python objects of :class:`~hil.drive.core.EmulatedDrive` (its monitor, modes,
interpolator, loops and state machine) own the drive's state.  On the first cycle of a
steady state (:meth:`CompiledPath.run`: OPERATION ENABLED in CSP, CSV, CST or voltage
mode with the drive's loops, the controlword and mode those of the cycle before, no link
cause, no latched fault, no braking) their state is copied into flat arrays, and from then on
each cycle is one call of :func:`hil.drive.compiled.steady_cycle`.  The first cycle it
declines (or a link cause, a latched fault, a parameter written) copies the state back
(:meth:`CompiledPath.leave`) and the Python path runs that cycle from the same state, so
the Python path stays the only one that changes state, faults or reacts.  While the
arrays hold the state, the objects' values are those of the cycle the path was entered
at: a reader of the drive's internals from outside the cycle calls
:meth:`~hil.drive.core.EmulatedDrive.settle` first (:class:`hil.drive.objects.DriveObjects`
does).
"""

import numpy as np

from hil.cia402 import EnableSequencer, State, base_statusword
from hil.drive import compiled as C
from hil.drive.faults import OVERSPEED_FACTOR
from hil.drive.monitor import I2T_COOLED, I2T_WARNING, PEAK_TIME_S, PEAK_TRIP_FACTOR
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    MODE_CSV,
    MODE_VOLTAGE,
    Setpoint,
    axis_records,
    message_pair,
)

#: the modes the compiled path runs
CYCLIC = frozenset((MODE_CSP, MODE_CSV, MODE_CST, MODE_VOLTAGE))
#: cycles of :func:`warm`: the drives enabled, holding, and on the compiled path long
#: enough that every kernel of both paths has run
WARM_CYCLES = 2000
#: controlword bits 7, 3, 2, 1, 0 of enable operation (hil.cia402.ENABLE_OPERATION): the
#: only command under which OPERATION ENABLED takes no transition
_ENABLE_MASK, _ENABLE_VALUE = 0x008F, 0x000F
#: the states whose cycle runs compiled with the power stage off (the power-off cycle)
IDLE_STATES = frozenset((State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON,
                         State.SWITCHED_ON))


class CompiledPath:
    """The compiled path of ``drive`` (see the module docstring).

    Attributes:
        active: the arrays hold the drive's state.
        idle: ... of a power-off steady state (:data:`IDLE_STATES`).
        cycles: cycles run compiled since the drive was built; idle_cycles: of those,
            power-off cycles.
        exits: how often each ``EXIT_*`` code of :mod:`hil.drive.compiled` handed a cycle
            back to Python (index: the code).
        row_written: the last cycle wrote the tick's recording row (:meth:`set_row`).
    """

    def __init__(self, drive):
        self.drive = drive
        plant = drive.plant
        self.prm = np.zeros(C.N_PRM)
        self.fst = np.zeros(2 * C.N_FST)  # the state, then the cycle's working copy
        self.ist = np.zeros(2 * C.N_IST, dtype=np.int64)
        self.spf = np.zeros(C.N_SPF)
        self.spi = np.zeros(3, dtype=np.int64)
        self.fbf = np.zeros(C.N_FBF)
        self.ring_f = np.zeros((1, 1))
        self.ring_i = np.zeros((1, 1), dtype=np.int64)
        self.ist[C.J_ROW] = -1
        self.row_written = False
        self.saved = np.zeros(plant.state.size + plant.inp.size + plant.out.size)
        self.active = self.idle = False
        self.cycles = self.idle_cycles = 0
        self.exits = [0] * (C.EXIT_PLANT + 1)
        self._generation = -1

    def bind_ring(self, ring_f: np.ndarray, ring_i: np.ndarray) -> None:
        """Write each compiled cycle's recording row into these planes of the ring (this
        axis's ``floats`` and ``ints``, :class:`~hil.runtime.recording.Recorder`), at the
        column :meth:`set_row` gives."""
        self.ring_f, self.ring_i = ring_f, ring_i

    def set_row(self, j: int) -> None:
        """This tick's row is column ``j`` of the ring (-1: not recorded);
        :attr:`row_written` says, after the tick, whether the last cycle wrote it."""
        self.ist[C.J_ROW] = j
        self.row_written = False

    def run(self, sp, fb) -> bool:
        """Run this cycle compiled if the drive is in its steady state; False: the Python
        path must run it (the state is back in the drive's objects)."""
        d = self.drive
        if self.active:
            # a link cause acts on a drive whose power stage may be on (6007h), not on one
            # with the pulses off
            if ((d.link_causes and not self.idle) or d.faults.latched
                    or d.params.generation != self._generation):
                self.row_written = False
                self.leave()
                return False
        elif not self._enter(sp):
            self.row_written = False
            return False
        spi = self.spi
        spi[C.I_SEQ] = sp.seq
        spi[C.I_CW] = sp.controlword
        spi[C.I_MODE] = sp.mode
        spf = self.spf
        spf[C.S_IQ] = sp.iq_ref_a
        spf[C.S_ID] = sp.id_ref_a
        spf[C.S_UD] = sp.ud_v
        spf[C.S_UQ] = sp.uq_v
        spf[C.S_POS] = sp.target_position_counts
        spf[C.S_VEL] = sp.target_velocity_counts_s
        spf[C.S_VOFF] = sp.velocity_offset_counts_s
        plant = d.plant
        status = C.steady_cycle(self.prm, self.fst, self.ist, spf, spi, plant.params,
                                plant.state, plant.inp, plant.out, self.saved, self.fbf,
                                self.ring_f, self.ring_i)
        if status:
            self.exits[status] += 1
            self.row_written = False
            self.leave()
            return False
        self.row_written = True
        self.cycles += 1
        self.idle_cycles += self.idle
        d.tick += 1
        fb.seq = sp.seq
        fb.statusword = int(self.ist[C.J_STATUSWORD])
        (fb.time_s, fb.encoder_counts, fb.scale_counts, fb.velocity_counts_s, fb.iq_a,
         fb.id_a) = self.fbf.tolist()
        fb.fault = d.fault
        return True

    def _enter(self, sp) -> bool:
        """Pack the state if this cycle starts a steady state: OPERATION ENABLED, or with
        the power stage off one of :data:`IDLE_STATES` under a controlword that takes no
        transition there."""
        d = self.drive
        cw = sp.controlword
        if (d.faults.latched or d.brake.active or d._override >= 0 or d._link_handled
                or sp.mode not in CYCLIC or cw != d._previous_cw):
            return False
        state = d.sm.state
        if state in IDLE_STATES:
            if d._limited or cw != d.sm._previous_controlword or not d.sm.stays(cw):
                return False
            self._pack_drive(sp)
            self._pack_idle(state)
            self.active = self.idle = True
            return True
        if (d.loops is None or state != State.OPERATION_ENABLED or d.link_causes
                or sp.mode != d.modes._mode or cw & _ENABLE_MASK != _ENABLE_VALUE):
            return False
        self._pack_drive(sp)
        self._pack_loops()
        self.active = True
        return True

    def _pack_drive(self, sp) -> None:
        """What both steady states run on: the drive's, the monitor's and the holding
        brake's parameters and state."""
        d = self.drive
        p, m, modes = d.params, d.monitor, d.modes
        trip = p.i2t_trip_a2s
        bounds = d._bounds
        prm = self.prm
        prm[[C.R_RPC, C.R_SPEED_PERIOD, C.R_CYCLE]] = (d.rad_per_count, d.speed_period,
                                                       d.plant.pwm_period)
        prm[[C.R_LIMIT_MIN, C.R_LIMIT_MAX, C.R_MAX_SPEED, C.R_MAX_CURRENT]] = (
            p.limit_min, p.limit_max, p.max_speed, p.max_current_a)
        prm[[C.R_FE_WINDOW, C.R_FE_TIME, C.R_POS_WINDOW, C.R_POS_WINDOW_TIME]] = (
            p.fe_window, p.fe_time_s, p.position_window, p.position_window_time_s)
        # each product as the Python path forms it
        prm[[C.R_I2T_TRIP, C.R_I2T_COOLED, C.R_I2T_WARNING, C.R_CONTINUOUS2]] = (
            trip, I2T_COOLED * trip, I2T_WARNING * trip, p.continuous_current_a ** 2)
        prm[[C.R_OVERSPEED, C.R_STANDSTILL, C.R_INTERP_PERIOD, C.R_SHIFT, C.R_TWO]] = (
            OVERSPEED_FACTOR * p.max_speed, m.standstill(), p.interpolation_period_s,
            modes.shift_counts, 2.0)
        prm[[C.R_B_POSITION, C.R_B_VELOCITY, C.R_B_CURRENT, C.R_B_VOLTAGE]] = (
            bounds.position_counts, bounds.velocity_counts_s, bounds.current_a,
            bounds.voltage_v)
        brake = d.holding_brake
        prm[[C.R_MAX_CURRENT2, C.R_PEAK_TRIP2, C.R_PEAK_TIME, C.R_VOLTAGE_OK,
             C.R_BRAKE_PRESENT, C.R_BRAKE_CLOSING]] = (
            p.max_current_a ** 2, (PEAK_TRIP_FACTOR * p.max_current_a) ** 2, PEAK_TIME_S,
            float(MODE_VOLTAGE in bounds.modes), float(brake.present), brake.closing_time_s)
        self._generation = p.generation
        fst = self.fst
        fst[[C.F_COUNTS_PREV, C.F_VELOCITY, C.F_LAST_GOOD_X, C.F_BRAKE_OFF]] = (
            d.counts_prev, d.velocity_counts_s, d._last_good_x, brake._off_s)
        fst[[C.F_I2T, C.F_FE_TIME, C.F_IN_WINDOW, C.F_SWITCH_NEG, C.F_SWITCH_POS,
             C.F_FOLLOWING_ERROR]] = (m.i2t_a2s, m._fe_time_s, m._in_window_s, *m._switches,
                                      m.following_error)
        fst[[C.F_DEMAND, C.F_SPEED, C.F_PEAK_TIME]] = modes.demand, modes.speed, m._peak_s
        ist = self.ist
        ist[[C.J_TICK, C.J_LIMITED, C.J_HOT, C.J_MONITOR_FLAGS, C.J_STATUSWORD]] = (
            d.tick, d._limited, int(m._hot), m.flags, d.sm.statusword)
        ist[[C.J_SPEED_RATIO, C.J_N_SUB]] = d.speed_ratio, d.plant.sub_per_pwm
        ist[[C.J_MODE, C.J_CONTROLWORD, C.J_IDLE]] = sp.mode, sp.controlword, 0

    def _pack_idle(self, state: State) -> None:
        """The power-off cycle's state: the CiA 402 state, none of its cycles run yet."""
        self.fst[C.F_IDLE_THETA] = np.nan
        self.ist[[C.J_IDLE, C.J_STATE, C.J_BASE_STATUSWORD]] = (1, state,
                                                                base_statusword(state))

    def _pack_loops(self) -> None:
        """OPERATION ENABLED's: the modes' interpolator and the loops."""
        d = self.drive
        it, lp = d.modes.interp, d.loops
        pos, spd = lp.pos, lp.speed
        prm = self.prm
        prm[[C.R_KV, C.R_FF, C.R_SYM_A, C.R_V_LIM]] = pos.kv, pos.ff, pos.sym.a, pos.v_lim
        prm[[C.R_KD_T, C.R_KP, C.R_KI_T, C.R_PI_LIMIT, C.R_INV_KT, C.R_I_MAX, C.R_KT,
             C.R_ANTIWINDUP]] = (spd.kd_t, spd.pi.kp, spd.pi.ki_t, spd.pi.limit,
                                 spd.inv_kt, spd.i_max, spd.kt,
                                 C.ANTIWINDUP_CODES[spd.antiwindup])
        for base, f in ((C.R_SET_B0, spd.set_filter), (C.R_CUR_B0, spd.cur_filter),
                        (C.R_NOTCH_B0, spd.notch)):
            prm[base:base + 5] = f.b0, f.b1, f.b2, f.a1, f.a2
        fst = self.fst
        fst[[C.F_START_A, C.F_START_B, C.F_END_A, C.F_END_B]] = (*it._start, *it._end)
        fst[[C.F_SYM_Y, C.F_POS_ERROR, C.F_W_CMD, C.F_IQ]] = (pos.sym.y, pos.error, lp.w_cmd,
                                                               lp.iq)
        fst[[C.F_INTEG, C.F_E_PREV]] = spd.pi.integ, spd.e_prev
        fst[[C.F_SET_Z1, C.F_SET_Z2, C.F_CUR_Z1, C.F_CUR_Z2, C.F_NOTCH_Z1, C.F_NOTCH_Z2]] = (
            spd.set_filter.z1, spd.set_filter.z2, spd.cur_filter.z1, spd.cur_filter.z2,
            spd.notch.z1, spd.notch.z2)
        ist = self.ist
        ist[[C.J_INTERP_SEQ, C.J_CYCLES, C.J_LENGTH]] = it.seq, it._cycles, it._length
        ist[C.J_POSITION_RATIO] = lp.position_ratio

    def leave(self) -> None:
        """Copy the state back into the drive's objects (nothing when not active)."""
        if not self.active:
            return
        self.active = False
        d = self.drive
        m = d.monitor
        f = self.fst.tolist()
        i = self.ist.tolist()
        d.counts_prev, d.velocity_counts_s = f[C.F_COUNTS_PREV], f[C.F_VELOCITY]
        d._last_good_x = f[C.F_LAST_GOOD_X]
        d.tick, d._limited = i[C.J_TICK], i[C.J_LIMITED]
        d.holding_brake._off_s = f[C.F_BRAKE_OFF]
        m.i2t_a2s, m._hot, m.flags = f[C.F_I2T], bool(i[C.J_HOT]), i[C.J_MONITOR_FLAGS]
        m._switches = (f[C.F_SWITCH_NEG], f[C.F_SWITCH_POS])
        d.sm._statusword = i[C.J_STATUSWORD]
        if self.idle:
            self.idle = False
            m.reset()
            theta = f[C.F_IDLE_THETA]
            if theta == theta:  # a power-off cycle ran: the last one's hold and reset
                last = Setpoint(controlword=i[C.J_CONTROLWORD], mode=i[C.J_MODE],
                                target_position_counts=f[C.F_IDLE_POS],
                                velocity_offset_counts_s=f[C.F_IDLE_VOFF])
                d.modes.hold(last, theta, f[C.F_IDLE_W])
                if d.loops is not None:
                    d.loops.reset(theta)
            return
        modes, it, lp = d.modes, d.modes.interp, d.loops
        pos, spd = lp.pos, lp.speed
        m._fe_time_s, m._in_window_s = f[C.F_FE_TIME], f[C.F_IN_WINDOW]
        m._peak_s = f[C.F_PEAK_TIME]
        m.following_error = f[C.F_FOLLOWING_ERROR]
        modes.demand, modes.speed = f[C.F_DEMAND], f[C.F_SPEED]
        it.seq, it._cycles, it._length = i[C.J_INTERP_SEQ], i[C.J_CYCLES], i[C.J_LENGTH]
        it._start = (f[C.F_START_A], f[C.F_START_B])
        it._end = (f[C.F_END_A], f[C.F_END_B])
        pos.sym.y, pos.error = f[C.F_SYM_Y], f[C.F_POS_ERROR]
        lp.w_cmd, lp.iq = f[C.F_W_CMD], f[C.F_IQ]
        spd.pi.integ, spd.e_prev = f[C.F_INTEG], f[C.F_E_PREV]
        spd.set_filter.z1, spd.set_filter.z2 = f[C.F_SET_Z1], f[C.F_SET_Z2]
        spd.cur_filter.z1, spd.cur_filter.z2 = f[C.F_CUR_Z1], f[C.F_CUR_Z2]
        spd.notch.z1, spd.notch.z2 = f[C.F_NOTCH_Z1], f[C.F_NOTCH_Z2]


def warm(drives, cycles: int = WARM_CYCLES, stop=lambda: False) -> int:
    """Run ``drives`` (a :class:`~hil.drive.core.DriveSet` of compiled drives) enabled as a
    controller enables them, then holding their position in CSP (CST on a drive without
    loops), for ``cycles`` cycles or until ``stop()``: every kernel of the Python and the
    compiled path is compiled, or loaded from numba's cache, by then.  Returns the cycles
    run; the drives and their plants have moved and are to be built afresh."""
    sp, fb = message_pair(len(drives.drives))
    enable = EnableSequencer(timeout_cycles=cycles)
    enable.enable()
    n = 0
    while n < cycles and not stop():
        sp.controlword = enable.next_controlword(axis_records(fb)[0].statusword)
        for s, f, d in zip(axis_records(sp), axis_records(fb), drives.drives):
            s.mode = MODE_CSP if d.loops is not None else MODE_CST
            s.target_position_counts = f.encoder_counts
        drives.cycle(sp, fb)
        n += 1
    return n
