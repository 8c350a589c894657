"""Frequency-response estimation from an excitation u and a response y (H1 estimator).

Both signals are cut into segments, each segment is Fourier transformed, and the cross
spectrum S_uy = mean(conj(U)·Y) and the auto spectra S_uu = mean(|U|²), S_yy = mean(|Y|²)
are averaged over the segments.  Then

    H(f) = S_uy / S_uu,        coherence γ²(f) = |S_uy|² / (S_uu · S_yy).

H1 is unbiased by noise on y; γ² is 1 for a noise-free linear system and falls where
noise or nonlinearity dominates (with a single segment it is 1 by construction).  Two
ways to cut the segments:

* ``period=`` — periodic excitation (a PRBS repeated several times): whole periods with a
  rectangular window, the first ``discard_periods`` dropped as transient.  The excitation
  is then exactly periodic in every segment, so there is no leakage.
* ``segment=`` — any excitation (Welch): segments of that length with a Hann window and
  50 % overlap, each with its mean removed.

Frequencies are the segment's DFT bins from 1 / (segment duration) up to the Nyquist
limit; bins the excitation leaves without power (the zeros of a held PRBS) are dropped.
"""

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.signal import find_peaks, get_window

#: Bins whose input power is below this fraction of the largest are not excited.
MIN_RELATIVE_POWER = 1e-10
#: γ² below which a bin is taken for noise or nonlinearity: no peak is found there
#: (:func:`peaks`) and the Bode plot draws it grey
MIN_COHERENCE = 0.9
#: the drop from the lowest frequency's gain that defines the bandwidth, dB
BANDWIDTH_DROP_DB = 3.0
CSV_COLUMNS = ("freq_hz", "magnitude_db", "phase_deg", "coherence")


class EstimateError(ValueError):
    """Signals or averaging settings that do not allow an estimate; the message says why."""


@dataclass(frozen=True)
class FrequencyResponse:
    """A measured frequency response; all arrays have shape (m,).

    ``h`` is the complex response y/u (unit of y per unit of u), ``magnitude_db`` is
    20·log10|h|, ``phase_deg`` the phase of h unwrapped from the lowest frequency, which
    lies in (-180, 180] (:func:`unwrapped_phase_deg`), ``coherence`` γ² in [0, 1];
    ``averages`` the number of segments averaged (0: not known, as read from a file).
    """

    freq_hz: np.ndarray
    h: np.ndarray
    magnitude_db: np.ndarray
    phase_deg: np.ndarray
    coherence: np.ndarray
    averages: int

    @classmethod
    def from_h(cls, freq_hz, h, coherence, averages: int = 1) -> "FrequencyResponse":
        """Build from the complex response; magnitude and unwrapped phase are derived."""
        h = np.asarray(h, dtype=complex)
        with np.errstate(divide="ignore"):
            magnitude_db = 20.0 * np.log10(np.abs(h))
        return cls(freq_hz=np.asarray(freq_hz, dtype=float), h=h, magnitude_db=magnitude_db,
                   phase_deg=unwrapped_phase_deg(h),
                   coherence=np.asarray(coherence, dtype=float), averages=averages)

    @property
    def resolution_hz(self) -> float:
        """Spacing of the frequency points (1 / segment duration)."""
        return float(self.freq_hz[1] - self.freq_hz[0]) if self.freq_hz.size > 1 else math.nan


def unwrapped_phase_deg(h: np.ndarray) -> np.ndarray:
    """Phase of ``h`` (shape (m,), in order of frequency), deg: unwrapped from the first
    point, then shifted by a whole number of turns so that the first lies in (-180, 180]
    (a closed loop starts near 0 deg; the phase lag beyond -180 deg is then the loop's,
    not the unwrapping's)."""
    phase = np.degrees(np.unwrap(np.angle(h)))
    if phase.size:
        phase -= 360.0 * math.ceil((phase[0] - 180.0) / 360.0)
    return phase


@dataclass(frozen=True)
class Peak:
    """A resonance peak: its frequency, height and prominence above its surroundings."""

    freq_hz: float
    magnitude_db: float
    prominence_db: float


def estimate(u, y, dt_s: float, *, period: int | None = None, segment: int | None = None,
             discard_periods: int = 1) -> FrequencyResponse:
    """H1 estimate of y/u from equally long 1-D signals sampled every ``dt_s`` seconds.

    Give exactly one of ``period`` (samples per period of a periodic excitation that
    starts at sample 0; ``discard_periods`` leading periods are dropped, a trailing
    partial period is ignored) or ``segment`` (Welch segment length in samples).
    """
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if u.ndim != 1 or u.shape != y.shape:
        raise EstimateError(f"u and y must be 1-D and equally long, got {u.shape} and {y.shape}")
    if not dt_s > 0.0:
        raise EstimateError(f"sample time must be positive, got {dt_s} s")
    if (period is None) == (segment is None):
        raise EstimateError("give exactly one of period= (periodic) or segment= (Welch)")
    if period is not None:
        us = _periodic_segments(u, period, discard_periods)
        ys = _periodic_segments(y, period, discard_periods)
        window = np.ones(period)
    else:
        us, ys = _welch_segments(u, segment), _welch_segments(y, segment)
        window = get_window("hann", segment)
    freq = np.fft.rfftfreq(window.size, dt_s)
    return _h1(np.fft.rfft(us * window, axis=1), np.fft.rfft(ys * window, axis=1), freq)


def _periodic_segments(x: np.ndarray, period: int, discard: int) -> np.ndarray:
    """Whole periods after the discarded ones, shape (averages, period)."""
    if period < 2 or discard < 0:
        raise EstimateError(f"period must be >= 2 and discard_periods >= 0, "
                            f"got {period} and {discard}")
    whole = x.size // period
    if whole <= discard:
        raise EstimateError(f"{x.size} samples hold {whole} whole periods of {period}; "
                            f"need more than the {discard} discarded")
    return x[discard * period:whole * period].reshape(whole - discard, period)


def _welch_segments(x: np.ndarray, segment: int) -> np.ndarray:
    """Half-overlapping segments with their means removed, shape (averages, segment)."""
    if segment < 2 or segment > x.size:
        raise EstimateError(f"segment must be within 2..{x.size} samples, got {segment}")
    step = segment // 2
    starts = range(0, x.size - segment + 1, step)
    segs = np.stack([x[s:s + segment] for s in starts])
    return segs - segs.mean(axis=1, keepdims=True)


def _h1(uf: np.ndarray, yf: np.ndarray, freq: np.ndarray) -> FrequencyResponse:
    """Average the spectra of the segments' DFTs (shape (averages, bins), bin frequencies
    ``freq``) into H1 and γ²."""
    suu = np.mean(np.abs(uf) ** 2, axis=0)
    syy = np.mean(np.abs(yf) ** 2, axis=0)
    suy = np.mean(np.conj(uf) * yf, axis=0)
    if not suu[1:].max() > 0.0:
        raise EstimateError("the excitation u carries no power above 0 Hz")
    keep = suu > MIN_RELATIVE_POWER * suu[1:].max()
    keep[0] = False
    suu, syy, suy = suu[keep], syy[keep], suy[keep]
    coherence = np.divide(np.abs(suy) ** 2, suu * syy, out=np.zeros_like(suu),
                          where=syy > 0.0)
    return FrequencyResponse.from_h(freq[keep], suy / suu, coherence, uf.shape[0])


def bandwidth_hz(fr: FrequencyResponse, drop_db: float = BANDWIDTH_DROP_DB) -> float | None:
    """First frequency where the magnitude falls ``drop_db`` below its value at the lowest
    frequency point, interpolated linearly over log frequency; None when it never does."""
    level = fr.magnitude_db[0] - drop_db
    below = np.flatnonzero(fr.magnitude_db < level)
    if below.size == 0:
        return None
    i = int(below[0])
    m0, m1 = fr.magnitude_db[i - 1], fr.magnitude_db[i]
    l0, l1 = np.log(fr.freq_hz[i - 1]), np.log(fr.freq_hz[i])
    return float(np.exp(l0 + (level - m0) / (m1 - m0) * (l1 - l0)))


def peaks(fr: FrequencyResponse, threshold_db: float = 6.0,
          min_coherence: float = MIN_COHERENCE) -> tuple[Peak, ...]:
    """Resonance peaks: local maxima of the magnitude standing at least ``threshold_db``
    above the higher of the minima that separate them from higher ground on either side
    (topographic prominence), measured with coherence of at least ``min_coherence`` (so
    noise ripple where the response is buried is not taken for a resonance); in order of
    frequency."""
    index, props = find_peaks(fr.magnitude_db, prominence=threshold_db)
    return tuple(Peak(freq_hz=float(fr.freq_hz[i]), magnitude_db=float(fr.magnitude_db[i]),
                      prominence_db=float(p)) for i, p in zip(index, props["prominences"])
                 if fr.coherence[i] >= min_coherence)


def write_csv(path: str | Path, fr: FrequencyResponse) -> Path:
    """Write freq_hz, magnitude_db, phase_deg, coherence as CSV (values printed to full
    precision, so :func:`read_csv` gives them back exactly); returns the path."""
    path = Path(path)
    with path.open("w", newline="") as f:
        out = csv.writer(f, lineterminator="\n")
        out.writerow(CSV_COLUMNS)
        for row in zip(fr.freq_hz, fr.magnitude_db, fr.phase_deg, fr.coherence):
            out.writerow([repr(float(v)) for v in row])
    return path


def read_csv(path: str | Path) -> FrequencyResponse:
    """Read a file written by :func:`write_csv`; h is rebuilt from magnitude and phase.
    The file does not hold the number of averages: ``averages`` reads back as 0."""
    path = Path(path)
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(rows[0]) != CSV_COLUMNS:
        raise EstimateError(f"{path}:1: header must be {','.join(CSV_COLUMNS)}")
    data = np.empty((len(rows) - 1, len(CSV_COLUMNS)))
    for number, row in enumerate(rows[1:], start=2):
        try:
            data[number - 2] = [float(v) for v in row]
        except ValueError as e:
            raise EstimateError(f"{path}:{number}: need {len(CSV_COLUMNS)} numbers, "
                                f"got {row}") from e
    freq, mag, phase, coh = data.T
    h = 10.0 ** (mag / 20.0) * np.exp(1j * np.radians(phase))
    return FrequencyResponse(freq_hz=freq, h=h, magnitude_db=mag, phase_deg=phase,
                             coherence=coh, averages=0)


def bode_figure(fr: FrequencyResponse, title: str = "",
                reference: FrequencyResponse | None = None,
                marked_peaks: tuple[Peak, ...] | None = None,
                reference_label: str = "reference"):
    """Bode diagram with its coherence, over log frequency: magnitude (dB) with the -3 dB
    level and :func:`bandwidth_hz` marked and the resonance peaks annotated; phase (deg,
    unwrapped from the lowest frequency); coherence γ² with :data:`MIN_COHERENCE`.  Bins
    below it are drawn grey in magnitude and phase.  ``marked_peaks``: the peaks to
    annotate (None: :func:`peaks` of ``fr``); ``reference``: a response drawn dashed (for
    example the analytic one), named ``reference_label`` in the legend.  Returns the matplotlib Figure."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MultipleLocator

    fig = Figure(figsize=(8.0, 8.5))
    mag_ax, phase_ax, coh_ax = fig.subplots(
        3, 1, sharex=True, gridspec_kw={"height_ratios": (3, 2.2, 1.3)})
    poor = fr.coherence < MIN_COHERENCE
    grey = {"color": "0.7", "linewidth": 0.8}
    for ax, values in ((mag_ax, fr.magnitude_db), (phase_ax, fr.phase_deg)):
        ax.semilogx(fr.freq_hz, values, **grey,
                    label=f"γ² < {MIN_COHERENCE:g}: noise or nonlinearity dominates"
                    if poor.any() else None)
        ax.semilogx(fr.freq_hz, np.ma.masked_where(poor, values), color="C0",
                    label=f"measured, γ² ≥ {MIN_COHERENCE:g}")
    if reference is not None:
        mag_ax.semilogx(reference.freq_hz, reference.magnitude_db, "k--", linewidth=0.9,
                        label=reference_label)
        phase_ax.semilogx(reference.freq_hz, reference.phase_deg, "k--", linewidth=0.9)
    _mark_bandwidth(fr, (mag_ax, phase_ax, coh_ax))
    marked = peaks(fr) if marked_peaks is None else marked_peaks
    if marked:  # room above the highest for its label
        finite = fr.magnitude_db[np.isfinite(fr.magnitude_db)]
        mag_ax.set_ylim(top=max(float(finite.max()), max(p.magnitude_db for p in marked)) + 12.0)
    for p in marked:
        mag_ax.annotate(f"{p.freq_hz:.0f} Hz\n{p.magnitude_db:+.1f} dB",
                        xy=(p.freq_hz, p.magnitude_db), xytext=(0, 14),
                        textcoords="offset points", ha="center", va="bottom", fontsize=8,
                        arrowprops={"arrowstyle": "-|>", "color": "C3", "linewidth": 0.8})
    coh_ax.semilogx(fr.freq_hz, fr.coherence, color="C0", linewidth=0.8, label="coherence γ²")
    coh_ax.axhline(MIN_COHERENCE, color="C3", linestyle="--", linewidth=0.9,
                   label=f"γ² = {MIN_COHERENCE:g}: peaks need at least this")
    coh_ax.set_ylim(0.0, 1.05)
    span = np.ptp(fr.phase_deg) if fr.phase_deg.size else 0.0
    phase_ax.yaxis.set_major_locator(MultipleLocator(90.0 if span <= 720.0 else 180.0))
    mag_ax.set_ylabel("magnitude / dB")
    phase_ax.set_ylabel("phase / deg\n(unwrapped from the lowest frequency)", fontsize=9)
    coh_ax.set_ylabel("coherence γ²")
    coh_ax.set_xlabel("frequency / Hz")
    handles, labels = mag_ax.get_legend_handles_labels()
    if not any(label.startswith("−3 dB bandwidth") for label in labels):
        handles.append(Line2D([], [], linestyle="none"))
        labels.append("no −3 dB crossing measured")
    mag_ax.legend(handles, labels, fontsize=8, loc="lower left")
    coh_ax.legend(fontsize=8, loc="lower left")
    for ax in (mag_ax, phase_ax, coh_ax):
        ax.grid(True, which="both", alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def _mark_bandwidth(fr: FrequencyResponse, axes) -> None:
    """The -3 dB level on the magnitude (the first of ``axes``) and the bandwidth, when
    the magnitude crosses it, on every one of ``axes``."""
    level = fr.magnitude_db[0] - BANDWIDTH_DROP_DB
    bw = bandwidth_hz(fr)
    axes[0].axhline(level, color="0.4", linestyle=":", linewidth=0.9,
                    label=f"−3 dB of the gain at {fr.freq_hz[0]:.3g} Hz")
    if bw is None:
        return
    for ax in axes:
        ax.axvline(bw, color="C2", linestyle="--", linewidth=0.9,
                   label=f"−3 dB bandwidth {bw:.1f} Hz" if ax is axes[0] else None)


def bode_plot(fr: FrequencyResponse, path: str | Path, title: str = "",
              reference: FrequencyResponse | None = None,
              marked_peaks: tuple[Peak, ...] | None = None) -> Path:
    """:func:`bode_figure` as a PNG at ``path`` (its folder made when missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    bode_figure(fr, title, reference, marked_peaks).savefig(path, dpi=110)
    return path
