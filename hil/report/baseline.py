"""The machine's own timer baseline for a report: ``cyclictest`` at the run's period,
kept as its whole histogram so the report can draw it beside the run's lateness.

:func:`run_cyclictest_baseline` runs ``cyclictest`` as :func:`hil.rt.cyclictest.run_cyclictest`
does (SCHED_FIFO, memory locked, 1 µs bins) but keeps the histogram, not only its
percentiles; the percentiles are :func:`hil.rt.cyclictest.parse_histogram`'s (nearest rank,
whole µs: a bin holds the latencies from its value up to the next µs).
"""

from dataclasses import dataclass

import numpy as np

from hil.rt.cyclictest import (
    DEFAULT_HISTOGRAM_US,
    cyclictest_histogram,
    parse_histogram,
)
from hil.rt.loop import Percentiles


@dataclass(frozen=True, eq=False)
class CyclictestBaseline:
    """One cyclictest run reduced to what a report shows.

    Attributes:
        interval_us: its wake-up interval (µs).
        latency_us: p50, p99, p99.9 and max of its wake-up latency (µs).
        bins_us: the lower edge of each 1 µs histogram bin (µs), ascending.
        counts: wake-ups per bin (all threads summed).
        overflows: wake-ups later than the last bin (counted in ``latency_us``, not in
            ``counts``).
    """
    interval_us: int
    latency_us: Percentiles
    bins_us: np.ndarray
    counts: np.ndarray
    overflows: int

    @classmethod
    def from_histogram(cls, text: str, interval_us: int) -> "CyclictestBaseline":
        """From cyclictest's ``-h`` output (``--histfile``); raises
        :class:`~hil.rt.cyclictest.CyclictestError` if ``text`` is not one."""
        latency_us = parse_histogram(text)
        bins_us, counts, overflows = [], [], 0
        for line in text.splitlines():
            if line.startswith("# Histogram Overflows:"):
                overflows = sum(int(v) for v in line.partition(":")[2].split())
                continue
            fields = line.split()
            if len(fields) >= 2 and fields[0].isdigit():
                bins_us.append(int(fields[0]))
                counts.append(sum(int(c) for c in fields[1:]))
        return cls(interval_us=int(interval_us), latency_us=latency_us,
                   bins_us=np.array(bins_us, dtype=np.int64),
                   counts=np.array(counts, dtype=np.int64), overflows=overflows)

    @property
    def samples(self) -> int:
        """Wake-ups measured."""
        return int(self.counts.sum()) + self.overflows

    @property
    def min_us(self) -> float | None:
        """The lowest non-empty bin (µs), or None when no wake-up fell in a bin."""
        filled = self.bins_us[self.counts > 0]
        return float(filled[0]) if filled.size else None


def run_cyclictest_baseline(interval_us: int, seconds: float, cpu: int | None = None,
                            priority: int = 80) -> CyclictestBaseline | None:
    """Run ``cyclictest -q -m -p <priority> -i <interval_us> -D <seconds> -h <range>``.

    Args:
        interval_us: wake-up interval (µs): the run's period.
        seconds: duration, rounded up to whole seconds (cyclictest's resolution).
        cpu: pin the measuring thread to this CPU, or leave it free.
        priority: SCHED_FIFO priority of the measuring thread.

    Returns:
        The baseline, or None when cyclictest is not installed (``apt-get install rt-tests``).

    Raises:
        CyclictestError: it ran and failed (e.g. SCHED_FIFO refused to a non-root user).
    """
    text = cyclictest_histogram(interval_us, seconds, priority, cpu, DEFAULT_HISTOGRAM_US)
    return None if text is None else CyclictestBaseline.from_histogram(text, interval_us)
