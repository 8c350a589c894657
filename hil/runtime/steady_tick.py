"""The emulator's tick in one compiled call, from the setpoint's bytes to the answer's
(issue 12 part 6: "Python touches only the socket").

In steady state -- one axis, one drive cycle per tick, a UDP link whose controller is
pinned, the drive's compiled path holding its state (:mod:`hil.drive.compiled_path`:
OPERATION ENABLED in CSP, CSV or CST, nothing to react to), the watchdog content, no
injection under way -- a tick is: read the datagram (Python: the socket), then one call
of :func:`steady_tick` that decodes the setpoint (:func:`io_adapters.codec_compiled.
decode_setpoint`), checks its session and frame number, runs the drive cycle
(:func:`hil.drive.compiled.steady_cycle`, which writes the axis's recording row), stamps
and encodes the feedback (:func:`io_adapters.codec_compiled.encode_feedback`) and writes
the row's common part; then (Python) the endpoint's books and the send
(:class:`io_adapters.udp_steady.SteadyLink`), the watchdog's "heard", the drive's
counters.

Anything outside that case is declined *before* any state has changed: the datagram goes
back to the endpoint and :meth:`hil.runtime.emulator.Emulator.step`'s Python path runs
the tick as it always has (the endpoint counts and judges the datagram, the drive's
Python path reacts), so there is one owner of every decision and the compiled tick adds
nothing but speed.  tests/test_tick_steady.py runs the same datagrams through an emulator
with and one without it and compares every feedback byte, recording row and counter.

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
from io_adapters.udp import UdpEndpoint
from io_adapters.udp_steady import L_PEER_FRAME, L_PEER_SESSION, L_RX_NS, SteadyLink

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


@njit(cache=True, _nrt=False)
def steady_tick(buf, n, sp_ints, sp_floats, link, fb_ints, out, prm, fst, ist, spf, spi,
                saved, fbf, p, s, inp, plant_out, ring_f, ring_i, common, j, tick_ns,
                scratch_f, scratch_i):
    """One tick (see the module docstring).  ``buf[:n]``: the datagram; ``sp_ints``,
    ``sp_floats``, ``link``, ``fb_ints``, ``out``: :class:`~io_adapters.udp_steady.
    SteadyLink`'s arrays; ``prm`` .. ``fbf``: the drive's compiled path's
    (:class:`~hil.drive.compiled_path.CompiledPath`); ``p``, ``s``, ``inp``,
    ``plant_out``: the plant's; ``ring_f``, ``ring_i``: this axis's planes of the
    recording's ring, ``common`` its common block, ``j`` the row's column (-1: not
    recorded); ``tick_ns``: the tick's start (monotonic ns); ``scratch_f`` float64[7+],
    ``scratch_i`` int64[5+].  Returns the answer's length, or :data:`UNENCODED` (the tick
    ran), or a ``DECLINED_*`` code (nothing changed)."""
    if not K.decode_setpoint(buf, n, sp_ints, sp_floats):
        return DECLINED_FRAME
    if sp_ints[K.I_SESSION] != link[L_PEER_SESSION]:
        return DECLINED_SEQUENCE
    ahead = (sp_ints[K.I_FRAME] - link[L_PEER_FRAME]) & U32
    if ahead == 0 or ahead > U32 // 2:  # a repeat or an older frame: counted in Python
        return DECLINED_SEQUENCE
    for k in range(C.N_SPF):  # the setpoint applied so far, back if the cycle declines
        scratch_f[k] = spf[k]
    for k in range(3):
        scratch_i[k] = spi[k]
    for k in range(7):
        spf[_SPF_SLOT[k]] = sp_floats[k]
    spi[C.I_SEQ], spi[C.I_CW] = sp_ints[K.I_SEQ], sp_ints[K.I_CONTROLWORD]
    spi[C.I_MODE] = sp_ints[K.I_MODE]
    ist[C.J_ROW] = j
    status = C.steady_cycle(prm, fst, ist, spf, spi, p, s, inp, plant_out, saved, fbf,
                            ring_f, ring_i)
    ist[C.J_ROW] = -1
    if status != C.DONE:
        for k in range(C.N_SPF):
            spf[k] = scratch_f[k]
        for k in range(3):
            spi[k] = scratch_i[k]
        return DECLINED_CYCLE
    fb_ints[K.F_SEQ] = spi[C.I_SEQ]
    fb_ints[K.F_STATUSWORD] = ist[C.J_STATUSWORD]
    fb_ints[K.F_SP_T_NS] = sp_ints[K.I_T_NS]
    fb_ints[K.F_SP_RX_NS] = link[L_RX_NS]
    fb_ints[K.F_TICK_NS] = tick_ns
    fb_ints[K.F_T_NS] = _monotonic_ns(scratch_i[3:5])
    length = K.encode_feedback(out, fb_ints, fbf)
    if j >= 0:
        common[R_TICK_START, j] = tick_ns
        common[R_SP_T_NS, j] = sp_ints[K.I_T_NS]
        common[R_SP_RX_NS, j] = link[L_RX_NS]
        common[R_FB_T_NS, j] = fb_ints[K.F_T_NS]
        common[R_SP_NEW, j] = 1
        common[R_SP_SEQ, j] = spi[C.I_SEQ]
        common[R_SP_REFUSED, j] = 0
    return length if length > 0 else UNENCODED


class SteadyTick:
    """The compiled tick of ``emulator`` through ``link`` (see the module docstring);
    build it with :meth:`for_emulator`, which returns None where it never applies.

    Attributes:
        ticks: ticks run compiled.
        declined: ticks that read a datagram and handed it to the Python path, by
            ``DECLINED_*`` code.
        dirty: the emulator's Setpoint and Feedback records are behind the arrays
            (:meth:`settle`).
    """

    def __init__(self, emulator, link: SteadyLink):
        self.emulator = emulator
        self.link = link
        self.drive = drive = emulator.drives.drives[0]
        self.path = path = drive.compiled
        plant = drive.plant
        self._arrays = (link.buf, 0, link.sp_ints, link.sp_floats, link.link, link.fb_ints,
                        link.out, path.prm, path.fst, path.ist, path.spf, path.spi,
                        path.saved, path.fbf, plant.params, plant.state, plant.inp,
                        plant.out, path.ring_f, path.ring_i, emulator.recorder.common)
        self._scratch_f = np.zeros(C.N_SPF)
        self._scratch_i = np.zeros(5, np.int64)
        self.ticks = 0
        self.declined = {DECLINED_FRAME: 0, DECLINED_SEQUENCE: 0, DECLINED_CYCLE: 0}
        self.dirty = False
        # compiled (or loaded from numba's cache) now, before any clock starts: a
        # zero-length datagram is declined at once and changes nothing
        steady_tick(*self._arrays, -1, 0, self._scratch_f, self._scratch_i)

    @classmethod
    def for_emulator(cls, emulator) -> "SteadyTick | None":
        """The compiled tick of an emulator that can take one: one axis, one drive cycle
        per tick, a UDP device endpoint refusing what its drive refuses, no SYNC, the
        drive's compiled path; else None."""
        ep = emulator.endpoint
        drives = emulator.drives.drives
        if (len(drives) != 1 or emulator.timing.cycles_per_tick != 1
                or type(ep) is not UdpEndpoint or emulator.sync_lock is not None
                or drives[0].compiled is None
                or ep.setpoint_bounds != (drives[0].setpoint_bounds(),)):
            return None
        return cls(emulator, SteadyLink(ep))

    def tick(self, k: int, t_ns: int) -> bool:
        """Run tick ``k``, started at ``t_ns`` (monotonic ns), compiled if it may; False:
        nothing changed, the Python path runs it (a datagram read is back in the
        endpoint)."""
        em, path, d = self.emulator, self.path, self.drive
        if (not path.active or d.link_causes or d.faults.latched or em.watchdog.tripped
                or d.params.generation != path._generation or em.injectors[0].busy):
            return False
        link = self.link
        n = link.receive()
        if not n:
            return False
        a = self._arrays
        link.fb_ints[K.F_FAULT] = d.fault
        j = em.recorder.steady_row()
        result = steady_tick(a[0], n, a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], a[10],
                             a[11], a[12], a[13], a[14], a[15], a[16], a[17], a[18], a[19],
                             a[20], j, t_ns, self._scratch_f, self._scratch_i)
        if result < 0:
            self.declined[result] += 1
            link.decline()
            return False
        self.ticks += 1
        self.dirty = True
        path.cycles += 1
        d.tick += 1
        em.watchdog.heard_steady()
        try:
            link.commit(result)
        except AdapterError as e:
            em._adapter_error("send", e)
        if result == UNENCODED:
            self._answer_in_python(j)
        return True

    def _answer_in_python(self, j: int) -> None:
        """The answer the compiled writer declined (a non-finite value), sent by the
        Python encoder as the Python path sends it."""
        self.settle()
        em = self.emulator
        try:
            em.endpoint.send_feedback(em._fb)
        except AdapterError as e:
            em._adapter_error("send", e)
        if j >= 0:
            em.recorder.common[R_FB_T_NS, j] = em._fb.t_ns

    def settle(self) -> None:
        """Write the emulator's Setpoint and Feedback records from the arrays (the last
        setpoint applied, the last answer), if compiled ticks ran since the last call."""
        if not self.dirty:
            return
        self.dirty = False
        sp, fb, path = self.emulator._sp, self.emulator._fb, self.path
        f = self.link.fb_ints.tolist()
        sp.seq, sp.controlword, sp.mode = path.spi.tolist()
        for name, value in zip(C.SP_FLOATS, path.spf.tolist()):
            setattr(sp, name, value)
        sp.t_ns, sp.rx_ns = f[K.F_SP_T_NS], f[K.F_SP_RX_NS]
        fb.seq, fb.statusword, fb.fault = f[K.F_SEQ], f[K.F_STATUSWORD], self.drive.fault
        for name, value in zip(K.FB_FLOAT_FIELDS, path.fbf.tolist()):
            setattr(fb, name, value)
        fb.sp_t_ns, fb.sp_rx_ns = f[K.F_SP_T_NS], f[K.F_SP_RX_NS]
        fb.t_ns, fb.tick_ns = f[K.F_T_NS], f[K.F_TICK_NS]
