"""The controller's own measuring functions, run in lock-step against the plant.

Like SINUMERIK's drive measuring functions they open the outer loops: a
current-loop measurement drives the current setpoint with the speed loop off,
a speed-loop measurement drives the speed setpoint with the position loop off,
a position step jumps the position setpoint past the interpolator.  Frequency
responses use a PRBS on that setpoint (plus an offset, so that a speed-loop
measurement stays clear of the friction reversal) and the H1 estimate over
whole PRBS periods.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.controller.interpolator import ProfileSamples
from hil.measure.frequency_response import FrequencyResponse, estimate
from hil.measure.prbs import prbs
from hil.sim import LockStep, SimResult
from plant.config import MachineConfig

#: what each measurement drives and reads (SimResult signal names)
LOOPS = {"current": ("iq_set", "iq_meas"), "speed": ("w_set", "w_act")}


@dataclass(frozen=True)
class StepResponse:
    """A step measurement.

    Attributes:
        t_s: time from the step, s, shape (n,).
        setpoint, response: the commanded and measured signal, shape (n,), in ``unit``.
        unit: unit of both.
        step: the step height.
        rise_time_s: 10 % to 90 % of the step.
        overshoot_pct: peak beyond the final value, % of the step.
        final: mean response over the last tenth.
        sim: the whole recording.
    """
    t_s: np.ndarray
    setpoint: np.ndarray
    response: np.ndarray
    unit: str
    step: float
    rise_time_s: float
    overshoot_pct: float
    final: float
    sim: SimResult


def step_figures(t: np.ndarray, y: np.ndarray, y0: float, step: float):
    """(rise time 10-90 % in s, overshoot in % of the step, final value) of a step from y0."""
    rel = (y - y0) / step
    n = len(y)
    final = float(np.mean(y[-max(1, n // 10):]))
    i10 = int(np.argmax(rel >= 0.1))
    i90 = int(np.argmax(rel >= 0.9))
    rise = float(t[i90] - t[i10]) if rel.max() >= 0.9 else math.nan
    overshoot = float(100.0 * (rel.max() - (final - y0) / step))
    return rise, overshoot, final


def _session(cfg: MachineConfig, x0: float) -> LockStep:
    ls = LockStep(cfg, x0)
    ls.enable()
    return ls


def _step(sim: SimResult, sig_set: str, sig_act: str, unit: str, scale: float, t0: float,
          step: float, y0: float = 0.0) -> StepResponse:
    t = sim["t_s"] - t0
    y = sim[sig_act] * scale
    post = t >= 0.0
    rise, over, final = step_figures(t[post], y[post], y0, step)
    return StepResponse(t, sim[sig_set] * scale, y, unit, step, rise, over, final, sim)


def current_step(cfg: MachineConfig, step_a: float, duration_s: float = 0.003,
                 x0: float = 0.0, pre_s: float = 0.001) -> StepResponse:
    """q-current setpoint step of ``step_a`` (A) with the speed loop off; the rotor is free,
    so keep ``duration_s`` short against the back-EMF build-up (as the drive's own
    current-loop measurement does)."""
    ls = _session(cfg, x0)
    ls.ctrl.run_source("current", lambda t: step_a if t >= pre_s else 0.0)
    sim = ls.run(duration_s + pre_s)
    return _step(sim, "iq_set", "iq_meas", "A", 1.0, pre_s, step_a)


def speed_step(cfg: MachineConfig, step: float, duration_s: float = 0.05, x0: float = 0.0,
               pre_s: float = 0.002) -> StepResponse:
    """Speed setpoint step of ``step`` (table velocity, m/s or rad/s) with the position loop
    off; the response is the table velocity measured from the motor encoder."""
    ls = _session(cfg, x0)
    w = step / ls.ctrl.ratio
    ls.ctrl.run_source("speed", lambda t: w if t >= pre_s else 0.0)
    sim = ls.run(duration_s + pre_s)
    return _step(sim, "w_set", "w_act", "m/s", ls.ctrl.ratio, pre_s, step)


def position_step(cfg: MachineConfig, x0: float, step: float,
                  duration_s: float = 0.3) -> StepResponse:
    """Position setpoint step of ``step`` (m or rad) from ``x0``, past the interpolator."""
    ls = _session(cfg, x0)
    target = x0 + step
    hold = np.array([target, target])
    zero = np.zeros(2)
    ls.ctrl.run_points(ProfileSamples(np.array([0.0, ls.ctrl.ipo_period_s]), hold, zero, zero))
    sim = ls.run(duration_s)
    return _step(sim, "x_set", "x_act", "m", 1.0, 0.0, step, y0=x0)


@dataclass(frozen=True)
class BodeMeasurement:
    """A frequency response and what produced it.

    Attributes:
        loop: "current" or "speed".
        response: the H1 estimate, setpoint -> actual value.
        dt_s: sample time of the estimate (the loop's cycle).
        sim: the whole recording.
    """
    loop: str
    response: FrequencyResponse
    dt_s: float
    sim: SimResult


def bode(cfg: MachineConfig, loop: str, amplitude: float, offset: float = 0.0,
         order: int = 12, hold: int = 1, periods: int = 4, x0: float = 0.0,
         progress=None) -> BodeMeasurement:
    """Closed-loop frequency response of the current loop (amplitude and offset in A) or the
    speed loop (rad/s at the motor, m/s for linear motors) with a PRBS of ``order``,
    ``hold`` samples per bit and ``periods`` periods (the first is discarded).  The
    response's coherence is from the spectra averaged over those ``periods`` periods: 1 by
    construction with one, biased toward 1 with few."""
    if loop not in LOOPS:
        raise ValueError(f"loop must be one of {', '.join(LOOPS)}, not {loop!r}")
    ls = _session(cfg, x0)
    dt = ls.plant.pwm_period * ls.ctrl.sec.speed_cycle_ratio
    exc = prbs(order, amplitude, dt, hold=hold, periods=periods + 1)
    signal = exc.signal
    last = len(signal) - 1
    lead_in = int(round(0.05 / dt))  # let the offset settle before the PRBS starts

    def excitation(t: float) -> float:
        k = int(round(t / dt)) - lead_in
        return signal[k] if 0 <= k <= last else 0.0

    ls.ctrl.run_source(loop, lambda t: offset, excitation)
    sim = ls.run((len(signal) + lead_in) * dt, progress)
    stride = ls.ctrl.sec.speed_cycle_ratio
    u_name, y_name = LOOPS[loop]
    u = sim[u_name][::stride][lead_in:lead_in + len(signal)]
    y = sim[y_name][::stride][lead_in:lead_in + len(signal)]
    fr = estimate(u - offset, y - np.mean(y), dt, period=exc.period_samples)
    return BodeMeasurement(loop, fr, dt, sim)


def write_step_csv(path: Path, res: StepResponse) -> Path:
    """Columns t_s, setpoint, response (units in the header comment)."""
    header = f"unit: {res.unit}\nt_s,setpoint,response"
    np.savetxt(path, np.column_stack([res.t_s, res.setpoint, res.response]), delimiter=",",
               header=header, comments="# ")
    return path
