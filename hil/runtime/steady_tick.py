"""The emulator's steady loop in compiled code: many ticks in one call, each from the
deadline's wait to the answer's send (issue 29; issue 12 part 6 began it with one tick).

In steady state -- a UDP link whose controller is pinned, every drive's compiled path
holding its state (:mod:`hil.drive.compiled_path`: OPERATION ENABLED in CSP, CSV or CST,
nothing to react to), the watchdog content, no injection under way or waiting at the
injection port (:mod:`io_adapters.inject_port`) -- one call of :func:`steady_run` (one
axis) or :func:`steady_run_group` (a machine of up to
:data:`~io_adapters.codec_compiled.MAX_AXES` axes) runs tick after tick.  Each tick waits
for its deadline (:func:`hil.rt.clock.sleep_until_ns`, the loop's own wait), reads the
datagrams queued for it (:func:`io_adapters.udp_steady.receive`: non-blocking
``recvmsg`` within the endpoint's receive budget; a stranger's datagram that cannot be a
HELLO is counted foreign there and then), decodes each setpoint
(:func:`io_adapters.codec_compiled.decode_setpoint`) and checks its session and frame
number (an older one also against the drives' bounds, as the endpoint's drain takes it
before the newest overwrites it), runs the tick's drive cycles on the newest setpoint, or
on the one the drives hold when none came (:func:`hil.drive.compiled.steady_cycle`, each
axis in turn, as many as a tick has PWM periods; it writes the axis's recording row),
stamps and encodes the feedback (:func:`io_adapters.codec_compiled.encode_feedback`),
writes the row's common part, keeps the endpoint's books and the watchdog's count, sends
the answer (``sendto``) and finishes the row with the loop's lateness and compute time
(the ring's ``end_tick``).  A silent tick runs compiled only while it changes nothing in
the watchdog but its count (:meth:`~hil.runtime.watchdog.Watchdog.steady_counts`): the
tick that trips it, or finds the controller absent, is the Python path's, and so is the
first heard tick after an absence; while the controller is absent (before the first
setpoint, or after a silence with every drive's power stage off) a silent tick sends no
answer and changes nothing, and runs compiled.

The call releases the GIL, so the emulator's other threads (the recording's answer
thread) no longer delay a tick, and returns to Python (:class:`SteadyTick`, called by the
loop's :func:`hil.rt.loop.run_ticks` as its ``burst``):

* at the first tick it must decline, after that tick's wait, with every state as it was:
  the datagrams go back to the endpoint and :meth:`hil.runtime.emulator.Emulator.step`'s
  Python path runs that tick (the endpoint counts and judges the datagrams, the drive's
  Python path reacts; a cycle that declines after others ran has them put back from a
  snapshot taken at the tick's start), so there is one owner of every decision and the
  compiled loop adds nothing but speed;
* after a tick that overran (ended after the next deadline): the loop's overrun policy
  is Python's (:func:`~hil.rt.loop.run_ticks`);
* after a tick whose answer the Python encoder must send (a non-finite value) or whose
  send failed otherwise than for room (counted and logged in Python);
* at a stop request (``stop``, written by :meth:`hil.runtime.streaming_loop.
  StreamingLoop.request_stop` from any thread), checked before every tick;
* after :data:`BURST_S` of ticks at most: Python's signal handlers run only between
  calls, so SIGTERM and SIGINT are served within that time (and the loop's other
  Python-side checks run at least that often).

The same compiled function runs one tick without waiting when the Python loop calls
:meth:`hil.runtime.emulator.Emulator.step` (``SteadyTick.tick``: a benchmark's or a
test's own pacing), so both entries share every line of the tick.
tests/test_tick_steady.py runs the same datagrams through an emulator with and one without
it (1, 2 and 5 axes) and compares every feedback value, recording row and counter; and
through ``hil run``'s loop, bursts and all.

While compiled ticks run, the emulator's Setpoint and Feedback records are not written
(that would cost what the compiled tick saves); :meth:`SteadyTick.settle` writes them
from the arrays before anything in Python reads them (the Python path's next tick, the
safe state, the report).
"""

import math
import time

import numpy as np
from numba import njit

from hil.drive import compiled as C
from hil.rt.clock import now_ns, sleep_until_ns
from io_adapters import codec_compiled as K
from io_adapters import udp_steady as U
from io_adapters.base import AdapterError
from io_adapters.codec import U32
from io_adapters.messages import FeedbackGroup, axis_records
from io_adapters.msgpack_endpoint import MAX_DROPOUT
from io_adapters.udp import UdpEndpoint
from io_adapters.udp_steady import (
    L_CLOCK,
    L_FRAMES,
    L_LENGTHS,
    L_PEER_FRAME,
    L_PEER_SESSION,
    L_RX_NS,
    SteadyLink,
)

#: the most time one call runs ticks, s: Python's signal handlers wait for its end
BURST_S = 0.01
#: the common part of a recording row that a tick writes (hil.runtime.recording._COMMON):
#: the loop's (tick, lateness, compute), then the tick's
R_TICK, R_LATENESS, R_COMPUTE = range(3)
R_TICK_START, R_SP_T_NS, R_SP_RX_NS, R_FB_T_NS, R_SP_NEW, R_SP_SEQ, R_SP_REFUSED = range(3, 10)
#: why a tick was declined (the Python path runs it); > 0: the answer's length
DECLINED_FRAME, DECLINED_SEQUENCE, DECLINED_CYCLE = -1, -2, -3
#: ... and, the tick's receive declined (its datagrams handed back), or a tick that would
#: change the watchdog beyond its count (the tick that trips it or finds the controller
#: absent, the one that hears it again)
DECLINED_RECEIVE, DECLINED_SILENT = -4, -5
#: the tick ran but its answer did not encode (the Python path sends it)
UNENCODED = 0
#: ``run``: the call's inputs (first tick, the loop's t0, period, end tick, most ticks,
#: spin before a deadline, waits (1) or runs one tick now (0), drive cycles per tick, the
#: ring's slots), then what it did (ticks run, why it returned, the last wake-up, the
#: last tick's end, its ring column; heard, silent and queued ticks among those run)
(N_K, N_T0, N_PERIOD, N_END, N_LIMIT, N_SPIN, N_TIMED, N_CYCLES, N_SLOTS, N_DONE,
 N_REASON, N_WAKE, N_END_NS, N_ROW, N_HEARD, N_SILENT, N_QUEUED, N_RUN) = range(18)
#: why a call returned: its ticks all ran on time up to its bound, the loop's end or a
#: stop request; the last tick overran; a tick was declined (``run[N_WAKE]``: its
#: wake-up; N_DECLINED holds the DECLINED_* code); the last tick's send failed; the last
#: tick's answer is the Python encoder's
(ENDED, OVERRAN, DECLINED, SEND_FAILED, ANSWER_IN_PYTHON) = range(5)
N_DECLINED = N_RUN
#: ``trace`` columns, per tick run compiled in a timed call (a benchmark's; none in hil
#: run): woken, datagrams read, answer encoded and row written, books kept (the send
#: begins), answer sent (the tick's end: its compute time ends there, as the ring's
#: end_tick has it), the wake-up latency (the sleep's end after its target, the deadline
#: less the spin: :func:`hil.rt.clock.sleep_until_ns`)
T_WAKE, T_RECEIVED, T_WORKED, T_SENDING, T_SENT, T_WAKE_LATENCY, N_TRACE = range(7)
#: the wire's setpoint floats (codec_compiled.SP_FLOAT_FIELDS) in the drive's ``spf``
_SPF_SLOT = tuple(C.SP_FLOATS.index(name) for name in K.SP_FLOAT_FIELDS)


@njit(cache=True, inline="always")
def _keep(snap, offset, arr, back):
    """``snap[offset:offset + arr.size] = arr``, or (``back``) the other way; the next
    offset."""
    for k in range(arr.size):
        if back:
            arr[k] = snap[offset + k]
        else:
            snap[offset + k] = arr[k]
    return offset + arr.size


@njit(cache=True, inline="always")
def _axis_state(snap_f, snap_i, fst, fbf, s, inp, out, ist, back):
    """Keep everything a drive cycle changes in the axis's snapshot rows (after its
    setpoint's ``N_SPF`` floats and 3 ints), or (``back``) put it back from them."""
    at = _keep(snap_f, C.N_SPF, fst[:C.N_FST], back)
    at = _keep(snap_f, at, fbf, back)
    at = _keep(snap_f, at, s, back)
    at = _keep(snap_f, at, inp, back)
    _keep(snap_f, at, out, back)
    _keep(snap_i, 3, ist[:C.N_IST], back)


@njit(cache=True, inline="always")
def _take(buf, n, sp_ints, axis_ints, sp_floats, session, after_frame):
    """Decode the setpoint ``buf[:n]`` and check it is the peer's (``session``) and in
    sequence after frame ``after_frame`` (1 to ``MAX_DROPOUT`` ahead); 0, or the
    ``DECLINED_*`` code (a repeat, an older frame or a jump is judged and counted in
    Python: io_adapters.msgpack_endpoint's sequence rule)."""
    if not K.decode_setpoint(buf, n, sp_ints, axis_ints, sp_floats):
        return DECLINED_FRAME
    if sp_ints[K.I_SESSION] != session:
        return DECLINED_SEQUENCE
    ahead = (sp_ints[K.I_FRAME] - after_frame) & U32
    if ahead == 0 or ahead > MAX_DROPOUT:
        return DECLINED_SEQUENCE
    return 0


@njit(cache=True, inline="always")
def _apply(axis_ints, sp_floats, seq, a, spf, spi):
    """Axis ``a``'s values of the decoded setpoint ``seq`` into the drive's arrays."""
    for k in range(7):
        spf[_SPF_SLOT[k]] = sp_floats[a, k]
    spi[C.I_SEQ] = seq
    spi[C.I_CW] = axis_ints[a, K.A_CONTROLWORD]
    spi[C.I_MODE] = axis_ints[a, K.A_MODE]


@njit(cache=True, inline="always")
def _every_axis(n_axes, spfs, spis, fsts, fbfs, ss, inps, outs, ists, snap_f, snap_i, whole,
                back):
    """Keep every axis's setpoint arrays (with ``whole``, all that its drive cycle changes
    too) in the snapshots, or (``back``) put them back from them."""
    for a in range(n_axes):
        _keep(snap_f[a], 0, spfs[a], back)
        _keep(snap_i[a], 0, spis[a], back)
        if whole:
            _axis_state(snap_f[a], snap_i[a], fsts[a], fbfs[a], ss[a], inps[a], outs[a],
                        ists[a], back)


@njit(cache=True, inline="always")
def _tick(bufs, n, sp_ints, axis_ints, sp_floats, link, fb_ints, fb_axis_ints, fb_floats,
          out, prms, fsts, ists, spfs, spis, saveds, fbfs, ps, ss, inps, outs, rings_f,
          rings_i, common, j, tick_ns, n_cycles, snap_f, snap_i):
    """One tick on the datagrams ``bufs[:n]`` (oldest first, ``link[L_LENGTHS + i]``
    bytes of row i; ``n`` 0: none came, the drives run on the setpoint they hold),
    started at ``tick_ns``, its recording row in column ``j`` (-1: not recorded); every
    per-axis argument a tuple.  Returns the answer's length, or :data:`UNENCODED` (the
    tick ran), or a ``DECLINED_*`` code (nothing changed)."""
    n_axes = len(prms)
    # every axis as it was: its setpoint arrays always (the cycle reads them), and all the
    # cycle changes where a later cycle or axis may still decline
    whole = n_cycles > 1 or n_axes > 1
    _every_axis(n_axes, spfs, spis, fsts, fbfs, ss, inps, outs, ists, snap_f, snap_i, whole,
                False)
    # the datagrams, oldest first: each the peer's and newer than the one before; the
    # endpoint's drain takes every one it does not refuse, and only the newest reaches
    # the drives
    after = link[L_PEER_FRAME]
    for i in range(n):
        code = _take(bufs[i], link[L_LENGTHS + i], sp_ints, axis_ints, sp_floats,
                     link[L_PEER_SESSION], after)
        if code == 0 and i < n - 1:
            for a in range(n_axes):
                _apply(axis_ints, sp_floats, 0, a, spfs[a], spis[a])
                if C._refused(prms[a], spfs[a], axis_ints[a, K.A_MODE]):
                    code = DECLINED_CYCLE
                    break
        if code:
            _every_axis(n_axes, spfs, spis, fsts, fbfs, ss, inps, outs, ists, snap_f, snap_i,
                        False, True)
            return code
        after = link[L_FRAMES + i] = sp_ints[K.I_FRAME]
    heard = n > 0
    if heard:
        seq = sp_ints[K.I_SEQ]
        for a in range(n_axes):
            _apply(axis_ints, sp_floats, seq, a, spfs[a], spis[a])
    else:  # a silent tick: the drives run on the setpoint they hold
        seq = fb_ints[K.F_SEQ]
    for _ in range(n_cycles):  # as the Python tick: each cycle steps every axis in turn
        for a in range(n_axes):
            ist = ists[a]
            ist[C.J_ROW] = j
            status = C.steady_cycle(prms[a], fsts[a], ist, spfs[a], spis[a], ps[a], ss[a],
                                    inps[a], outs[a], saveds[a], fbfs[a], rings_f[a],
                                    rings_i[a])
            ist[C.J_ROW] = -1
            if status != C.DONE:
                _every_axis(n_axes, spfs, spis, fsts, fbfs, ss, inps, outs, ists, snap_f,
                            snap_i, whole, True)
                return DECLINED_CYCLE
    for a in range(n_axes):
        fb_axis_ints[a, K.A_STATUSWORD] = ists[a][C.J_STATUSWORD]
        C._copy(fbfs[a], fb_floats[a], C.N_FBF)
    if heard:  # a silent tick's answer echoes the setpoint it holds, as fb_ints has it
        fb_ints[K.F_SEQ] = seq
        fb_ints[K.F_SP_T_NS] = sp_ints[K.I_T_NS]
        fb_ints[K.F_SP_RX_NS] = link[L_RX_NS]
    fb_ints[K.F_TICK_NS] = tick_ns
    fb_ints[K.F_T_NS] = now_ns(link[L_CLOCK:])
    length = K.encode_feedback(out, fb_ints, fb_axis_ints, fb_floats)
    if j >= 0:  # Recorder.record's common part; a silent tick's stamps are 0
        common[R_TICK_START, j] = tick_ns if heard else 0
        common[R_SP_T_NS, j] = sp_ints[K.I_T_NS] if heard else 0
        common[R_SP_RX_NS, j] = link[L_RX_NS] if heard else 0
        common[R_FB_T_NS, j] = fb_ints[K.F_T_NS] if heard else 0
        common[R_SP_NEW, j] = 1 if heard else 0
        common[R_SP_SEQ, j] = seq
        common[R_SP_REFUSED, j] = 0
    return length if length > 0 else UNENCODED


@njit(cache=True, inline="always")
def _column(counters, slots):
    """The ring's column for the next row, or -1 when the writer has not taken enough
    (Recorder._next_column)."""
    committed = counters[0]
    return -1 if committed - counters[1] >= slots else committed % slots


@njit(cache=True, inline="always")
def _end_tick(common, counters, slots, k, lateness_ns, compute_ns):
    """Recorder.end_tick: finish tick ``k``'s row, or count it lost (the ring full)."""
    committed = counters[0]
    if committed - counters[1] >= slots:
        counters[2] += 1
        counters[3] = k
        return
    j = committed % slots
    common[R_TICK, j] = k
    common[R_LATENESS, j] = lateness_ns
    common[R_COMPUTE, j] = compute_ns
    counters[0] = committed + 1  # after the row: the writer reads rows below this count


@njit(cache=True, nogil=True, _nrt=False)
def _run(bufs, sp_ints, axis_ints, sp_floats, link, books, fb_ints, fb_axis_ints, fb_floats,
         out, hdr, iov, slots, name_slots, names, ctrl, peer_name, send_name, hello_leads,
         peek, prms, fsts, ists, spfs, spis, saveds, fbfs, ps, ss, inps, outs, rings_f,
         rings_i, common, counters, run, wd, stop, trace, snap_f, snap_i):
    """The loop of :func:`steady_run_group` (module docstring)."""
    k0, t0, period, end, limit = run[N_K], run[N_T0], run[N_PERIOD], run[N_END], run[N_LIMIT]
    spin, timed, n_cycles, n_slots = run[N_SPIN], run[N_TIMED], run[N_CYCLES], run[N_SLOTS]
    clock = link[L_CLOCK:]
    done = heard = silent = queued = 0
    reason = ENDED
    run[N_DECLINED] = 0
    while done < limit:
        k = k0 + done
        if k >= end or stop[0]:
            break
        deadline = t0 + k * period
        if timed:
            wake, slept = sleep_until_ns(deadline, spin, clock)
        else:
            wake = slept = run[N_WAKE]
        run[N_WAKE] = wake
        n = U.receive(link, bufs, hdr, iov, slots, name_slots, names, ctrl, peer_name,
                      hello_leads, peek, books)
        # the watchdog (Watchdog.update on a link without conditions): a heard tick while
        # the controller is absent, or a silent one that reaches the limit, changes the
        # drives' link causes; an absent controller's silent tick changes nothing
        absent = wd[0] >= wd[2]
        if n < 0 or (n > 0 and absent) or (
                n == 0 and not absent and not (wd[1] <= 0 and wd[0] + 1 < wd[2])):
            run[N_DECLINED] = DECLINED_RECEIVE if n < 0 else DECLINED_SILENT
            reason = DECLINED
            break
        received = now_ns(clock)
        j = _column(counters, n_slots)
        result = _tick(bufs, n, sp_ints, axis_ints, sp_floats, link, fb_ints, fb_axis_ints,
                       fb_floats, out, prms, fsts, ists, spfs, spis, saveds, fbfs, ps, ss,
                       inps, outs, rings_f, rings_i, common, j, wake, n_cycles, snap_f,
                       snap_i)
        if result < 0:
            run[N_DECLINED] = result
            reason = DECLINED
            break
        worked = now_ns(clock)
        if n:
            U.take(link, n, books)
            wd[0], wd[1] = 0, -1
            heard += 1
            queued += n > 1
        else:
            U.idle(books)
            if not absent:
                wd[0] += 1
            silent += 1
        sending = now_ns(clock) if timed else 0
        # the drives answer while the controller was heard within the limit
        sent = U.send(link, out, result, fb_ints, send_name, books) if wd[0] < wd[2] else 0
        done += 1
        run[N_ROW] = j
        if sent < 0:
            reason = SEND_FAILED
            break
        if result == UNENCODED:
            reason = ANSWER_IN_PYTHON
            break
        if timed:
            t_end = now_ns(clock)
            _end_tick(common, counters, n_slots, k, wake - deadline, t_end - wake)
            run[N_END_NS] = t_end
            if k < trace.shape[0]:
                trace[k, T_WAKE], trace[k, T_RECEIVED] = wake, received
                trace[k, T_WORKED], trace[k, T_SENDING], trace[k, T_SENT] = worked, sending, t_end
                trace[k, T_WAKE_LATENCY] = slept - (deadline - spin)
            if t_end > deadline + period:
                reason = OVERRAN
                break
    run[N_DONE], run[N_REASON] = done, reason
    run[N_HEARD], run[N_SILENT], run[N_QUEUED] = heard, silent, queued


@njit(cache=True, nogil=True, _nrt=False)
def steady_run(bufs, sp_ints, axis_ints, sp_floats, link, books, fb_ints, fb_axis_ints,
               fb_floats, out, hdr, iov, slots, name_slots, names, ctrl, peer_name,
               send_name, hello_leads, peek, prm, fst, ist, spf, spi, saved, fbf, p, s, inp,
               plant_out, ring_f, ring_i, common, counters, run, wd, stop, trace, snap_f,
               snap_i):
    """Ticks of a single-axis machine (see the module docstring), its arrays passed one
    by one (a tuple costs the call more than a tick saves).  ``bufs`` .. ``peek``:
    :class:`~io_adapters.udp_steady.SteadyLink`'s arrays; ``prm`` .. ``fbf``: the
    drive's compiled path's (:class:`~hil.drive.compiled_path.CompiledPath`); ``p``,
    ``s``, ``inp``, ``plant_out``: the plant's; ``ring_f``, ``ring_i``: the axis's planes
    of the recording's ring, ``common`` its common block and ``counters`` its counters;
    ``run``: int64[N_RUN + 1], the call's inputs and what it did (``N_*``); ``wd``: the
    watchdog's count (:meth:`~hil.runtime.watchdog.Watchdog.steady_counts`); ``stop``:
    int64[1], nonzero: stop before the next tick; ``trace``: int64[ticks, N_TRACE] of per-tick
    stamps (``T_*``, row k for tick k; zero rows: none kept); ``snap_f``, ``snap_i``: the
    per-axis snapshots (:class:`SteadyTick`)."""
    _run(bufs, sp_ints, axis_ints, sp_floats, link, books, fb_ints, fb_axis_ints, fb_floats,
         out, hdr, iov, slots, name_slots, names, ctrl, peer_name, send_name, hello_leads,
         peek, (prm,), (fst,), (ist,), (spf,), (spi,), (saved,), (fbf,), (p,), (s,), (inp,),
         (plant_out,), (ring_f,), (ring_i,), common, counters, run, wd, stop, trace, snap_f,
         snap_i)


@njit(cache=True, nogil=True, _nrt=False)
def steady_run_group(bufs, sp_ints, axis_ints, sp_floats, link, books, fb_ints,
                     fb_axis_ints, fb_floats, out, hdr, iov, slots, name_slots, names, ctrl,
                     peer_name, send_name, hello_leads, peek, prms, fsts, ists, spfs, spis,
                     saveds, fbfs, ps, ss, inps, outs, rings_f, rings_i, common, counters,
                     run, wd, stop, trace, snap_f, snap_i):
    """Ticks of a machine of several axes: :func:`steady_run` with a tuple of every
    axis's array in place of each per-axis array."""
    _run(bufs, sp_ints, axis_ints, sp_floats, link, books, fb_ints, fb_axis_ints, fb_floats,
         out, hdr, iov, slots, name_slots, names, ctrl, peer_name, send_name, hello_leads,
         peek, prms, fsts, ists, spfs, spis, saveds, fbfs, ps, ss, inps, outs, rings_f,
         rings_i, common, counters, run, wd, stop, trace, snap_f, snap_i)


class SteadyTick:
    """The compiled steady loop of ``emulator`` through ``link`` (see the module
    docstring); build it with :meth:`for_emulator`, which returns None where it never
    applies.

    Attributes:
        ticks: ticks run compiled.
        silent: of those, ticks that heard no setpoint (the drives ran on the one they
            hold, as the Python tick runs them).
        queued: of those, ticks that took more than one setpoint queued in the socket.
        calls: calls of the compiled loop that ran at least one tick.
        python_ns: time :meth:`burst` spent in Python around its calls (ns): the loop's
            glue, shared by the ticks the calls ran.
        declined: ticks that read a datagram and handed it to the Python path, by
            ``DECLINED_*`` code (frame, sequence, cycle).
        trace: int64[ticks, N_TRACE], per-tick stamps of the ticks run by :meth:`burst`
            (row k for tick k; no rows unless :meth:`keep_trace` gave some).
        dirty: the emulator's Setpoint and Feedback records are behind the arrays
            (:meth:`settle`).
    """

    def __init__(self, emulator, link: SteadyLink):
        self.emulator = emulator
        self.link = link
        self.drives = drives = emulator.drives.drives
        self.paths = paths = tuple(d.compiled for d in drives)
        plants = [d.plant for d in drives]
        group = len(drives) > 1
        snap_width = C.N_SPF + C.N_FST + C.N_FBF + max(
            p.state.size + p.inp.size + p.out.size for p in plants)
        per_axis = [tuple(getattr(x, name) for x in paths)
                    for name in ("prm", "fst", "ist", "spf", "spi", "saved", "fbf")]
        per_axis += [tuple(getattr(p, name) for p in plants)
                     for name in ("params", "state", "inp", "out")]
        per_axis += [tuple(x.ring_f for x in paths), tuple(x.ring_i for x in paths)]
        recorder, loop = emulator.recorder, emulator.loop
        period = emulator.timing.period_ns
        self.run = run = np.zeros(N_RUN + 1, np.int64)
        run[N_PERIOD], run[N_CYCLES], run[N_SLOTS] = period, emulator.timing.cycles_per_tick, \
            recorder.slots
        self.limit = max(1, math.ceil(BURST_S * 1e9 / period))
        self.wd = np.zeros(3, np.int64)
        self.trace = np.zeros((0, N_TRACE), np.int64)
        self.cycles = emulator.timing.cycles_per_tick
        self._args = [link.bufs, link.sp_ints, link.axis_ints, link.sp_floats, link.link,
                      link.books, link.fb_ints, link.fb_axis_ints, link.fb_floats, link.out,
                      link.hdr, link.iov, link.slots, link.name_slots, link.names, link.ctrl,
                      link.peer_name, link.send_name, link.hello_leads, link.peek,
                      *(per_axis if group else (a[0] for a in per_axis)), recorder.common,
                      recorder.ring.counters, run, self.wd, loop.stop_word, self.trace,
                      np.zeros((len(drives), snap_width)),
                      np.zeros((len(drives), 3 + C.N_IST), np.int64)]
        self._trace_at = len(self._args) - 3
        self._call = steady_run_group if group else steady_run
        self._faults_written = False
        # fb_ints echo the setpoint the drives hold (else the Python path's records do)
        self._holding = False
        self.ticks = self.silent = self.queued = self.calls = self.python_ns = 0
        self.declined = {DECLINED_FRAME: 0, DECLINED_SEQUENCE: 0, DECLINED_CYCLE: 0}
        self.dirty = False
        # compiled (or loaded from numba's cache) now, before any clock starts: a call
        # asked for no tick runs none and changes nothing
        self._call(*self._args)

    @classmethod
    def for_emulator(cls, emulator) -> "SteadyTick | None":
        """The compiled loop of an emulator that can take one: at most
        :data:`~io_adapters.codec_compiled.MAX_AXES` axes, a UDP device endpoint on the
        msgpack wire refusing what its drives refuse, no SYNC, every drive's compiled
        path, a platform whose C structures :mod:`io_adapters.udp_steady` knows; else
        None."""
        ep = emulator.endpoint
        drives = emulator.drives.drives
        if (not U.AVAILABLE or len(drives) > K.MAX_AXES or type(ep) is not UdpEndpoint
                or ep.wire.name != "msgpack"
                or emulator.sync_lock is not None or any(d.compiled is None for d in drives)
                or ep.setpoint_bounds != tuple(d.setpoint_bounds() for d in drives)):
            return None
        return cls(emulator, SteadyLink(ep, len(drives)))

    def as_dict(self) -> dict:
        """What the compiled loop ran, JSON-ready (``report.json``'s ``compiled_loop``):
        ticks, of those silent and queued ones, calls, the ticks it declined by reason,
        and the drives' cycles that went to Python, by exit reason."""
        names = {DECLINED_FRAME: "frame", DECLINED_SEQUENCE: "sequence",
                 DECLINED_CYCLE: "cycle"}
        return {"ticks": self.ticks, "silent": self.silent, "queued": self.queued,
                "calls": self.calls,
                "declined": {names[c]: n for c, n in self.declined.items()},
                "drive_exits": {name: sum(p.exits[code] for p in self.paths)
                                for code, name in C.EXIT_NAMES.items()}}

    def keep_trace(self, n_ticks: int) -> np.ndarray:
        """Keep the stamps of the first ``n_ticks`` ticks :meth:`burst` runs in
        :attr:`trace` (a benchmark's; zeroed rows: ticks not run compiled)."""
        self.trace = np.zeros((n_ticks, N_TRACE), np.int64)
        self._args[self._trace_at] = self.trace
        return self.trace

    def burst(self, k: int, t0_ns: int, end: int) -> tuple[int, int | None, int | None]:
        """Run ticks ``k``, ``k + 1``, ... (deadline ``t0_ns + k * period``, up to tick
        ``end`` - 1) compiled, each waited for, ended and its row finished, as
        :func:`hil.rt.loop.run_ticks` runs them (its ``burst``): (ticks run, the end of the
        last one run (monotonic ns; None when none ran), the wake-up of the tick after it
        when that one was woken and declined: the Python path runs it without waiting
        again (None: not woken))."""
        entered = time.monotonic_ns()
        if not self._may_run():
            return 0, None, None
        run = self.run
        run[N_K], run[N_T0], run[N_END] = k, t0_ns, end
        run[N_LIMIT], run[N_TIMED] = self.limit, 1
        run[N_SPIN] = self.emulator.loop.clock.spin_ns
        done, reason = self._call_compiled(entered)
        if not done:
            return 0, None, int(run[N_WAKE]) if reason == DECLINED else None
        last_end = int(run[N_END_NS])
        if reason in (SEND_FAILED, ANSWER_IN_PYTHON):  # its end is Python's
            last = k + done - 1
            wake = int(run[N_WAKE])
            last_end = now = self.emulator.loop.clock.now_ns()
            self.emulator.recorder.wrote_row(int(run[N_ROW]))
            self.emulator.recorder.end_tick(last, wake - (t0_ns + last * run[N_PERIOD]),
                                            now - wake)
        return done, last_end, int(run[N_WAKE]) if reason == DECLINED else None

    def tick(self, k: int, t_ns: int) -> int | None:
        """Run tick ``k``, started at ``t_ns`` (monotonic ns), now, compiled if it may
        (:meth:`hil.runtime.emulator.Emulator.step`; the caller ends it and finishes its
        row): the setpoints heard (1, or 0 in a silent tick); None: nothing changed, the
        Python path runs it (a datagram read is back in the endpoint)."""
        if not self._may_run():
            return None
        run = self.run
        run[N_K], run[N_END], run[N_LIMIT], run[N_TIMED], run[N_WAKE] = k, k + 1, 1, 0, t_ns
        done, _ = self._call_compiled(None)
        if not done:
            return None
        self.emulator.recorder.wrote_row(int(run[N_ROW]))
        return int(run[N_HEARD])

    def _may_run(self) -> bool:
        """Every drive's compiled path holds its state with nothing to react to, no
        injection is under way or waiting at the injection port, the watchdog is content
        and the link ready."""
        em = self.emulator
        watchdog = em.watchdog
        port = em.inject_port
        if (not watchdog.steady_counts(self.wd) or not self.link.ready()
                or (port is not None and port.requests)):
            return self._python()
        causes = watchdog.steady_causes()
        for d, path, inj in zip(self.drives, self.paths, em.injectors):
            # a drive with its power stage off (the power-off cycle) ignores the cause of
            # an absent controller
            if (not path.active or d.link_causes != (causes if path.idle else 0)
                    or d.faults.latched or inj.busy
                    or d.params.generation != path._generation):
                return self._python()
        return True

    def _call_compiled(self, entered: int | None) -> tuple[int, int]:
        """Call the compiled loop on the state of now and take its counts back: (ticks
        run, why it returned); ``entered``: when :meth:`burst` was called (monotonic
        ns), whose time outside the call :attr:`python_ns` adds up (None: not kept)."""
        em, link, run = self.emulator, self.link, self.run
        if not self._holding:  # the answer echoes the setpoint the Python path took last
            f, ep = link.fb_ints, em.endpoint
            f[K.F_SEQ], f[K.F_SP_T_NS], f[K.F_SP_RX_NS] = em._sp.seq, ep._sp_t_ns, ep._sp_rx_ns
        if not self._faults_written:  # 603Fh changes in the Python path's ticks only
            for a, d in enumerate(self.drives):
                link.fb_axis_ints[a, K.A_FAULT] = d.fault
            self._faults_written = True
        link.prepare()
        called = time.monotonic_ns()
        self._call(*self._args)
        returned = time.monotonic_ns()
        done, reason = int(run[N_DONE]), int(run[N_REASON])
        link.settle(done > 0)
        em.watchdog.steady_settle(self.wd)
        if done:
            self.calls += 1
            self.ticks += done
            self.silent += int(run[N_SILENT])
            self.queued += int(run[N_QUEUED])
            em.setpoints_heard += int(run[N_HEARD])
            self.dirty = self._holding = True
            cycles = done * self.cycles
            for d, path in zip(self.drives, self.paths):
                path.cycles += cycles
                d.tick += cycles
        if reason == DECLINED:
            code = int(run[N_DECLINED])
            if code in self.declined:
                self.declined[code] += 1
            link.hand_back()  # what the tick read (and the budget it left)
            self._python()
        elif reason == SEND_FAILED:
            em._adapter_error("send", link.send_error())
        elif reason == ANSWER_IN_PYTHON:
            self._answer_in_python(int(run[N_ROW]))
        if entered is not None:
            self.python_ns += called - entered + time.monotonic_ns() - returned
        return done, reason

    def _python(self) -> bool:
        """The Python path runs the next tick: it writes 603Fh and answers with its own
        records, which the next compiled tick cannot echo."""
        self._faults_written = self._holding = False
        return False
    def _answer_in_python(self, row: int) -> None:
        """The answer the compiled writer declined (a non-finite value), sent by the
        Python encoder as the Python path sends it; ``row``: the tick's column in the
        ring (-1: none)."""
        self.settle()
        em = self.emulator
        try:
            em.endpoint.send_feedback(em._fb)
        except AdapterError as e:
            em._adapter_error("send", e)
        if row >= 0:
            em.recorder.common[R_FB_T_NS, row] = em._fb.t_ns

    def settle(self) -> None:
        """Write the emulator's Setpoint and Feedback records (plain or groups) from the
        arrays -- the last setpoint applied, the last answer -- as the Python path leaves
        them, if compiled ticks ran since the last call."""
        if not self.dirty:
            return
        self.dirty = False
        sp, fb = self.emulator._sp, self.emulator._fb
        f = self.link.fb_ints.tolist()
        sp.seq, sp.t_ns, sp.rx_ns = f[K.F_SEQ], f[K.F_SP_T_NS], f[K.F_SP_RX_NS]
        fb.seq, fb.sp_t_ns, fb.sp_rx_ns = f[K.F_SEQ], f[K.F_SP_T_NS], f[K.F_SP_RX_NS]
        fb.t_ns, fb.tick_ns = f[K.F_T_NS], f[K.F_TICK_NS]
        for s, fa, d, path in zip(axis_records(sp), axis_records(fb), self.drives,
                                  self.paths):
            s.seq, s.controlword, s.mode = path.spi.tolist()
            s.t_ns = f[K.F_SP_T_NS]
            for name, value in zip(C.SP_FLOATS, path.spf.tolist()):
                setattr(s, name, value)
            fa.seq, fa.statusword, fa.fault = f[K.F_SEQ], int(path.ist[C.J_STATUSWORD]), d.fault
            for name, value in zip(K.FB_FLOAT_FIELDS, path.fbf.tolist()):
                setattr(fa, name, value)
        if isinstance(fb, FeedbackGroup):
            fb.time_s = fb.axes[0].time_s
