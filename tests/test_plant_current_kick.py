"""The first-order current lag's push on the mechanics (issue 30, the cogging trace of the
second generator): kick-drift sub-steps meet the exact motion at their boundaries.

Checked against the closed form, not the kernel: a frictionless rigid axis driven by the
lag di/dt = (c_k - i) / T_cl toward targets c_k held for one PWM period each.  Over a period
from t_k, i(s) = c_k + (i_k - c_k) e^(-s/T), so the velocity gains
K/M (c_k dt + (i_k - c_k) T (1 - e^(-dt/T))) and the position
v_k dt + K/M (c_k dt^2/2 + (i_k - c_k) T (dt - T (1 - e^(-dt/T)))), period by period.

Where the kick was the current at the sub-step's start (before issue 30), a rigid screw with
T = 0.5 ms strayed from it by 95 nm within 0.1 s of random setpoints at one sub-step per
250 us PWM period (6 nm at four); with the lag's current averaged around the kick it stays
on the closed form to round-off (below 1 pm), at one sub-step per period and at four.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from plant import Plant
from plant.config import load_machine
from plant.effects.pmsm import first_order_kick_weights

SCREW = Path(__file__).resolve().parents[1] / "configs" / "identify" / "bench_screw.toml"
#: PWM periods of the stimulus (0.1 s at 4 kHz)
PERIODS = 400


def _closed_form(targets: np.ndarray, dt: float, t_cl: float, accel_per_amp: float
                 ) -> np.ndarray:
    """Table position (m) at the start of every period and after the last, from rest at 0:
    the lag's exact current integrated twice in closed form, period by period."""
    decay = math.exp(-dt / t_cl)
    x, v, i = 0.0, 0.0, 0.0
    out = [x]
    for c in targets:
        x += v * dt + accel_per_amp * (c * dt * dt / 2 + (i - c) * t_cl
                                       * (dt - t_cl * (1.0 - decay)))
        v += accel_per_amp * (c * dt + (i - c) * t_cl * (1.0 - decay))
        i = c + (i - c) * decay
        out.append(x)
    return np.array(out)


@pytest.mark.parametrize("substeps", [1, 4])
def test_lag_driven_axis_meets_the_closed_form(substeps):
    period = 2.5e-4
    overrides = {"friction": {"viscous_ns_per_m": 0.0, "coulomb_n": 0.0},
                 "simulation": {"substep_s": period / substeps}}
    cfg = load_machine(SCREW, overrides)
    plant = Plant(cfg)
    assert plant.sub_per_pwm == substeps and plant.pwm_period == pytest.approx(period)
    mo, r = cfg.motor, cfg.mechanics.lead_m / (2 * math.pi)
    mass = mo.inertia_kgm2 / r ** 2 + cfg.table.mass_kg
    targets = np.random.default_rng(30).uniform(-3.0, 3.0, PERIODS)
    exact = _closed_form(targets, period, cfg.current_loop.time_constant_s,
                         mo.torque_constant_nm_per_a / r / mass)
    x = [plant.output("table_pos")]
    for c in targets:
        plant.set_input(iq_ref_a=c)
        assert plant.step(substeps) == 0
        x.append(plant.output("table_pos"))
    err = np.abs(np.array(x) - exact)
    # round-off of positions up to 0.6 mm
    assert err.max() < 1e-12, err.max()


@pytest.mark.parametrize("dt, t_cl", [(2.5e-4, 5e-4), (2e-5, 1e-5), (1e-6, 1e-2),
                                       (1e-3, 1e-6)])
def test_kick_weights_are_the_lags_averages(dt, t_cl):
    """The two weights against the averages they stand for, by adaptive quadrature (scipy's
    quad): 1 - s/dt and s/dt weighting e^(-s/T) over a sub-step, per sub-step (the second
    less the e^(-dt/T) / 2 that the next sub-step's start current carries)."""
    from scipy.integrate import quad

    now, after = first_order_kick_weights(dt, t_cl)
    opts = {"epsabs": 1e-14, "epsrel": 1e-12, "limit": 200, "points": [min(dt, t_cl) / 10]}
    ref_now = quad(lambda s: (1 - s / dt) * math.exp(-s / t_cl), 0, dt, **opts)[0] / dt
    ref_after = quad(lambda s: s / dt * math.exp(-s / t_cl), 0, dt, **opts)[0] / dt
    assert now == pytest.approx(ref_now, rel=1e-9)
    assert after + 0.5 * math.exp(-dt / t_cl) == pytest.approx(ref_after, rel=1e-9)
