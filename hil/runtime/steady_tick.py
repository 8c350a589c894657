"""The emulator's tick in one compiled call, from the setpoint's bytes to the answer's
(issue 12 part 6: "Python touches only the socket").

In steady state -- a UDP link whose controller is pinned, every drive's compiled path
holding its state (:mod:`hil.drive.compiled_path`: OPERATION ENABLED in CSP, CSV or CST,
nothing to react to), the watchdog content, no injection under way -- a tick is: read
the datagrams queued for it, within the endpoint's receive budget (Python: the socket;
usually one, none in a silent tick, several after a late tick; a stranger's datagram
that cannot be a HELLO is counted foreign there and then), then one call of
:func:`steady_tick` (one axis) or :func:`steady_tick_group` (a machine of up to
:data:`~io_adapters.codec_compiled.MAX_AXES` axes) that decodes each setpoint
(:func:`io_adapters.codec_compiled.decode_setpoint`) and checks its session and frame
number (an older one also against the drives' bounds, as the endpoint's drain takes it
before the newest overwrites it), runs the tick's drive cycles on the newest setpoint,
or on the one the drives hold when none came (:func:`hil.drive.compiled.steady_cycle`,
each axis in turn, as many as a tick has PWM periods; it writes the axis's recording
row), stamps and encodes the feedback (:func:`io_adapters.codec_compiled.encode_feedback`)
and writes the row's common part; then (Python) the endpoint's books and the send
(:class:`io_adapters.udp_steady.SteadyLink`), the watchdog's count, the drives'
counters.  A silent tick runs compiled only while it changes nothing in the watchdog but
its count (:meth:`~hil.runtime.watchdog.Watchdog.may_stay_silent`): the tick that trips
it is the Python path's.

Anything outside that case is declined with every state as it was: the datagrams go
back to the endpoint and :meth:`hil.runtime.emulator.Emulator.step`'s Python path runs
the tick as it always has (the endpoint counts and judges the datagrams, the drive's
Python path reacts; a cycle that declines after others ran has them put back from a
snapshot taken at the tick's start), so there is one owner of every decision and the
compiled tick adds nothing but speed.  tests/test_tick_steady.py runs the same datagrams
through an emulator with and one without it and compares every feedback value, recording
row and counter.

While compiled ticks run, the emulator's Setpoint and Feedback records are not written
(that would cost what the compiled tick saves); :meth:`SteadyTick.settle` writes them
from the arrays before anything in Python reads them (the Python path's next tick, the
safe state, the report).
"""

import time

import numpy as np
from numba import njit, types

from hil.drive import compiled as C
from io_adapters import codec_compiled as K
from io_adapters.base import AdapterError
from io_adapters.codec import U32
from io_adapters.messages import FeedbackGroup, axis_records
from io_adapters.msgpack_endpoint import MAX_DROPOUT
from io_adapters.udp import UdpEndpoint
from io_adapters.udp_steady import (
    L_CALL_NS,
    L_CLOCK,
    L_FRAMES,
    L_LENGTHS,
    L_PEER_FRAME,
    L_PEER_SESSION,
    L_RX_NS,
    SteadyLink,
)

#: the C library's clock, resolved by name when the kernel is linked (so that numba can
#: cache it, as it cannot a ctypes pointer): the same clock as ``time.monotonic_ns()``
_clock_gettime = types.ExternalFunction("clock_gettime",
                                        types.int32(types.int32, types.voidptr))
CLOCK_MONOTONIC = time.CLOCK_MONOTONIC
#: the common part of a recording row that a tick writes (hil.runtime.recording._COMMON)
R_TICK_START, R_SP_T_NS, R_SP_RX_NS, R_FB_T_NS, R_SP_NEW, R_SP_SEQ, R_SP_REFUSED = range(3, 10)
#: why a tick was declined (the Python path runs it); > 0: the answer's length
DECLINED_FRAME, DECLINED_SEQUENCE, DECLINED_CYCLE = -1, -2, -3
#: the tick ran but its answer did not encode (the Python path sends it)
UNENCODED = 0
#: the wire's setpoint floats (codec_compiled.SP_FLOAT_FIELDS) in the drive's ``spf``
_SPF_SLOT = tuple(C.SP_FLOATS.index(name) for name in K.SP_FLOAT_FIELDS)


@njit(cache=True, inline="always")
def _monotonic_ns(timespec):
    _clock_gettime(CLOCK_MONOTONIC, timespec.ctypes)
    return timespec[0] * 1_000_000_000 + timespec[1]


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


@njit(cache=True, _nrt=False)
def _tick(bufs, n, sp_ints, axis_ints, sp_floats, link, fb_ints, fb_axis_ints, fb_floats,
          out, prms, fsts, ists, spfs, spis, saveds, fbfs, ps, ss, inps, outs, rings_f,
          rings_i, common, j, tick_ns, n_cycles, snap_f, snap_i):
    """The tick of :func:`steady_tick_group`, every per-axis argument a tuple."""
    if n < 0:
        return DECLINED_FRAME
    # the call's own time ends at the answer's stamp (hil bench tick reports it)
    link[L_CALL_NS] = _monotonic_ns(link[L_CLOCK:])
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
    fb_ints[K.F_T_NS] = _monotonic_ns(link[L_CLOCK:])
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


@njit(cache=True, _nrt=False)
def steady_tick(bufs, n, sp_ints, axis_ints, sp_floats, link, fb_ints, fb_axis_ints,
                fb_floats, out, prm, fst, ist, spf, spi, saved, fbf, p, s, inp, plant_out,
                ring_f, ring_i, common, j, tick_ns, n_cycles, snap_f, snap_i):
    """One tick of a single-axis machine (see the module docstring), its arrays passed one
    by one (a tuple costs the call more than the tick saves).  ``bufs[:n]``: the
    datagrams, oldest first, ``link[L_LENGTHS + i]`` bytes of row i (the newest is
    applied, the older ones are taken and superseded, as the endpoint's drain does;
    ``n`` 0: none came, the tick runs on the setpoint the drives hold; < 0: nothing to
    do, declined at once); ``sp_ints`` .. ``out``:
    :class:`~io_adapters.udp_steady.SteadyLink`'s arrays;
    ``prm`` .. ``fbf``: the drive's compiled path's
    (:class:`~hil.drive.compiled_path.CompiledPath`); ``p``, ``s``, ``inp``,
    ``plant_out``: the plant's; ``ring_f``, ``ring_i``: the axis's planes of the
    recording's ring, ``common`` its common block, ``j`` the row's column (-1: not
    recorded); ``tick_ns``: the tick's start (monotonic ns); ``n_cycles``: drive cycles
    per tick; ``snap_f``, ``snap_i``: the per-axis snapshots (:class:`SteadyTick`).
    Returns the answer's length, or :data:`UNENCODED` (the tick ran), or a ``DECLINED_*``
    code (nothing changed)."""
    return _tick(bufs, n, sp_ints, axis_ints, sp_floats, link, fb_ints, fb_axis_ints,
                 fb_floats, out, (prm,), (fst,), (ist,), (spf,), (spi,), (saved,), (fbf,),
                 (p,), (s,), (inp,), (plant_out,), (ring_f,), (ring_i,), common, j, tick_ns,
                 n_cycles, snap_f, snap_i)


@njit(cache=True, _nrt=False)
def steady_tick_group(bufs, n, sp_ints, axis_ints, sp_floats, link, fb_ints,
                      fb_axis_ints, fb_floats, out, prms, fsts, ists, spfs, spis, saveds,
                      fbfs, ps, ss, inps, outs, rings_f, rings_i, common, j, tick_ns,
                      n_cycles, snap_f, snap_i):
    """One tick of a machine of several axes: :func:`steady_tick` with a tuple of every
    axis's array in place of each per-axis array."""
    return _tick(bufs, n, sp_ints, axis_ints, sp_floats, link, fb_ints, fb_axis_ints,
                 fb_floats, out, prms, fsts, ists, spfs, spis, saveds, fbfs, ps, ss, inps,
                 outs, rings_f, rings_i, common, j, tick_ns, n_cycles, snap_f, snap_i)


class SteadyTick:
    """The compiled tick of ``emulator`` through ``link`` (see the module docstring);
    build it with :meth:`for_emulator`, which returns None where it never applies.

    Attributes:
        ticks: ticks run compiled.
        silent: of those, ticks that heard no setpoint (the drives ran on the one they
            hold, as the Python tick runs them).
        queued: of those, ticks that took more than one setpoint queued in the socket.
        declined: ticks that read a datagram and handed it to the Python path, by
            ``DECLINED_*`` code.
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
        # the call's arguments; the datagrams' count (index 1), the row and the tick's
        # start (self._j, + 1) are written per tick
        head = [link.bufs, -1, link.sp_ints, link.axis_ints, link.sp_floats, link.link,
                link.fb_ints, link.fb_axis_ints, link.fb_floats, link.out,
                *(per_axis if group else (a[0] for a in per_axis)), emulator.recorder.common]
        self._j = len(head)
        self.cycles = emulator.timing.cycles_per_tick
        self._args = head + [-1, 0, self.cycles, np.zeros((len(drives), snap_width)),
                             np.zeros((len(drives), 3 + C.N_IST), np.int64)]
        self._call = steady_tick_group if group else steady_tick
        self._faults_written = False
        # fb_ints echo the setpoint the drives hold (else the Python path's records do)
        self._holding = False
        self.ticks = self.silent = self.queued = 0
        self.declined = {DECLINED_FRAME: 0, DECLINED_SEQUENCE: 0, DECLINED_CYCLE: 0}
        self.dirty = False
        # compiled (or loaded from numba's cache) now, before any clock starts: a negative
        # length is declined at once and changes nothing
        self._call(*self._args)

    @classmethod
    def for_emulator(cls, emulator) -> "SteadyTick | None":
        """The compiled tick of an emulator that can take one: at most
        :data:`~io_adapters.codec_compiled.MAX_AXES` axes, a UDP device endpoint on the
        msgpack wire refusing what its drives refuse, no SYNC, every drive's compiled path;
        else None."""
        ep = emulator.endpoint
        drives = emulator.drives.drives
        if (len(drives) > K.MAX_AXES or type(ep) is not UdpEndpoint
                or ep.wire.name != "msgpack"
                or emulator.sync_lock is not None or any(d.compiled is None for d in drives)
                or ep.setpoint_bounds != tuple(d.setpoint_bounds() for d in drives)):
            return None
        return cls(emulator, SteadyLink(ep, len(drives)))

    def tick(self, k: int, t_ns: int) -> int | None:
        """Run tick ``k``, started at ``t_ns`` (monotonic ns), compiled if it may: the
        setpoints heard (1, or 0 in a silent tick); None: nothing changed, the Python
        path runs it (a datagram read is back in the endpoint)."""
        em = self.emulator
        for d, path, inj in zip(self.drives, self.paths, em.injectors):
            if (not path.active or d.link_causes or d.faults.latched or inj.busy
                    or d.params.generation != path._generation):
                return self._python()
        watchdog = em.watchdog
        if watchdog.tripped:
            return self._python()
        link = self.link
        n = link.receive()
        if n < 0:
            return self._python()
        if n == 0 and not watchdog.may_stay_silent():
            link.decline()  # the Python path's receive goes on within the same budget
            return self._python()
        if not self._holding:  # the answer echoes the setpoint the Python path took last
            f, ep = link.fb_ints, em.endpoint
            f[K.F_SEQ], f[K.F_SP_T_NS], f[K.F_SP_RX_NS] = em._sp.seq, ep._sp_t_ns, ep._sp_rx_ns
        if not self._faults_written:  # 603Fh changes in the Python path's ticks only
            for a, d in enumerate(self.drives):
                link.fb_axis_ints[a, K.A_FAULT] = d.fault
            self._faults_written = True
        args, j = self._args, self._j
        args[1], args[j], args[j + 1] = n, em.recorder.steady_row(), t_ns
        result = self._call(*args)
        if result < 0:
            self.declined[result] += 1
            link.decline()
            return self._python()
        self.ticks += 1
        self.dirty = self._holding = True
        for d, path in zip(self.drives, self.paths):
            path.cycles += self.cycles
            d.tick += self.cycles
        if n:
            watchdog.heard_steady()
            self.queued += link.take() > 0
        else:
            watchdog.silent_steady()
            link.idle()
            self.silent += 1
        try:
            link.send(result)
        except AdapterError as e:
            em._adapter_error("send", e)
        if result == UNENCODED:
            self._answer_in_python(args[j])
        return 1 if n else 0

    def _python(self) -> None:
        """The Python path runs the tick: it writes 603Fh and answers with its own
        records, which the next compiled tick cannot echo."""
        self._faults_written = self._holding = False

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
