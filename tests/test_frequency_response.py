"""PRBS excitation (hil.measure.prbs) and frequency-response estimation
(hil.measure.frequency_response) against independent references: the exact frequency
response of discrete-time systems (scipy.signal.dfreqresp), their analytic -3 dB and
resonance frequencies, and the defining properties of maximum-length sequences."""

import math

import numpy as np
import pytest
from scipy import signal

from hil.measure import frequency_response as F
from hil.measure.prbs import POLYNOMIALS, ExcitationError, mls_bits, prbs

DT_S = 1e-3                      # 1 kHz sample rate
NOISE = 1e-3                     # standard deviation of the measurement noise on y
MAG_TOL_DB = 1.0
PHASE_TOL_DEG = 5.0


def low_pass(fc_hz: float):
    """y[k] = a y[k-1] + (1 - a) u[k], a = exp(-2π fc dt): unit DC gain."""
    a = math.exp(-2.0 * math.pi * fc_hz * DT_S)
    return ([1.0 - a, 0.0], [1.0, -a], DT_S)


def resonance(f_hz: float, zeta: float):
    """ω²/(s² + 2ζωs + ω²) discretised with a zero-order hold."""
    w = 2.0 * math.pi * f_hz
    num, den, _ = signal.cont2discrete(([w * w], [1.0, 2.0 * zeta * w, w * w]), DT_S, "zoh")
    return (np.trim_zeros(num.ravel(), "f"), den, DT_S)


def delay(samples: int):
    """y[k] = u[k - samples]."""
    return ([1.0], [1.0] + [0.0] * samples, DT_S)


SYSTEMS = {"low_pass_50hz": low_pass(50.0), "resonance_60hz": resonance(60.0, 0.05),
           "delay_3": delay(3)}


def simulate(system, u: np.ndarray, seed: int = 7) -> np.ndarray:
    """The system's response to u plus white measurement noise (fixed seed)."""
    _, y = signal.dlsim(system, u[:, None])
    return y.ravel() + NOISE * np.random.default_rng(seed).standard_normal(u.size)


def exact(system, freq_hz: np.ndarray) -> np.ndarray:
    _, h = signal.dfreqresp(system, w=2.0 * math.pi * freq_hz * DT_S)
    return h


def assert_matches_exact(fr: F.FrequencyResponse, system) -> None:
    """Within 1 dB and 5° of the exact response from the lowest point up to fs/4."""
    band = fr.freq_hz <= 0.25 / DT_S
    assert fr.freq_hz[0] < 2.0 and band.sum() > 200
    ratio = fr.h[band] / exact(system, fr.freq_hz[band])
    mag_err = np.abs(20.0 * np.log10(np.abs(ratio)))
    phase_err = np.abs(np.degrees(np.angle(ratio)))
    worst = int(np.argmax(mag_err))
    assert mag_err.max() < MAG_TOL_DB, f"{mag_err[worst]:.2f} dB at {fr.freq_hz[worst]:.1f} Hz"
    worst = int(np.argmax(phase_err))
    assert phase_err.max() < PHASE_TOL_DEG, \
        f"{phase_err[worst]:.2f} deg at {fr.freq_hz[worst]:.1f} Hz"


def prbs_response(system, hold: int = 1):
    exc = prbs(10 if hold == 1 else 9, 1.0, DT_S, hold=hold, periods=6)
    return F.estimate(exc.signal, simulate(system, exc.signal), DT_S,
                      period=exc.period_samples), exc


# --- PRBS -----------------------------------------------------------------------------

def test_first_bits_of_order_5_by_hand():
    """x^5 + x^3 + 1 from the all-ones state: a[k+5] = a[k+3] XOR a[k], worked by hand:
    1 1 1 1 1, then 1^1=0, 1^1=0, 0^1=1, 0^1=1, 1^1=0, 1^0=1, 0^0=0."""
    assert mls_bits(5)[:12].tolist() == [1, 1, 1, 1, 1, 0, 0, 1, 1, 0, 1, 0]


@pytest.mark.parametrize("order", sorted(POLYNOMIALS))
def test_maximum_length_properties(order):
    """Every tabulated polynomial gives a maximum-length sequence: period N = 2^n - 1 with
    one more +A than -A, and the two-level circular autocorrelation N·A² at lag 0, -A² at
    every other lag (which also rules out any shorter period)."""
    amplitude = 0.5
    exc = prbs(order, amplitude, DT_S, periods=2)
    n = 2 ** order - 1
    assert exc.sequence_length == n and exc.signal.size == 2 * n
    one = exc.signal[:n]
    assert np.array_equal(exc.signal[n:], one)
    assert (one > 0).sum() == (one < 0).sum() + 1
    spectrum = np.fft.fft(one)
    autocorrelation = np.fft.ifft(spectrum * np.conj(spectrum)).real
    assert autocorrelation[0] == pytest.approx(n * amplitude ** 2)
    assert np.allclose(autocorrelation[1:], -amplitude ** 2, atol=1e-9 * n)


def test_autocorrelation_of_order_5_directly():
    """The same two-level property by plain sums over the 31 lags (no FFT)."""
    s = prbs(5, 1.0, DT_S, periods=1).signal
    values = {round(np.dot(s, np.roll(s, lag))) for lag in range(1, 31)}
    assert values == {-1} and int(np.dot(s, s)) == 31


def test_hold_repeats_each_bit_and_sets_the_bit_period():
    """hold = 3: every bit appears 3 times in a row; bit period 3·dt."""
    exc = prbs(6, 2.0, DT_S, hold=3, periods=3)
    bits = np.where(mls_bits(6) == 1, 2.0, -2.0)
    assert exc.signal.size == 3 * 3 * 63 and exc.period_samples == 189
    assert np.array_equal(exc.signal[:189].reshape(63, 3), np.repeat(bits[:, None], 3, 1))
    assert exc.bit_period_s == pytest.approx(3 * DT_S)


@pytest.mark.parametrize("order, amplitude, hold, periods", [
    (4, 1.0, 1, 1), (21, 1.0, 1, 1), (8, 0.0, 1, 1), (8, 1.0, 0, 1), (8, 1.0, 1, 0)])
def test_impossible_excitations_refused(order, amplitude, hold, periods):
    """Orders outside the table 5..20, zero amplitude, hold or periods."""
    with pytest.raises(ExcitationError):
        prbs(order, amplitude, DT_S, hold=hold, periods=periods)


# --- estimate against the exact response ----------------------------------------------

@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_prbs_estimate_matches_exact_response(name):
    """PRBS of order 10 (N = 1023), 6 periods, the first discarded: the H1 estimate is
    within 1 dB and 5° of dfreqresp from 0.98 Hz up to fs/4 = 250 Hz."""
    fr, _ = prbs_response(SYSTEMS[name])
    assert fr.averages == 5
    assert fr.freq_hz[-1] == pytest.approx(511 / (1023 * DT_S))
    assert_matches_exact(fr, SYSTEMS[name])


def test_held_prbs_estimate_matches_and_skips_the_unexcited_bin():
    """hold = 2 puts a spectral zero at 1/(2 dt) = fs/2 (bin N of 2N); that bin is dropped
    and the rest of the band still matches the exact response."""
    fr, exc = prbs_response(SYSTEMS["resonance_60hz"], hold=2)
    n = exc.period_samples
    assert fr.freq_hz.size == n // 2 - 1
    assert not np.any(np.isclose(fr.freq_hz, 0.5 / DT_S))
    assert_matches_exact(fr, SYSTEMS["resonance_60hz"])


@pytest.mark.parametrize("name", ["low_pass_50hz", "delay_3"])
def test_welch_estimate_with_random_excitation_matches(name):
    """Non-periodic white-noise excitation, Welch with Hann windows of 1024 samples and
    50 % overlap (127 averages): within 1 dB and 5° of dfreqresp up to fs/4."""
    u = np.random.default_rng(3).standard_normal(65536)
    fr = F.estimate(u, simulate(SYSTEMS[name], u), DT_S, segment=1024)
    assert fr.averages == 127
    assert fr.freq_hz[-1] == pytest.approx(0.5 / DT_S)
    assert_matches_exact(fr, SYSTEMS[name])


def test_noise_free_coherence_is_one_and_noise_lowers_it():
    """γ² = 1 for a noise-free linear system; with noise comparable to the response it
    drops well below 1 (reference: the definition |S_uy|² / (S_uu S_yy))."""
    exc = prbs(8, 1.0, DT_S, periods=4)
    _, y = signal.dlsim(SYSTEMS["delay_3"], exc.signal[:, None])
    clean = F.estimate(exc.signal, y.ravel(), DT_S, period=exc.period_samples)
    noisy_y = y.ravel() + np.random.default_rng(1).standard_normal(y.size)
    noisy = F.estimate(exc.signal, noisy_y, DT_S, period=exc.period_samples)
    assert np.allclose(clean.coherence, 1.0)
    assert np.median(noisy.coherence) < 0.8


def test_coherence_follows_the_signal_to_noise_ratio():
    """y = H u + white noise of σ = 0.2 on the 50 Hz low-pass, 40 periods of a PRBS of
    order 8: γ² = |H|² S_uu / (|H|² S_uu + N σ²) per bin (S_uu = |U|² of one period of N
    samples, N σ² the noise's), near 1 at low frequency and well below where |H| has
    fallen into the noise; the estimate within 0.06 of it averaged over 16 bins."""
    system, sigma = SYSTEMS["low_pass_50hz"], 0.2
    exc = prbs(8, 1.0, DT_S, periods=41)
    _, y = signal.dlsim(system, exc.signal[:, None])
    y = y.ravel() + sigma * np.random.default_rng(5).standard_normal(y.size)
    fr = F.estimate(exc.signal, y, DT_S, period=exc.period_samples)
    n = exc.period_samples
    suu = np.abs(np.fft.rfft(exc.signal[:n])) ** 2
    suu = suu[np.rint(fr.freq_hz * n * DT_S).astype(int)]
    gain2 = np.abs(exact(system, fr.freq_hz)) ** 2
    expected = gain2 * suu / (gain2 * suu + n * sigma ** 2)
    assert expected[0] > 0.95 and expected[-1] < 0.45
    bands = fr.coherence.size // 16 * 16
    got, want = (c[:bands].reshape(-1, 16).mean(axis=1) for c in (fr.coherence, expected))
    assert np.abs(got - want).max() < 0.06


def test_phase_starts_within_half_a_turn_and_unwraps_beyond():
    """A 3-sample delay: -1080 f T deg, continued past -180 deg rather than wrapped, from
    a first point in (-180, 180]; a response whose first point is -1 with a negative zero
    imaginary part (np.angle: -180 deg) starts at +180 deg, the whole curve one turn up."""
    fr, _ = prbs_response(SYSTEMS["delay_3"])
    assert -180.0 < fr.phase_deg[0] <= 180.0
    np.testing.assert_allclose(fr.phase_deg, -1080.0 * fr.freq_hz * DT_S, atol=PHASE_TOL_DEG)
    h = np.array([complex(-1.0, -0.0), 1j, 1.0, -1j, -1.0])  # -180, -270, -360, -450, -540
    np.testing.assert_allclose(F.FrequencyResponse.from_h(np.arange(1.0, 6.0), h,
                                                          np.ones(5)).phase_deg,
                               [180.0, 90.0, 0.0, -90.0, -180.0])


def test_bandwidth_of_first_order_low_pass():
    """|H|² = (1-a)² / (1 - 2a cos ωT + a²) = 1/2 at cos ωT = (1 + a² - 2(1-a)²) / (2a):
    the measured -3 dB frequency is within one frequency bin of it."""
    fr, _ = prbs_response(SYSTEMS["low_pass_50hz"])
    a = math.exp(-2.0 * math.pi * 50.0 * DT_S)
    f3 = math.acos((1.0 + a * a - 2.0 * (1.0 - a) ** 2) / (2.0 * a)) / (2.0 * math.pi * DT_S)
    assert abs(F.bandwidth_hz(fr) - f3) < fr.resolution_hz


def test_bandwidth_is_none_without_a_crossing():
    """A pure delay has 0 dB everywhere: no -3 dB crossing."""
    fr, _ = prbs_response(SYSTEMS["delay_3"])
    assert F.bandwidth_hz(fr) is None


def test_peaks_finds_the_resonance_within_one_bin():
    """The resonance's peak frequency from dfreqresp on a 0.01 Hz grid; peaks() reports
    that one peak, within one frequency bin, with its height within 1 dB."""
    system = SYSTEMS["resonance_60hz"]
    fr, _ = prbs_response(system)
    grid = np.arange(1.0, 250.0, 0.01)
    h = np.abs(exact(system, grid))
    found = F.peaks(fr)
    assert len(found) == 1
    assert abs(found[0].freq_hz - grid[np.argmax(h)]) <= fr.resolution_hz
    assert abs(found[0].magnitude_db - 20.0 * math.log10(h.max())) < 1.0


def test_peaks_none_on_a_monotonic_response():
    """A first-order low-pass falls monotonically (analytic): no peak."""
    fr, _ = prbs_response(SYSTEMS["low_pass_50hz"])
    assert F.peaks(fr) == ()


# --- files and refusals -----------------------------------------------------------------

def test_csv_round_trip(tmp_path):
    """write_csv → read_csv gives the same numbers exactly (printed with repr) and h
    rebuilt from magnitude and phase."""
    fr, _ = prbs_response(SYSTEMS["resonance_60hz"])
    back = F.read_csv(F.write_csv(tmp_path / "fr.csv", fr))
    assert (tmp_path / "fr.csv").read_text().splitlines()[0] == \
        "freq_hz,magnitude_db,phase_deg,coherence"
    for name in ("freq_hz", "magnitude_db", "phase_deg", "coherence"):
        assert np.array_equal(getattr(back, name), getattr(fr, name)), name
    assert np.allclose(back.h, fr.h, rtol=1e-12, atol=0.0)


def test_csv_bad_row_named_with_its_line(tmp_path):
    """A row with three numbers (line 3) is refused with the file and line."""
    path = tmp_path / "fr.csv"
    path.write_text("freq_hz,magnitude_db,phase_deg,coherence\n1.0,0.0,0.0,1.0\n2.0,-1,5\n")
    with pytest.raises(F.EstimateError, match=f"{path}:3: need 4 numbers"):
        F.read_csv(path)


def test_bode_figure_marks_bandwidth_peaks_and_coherence():
    """The resonance's Bode figure: three panels (magnitude, phase, coherence); the
    bandwidth marker stands at bandwidth_hz on each; the resonance peaks() finds is
    annotated with its frequency and height; the coherence panel draws the estimate's γ²
    and the MIN_COHERENCE line."""
    fr, _ = prbs_response(SYSTEMS["resonance_60hz"])
    bw = F.bandwidth_hz(fr)
    assert bw is not None
    mag_ax, phase_ax, coh_ax = F.bode_figure(fr).axes
    for ax in (mag_ax, phase_ax, coh_ax):
        marks = [line for line in ax.get_lines() if line.get_color() == "C2"]
        assert [line.get_xdata()[0] for line in marks] == [bw]
    assert f"−3 dB bandwidth {bw:.1f} Hz" in mag_ax.get_legend_handles_labels()[1]
    (peak,) = F.peaks(fr)
    assert [t.get_text() for t in mag_ax.texts] == [
        f"{peak.freq_hz:.0f} Hz\n{peak.magnitude_db:+.1f} dB"]
    assert mag_ax.texts[0].xy == (peak.freq_hz, peak.magnitude_db)
    coherence = [line for line in coh_ax.get_lines() if line.get_label() == "coherence γ²"]
    np.testing.assert_array_equal(coherence[0].get_ydata(), fr.coherence)
    assert any(np.all(np.asarray(line.get_ydata()) == F.MIN_COHERENCE)
               for line in coh_ax.get_lines())


def test_bode_figure_greys_incoherent_bins_and_says_so():
    """The 50 Hz low-pass with noise of σ = 0.2 (its γ² falls below 0.9 at high
    frequency): the solid magnitude curve leaves those bins out, a grey one holds them,
    and the legend names the threshold; with the pass band's gain never 3 dB down the
    legend says there is no crossing instead of a bandwidth."""
    exc = prbs(8, 1.0, DT_S, periods=41)
    _, y = signal.dlsim(SYSTEMS["low_pass_50hz"], exc.signal[:, None])
    y = y.ravel() + 0.2 * np.random.default_rng(5).standard_normal(y.size)
    fr = F.estimate(exc.signal, y, DT_S, period=exc.period_samples)
    poor = fr.coherence < F.MIN_COHERENCE
    assert poor.any() and not poor.all()
    mag_ax = F.bode_figure(fr).axes[0]
    solid = next(line for line in mag_ax.get_lines() if line.get_label().startswith("measured"))
    np.testing.assert_array_equal(np.ma.getmaskarray(solid.get_ydata()), poor)
    assert any(label.startswith("γ² < 0.9") for label in mag_ax.get_legend_handles_labels()[1])
    flat, _ = prbs_response(SYSTEMS["delay_3"])
    legend = F.bode_figure(flat).axes[0].get_legend()
    assert "no −3 dB crossing measured" in [t.get_text() for t in legend.get_texts()]


def test_bode_plot_writes_a_png(tmp_path):
    """The plot is a PNG file (its 8-byte signature), written into a new folder."""
    fr, _ = prbs_response(SYSTEMS["low_pass_50hz"])
    h = exact(SYSTEMS["low_pass_50hz"], fr.freq_hz)
    reference = F.FrequencyResponse.from_h(fr.freq_hz, h, np.ones(h.size))
    path = F.bode_plot(fr, tmp_path / "plots" / "bode.png", "low pass", reference)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("kwargs", [{}, {"period": 100, "segment": 100}, {"period": 1000},
                                    {"segment": 5000}, {"period": 100, "discard_periods": 10}])
def test_impossible_estimates_refused(kwargs):
    """Neither or both averaging modes, fewer whole periods than discarded, a segment
    longer than the signal: EstimateError (a ValueError) saying so."""
    u = np.ones(1000)
    with pytest.raises(F.EstimateError):
        F.estimate(u, u, DT_S, **kwargs)


def test_unequal_signals_and_silent_excitation_refused():
    """u and y of different lengths, or a u without power: refused, saying why."""
    with pytest.raises(ValueError, match="equally long"):
        F.estimate(np.ones(100), np.ones(99), DT_S, segment=50)
    with pytest.raises(F.EstimateError, match="no power"):
        F.estimate(np.zeros(400), np.ones(400), DT_S, period=100)
