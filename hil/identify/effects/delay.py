"""A measurement or transport delay: what neither residual sees.

When the position and the current are measured equally late, the inverse model's force
balance holds in the delayed signals and the encoders agree with each other; only the
closed loop notices, because the controller acts on old feedback.  The evidence is the
lag of the cross-correlation between the measured effort and the closed-loop replay's,
and the fit picks the delay (whole PWM periods, as the drive samples) whose replay
matches best.
"""

import numpy as np

from hil.identify.effects.base import REPLAY, Effect, Term
from hil.identify.replay import ERROR_START

#: longest delay looked for, in PWM periods (the plant's ring holds 32)
MAX_PERIODS = 32


def xcorr_lag(measured: np.ndarray, model: np.ndarray, max_lag: int) -> float:
    """Lag (samples, sub-sample by a parabola through the peak) by which ``measured``
    trails ``model``; both signals are differenced first so that their slow common
    content does not flatten the peak."""
    a = np.diff(measured) - np.mean(np.diff(measured))
    b = np.diff(model) - np.mean(np.diff(model))
    n = a.size
    c = np.array([float(a[lag:] @ b[:n - lag]) for lag in range(max_lag + 1)])
    k = int(np.argmax(c))
    if 0 < k < max_lag:
        den = c[k - 1] - 2 * c[k] + c[k + 1]
        if den < 0:
            return k + 0.5 * (c[k - 1] - c[k + 1]) / den
    return float(k)


class TimeDelay(Effect):
    """Feedback (position and current) measured late."""
    name = "time_delay"
    domain = REPLAY

    def declared(self, ctx):
        d = ctx.cfg.sensors.delay_s
        return Term(self, {"delay_s": d}, np.zeros(0)) if d > 0 else None

    def propose(self, ctx, residual, model):
        rep = model.replay()
        if rep is None or rep.status != 0:
            return None
        pwm = model.pwm_period
        dt = ctx.rec.dt
        max_lag = max(1, int(np.ceil(MAX_PERIODS * pwm / dt)))
        lag = xcorr_lag(ctx.rec.effort[ERROR_START:], rep.effort[ERROR_START:], max_lag)
        base = ctx.cfg.sensors.delay_s
        guess = round(lag * dt / pwm)
        if guess < 1:
            return None
        err0 = model.effort_error(rep)
        best = None
        for periods in sorted({max(1, guess - 1), guess, min(MAX_PERIODS, guess + 1)}):
            d = base + periods * pwm
            trial = model.replay(extra={"sensors": {"delay_s": d}})
            if trial is None or trial.status != 0:
                continue
            err = model.effort_error(trial)
            if best is None or err < best[0]:
                best = (err, d)
        if best is None:
            return None
        ex = max(0.0, 1.0 - (best[0] / err0) ** 2) if err0 > 0 else 0.0
        ev = {"explained": ex, "xcorr_lag_s": lag * dt,
              "text": f"the measured effort trails the model's by {lag * dt * 1e3:.3g} ms "
                      f"(cross-correlation peak); the replay fits best with "
                      f"{best[1] * 1e3:.4g} ms"}
        return Term(self, {"delay_s": float(best[1])}, np.zeros(0), True, ev)

    def columns(self, ctx, shape):
        return np.zeros((ctx.rec.n, 0))

    def n_coef(self, shape):
        return 0

    def params(self, ctx, shape, coef):
        return {"delay_s": shape["delay_s"]}

    def overrides(self, ctx, shape, coef, model):
        return {"sensors": {"delay_s": shape["delay_s"]}}
