"""How the controller's loop and the emulator's meet: alignment, and lock-step timing.

The emulator and ``hil controller`` run separate loops at the same period on one clock
grid each.  :func:`align` places the controller's ticks between the drive's, so that each
setpoint reaches the drive before its next cycle and each feedback comes back before the
controller's next tick: then controller tick k reads drive cycle k-1 and its setpoint
drives cycle k, exactly as in the lock-step simulation (:class:`hil.sim.LockStep`).
:func:`in_step` says, tick by tick, whether that held (a late tick on either side, a VM
pause, a lost frame break it), and :func:`settled_rows` which servo-trace rows are far
enough from any break to match the lock-step simulation.

A link whose master produces SYNC (``can://``, CANopen CiA 402: the controller endpoint
has ``sync_producer``) works the other way round, as a CANopen network does: the drive
keeps its own cycle (the PWM period) and takes the master's setpoint once per SYNC, so the
emulator moves its ticks (:class:`SyncLock`, on a :class:`ShiftableClock`) to put each
SYNC :data:`SYNC_PHASE` of a tick before the tick that takes it, as a drive synchronises
its control cycle to SYNC; and :func:`align` only sends SYNC on the controller's period
until the drive answers and has locked.  The drive answers SYNC k with the TPDOs of the
newest tick before it, whose setpoint came with SYNC k-1, so a controller that sends SYNC
every tick (``hil controller``) reads at tick k the drive's tick k-2: one tick more than
lock-step timing (the endpoint's ``feedback_delay_ticks``; :class:`hil.sim.LockStep`
models it with the same option).  The drive's clock is not on that wire (``drive_clock``
False): :func:`in_step` then checks the lag alone.
"""

import statistics
import time
from dataclasses import dataclass

import numpy as np

from hil.cia402 import DISABLE_VOLTAGE
from hil.rt.clock import MonotonicClock
from io_adapters import Endpoint, Feedback, Setpoint

#: feedbacks the alignment waits for
ALIGN_SAMPLES = 64
#: how long the alignment waits for an answer before sending again, s
RESEND_S = 0.05
#: the first aligned tick comes at least this long after the alignment: room for what
#: runs before the loop's first wait (its arrays reset, the counters read), so that tick
#: 0 is on time and on the aligned phase
START_MARGIN_NS = 10_000_000
#: a controller tick's own work before its setpoint leaves (ctrl.tick and the feedback
#: poll: 6-15 µs measured), added to the measured send time
TICK_ALLOWANCE_NS = 15_000
#: stamps of two processes on one machine (one clock) differ by less than this
SHARED_CLOCK_MAX_NS = 10_000_000
#: a pause's effect on the following error has decayed after this long: the position
#: loop's time constant 1/K_v is 30 ms on the Arrow 500 X (e^-6.7 after 0.2 s)
SETTLE_WINDOW_S = 0.2
#: the same over a link with feedback delayed by a tick more (``can://``): the speed loop
#: has less phase margin and its ~150 Hz mode decays more slowly.  A one-tick 28 A kick
#: in the lock-step simulation of the Arrow 500 X at 2 kHz leaves more than 1 µm of
#: following error for 0.23-0.47 s with the delay (0.08-0.14 s without; the longest at
#: standstill, where the stiction holds the offset)
DELAYED_SETTLE_WINDOW_S = 0.5
#: runs of at most this many ticks out of step are glitches: a setpoint that missed its
#: cycle (the drive holds the previous one a cycle longer) or a feedback that missed its
#: tick (the controller extrapolates over it).  Measured on the Arrow 500 X at 2 kHz:
#: they move the following error by less than 2 µm, so only their own ticks count out.
GLITCH_TICKS = 2
U32 = 0xFFFFFFFF
#: SYNC-locked drive: the tick that takes a SYNC comes this fraction of a tick after the
#: SYNC is latched, and that tick, when its SYNC is not latched yet, waits up to SYNC_WAIT
#: of a tick for it.  The SYNC must be latched before the tick's cycle (early side: the
#: master's lateness, the transport's and the receive thread's jitter: SYNC_PHASE +
#: SYNC_WAIT) and the tick before must have written its feedback when the SYNC comes
#: (late side: the emulator's lateness plus its compute, ~0.1 ms at 2 kHz: 1 - SYNC_PHASE
#: less that).  At 2 kHz: 0.32 ms early, about 0.25 ms late.
SYNC_PHASE = 0.3
SYNC_WAIT = 0.35
#: SYNCs whose median phase makes one correction of the drive's ticks
SYNC_LOCK_SAMPLES = 16
#: corrections below this fraction of a period are left out (jitter, not drift)
SYNC_DEADBAND = 0.05
#: once locked, one correction moves the ticks by this fraction of a period at most
#: (the samples after a pause can mislead; the first correction after SYNC (re)starts
#: is made in full)
SYNC_MAX_STEP = 0.1
#: a SYNC older than this many SYNC intervals at a tick means SYNC stopped: the lock
#: restarts
SYNC_LOST_INTERVALS = 4
#: ticks the controller sends SYNC on its period before its loop starts (and at least
#: until ALIGN_SAMPLES answers came): time for the drive to lock, a few corrections
SYNC_ALIGN_TICKS = 8 * SYNC_LOCK_SAMPLES


class DriveNotAnswering(RuntimeError):
    """No feedback came back from the adapter within the connect timeout."""


@dataclass(frozen=True)
class Alignment:
    """Where this loop's ticks sit relative to the drive's.

    With the drive's tick at E, its feedback sent ``hold`` later and arriving after the
    transport time d, and this loop's setpoint sent ``compute`` after its tick C and
    arriving d later, the feedback is in time for C when C > E + hold + d, and the setpoint
    for the drive's next tick when C + compute + d < E + T.  Equal margins on both sides:
    C = E + (T + hold - compute) / 2, whatever d is.  ``hold`` is a difference on the
    drive's clock, always known.  E itself is known when the two processes share a clock
    (one machine; recognised by every stamp being causal): the drive sends the start of the
    tick that produced each feedback (``tick_ns``; a drive that does not is taken to read
    its setpoint at the start of its tick, so the arrival stamp it echoes, ``sp_rx_ns``,
    stands in).  Otherwise E is estimated from the feedback arrivals as if d were 0.

    Attributes:
        reference_ns: a drive tick (shared clock) or a feedback arrival, on this machine's
            monotonic clock, ns.
        offset_ns: this loop's ticks fall this long after ``reference_ns``, modulo T.
        hold_ns: median time from the drive's tick to its feedback leaving.
        compute_ns: this loop's time from its tick to its setpoint leaving (estimate).
        one_way_ns: median feedback transport, or None when the clocks are not shared.
        samples: feedbacks measured.
        by_sync: the drive locks its cycle to this loop's SYNC (:func:`align_by_sync`):
            ``reference_ns`` is the first SYNC sent, the offset 0, ``hold_ns`` the
            time between two SYNCs (the drive holds its answer until the next).
    """
    reference_ns: int
    offset_ns: int
    hold_ns: int
    compute_ns: int
    one_way_ns: int | None
    samples: int
    by_sync: bool = False

    def first_deadline(self, period_ns: int, not_before_ns: int) -> int:
        """The first aligned instant at or after ``not_before_ns``."""
        phase = self.reference_ns + self.offset_ns
        return phase + -(-(not_before_ns - phase) // period_ns) * period_ns

    def as_dict(self) -> dict:
        """In µs, JSON-ready."""
        return {"shared_clock": self.one_way_ns is not None, "by_sync": self.by_sync,
                "offset_us": self.offset_ns / 1e3, "hold_us": self.hold_ns / 1e3,
                "compute_us": self.compute_ns / 1e3, "samples": self.samples,
                "one_way_us": None if self.one_way_ns is None else self.one_way_ns / 1e3}


def _median(values) -> int:
    return round(statistics.median(values))


def _phase(times: list[int], period_ns: int) -> int:
    """A time with the median phase of ``times`` modulo ``period_ns`` (near times[0])."""
    half = period_ns // 2
    return times[0] + _median((t - times[0] + half) % period_ns - half for t in times)


def align(ep: Endpoint, sp: Setpoint, fb: Feedback, period_ns: int,
          timeout_s: float) -> Alignment:
    """Exchange disable-voltage setpoints for feedback until :data:`ALIGN_SAMPLES` came
    back (see :class:`Alignment`); raises :class:`DriveNotAnswering` after ``timeout_s``
    without them.  An endpoint with ``sync_producer`` goes to :func:`align_by_sync`."""
    if getattr(ep, "sync_producer", False):
        return align_by_sync(ep, sp, fb, period_ns, timeout_s)
    deadline = time.monotonic() + timeout_s
    arrivals, ticks, holds, downs, computes, causal = [], [], [], [], [], True
    sp.controlword = DISABLE_VOLTAGE.value
    ep.send_setpoint(sp)
    while len(arrivals) < ALIGN_SAMPLES:
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            raise DriveNotAnswering(f"no feedback from {ep!r} within {timeout_s:g} s "
                                    f"({len(arrivals)} of {ALIGN_SAMPLES}); is `hil run` "
                                    "serving this adapter?")
        got = ep.recv_feedback(fb, min(remaining, RESEND_S))
        sp.seq = (sp.seq + 1) & U32
        ep.send_setpoint(sp)
        if got:
            arrivals.append(fb.rx_ns)
            tick = fb.tick_ns or fb.sp_rx_ns
            ticks.append(tick)
            holds.append(fb.t_ns - tick)
            downs.append(fb.rx_ns - fb.t_ns)
            computes.append(time.monotonic_ns() - fb.rx_ns + TICK_ALLOWANCE_NS)
            causal = (causal and 0 < fb.rx_ns - fb.t_ns < SHARED_CLOCK_MAX_NS
                      and 0 < fb.sp_rx_ns - fb.sp_t_ns < SHARED_CLOCK_MAX_NS)
    hold, compute = _median(holds), _median(computes)
    if causal:
        reference, one_way = _phase(ticks, period_ns), _median(downs)
        offset = (period_ns + hold - compute) // 2
    else:
        reference, one_way = _phase(arrivals, period_ns), None
        offset = (period_ns - hold - compute) // 2
    return Alignment(reference, offset % period_ns, hold, compute, one_way, len(arrivals))


def align_by_sync(ep: Endpoint, sp: Setpoint, fb: Feedback, period_ns: int,
                  timeout_s: float) -> Alignment:
    """For a master that produces SYNC: the drive locks its cycle to our SYNC
    (:class:`SyncLock`), so there is no phase to find.  Send disable-voltage setpoints,
    each with its SYNC, on a grid of ``period_ns`` for :data:`SYNC_ALIGN_TICKS` ticks and
    until :data:`ALIGN_SAMPLES` answers came; the loop then continues on the same grid
    (offset 0), so the drive's lock holds.  Raises :class:`DriveNotAnswering` after
    ``timeout_s`` without them."""
    clock = MonotonicClock.for_period(period_ns)
    deadline = time.monotonic() + timeout_s
    sp.controlword = DISABLE_VOLTAGE.value
    holds, computes, samples, k = [], [], 0, 0
    reference = clock.now_ns() + period_ns
    while k < SYNC_ALIGN_TICKS or samples < ALIGN_SAMPLES:
        if time.monotonic() > deadline:
            raise DriveNotAnswering(f"no feedback from {ep!r} within {timeout_s:g} s "
                                    f"({samples} of {ALIGN_SAMPLES}); is `hil run` "
                                    "serving this adapter?")
        woke = clock.sleep_until(reference + k * period_ns)
        if ep.recv_feedback(fb, 0.0):
            samples += 1
            holds.append(fb.t_ns - fb.sp_rx_ns)
        sp.seq = (sp.seq + 1) & U32
        ep.send_setpoint(sp)
        computes.append(time.monotonic_ns() - woke + TICK_ALLOWANCE_NS)
        k += 1
    return Alignment(reference, 0, _median(holds), _median(computes), None, samples,
                     by_sync=True)


def in_step(cols: dict, period_s: float, delay_ticks: int = 0,
            drive_clock: bool = True) -> np.ndarray:
    """Per recorded tick: the exchange was the lock-step simulation's -- the feedback read
    answers the setpoint sent ``delay_ticks`` ticks before the last one (lag
    ``delay_ticks``; 0: the tick before, lock-step timing) and, with ``drive_clock``,
    comes from the drive cycle one period after the one read the tick before (its time
    stamp advanced by one period) and from the cycle the run's ticks usually read: the
    drive's time stamp less the tick's time (to a thousandth of a period) is one the
    run's ticks had for :data:`SETTLE_WINDOW_S` in all (or as often as the commonest, in
    a shorter run).  So ticks that went on reading a cycle ahead after a feedback came a
    cycle early, each advancing by one period, are out of step until a repeat takes them
    back (seen: three ticks, the middle one with lag 0); a lasting change of offset (the
    drive skipped ticks after a stall) counts out only where it happens.  Without the
    drive's clock on the wire (``can://``) the lag alone says it: a tick without new
    feedback has a larger one."""
    ok = cols["lag_ticks"] == delay_ticks
    if drive_clock and ok.size:
        fb_time = cols["fb_time_s"]
        advance = np.diff(fb_time, prepend=fb_time[:1] - period_s)
        ok &= np.abs(advance - period_s) < 1e-3 * period_s
        offset = np.round((fb_time - cols["tick"] * period_s) / period_s * 1e3)
        _, which, count = np.unique(offset, return_inverse=True, return_counts=True)
        ok &= count[which] >= min(round(SETTLE_WINDOW_S / period_s), count.max())
    return ok


def settled_rows(cols: dict, every: int, period_s: float, delay_ticks: int = 0,
                 drive_clock: bool = True, glitch_window_s: float = 0.0) -> np.ndarray:
    """Per servo-trace row (ticks that are multiples of ``every``): True when no timing
    fault's effect remains in it.  A fault is a run of ticks not :func:`in_step` (with
    ``delay_ticks`` and ``drive_clock``); its effect lasts ``glitch_window_s`` after a run
    of at most :data:`GLITCH_TICKS` ticks (a late tick, one missing feedback: the
    controller extrapolates over it; by default no longer than its own ticks, which holds
    where a tick is long against the loops' settling: a caller at 8 kHz gives the speed
    loop's few ms), and :data:`SETTLE_WINDOW_S` after a longer one (a process or the VM
    paused); :data:`DELAYED_SETTLE_WINDOW_S` with ``delay_ticks``."""
    bad = np.flatnonzero(~in_step(cols, period_s, delay_ticks, drive_clock))
    settle_s = SETTLE_WINDOW_S if delay_ticks == 0 else DELAYED_SETTLE_WINDOW_S
    n = len(cols["tick"])
    touched = np.zeros(n, dtype=bool)
    if bad.size:
        split = np.flatnonzero(np.diff(bad) > 1)
        for first, last in zip(bad[np.r_[0, split + 1]], bad[np.r_[split, bad.size - 1]]):
            window = glitch_window_s if last - first < GLITCH_TICKS else settle_s
            touched[first:last + 1 + round(window / period_s)] = True
    return ~touched[np.flatnonzero(cols["tick"] % every == 0)]


class ShiftableClock:
    """A clock whose deadlines can be moved: ``sleep_until(d)`` waits until
    ``d + offset_ns`` on ``base`` and reports times less the offset, so a
    :class:`~hil.rt.loop.RealTimeLoop` on it measures lateness against the moved
    deadlines.  :meth:`shift` takes effect at the next deadline (not in the middle of a
    tick's measurement).

    Attributes:
        offset_ns: how far the deadlines have been moved (later when positive).
        deadline_ns: the last deadline slept to, on the base clock.
    """

    def __init__(self, base):
        self.base = base
        self.offset_ns = 0
        self.deadline_ns = 0
        self._pending_ns = 0

    def now_ns(self) -> int:
        return self.base.now_ns() - self.offset_ns

    def sleep_until(self, deadline_ns: int) -> int:
        if self._pending_ns:
            self.offset_ns += self._pending_ns
            self._pending_ns = 0
        self.deadline_ns = deadline_ns + self.offset_ns
        return self.base.sleep_until(self.deadline_ns) - self.offset_ns

    def shift(self, ns: int) -> None:
        """Move the deadlines from the next one on by ``ns`` (earlier when negative)."""
        self._pending_ns += int(ns)


class SyncLock:
    """The emulator's ticks locked to the master's SYNC (``can://``), as a CiA 402 drive
    synchronises its control cycle to SYNC: the loop's ticks are moved, on its
    :class:`ShiftableClock`, so that the tick that takes a SYNC's setpoint comes
    :data:`SYNC_PHASE` of a tick after the SYNC was latched, whatever the communication
    cycle (a SYNC every tick, or every few ticks: the drive interpolates in between).
    The tick before a SYNC then wrote the feedback the SYNC sends.  While locked, the tick
    due to take the next SYNC (the mean SYNC interval in ticks after the one that took the
    last) waits up to :data:`SYNC_WAIT` of a tick for it (:attr:`wait_s`, the timeout of
    that tick's receive) rather than run on the setpoint before, and so does every tick
    after it until the SYNC comes (or the lock is lost); the ticks before it wait for
    nothing.  With a SYNC every tick, every tick may wait.

    Call :meth:`update` once per tick, after the receive, with the endpoint's
    ``last_sync_ns``.  Each tick that sees a new SYNC measures its phase (its deadline
    less the SYNC's latch time; one outside -1/2 to 1 tick is a late tick or a pause, not
    the phase, and is left out); every :data:`SYNC_LOCK_SAMPLES` of them, the ticks move by
    the median's distance from the target, taken the short way round the tick, unless it
    is within :data:`SYNC_DEADBAND`, and by :data:`SYNC_MAX_STEP` at most once locked.
    Both loops run on one clock, so after the first correction the phase only holds; a
    SYNC older than :data:`SYNC_LOST_INTERVALS` SYNC intervals at a tick starts the lock
    afresh.

    Attributes:
        moves: corrections made.
        phase_ns: the last median phase measured (None before the first).
        interval_ns: the last interval between two SYNCs (0 before the second).
        wait_s: how long the next tick's receive may wait for SYNC, s.
    """

    def __init__(self, clock: ShiftableClock, period_ns: int):
        self.clock = clock
        self.period_ns = period_ns
        self.target_ns = round(SYNC_PHASE * period_ns)
        self.deadband_ns = round(SYNC_DEADBAND * period_ns)
        self.max_step_ns = round(SYNC_MAX_STEP * period_ns)
        self._locked = False
        self._phases = [0] * SYNC_LOCK_SAMPLES
        self._n = 0
        self._last_sync_ns = 0
        self.moves = 0
        self.phase_ns: int | None = None
        self.interval_ns = 0
        self._mean_ns = 0  # the SYNC interval averaged over about SYNC_LOCK_SAMPLES
        self._to_next = 0  # ticks from the next one to the one due to take the next SYNC
        self.wait_s = 0.0
        self._wait_s = SYNC_WAIT * period_ns * 1e-9

    def update(self, last_sync_ns: int) -> None:
        """This tick's view of the newest SYNC latch time (0: none yet)."""
        if self._measure(last_sync_ns):  # the SYNC after this one is due so many ticks on
            self._to_next = max(1, round(self._mean_ns / self.period_ns))
        self._to_next -= 1
        self.wait_s = self._wait_s if self._locked and self._to_next <= 0 else 0.0

    def _measure(self, last_sync_ns: int) -> bool:
        """Take this tick's view of the newest SYNC; True when it is a new one."""
        phase = self.clock.deadline_ns - last_sync_ns
        period = self.period_ns
        if last_sync_ns == self._last_sync_ns:
            if phase > SYNC_LOST_INTERVALS * max(self.interval_ns, period):
                self._n = 0
                self._locked = False
            return False
        if self._last_sync_ns:
            self.interval_ns = last_sync_ns - self._last_sync_ns
            self._mean_ns = round(self.interval_ns if not self._mean_ns else
                                  self._mean_ns + (self.interval_ns - self._mean_ns)
                                  / SYNC_LOCK_SAMPLES)
        self._last_sync_ns = last_sync_ns
        if not -period // 2 < phase < period:
            return True
        self._phases[self._n] = phase
        self._n += 1
        if self._n < SYNC_LOCK_SAMPLES:
            return True
        self._n = 0
        self.phase_ns = median = sorted(self._phases)[SYNC_LOCK_SAMPLES // 2]
        half = period // 2
        error = (median - self.target_ns + half) % period - half
        if self._locked:
            error = max(-self.max_step_ns, min(error, self.max_step_ns))
        self._locked = True
        if abs(error) > self.deadband_ns:
            self.clock.shift(-error)
            self.moves += 1
        return True

    def as_dict(self) -> dict:
        """In µs, JSON-ready."""
        return {"moves": self.moves, "target_us": self.target_ns / 1e3,
                "phase_us": None if self.phase_ns is None else self.phase_ns / 1e3,
                "sync_interval_us": self.interval_ns / 1e3,
                "offset_us": self.clock.offset_ns / 1e3}
