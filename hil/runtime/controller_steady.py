"""``hil controller``'s steady loop in compiled code: many ticks in one call, each from the
deadline's wait to the setpoint's send (issues 29 and 34: the five-axis machine at 8 kHz
needs a controller at compiled speed as much as an emulator).

While the program runs on a UDP link in steady state -- every axis's NC on its compiled
path (:mod:`hil.controller.compiled_path`: position control, the drive enabled, no
alarm), the controller welcomed by its drive, no injection planned -- one call of
:func:`controller_run` runs tick after tick, as
:meth:`hil.runtime.controller_proc.ControllerProcess.step` runs them: it waits for the
deadline (:func:`hil.rt.clock.sleep_until_ns`), reads the feedback queued for the tick
(:func:`io_adapters.udp_steady.receive`; every datagram the drive's, each decoded,
:func:`io_adapters.codec_compiled.decode_feedback`, and in sequence after the one before,
the newest taken, as the endpoint's drain takes it), or, when none came, moves the last
feedback on by one period at each drive's speed actual value, as the Python path bridges a
missing telegram; runs every axis's NC cycle (:func:`hil.controller.compiled.nc_compute`
on all, then :func:`~hil.controller.compiled.nc_commit` on all, so that an axis that
declines leaves every axis as it was); writes the setpoint (the next sequence number, each
axis's controlword, mode and currents or voltages) and sends it
(:func:`io_adapters.codec_compiled.encode_setpoint`, ``sendto``); records the tick's row
into the controller's arrays (``controller.npz``'s columns) and the loop's lateness and
compute time.

It returns to Python (:class:`ControllerSteady`, called by
:func:`hil.rt.loop.run_ticks` as the loop's ``burst``) at the first tick it must decline,
after that tick's wait and with every state as it was (the datagrams handed back to the
endpoint: the Python path reads, judges and runs that tick), after a tick that overran,
after the program's last recorded row, after a send that failed otherwise than for room
or a setpoint the compiled encoder declined (the Python path sends it), at a stop
request, and after :data:`hil.runtime.steady_tick.BURST_S` of ticks.  The Python path
stays the one owner of the alarms, the stop reactions, the enable sequence, the
injections, the program's start and the feedback timeout (the tick that reaches it is
declined).  tests/test_controller_steady.py runs two controllers, one with it, against two
emulators tick by tick and compares every setpoint byte, recorded row and counter.
"""

import numpy as np
from numba import njit

from hil.controller import compiled as NC
from hil.rt.clock import now_ns, sleep_until_ns
from hil.runtime import steady_tick as S
from hil.runtime.controller_files import CTRL_SIGNALS, FLOAT_COLUMNS
from io_adapters import codec_compiled as K
from io_adapters import udp_steady as U
from io_adapters.base import AdapterError
from io_adapters.codec import U32
from io_adapters.messages import MODE_CST, FeedbackGroup, axis_records
from io_adapters.msgpack_endpoint import MAX_DROPOUT
from io_adapters.udp import UdpEndpoint
from io_adapters.udp_steady import (
    L_FRAMES,
    L_LENGTHS,
    L_PEER_FRAME,
    L_PEER_SESSION,
    L_RX_NS,
    SteadyLink,
)

#: ``run``: the call's inputs (first tick, the loop's t0, period, end tick, most ticks,
#: spin, waits (1) or runs one tick now (0), the feedback timeout in ticks, rows to
#: record), the state it carries (silent ticks, rows recorded), then what it did (ticks
#: run, why it returned, the last wake-up, the last tick's end, the declined code, new
#: feedbacks taken)
(N_K, N_T0, N_PERIOD, N_END, N_LIMIT, N_SPIN, N_TIMED, N_TIMEOUT, N_ROWS_END, N_SILENT,
 N_ROWS, N_DONE, N_REASON, N_WAKE, N_END_NS, N_DECLINED, N_NEW, N_RUN) = range(18)
#: why a call returned, beyond :mod:`hil.runtime.steady_tick`'s ENDED, OVERRAN, DECLINED
#: and SEND_FAILED: the last row recorded; the setpoint is the Python encoder's to send
ROWS_DONE, SEND_IN_PYTHON = 5, 6
#: why a tick was declined: beyond steady_tick's receive and frame/sequence codes, the
#: feedback timeout reached, an NC cycle declined
DECLINED_TIMEOUT, DECLINED_NC = -6, -7
#: the setpoint's floats (codec_compiled.SP_FLOAT_FIELDS) the NC writes
_IQ, _ID, _UD, _UQ = (K.SP_FLOAT_FIELDS.index(n) for n in ("iq_ref_a", "id_ref_a", "ud_v",
                                                            "uq_v"))
#: controller.npz's float columns (hil.runtime.controller_files.FLOAT_COLUMNS): the NC's
#: signals, as indices into its state (hil.controller.compiled.SIGNALS), then the
#: feedback's q current, the motor position, the tick, the feedback's time
_SIGNAL_AT = tuple(NC.SIGNALS.index(n) for n in CTRL_SIGNALS)
_C_IQ, _C_MOTOR_POS, _C_TICK, _C_FB_TIME = (FLOAT_COLUMNS.index(n) for n in (
    "iq_meas", "motor_pos", "tick", "fb_time_s"))
#: the feedback's floats (codec_compiled.FB_FLOAT_FIELDS): time, encoder, scale, speed,
#: q and d current
_TIME, _ENC, _SCALE, _VEL, _FIQ, _FID = range(6)


@njit(cache=True, inline="always")
def _check(bufs, n, link, dec_ints, dec_axis_ints, dec_floats):
    """Decode the datagrams ``bufs[:n]``, oldest first, each the drive's and in sequence
    after the one before (the newest left in ``dec_*``); 0 or a DECLINED code."""
    after = link[L_PEER_FRAME]
    for i in range(n):
        if not K.decode_feedback(bufs[i], link[L_LENGTHS + i], dec_ints, dec_axis_ints,
                                 dec_floats):
            return S.DECLINED_FRAME
        if dec_ints[K.F_SESSION] != link[L_PEER_SESSION]:
            return S.DECLINED_SEQUENCE
        ahead = (dec_ints[K.F_FRAME] - after) & U32
        if ahead == 0 or ahead > MAX_DROPOUT:
            return S.DECLINED_SEQUENCE
        after = link[L_FRAMES + i] = dec_ints[K.F_FRAME]
    return 0


@njit(cache=True, nogil=True, _nrt=False)
def controller_run(bufs, link, books, hdr, iov, slots, name_slots, names, ctrl, peer_name,
                   send_name, hello_leads, peek, fb_ints, fb_axis_ints, fb_floats, fbx,
                   dec_ints, dec_axis_ints, dec_floats, ext, sp_ints, sp_axis_ints,
                   sp_floats, out, prms, fsts, ists, ptss, ffas, rings, scale_per_count,
                   rec_floats, rec_ints, rec_nc, lateness, compute, run, stop):
    """Ticks of the controller (module docstring).  ``bufs`` .. ``peek``:
    :class:`~io_adapters.udp_steady.SteadyLink`'s; ``fb_*``: the feedback last taken (its
    time_s per axis in column 0), ``fbx`` float64[2]: the record's own time_s (a group's:
    moved on alone by the bridge) and its arrival (monotonic ns); ``dec_*``: scratch for
    decoding, ``ext`` float64[axes, 6] scratch for the bridged feedback; ``sp_*``,
    ``out``: the setpoint and its bytes; ``prms`` .. ``rings``: each axis's NC arrays
    (:class:`~hil.controller.compiled_path.CompiledAxis`), ``scale_per_count``: scale
    counts per encoder count per axis; ``rec_floats`` float64[rows, axes, 16],
    ``rec_ints`` int64[rows, 7], ``rec_nc`` int64[rows]: the recording
    (``controller.npz``); ``lateness``, ``compute``: the loop's per-deadline arrays;
    ``run``: int64[N_RUN] (``N_*``); ``stop``: int64[1], nonzero: stop before the next
    tick."""
    k0, t0, period, end, limit = run[N_K], run[N_T0], run[N_PERIOD], run[N_END], run[N_LIMIT]
    spin, timed, timeout = run[N_SPIN], run[N_TIMED], run[N_TIMEOUT]
    clock = link[U.L_CLOCK:]
    n_axes = len(prms)
    period_s = period * 1e-9
    done = taken = 0
    reason = S.ENDED
    run[N_DECLINED] = 0
    while done < limit:
        k = k0 + done
        if k >= end or stop[0]:
            break
        deadline = t0 + k * period
        wake = sleep_until_ns(deadline, spin, clock)[0] if timed else now_ns(clock)
        run[N_WAKE] = wake
        n = U.receive(link, bufs, hdr, iov, slots, name_slots, names, ctrl, peer_name,
                      hello_leads, peek, books)
        if n < 0:
            run[N_DECLINED] = S.DECLINED_RECEIVE
            reason = S.DECLINED
            break
        code = _check(bufs, n, link, dec_ints, dec_axis_ints, dec_floats)
        if code == 0 and n == 0 and run[N_SILENT] + 1 >= timeout:
            code = DECLINED_TIMEOUT  # the Python path runs the tick and fails the run
        if code:
            run[N_DECLINED] = code
            reason = S.DECLINED
            break
        # the feedback the NC reads: the newest taken, or the last moved on a period
        for a in range(n_axes):
            for c in range(6):
                ext[a, c] = dec_floats[a, c] if n else fb_floats[a, c]
            if n:
                if a:
                    ext[a, _TIME] = dec_floats[0, _TIME]
            else:
                v = ext[a, _VEL]
                ext[a, _ENC] = ext[a, _ENC] + v * period_s
                ext[a, _SCALE] = ext[a, _SCALE] + v * scale_per_count[a] * period_s
        t_nc = now_ns(clock)
        for a in range(n_axes):
            fio = fsts[a][NC.FIO:]
            fio[NC.X_ENCODER], fio[NC.X_SCALE], fio[NC.X_VELOCITY] = (
                ext[a, _ENC], ext[a, _SCALE], ext[a, _VEL])
            fio[NC.X_IQ], fio[NC.X_ID] = ext[a, _FIQ], ext[a, _FID]
            ists[a][NC.IIO + NC.Y_STATUSWORD] = (dec_axis_ints[a, K.A_STATUSWORD] if n
                                                 else fb_axis_ints[a, K.A_STATUSWORD])
            if NC.nc_compute(prms[a], fsts[a], ists[a], ptss[a], ffas[a], rings[a]):
                code = DECLINED_NC
                break
        if code:
            run[N_DECLINED] = code
            reason = S.DECLINED
            break
        for a in range(n_axes):
            NC.nc_commit(fsts[a], ists[a], rings[a])
        nc_ns = now_ns(clock) - t_nc
        # the feedback taken (or bridged) is now the record's
        if n:
            for c in range(K.N_FB_INTS):
                fb_ints[c] = dec_ints[c]
            fbx[0] = dec_floats[0, _TIME]
            fbx[1] = link[L_RX_NS]
            for a in range(n_axes):
                fb_axis_ints[a, 0], fb_axis_ints[a, 1] = dec_axis_ints[a, 0], dec_axis_ints[a, 1]
                for c in range(6):
                    fb_floats[a, c] = ext[a, c]
            run[N_SILENT] = 0
            taken += 1
        else:
            for a in range(n_axes):
                fb_floats[a, _ENC], fb_floats[a, _SCALE] = ext[a, _ENC], ext[a, _SCALE]
            fbx[0] += period_s
            run[N_SILENT] += 1
        # the setpoint: Controller.tick's and MachineController.tick's
        seq = (sp_ints[K.I_SEQ] + 1) & U32
        sp_ints[K.I_SEQ] = seq
        for a in range(n_axes):
            fio, mode = fsts[a][NC.FIO:], ists[a][NC.IIO + NC.Y_MODE]
            sp_axis_ints[a, K.A_CONTROLWORD], sp_axis_ints[a, K.A_MODE] = NC.CONTROLWORD, mode
            if mode == MODE_CST:
                sp_floats[a, _IQ], sp_floats[a, _ID] = fio[NC.X_IQ_REF], fio[NC.X_ID_REF]
            else:
                sp_floats[a, _UD], sp_floats[a, _UQ] = fio[NC.X_UD], fio[NC.X_UQ]
        sp_ints[K.I_T_NS] = now_ns(clock)
        length = K.encode_setpoint(out, sp_ints, sp_axis_ints, sp_floats)
        if n:
            U.take(link, n, books)
        else:
            U.idle(books)
        sent = U.send(link, out, length, sp_ints, send_name, books) if length > 0 else 0
        # the row (ControllerProcess._record)
        i = run[N_ROWS]
        lag = (seq - 1 - fb_ints[K.F_SEQ]) & U32
        for a in range(n_axes):
            fst = fsts[a]
            row = rec_floats[i, a]
            for c in range(len(_SIGNAL_AT)):
                row[c] = fst[_SIGNAL_AT[c]]
            row[_C_IQ] = fb_floats[a, _FIQ]
            row[_C_MOTOR_POS] = fb_floats[a, _ENC] * prms[a][NC.R_RPC]
            row[_C_TICK] = ists[a][NC.J_TICK] - 1
            row[_C_FB_TIME] = fbx[0]
        r = rec_ints[i]
        r[0], r[1], r[2] = k, 1 if n else 0, lag
        if n:
            rx = fbx[1]
            r[3] = (rx - fb_ints[K.F_SP_T_NS]) - (fb_ints[K.F_T_NS] - fb_ints[K.F_SP_RX_NS])
            r[4], r[5], r[6] = fb_ints[K.F_SP_T_NS], fb_ints[K.F_T_NS], rx
        else:
            r[3] = r[4] = r[5] = r[6] = 0
        rec_nc[i] = nc_ns
        run[N_ROWS] = i + 1
        done += 1
        if sent < 0:
            reason = S.SEND_FAILED
            break
        if length <= 0:
            reason = SEND_IN_PYTHON
            break
        if timed:
            t_end = now_ns(clock)
            lateness[k], compute[k] = wake - deadline, t_end - wake
            run[N_END_NS] = t_end
            if run[N_ROWS] == run[N_ROWS_END]:
                reason = ROWS_DONE
                break
            if t_end > deadline + period:
                reason = S.OVERRAN
                break
        elif run[N_ROWS] == run[N_ROWS_END]:
            reason = ROWS_DONE
            break
    run[N_DONE], run[N_REASON], run[N_NEW] = done, reason, taken


class ControllerSteady:
    """The compiled steady loop of the controller ``proc``
    (:class:`~hil.runtime.controller_proc.ControllerProcess`, its endpoint open); build it
    with :meth:`for_process`, which returns None where it never applies.

    Attributes:
        ticks: ticks run compiled; calls: calls that ran at least one.
        declined: ticks handed to the Python path, by DECLINED code.
    """

    def __init__(self, proc, link: SteadyLink):
        self.proc = proc
        self.link = link
        self.ctrls = proc.mctrl.ctrls
        self.axes = tuple(c.compiled for c in self.ctrls)
        n = len(self.ctrls)
        self.fbx = np.zeros(2)
        self.dec_ints = np.zeros(K.N_FB_INTS, np.int64)
        self.dec_axis_ints = np.zeros((n, 2), np.int64)
        self.dec_floats = np.zeros((n, 6))
        self.ext = np.zeros((n, 6))
        self.scale_per_count = np.array(proc.scale_per_count, dtype=np.float64)
        self.run = np.zeros(N_RUN, np.int64)
        self.run[N_PERIOD] = proc.period_ns
        self.run[N_TIMEOUT] = proc.feedback_timeout
        self.run[N_ROWS_END] = proc.n_run
        self.limit = max(1, round(S.BURST_S * 1e9 / proc.period_ns))
        self.ticks = self.calls = 0
        self.declined: dict[int, int] = {}

    @classmethod
    def for_process(cls, proc) -> "ControllerSteady | None":
        """The compiled loop of a controller that can take one: a UDP endpoint on the
        msgpack wire, feedback of the tick before (no SYNC's delay), every axis's NC
        compiled, a platform whose C structures :mod:`io_adapters.udp_steady` knows;
        else None."""
        ep = proc.ep
        if (not U.AVAILABLE or type(ep) is not UdpEndpoint or ep.wire.name != "msgpack"
                or proc.delay_ticks or proc.lag_is_age
                or any(c.compiled is None for c in proc.mctrl.ctrls)
                or len(proc.mctrl.ctrls) > K.MAX_AXES):
            return None
        return cls(proc, SteadyLink(ep, len(proc.mctrl.ctrls)))

    def _args(self) -> list:
        link, proc, axes = self.link, self.proc, self.axes
        return [link.bufs, link.link, link.books, link.hdr, link.iov, link.slots,
                link.name_slots, link.names, link.ctrl, link.peer_name, link.send_name,
                link.hello_leads, link.peek, link.fb_ints, link.fb_axis_ints, link.fb_floats,
                self.fbx, self.dec_ints, self.dec_axis_ints, self.dec_floats, self.ext,
                link.sp_ints, link.axis_ints, link.sp_floats, link.out,
                tuple(x.prm for x in axes), tuple(x.fst for x in axes),
                tuple(x.ist for x in axes), tuple(x.pts for x in axes),
                tuple(x.ffa for x in axes), tuple(x.ring for x in axes),
                self.scale_per_count, proc.floats, proc.ints, proc.nc_ns,
                proc.loop.lateness_ns, proc.loop.compute_ns, self.run, proc.loop.stop_word]

    def warm(self) -> None:
        """Compile (or load from numba's cache) now, before the loop's clock starts: a
        call asked for no tick runs none and changes nothing."""
        self.run[N_LIMIT] = 0
        controller_run(*self._args())

    def _may_run(self) -> bool:
        """The program runs, no alarm, no injection planned, rows left to record, the link
        ready and every axis's NC on its compiled path."""
        proc = self.proc
        if (not proc.running or proc.mctrl.alarmed or proc.injections.planned
                or proc.rows >= proc.n_run or not self.link.ready()):
            return False
        return all(x.enter() for x in self.axes)

    def burst(self, k: int, t0_ns: int, end: int) -> tuple[int, int | None, int | None]:
        """Ticks from ``k`` on, waited for, as :func:`hil.rt.loop.run_ticks` runs them (see
        :meth:`hil.runtime.steady_tick.SteadyTick.burst` for what it returns)."""
        if not self._may_run():
            return 0, None, None
        run = self.run
        run[N_K], run[N_T0], run[N_END], run[N_LIMIT], run[N_TIMED] = k, t0_ns, end, \
            self.limit, 1
        run[N_SPIN] = self.proc.loop.clock.spin_ns
        done, reason = self._call()
        woke = int(run[N_WAKE]) if reason == S.DECLINED else None
        if not done:
            return 0, None, woke
        last_end = int(run[N_END_NS])
        if reason in (S.SEND_FAILED, SEND_IN_PYTHON):  # its end is Python's
            last = k + done - 1
            wake = int(run[N_WAKE])
            last_end = self.proc.loop.clock.now_ns()
            self.proc.loop.lateness_ns[last] = wake - (t0_ns + last * run[N_PERIOD])
            self.proc.loop.compute_ns[last] = last_end - wake
        return done, last_end, woke

    def tick(self, k: int) -> bool:
        """Run tick ``k`` now, compiled if it may (``ControllerProcess.step``: a test's own
        pacing); False: nothing changed, the Python path runs it."""
        if not self._may_run():
            return False
        run = self.run
        run[N_K], run[N_END], run[N_LIMIT], run[N_TIMED] = k, k + 1, 1, 0
        done, _ = self._call()
        return done > 0

    def _call(self) -> tuple[int, int]:
        """The compiled loop on the state of now, its counts and records back: (ticks
        run, why it returned)."""
        proc, link, run = self.proc, self.link, self.run
        self._load()
        link.prepare()
        run[N_SILENT], run[N_ROWS] = proc.silent, proc.rows
        controller_run(*self._args())
        done, reason = int(run[N_DONE]), int(run[N_REASON])
        link.settle(False)
        if done:
            self.calls += 1
            self.ticks += done
            self._settle(done)
        if reason == S.DECLINED:
            code = int(run[N_DECLINED])
            self.declined[code] = self.declined.get(code, 0) + 1
            link.hand_back()  # what the tick read
        elif reason == S.SEND_FAILED:
            link.send_error()
            proc.adapter_errors += 1
        elif reason == SEND_IN_PYTHON:
            try:
                proc.ep.send_setpoint(proc.sp)
            except AdapterError:  # counted as ControllerProcess.step counts it
                proc.adapter_errors += 1
        if reason == ROWS_DONE:
            proc.loop.request_stop()
        return done, reason

    def _load(self) -> None:
        """The feedback and setpoint records into the arrays (the Python path's ticks
        write the records)."""
        link, proc = self.link, self.proc
        fb, sp = proc.fb, proc.sp
        f, fa, ff = link.fb_ints, link.fb_axis_ints, link.fb_floats
        f[K.F_SEQ], f[K.F_SP_T_NS], f[K.F_SP_RX_NS], f[K.F_T_NS], f[K.F_TICK_NS] = (
            fb.seq, fb.sp_t_ns, fb.sp_rx_ns, fb.t_ns, fb.tick_ns)
        self.fbx[0], self.fbx[1] = fb.time_s, fb.rx_ns
        for a, r in enumerate(axis_records(fb)):
            fa[a, K.A_STATUSWORD], fa[a, K.A_FAULT] = r.statusword, r.fault
            ff[a] = [getattr(r, name) for name in K.FB_FLOAT_FIELDS]
        link.sp_ints[K.I_SEQ] = sp.seq
        for a, r in enumerate(axis_records(sp)):
            link.axis_ints[a] = r.controlword, r.mode
            link.sp_floats[a] = [getattr(r, name) for name in K.SP_FLOAT_FIELDS]

    def _settle(self, done: int) -> None:
        """The arrays into the records, the controllers and the process, after ``done``
        ticks."""
        link, proc, run = self.link, self.proc, self.run
        fb, sp = proc.fb, proc.sp
        f = link.fb_ints.tolist()
        ff = link.fb_floats.tolist()
        fa = link.fb_axis_ints.tolist()
        stamps = dict(seq=f[K.F_SEQ], sp_t_ns=f[K.F_SP_T_NS], sp_rx_ns=f[K.F_SP_RX_NS],
                      t_ns=f[K.F_T_NS], tick_ns=f[K.F_TICK_NS])
        for a, r in enumerate(axis_records(fb)):
            for name, value in stamps.items():
                setattr(r, name, value)
            r.statusword, r.fault = fa[a]
            for name, value in zip(K.FB_FLOAT_FIELDS, ff[a]):
                setattr(r, name, value)
        if isinstance(fb, FeedbackGroup):
            for name, value in stamps.items():
                setattr(fb, name, value)
        fb.time_s, fb.rx_ns = float(self.fbx[0]), int(self.fbx[1])
        seq, t_ns = int(link.sp_ints[K.I_SEQ]), int(link.sp_ints[K.I_T_NS])
        sp.seq, sp.t_ns = seq, t_ns
        for a, r in enumerate(axis_records(sp)):
            r.seq = seq
            r.controlword, r.mode = link.axis_ints[a].tolist()
            for name, value in zip(K.SP_FLOAT_FIELDS, link.sp_floats[a].tolist()):
                setattr(r, name, value)
        for x in self.axes:
            x.cycles += done
            x.write_signals()
        proc.rows, proc.silent = int(run[N_ROWS]), int(run[N_SILENT])

    def as_dict(self) -> dict:
        """What the compiled loop ran, JSON-ready (``summary.json``'s ``compiled_loop``)."""
        names = {S.DECLINED_FRAME: "frame", S.DECLINED_SEQUENCE: "sequence",
                 S.DECLINED_RECEIVE: "receive", DECLINED_TIMEOUT: "feedback timeout",
                 DECLINED_NC: "nc"}
        return {"ticks": self.ticks, "calls": self.calls,
                "declined": {names[c]: n for c, n in self.declined.items()}}

