"""Wake-up latency and lateness after the spin, each beside cyclictest of the same interval.

The loop's clock (:class:`hil.rt.clock.MonotonicClock`) sleeps until ``spin`` before each
deadline (:meth:`~hil.rt.clock.MonotonicClock.for_period`: 50 µs at 8 kHz and below) and
spins on the clock from there.  Two different things follow from one wake-up:

* **wake-up latency**: how late the sleep returned after the time it asked for (deadline -
  spin).  This is what cyclictest measures: its thread sleeps to an absolute time and
  reports how late it woke.
* **lateness after the spin**: wake - deadline, what the recording holds
  (``lateness_ns``): about 0 while the wake-up latency stays below the spin margin, and
  wake-up latency - spin beyond it.

The recording has only the second, so the loop's wake-up latency is known where the sleep
overshot the margin -- a lateness above :data:`OVERSHOOT_NS`: wake-up latency = spin +
lateness -- and is "at most spin" elsewhere: its percentiles are exact from the rank where
the lateness passes :data:`OVERSHOOT_NS` up, and reported as ``None`` ("<= spin") below.
(A preemption during the spin also makes a tick late; it is counted as a late wake-up,
which overstates the wake-up latency of that tick, never understates it.)  For cyclictest
the other way round: its lateness after the spin is ``max(0, latency - spin)`` per
wake-up, what a loop with this spin margin would have seen with cyclictest's wake-ups.
Both sides also give the share of wake-ups later than the spin margin.

Percentiles are nearest rank (:data:`hil.report.latency.PERCENTILE_DEFINITION`);
cyclictest's are :func:`hil.rt.cyclictest.parse_histogram`'s (whole µs, its overflows at
its maximum).
"""

import numpy as np

from hil.report.baseline import CyclictestBaseline
from hil.rt.clock import MonotonicClock
from hil.rt.loop import Percentiles

#: a lateness above this is a sleep that overshot the spin margin, ns (a clock read and
#: one pass of the spin loop take well under it)
OVERSHOOT_NS = 1_000
#: the percentiles reported (:class:`hil.rt.loop.Percentiles`'s keys)
KEYS = ("p50", "p99", "p999", "max")


def spin_ns(period_ns: int) -> int:
    """The spin margin of the loop's clock at ``period_ns`` (ns)."""
    return MonotonicClock.for_period(period_ns).spin_ns


def overshot(lateness_ns: np.ndarray) -> np.ndarray:
    """Which ticks' sleep overshot the spin margin (bool, shape of ``lateness_ns``): a
    lateness above :data:`OVERSHOOT_NS`; the others' wake-up latency is hidden by the spin."""
    return lateness_ns > OVERSHOOT_NS


def loop_wakeup_known_ns(lateness_ns: np.ndarray, period_ns: int) -> np.ndarray:
    """The loop's wake-up latencies that are known, ns: spin + lateness of the ticks whose
    sleep overshot the margin (:func:`overshot`), in their order; shape (k,), k <= n."""
    return lateness_ns[overshot(lateness_ns)] + spin_ns(period_ns)


def lateness_after_spin_us(latency_us, spin_us: float):
    """The lateness after a spin of ``spin_us`` that wake-ups ``latency_us`` late imply,
    µs: ``max(0, latency - spin)``, elementwise (a float or an array of any shape)."""
    return np.maximum(0.0, np.asarray(latency_us, dtype=float) - spin_us)


def loop_wakeup(lateness_ns: np.ndarray, period_ns: int) -> dict:
    """The loop's wake-up latency and lateness after the spin (µs; see the module
    docstring), from the lateness of every tick that ran.  Spin + lateness is monotone in
    the lateness, so its percentiles are those of the lateness plus the spin, where they
    are known."""
    if lateness_ns.size == 0:
        return {"samples": 0, "wakeup_us": dict.fromkeys(KEYS), "lateness_us":
                dict.fromkeys(KEYS), "beyond_spin": None}
    spin_us = spin_ns(period_ns) / 1e3
    lateness = Percentiles.of_ns_in_us(lateness_ns).as_dict()
    wakeup = {k: v + spin_us if v * 1e3 > OVERSHOOT_NS else None for k, v in lateness.items()}
    return {"samples": int(lateness_ns.size), "wakeup_us": wakeup, "lateness_us": lateness,
            "beyond_spin": float(overshot(lateness_ns).mean())}


def cyclictest_wakeup(base: CyclictestBaseline, period_ns: int) -> dict:
    """cyclictest's wake-up latency and the lateness after the spin it implies (µs):
    ``max(0, latency - spin)`` is monotone in the latency, so its percentiles are those of
    the latency less the spin."""
    spin_us = spin_ns(period_ns) / 1e3
    q = base.latency_us.as_dict()
    wakeup = {key: q[key] for key in KEYS}
    n = base.samples
    beyond = (int(base.counts[base.bins_us >= spin_us].sum()) + base.overflows) / n if n else None
    return {"interval_us": base.interval_us, "samples": n, "wakeup_us": wakeup,
            "lateness_us": {k: float(lateness_after_spin_us(v, spin_us))
                            for k, v in wakeup.items()},
            "beyond_spin": beyond}


def wakeup_report(lateness_ns: np.ndarray, period_ns: int,
                  cyclictest: CyclictestBaseline | None) -> dict:
    """``{"spin_us", "loop": loop_wakeup(...), "cyclictest": cyclictest_wakeup(...) or
    None}``."""
    return {"spin_us": spin_ns(period_ns) / 1e3, "loop": loop_wakeup(lateness_ns, period_ns),
            "cyclictest": None if cyclictest is None else cyclictest_wakeup(cyclictest,
                                                                            period_ns)}


def _cells(q: dict, none: str) -> str:
    """The percentiles of ``q``, ``none`` where one is None."""
    return "".join(f"{none:>9}" if q[k] is None else f"{q[k]:9.1f}" for k in KEYS)


def _share(x: float | None) -> str:
    return "       —" if x is None else f"{100 * x:7.3f} %"


def wakeup_rows(report: dict, note: str) -> list[str]:
    """The printed table of a latency report's ``wakeup`` (``note``: how cyclictest ran)."""
    w = report["wakeup"]
    spin, loop, cyc = w["spin_us"], w["loop"], w["cyclictest"]
    hidden = f"≤{spin:.0f}"
    rows = [("wake-up latency, loop", loop["wakeup_us"], hidden, loop["beyond_spin"]),
            ("lateness after the spin, loop", loop["lateness_us"], "—", None)]
    if cyc is not None:
        rows.insert(1, ("wake-up latency, cyclictest", cyc["wakeup_us"], "—",
                        cyc["beyond_spin"]))
        rows.append(("lateness after the spin, cyclictest", cyc["lateness_us"], "—", None))
    head = (f"{'timing, µs':<38}" + "".join(f"{name:>9}" for name in ("p50", "p99", "p99.9",
                                                                     "max"))
            + f"   later than the {spin:.0f} µs spin")
    return [head, *(f"  {label:<36}{_cells(q, none)}"
                    + ("" if share is None else f"  {_share(share)}")
                    for label, q, none, share in rows),
            f"  ({note}; a loop wake-up latency {hidden} µs is hidden by the spin)"]
