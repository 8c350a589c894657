"""Percentiles of a day of ticks in constant memory: a log-linear histogram of ns values.

A run of 24 h at 8 kHz has 691 million lateness samples; sorting them is out of the
question, so the run's figures come from a histogram that the recording's writer fills
batch by batch (vectorised, outside the real-time path):

* values below :data:`EXACT_NS` (1024 ns) each have their own bin: exact to the ns;
* above, a bin spans 1/512 of its lower edge (11 significant bits): a percentile is its
  bin's lower edge, at most 0.2 % below the value nearest rank would give.

The maximum is kept exactly.  Negative values (none from the loop's clock) count in the
first bin.  Percentiles are nearest rank as in :class:`hil.rt.loop.Percentiles`.
"""

import numpy as np

from hil.rt.loop import Percentiles, nearest_rank

#: values below this many ns are binned exactly
EXACT_NS = 1024
_SUB = EXACT_NS // 2
#: bins up to 2^62 ns (146 years)
N_BINS = EXACT_NS + 52 * _SUB


def bin_of(values_ns: np.ndarray) -> np.ndarray:
    """The bin index of each value (int64 array in, int64 array out)."""
    v = np.maximum(np.asarray(values_ns, dtype=np.int64), 0)
    exponent = np.frexp(v.astype(np.float64))[1]  # bit length, exact below 2^53
    shift = np.maximum(exponent - 10, 0)
    top = v >> shift
    return np.where(v < EXACT_NS, v, EXACT_NS + (shift - 1) * _SUB + (top - _SUB))


def lower_edge(bins: np.ndarray) -> np.ndarray:
    """The smallest ns value of each bin."""
    bins = np.asarray(bins, dtype=np.int64)
    shift = (bins - EXACT_NS) // _SUB + 1
    top = (bins - EXACT_NS) % _SUB + _SUB
    return np.where(bins < EXACT_NS, bins, top << np.maximum(shift, 0))


class LogHistogram:
    """Counts of ns values in the bins of the module docstring."""

    def __init__(self):
        self.counts = np.zeros(N_BINS, dtype=np.int64)
        self.n = 0
        self.max_ns = None

    def add(self, values_ns: np.ndarray) -> None:
        """Count ``values_ns`` (ns)."""
        if values_ns.size == 0:
            return
        self.counts += np.bincount(bin_of(values_ns), minlength=N_BINS)
        self.n += values_ns.size
        top = int(values_ns.max())
        self.max_ns = top if self.max_ns is None else max(self.max_ns, top)

    def percentiles_us(self) -> Percentiles:
        """p50, p99, p99.9 (bin lower edges) and the exact maximum, in µs; NaN when
        empty."""
        if self.n == 0:
            return Percentiles(*([float("nan")] * 4))
        cumulative = np.cumsum(self.counts)
        ranks = [nearest_rank(q, self.n) for q in (500, 990, 999)]
        edges = lower_edge(np.searchsorted(cumulative, ranks))
        p50, p99, p999 = (float(e) / 1e3 for e in edges)
        return Percentiles(p50=p50, p99=p99, p999=p999, max=self.max_ns / 1e3)
