"""What a study measures on each simulated machine: every output with its unit.

Output names carry their unit, as machine-file keys do (``settling_time_s``,
``following_error_max_um``); results, reports and constraints use these names.  A value
that does not exist on a sample (a step that never settles within the run, a response
without a resonance peak) is NaN, and the reports count those samples.
"""

import math
from dataclasses import dataclass

import numpy as np

from hil.measure.frequency_response import FrequencyResponse, bandwidth_hz, peaks


@dataclass(frozen=True)
class Output:
    """One output: its name (the unit in it), unit and meaning; ``nan_is_absent``: NaN
    means there is nothing to limit (no resonance peak, no phase crossover), so a
    tuning constraint on it is met."""
    name: str
    unit: str
    doc: str
    nan_is_absent: bool = False


OUTPUTS = {o.name: o for o in (
    Output("rise_time_s", "s", "10 % to 90 % of the step"),
    Output("lag_50pct_s", "s", "time from the step to half of it (the lag seed 000 §5 names)"),
    Output("overshoot_pct", "%", "peak beyond the target, % of the step (negative: it stays "
           "below the target within the run)"),
    Output("settling_time_s", "s", "from the step until the response stays within the "
           "settling band around the target (NaN: not within the run)"),
    Output("following_error_max_um", "um", "largest |setpoint - actual position| at the "
           "position-control cycle, over every axis"),
    Output("following_error_rms_um", "um", "rms following error over the run and the axes"),
    Output("contour_error_max_um", "um", "program: largest deviation of the NC's contour "
           "monitoring (actual against its loop model); circle: largest |r - R|"),
    Output("circularity_um", "um", "circular deviation G of ISO 230-4: max r - min r over "
           "the circle"),
    Output("alarms", "1", "NC alarms raised during the run"),
    Output("bandwidth_hz", "Hz", "-3 dB below the low-frequency gain (NaN: not within the "
           "measured band)"),
    Output("peaking_db", "dB", "largest magnitude above the low-frequency gain"),
    Output("resonance_freq_hz", "Hz", "the highest resonance peak (prominence >= 6 dB, "
           "coherence >= 0.9; NaN: none)", nan_is_absent=True),
    Output("resonance_peak_db", "dB", "that peak's magnitude against the low-frequency "
           "gain (NaN: none)", nan_is_absent=True),
    Output("phase_margin_deg", "deg", "open loop L = H/(1-H) from the closed-loop response "
           "H: the least angle between L and -1 where |L| passes 1 (NaN: no crossover)"),
    Output("gain_margin_db", "dB", "the least -|L| in dB where L passes the negative real "
           "axis above the first crossover (NaN: none within the measured band)",
           nan_is_absent=True),
    Output("y", "1", "analytic test function's value (pipeline checks only)"),
    Output("g", "1", "analytic test function's constraint value (pipeline checks only)"),
)}


@dataclass(frozen=True)
class StepMetrics:
    """Figures of a step response, seconds and % of the step."""
    rise_time_s: float
    lag_50pct_s: float
    overshoot_pct: float
    settling_time_s: float


def _crossing(t: np.ndarray, rel: np.ndarray, level: float) -> float:
    """First time ``rel`` reaches ``level`` (linear between samples); NaN if never."""
    above = np.flatnonzero(rel >= level)
    if above.size == 0:
        return math.nan
    i = int(above[0])
    if i == 0:
        return float(t[0])
    return float(t[i - 1] + (level - rel[i - 1]) / (rel[i] - rel[i - 1]) * (t[i] - t[i - 1]))


def step_metrics(t: np.ndarray, y: np.ndarray, y0: float, step: float,
                 band_pct: float) -> StepMetrics:
    """Figures of the response ``y`` (shape (n,)) at times ``t`` (s from the step) to a
    step from ``y0`` by ``step``; settling within ``band_pct`` % of the step around the
    target.  Crossings are interpolated linearly between samples, so the figures move
    smoothly with the parameters instead of in whole ticks."""
    rel = (y - y0) / step
    rise = _crossing(t, rel, 0.9) - _crossing(t, rel, 0.1)
    overshoot = 100.0 * (float(np.max(rel)) - 1.0)
    error = np.abs(rel - 1.0)
    band = band_pct / 100.0
    outside = np.flatnonzero(error > band)
    if outside.size == 0:
        settle = float(t[0])
    elif outside[-1] == rel.size - 1:
        settle = math.nan
    else:  # where the error falls through the band, linear between the two samples
        i = int(outside[-1])
        settle = float(t[i] + (error[i] - band) / (error[i] - error[i + 1]) * (t[i + 1] - t[i]))
    return StepMetrics(rise, _crossing(t, rel, 0.5), overshoot, settle)


def following_error_um(errors: list[np.ndarray]) -> dict[str, float]:
    """Max and rms of the following errors (m, one array per axis) in µm."""
    e = np.concatenate([np.asarray(x, dtype=float) for x in errors]) * 1e6
    return {"following_error_max_um": float(np.max(np.abs(e))),
            "following_error_rms_um": float(np.sqrt(np.mean(e * e)))}


def open_loop(fr: FrequencyResponse, prefilter: np.ndarray | None = None) -> np.ndarray:
    """The open loop L = T/(1-T) of a unity-feedback loop whose closed-loop response is
    ``fr`` (setpoint to actual value), T = H / F after the setpoint prefilter's response
    ``prefilter`` (complex, shape of ``fr.h``; None: no prefilter)."""
    t = fr.h if prefilter is None else fr.h / prefilter
    return t / (1.0 - t)


MIN_COHERENCE = 0.9  # bins below it are noise, not the loop (as for the resonance peaks)


def _crossings(x: np.ndarray, level: float, usable: np.ndarray) -> np.ndarray:
    """Indices i where ``x`` passes ``level`` between i and i+1, both bins usable."""
    above = x >= level
    return np.flatnonzero((above[:-1] != above[1:]) & usable[:-1] & usable[1:])


def _interpolate(x: np.ndarray, i: int, level: float, y: np.ndarray) -> float:
    """y, linear between the points i and i+1, where x passes ``level`` between them."""
    w = (x[i] - level) / (x[i] - x[i + 1])
    return float(y[i] + w * (y[i + 1] - y[i]))


def margins(fr: FrequencyResponse, prefilter: np.ndarray | None = None) -> dict[str, float]:
    """Phase margin (deg) and gain margin (dB) of the open loop L behind ``fr``, over the
    bins measured with coherence >= 0.9.  Phase margin: the least angle between L and -1
    where |L| passes 1, 180 deg - |phase of L in (-180, 180]| (a loop with resonances
    crosses more than once).  Gain margin: the least -20 log10 |L| where L passes the
    negative real axis above the first crossing (below it a loop with an integrator
    behind a PI starts near -180 deg)."""
    lo = open_loop(fr, prefilter)
    mag = 20.0 * np.log10(np.abs(lo))
    usable = fr.coherence >= MIN_COHERENCE
    gains = _crossings(mag, 0.0, usable)
    if gains.size == 0:
        return {"phase_margin_deg": math.nan, "gain_margin_db": math.nan}
    phase = np.degrees(np.angle(lo))
    pm = min(180.0 - abs(_interpolate(mag, i, 0.0, _continued(phase, i))) for i in gains)
    # L passes the negative real axis: its imaginary part changes sign where Re L < 0
    turns = [i for i in _crossings(lo.imag, 0.0, usable)
             if i > gains[0] and lo.real[i] < 0.0 and lo.real[i + 1] < 0.0]
    gm = min((-_interpolate(lo.imag, i, 0.0, mag) for i in turns), default=math.nan)
    return {"phase_margin_deg": pm, "gain_margin_db": gm}


def _continued(phase: np.ndarray, i: int) -> np.ndarray:
    """``phase`` (deg) with bin i+1 taken within 180 deg of bin i, for interpolating
    between the two across the +-180 deg seam."""
    out = phase.copy()
    out[i + 1] = phase[i] + (phase[i + 1] - phase[i] + 180.0) % 360.0 - 180.0
    return out


def response_figures(fr: FrequencyResponse, prefilter: np.ndarray | None = None
                     ) -> dict[str, float]:
    """Bandwidth, peaking, the highest resonance and the margins of a closed loop."""
    bw = bandwidth_hz(fr)
    base = float(fr.magnitude_db[0])
    found = peaks(fr)
    top = max(found, key=lambda p: p.magnitude_db) if found else None
    return {"bandwidth_hz": math.nan if bw is None else bw,
            "peaking_db": float(np.max(fr.magnitude_db) - base),
            "resonance_freq_hz": math.nan if top is None else top.freq_hz,
            "resonance_peak_db": math.nan if top is None else top.magnitude_db - base,
            **margins(fr, prefilter)}


def circle_figures(x: np.ndarray, y: np.ndarray, center: tuple[float, float],
                   radius: float) -> dict[str, float]:
    """Circularity (max r - min r) and the largest |r - R| of the path (x, y) in m, µm."""
    r = np.hypot(x - center[0], y - center[1])
    return {"circularity_um": float((r.max() - r.min()) * 1e6),
            "contour_error_max_um": float(np.max(np.abs(r - radius)) * 1e6)}
