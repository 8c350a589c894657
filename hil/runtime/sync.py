"""How the controller's loop and the emulator's meet: alignment, and lock-step timing.

The emulator and ``hil controller`` run separate loops at the same period on one clock
grid each.  :func:`align` places the controller's ticks between the drive's, so that each
setpoint reaches the drive before its next cycle and each feedback comes back before the
controller's next tick: then controller tick k reads drive cycle k-1 and its setpoint
drives cycle k, exactly as in the lock-step simulation (:class:`hil.sim.LockStep`).
:func:`in_step` says, tick by tick, whether that held (a late tick on either side, a VM
pause, a lost frame break it), and :func:`settled_rows` which servo-trace rows are far
enough from any break to match the lock-step simulation.
"""

import statistics
import time
from dataclasses import dataclass

import numpy as np

from hil.cia402 import DISABLE_VOLTAGE
from io_adapters import Endpoint, Feedback, Setpoint

#: feedbacks the alignment waits for
ALIGN_SAMPLES = 64
#: how long the alignment waits for an answer before sending again, s
RESEND_S = 0.05
#: a controller tick's own work before its setpoint leaves (ctrl.tick and the feedback
#: poll: 6-15 µs measured), added to the measured send time
TICK_ALLOWANCE_NS = 15_000
#: stamps of two processes on one machine (one clock) differ by less than this
SHARED_CLOCK_MAX_NS = 10_000_000
#: a pause's effect on the following error has decayed after this long: the position
#: loop's time constant 1/K_v is 30 ms on the Arrow 500 X (e^-6.7 after 0.2 s)
SETTLE_WINDOW_S = 0.2
#: runs of at most this many ticks out of step are glitches: a setpoint that missed its
#: cycle (the drive holds the previous one a cycle longer) or a feedback that missed its
#: tick (the controller extrapolates over it).  Measured on the Arrow 500 X at 2 kHz:
#: they move the following error by less than 2 µm, so only their own ticks count out.
GLITCH_TICKS = 2
U32 = 0xFFFFFFFF


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
    (one machine; recognised by every stamp being causal): the drive reads its setpoint at
    the start of its tick, so the setpoint arrival stamps it echoes (``sp_rx_ns``) carry
    its phase.  Otherwise E is estimated from the feedback arrivals as if d were 0.

    Attributes:
        reference_ns: a drive tick (shared clock) or a feedback arrival, on this machine's
            monotonic clock, ns.
        offset_ns: this loop's ticks fall this long after ``reference_ns``, modulo T.
        hold_ns: median time the drive took from reading a setpoint to sending feedback.
        compute_ns: this loop's time from its tick to its setpoint leaving (estimate).
        one_way_ns: median feedback transport, or None when the clocks are not shared.
        samples: feedbacks measured.
    """
    reference_ns: int
    offset_ns: int
    hold_ns: int
    compute_ns: int
    one_way_ns: int | None
    samples: int

    def first_deadline(self, period_ns: int, not_before_ns: int) -> int:
        """The first aligned instant at or after ``not_before_ns``."""
        phase = self.reference_ns + self.offset_ns
        return phase + -(-(not_before_ns - phase) // period_ns) * period_ns

    def as_dict(self) -> dict:
        """In µs, JSON-ready."""
        return {"shared_clock": self.one_way_ns is not None,
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
    without them."""
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
            ticks.append(fb.sp_rx_ns)
            holds.append(fb.t_ns - fb.sp_rx_ns)
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


def in_step(cols: dict, period_s: float) -> np.ndarray:
    """Per recorded tick: the exchange was the lock-step simulation's -- the feedback read
    answers the setpoint of the tick before (lag 0) and comes from the drive cycle one
    period after the one read the tick before (its time stamp advanced by one period)."""
    advance = np.diff(cols["fb_time_s"], prepend=cols["fb_time_s"][:1] - period_s)
    return (cols["lag_ticks"] == 0) & (np.abs(advance - period_s) < 1e-3 * period_s)


def settled_rows(cols: dict, every: int, period_s: float) -> np.ndarray:
    """Per servo-trace row (ticks that are multiples of ``every``): True when no timing
    fault's effect remains in it.  A fault is a run of ticks not :func:`in_step`; its
    effect lasts :data:`GLITCH_WINDOW_S` after a run of at most :data:`GLITCH_TICKS` ticks
    (a late tick, one missing feedback: the controller extrapolates over it), and
    :data:`SETTLE_WINDOW_S` after a longer one (a process or the VM paused)."""
    bad = np.flatnonzero(~in_step(cols, period_s))
    n = len(cols["tick"])
    touched = np.zeros(n, dtype=bool)
    if bad.size:
        split = np.flatnonzero(np.diff(bad) > 1)
        for first, last in zip(bad[np.r_[0, split + 1]], bad[np.r_[split, bad.size - 1]]):
            window = 0.0 if last - first < GLITCH_TICKS else SETTLE_WINDOW_S
            touched[first:last + 1 + round(window / period_s)] = True
    return ~touched[np.flatnonzero(cols["tick"] % every == 0)]
