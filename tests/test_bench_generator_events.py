"""The bench generator's switching instants: breakaway of a stuck load and the presliding
spring's restart at a reversal happen where they happen, not at an interval's end.

References:
* the breakaway of a rigid axis under a current step, by hand: the first-order current
  i(t) = I (1 - exp(-t/T)) reaches the breakaway force at t* = T ln(kf I / (kf I - F_H)),
  and beyond it M x'' = kf i(t) - F_C integrates in closed form (no viscous friction);
* how the time is cut into intervals: the solution of one ODE does not depend on it, so
  one long interval and 64 short ones must agree (a restart handled at an interval's
  end would put the presliding spring's origin where the interval began);
* the plant's kernel as a second solver at fine sub-steps (its semi-implicit Euler
  converges to the same equations), open loop under the same held currents: the gap
  between motor and load through the backlash's impacts and the table's position through
  the presliding spring's reversals.
"""

import math

import numpy as np
import pytest

from hil.bench.identify_gen.axis import Axis, axis_params
from hil.bench.identify_gen.cases import LEAD, SCREW, TWO_MASS, merged
from plant import Plant
from plant.config import load_machine

#: the bench's undeclared backlash (screw_backlash): 10 um of gap at the table
BACKLASH = merged(TWO_MASS, {"coupling": {"backlash_rad": 1e-5 / (LEAD / (2 * math.pi))}})
#: the bench's presliding spring (screw_presliding)
PRESLIDING = {"presliding": {"enabled": True, "stiffness_n_per_m": 3e7, "x1_m": 1e-6,
                             "exponent": 1.0}}


def test_stuck_axis_breaks_away_within_the_interval():
    """Rigid screw axis, Coulomb F_C = F_H, no viscous friction, at rest; a current step
    of kf I = 2 F_H held over one 4 ms interval: the load breaks away at t* = T ln 2 and
    travels x(4 ms) by the closed form (stuck to the end it would not move at all)."""
    p = axis_params(load_machine(SCREW, {"friction": {"viscous_ns_per_m": 0.0}}))
    assert p.fh == p.fc and p.b == 0.0 and p.b_motor == 0.0
    x0, dt = 0.1, 4e-3
    amp = 2.0 * p.fh / p.kf
    axis = Axis(p, x0)
    axis.step(dt, amp)
    tau, f_amp = p.t_cl, p.kf * amp
    t_star = tau * math.log(f_amp / (f_amp - p.fh))

    def g(t):  # M v(t) up to a constant
        return f_amp * (t + tau * math.exp(-t / tau)) - p.fc * t

    def big_g(t):  # M x(t) up to a linear function
        return f_amp * (t * t / 2 - tau * tau * math.exp(-t / tau)) - p.fc * t * t / 2

    v = (g(dt) - g(t_star)) / p.mass
    x = (big_g(dt) - big_g(t_star) - g(t_star) * (dt - t_star)) / p.mass
    assert axis.y[3] == pytest.approx(v, rel=1e-6)
    assert axis.table_position - x0 == pytest.approx(x, rel=1e-6)


def _run(p, x0, schedule):
    """An axis at rest at ``x0`` stepped by ``schedule``: (dt, current) per interval."""
    axis = Axis(p, x0)
    for dt, i_set in schedule:
        axis.step(dt, i_set)
    return axis


@pytest.mark.parametrize("over,i_back,tol", [(PRESLIDING, -1.0, 1e-10),
                                             (PRESLIDING, -0.4, 1e-10),
                                             (BACKLASH, -1.0, 2e-8)])
def test_one_interval_or_many_give_one_solution(over, i_back, tol):
    """Pushed forward for 20 ms, then a current that reverses the table within the next
    8 ms: that 8 ms as one interval or as 64 agree (positions to ``tol``, m; the
    presliding force to 1 mN), and the presliding spring restarted at the same place.
    Through the backlash the positions agree to nanometres only: the flanks' contact, a
    kink in the spring force and a step in the damper's, is stepped over by solve_ivp's
    error control rather than located as an event (a twentieth of the scale's step)."""
    p = axis_params(load_machine(SCREW, over))
    push = [(2.5e-4, 0.3)] * 80
    one = _run(p, 0.1, push + [(8e-3, i_back)])
    many = _run(p, 0.1, push + [(8e-3 / 64, i_back)] * 64)
    assert one.y[3] < 0.0, "the table did not reverse within the interval"
    assert np.allclose(one.y[[0, 2]], many.y[[0, 2]], rtol=0, atol=tol)
    assert one.y[5] == pytest.approx(many.y[5], abs=1e-3)
    assert one.x_rev == pytest.approx(many.x_rev, abs=1e-10)
    assert one.direction == many.direction


def _open_loop(over, sub, seconds):
    """Generator and plant (``sub`` sub-steps per PWM period) under the same held currents;
    returns (plant, generator) arrays of shape (n, 2): motor and table position, m."""
    cfg = load_machine(SCREW, {**over, "simulation": {"substep_s": 2.5e-4 / sub}})
    p = axis_params(cfg)
    plant = Plant(cfg, 0.1)
    axis = Axis(p, 0.1)
    period = 1.0 / cfg.motor.pwm_frequency_hz
    n = int(round(seconds / period))
    out = np.empty((n, 2, 2))
    for k in range(n):
        t = k * period
        i_set = 1.2 * math.sin(2 * math.pi * 2.5 * t) + 0.2 * math.sin(2 * math.pi * 11 * t)
        plant.set_input(iq_ref_a=i_set)
        plant.step(plant.sub_per_pwm)
        axis.step(period, i_set)
        out[k, 0] = plant.output("motor_pos") * p.ratio, plant.output("table_pos")
        out[k, 1] = axis.motor_position, axis.table_position
    return out[:, 0], out[:, 1]


def test_backlash_impacts_as_the_plant_at_fine_substeps():
    """Through the flank changes of 0.3 s of sine currents (Coulomb friction, the load
    sticking at each reversal): the gap, motor minus table, within 15 nm rms and 0.15 um
    at most of the plant's at 16 sub-steps per PWM period (the generator stuck to each
    interval's end before: 40 nm rms, 0.44 um)."""
    plant, gen = _open_loop(BACKLASH, 16, 0.3)
    d = np.diff(plant, axis=1)[:, 0] - np.diff(gen, axis=1)[:, 0]
    assert np.sqrt(np.mean(d * d)) < 15e-9
    assert np.max(np.abs(d)) < 0.15e-6


def test_presliding_reversals_as_the_plant_at_fine_substeps():
    """0.6 s of sine currents through the presliding spring's reversals: the table within
    0.3 um rms of the plant's at 16 sub-steps per PWM period (restarted at the
    intervals' ends before: 0.84 um)."""
    plant, gen = _open_loop(PRESLIDING, 16, 0.6)
    d = plant[:, 1] - gen[:, 1]
    assert np.sqrt(np.mean(d * d)) < 0.3e-6
