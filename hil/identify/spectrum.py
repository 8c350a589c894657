"""Residual spectra in the position domain (seed 002's method).

A disturbance tied to the mechanics (cogging, a pitch error) is periodic in a position,
not in time: its frequency in time changes with the speed.  Averaging the residual into
bins of table position while the axis moves, and taking the Fourier transform of that
profile, turns it into lines at fixed spatial frequencies whatever the speeds were.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PositionSpectrum:
    """Amplitude spectrum of a residual against a position.

    Attributes:
        cycles_per_unit: spatial frequencies (cycles per m, or per rad), shape (k,).
        amplitude: amplitude of each line in the residual's unit, shape (k,).
        step: the bin width (m or rad).
        resolution: the spacing of independent lines, 1 / (profile length), in cycles per
            unit; the spectrum is zero-padded to a finer grid for locating peaks.
    """
    cycles_per_unit: np.ndarray
    amplitude: np.ndarray
    step: float
    resolution: float = 0.0

    def peaks(self, count: int, min_cycles: float = 0.0) -> list[tuple[float, float]]:
        """The ``count`` highest local maxima between ``min_cycles`` and half the binning's
        Nyquist frequency (above it the bins' averaging attenuates and aliases):
        (cycles/unit, amplitude)."""
        f, a = self.cycles_per_unit, self.amplitude
        top = 0.25 / self.step
        out = [(float(f[i]), float(a[i])) for i in range(1, len(a) - 1)
               if a[i] >= a[i - 1] and a[i] >= a[i + 1] and min_cycles < f[i] < top]
        return sorted(out, key=lambda p: -p[1])[:count]


def position_spectrum(residual: np.ndarray, position: np.ndarray, mask: np.ndarray,
                      step: float) -> PositionSpectrum:
    """Spectrum of ``residual`` against ``position`` (both shape (n,)) over ``mask``.

    The residual is averaged in bins of width ``step``; bins never visited are filled by
    linear interpolation.  The mean is removed (it is no periodic effect) and the profile
    detrended, so that a slope along the travel does not leak into the low lines.
    """
    x = position[mask]
    r = residual[mask]
    if x.size < 8:
        return PositionSpectrum(np.zeros(0), np.zeros(0), step, 0.0)
    lo = float(x.min())
    nb = max(8, int((float(x.max()) - lo) / step) + 1)
    idx = np.minimum(((x - lo) / step).astype(np.int64), nb - 1)
    sums = np.bincount(idx, weights=r, minlength=nb)
    counts = np.bincount(idx, minlength=nb)
    seen = counts > 0
    centres = lo + (np.arange(nb) + 0.5) * step
    profile = np.interp(centres, centres[seen], sums[seen] / counts[seen])
    profile = profile - np.polyval(np.polyfit(centres, profile, 1), centres)
    window = np.hanning(nb)
    # zero-padding eightfold interpolates the spectrum: peaks fall between the lines
    spec = np.fft.rfft(profile * window, 8 * nb)
    # the Hann window halves a line's amplitude: 2/sum(w) restores it
    amp = 2.0 * np.abs(spec) / window.sum()
    freqs = np.fft.rfftfreq(8 * nb, step)
    return PositionSpectrum(freqs, amp, step, 1.0 / (nb * step))
