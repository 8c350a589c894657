"""Min/max per pixel: a signal of any length drawn at the screen's resolution without
averaging a spike away.

The time span is cut into ``pixels`` equal bins; each bin keeps its smallest and largest
sample, and the curve visits both (:meth:`Envelope.curve`), so a one-sample spike still
reaches its full height.  Samples arrive batch by batch (:meth:`Envelope.add`): memory is
the bins', whatever the length of the run.
"""

import numpy as np


class Envelope:
    """The min/max envelope of several channels over [t0_s, t1_s).

    Args:
        t0_s, t1_s: the span, s (t1_s > t0_s).
        pixels: bins across it (the plot's width in pixels).
        names: the channels.
    """

    def __init__(self, t0_s: float, t1_s: float, pixels: int, names: list[str]):
        if not t1_s > t0_s or pixels < 1:
            raise ValueError(f"an envelope needs t1_s > t0_s and pixels >= 1, got "
                             f"[{t0_s}, {t1_s}) in {pixels}")
        self.t0_s, self.t1_s, self.pixels = t0_s, t1_s, pixels
        self.width_s = (t1_s - t0_s) / pixels
        self.low = {n: np.full(pixels, np.inf) for n in names}
        self.high = {n: np.full(pixels, -np.inf) for n in names}

    def add(self, t_s: np.ndarray, columns: dict[str, np.ndarray]) -> None:
        """Take samples at times ``t_s`` (s, shape (n,)) of each channel (name -> (n,));
        those outside the span and NaN values are left out."""
        inside = (t_s >= self.t0_s) & (t_s < self.t1_s)
        if not inside.any():
            return
        bins = ((t_s[inside] - self.t0_s) / self.width_s).astype(np.int64)
        np.clip(bins, 0, self.pixels - 1, out=bins)
        for name in self.low:
            values = np.asarray(columns[name], dtype=np.float64)[inside]
            ok = np.isfinite(values)
            np.minimum.at(self.low[name], bins[ok], values[ok])
            np.maximum.at(self.high[name], bins[ok], values[ok])

    def curve(self) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """(t_s, kept, name -> values): two points per bin, its minimum then its maximum at
        the bin's centre, for the bins where some channel has a sample (``kept``: their
        indices); NaN where a channel has none (a gap in the line)."""
        filled = np.zeros(self.pixels, bool)
        for name in self.low:
            filled |= np.isfinite(self.low[name])
        kept = np.flatnonzero(filled)
        centre = self.t0_s + (kept + 0.5) * self.width_s
        t_s = np.repeat(centre, 2)
        values = {}
        for name in self.low:
            pair = np.empty(2 * kept.size)
            pair[0::2], pair[1::2] = self.low[name][kept], self.high[name][kept]
            pair[~np.isfinite(pair)] = np.nan
            values[name] = pair
        return t_s, kept, values
