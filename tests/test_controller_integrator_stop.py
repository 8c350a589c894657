"""The speed integrator's stop (issue 14 part 5; since issue 13 the ``speed_antiwindup`` modes
'conditional' and 'torque_setpoint'): conditional integration on the PI's own output or, as
SINAMICS freezes the I component at the torque limit, on the whole torque setpoint; against
hand-computed integrator values, and the LD386 finding that neither removes the 1 m step's
overshoot."""

import pytest

from hil.controller.blocks import PI
from hil.controller.config import load_controller
from hil.controller.loops import SpeedLoop
from hil.validate.experiments import moves
from plant.config import load_machine


def test_step_within_stops_the_integrator_on_the_total():
    """kp = 1, ki T = 0.1, limit 1: an error of 0.5 with 0.8 added downstream puts the total
    at 1.3, beyond the limit; the integrator stays, the output is the PI's own 0.5.  With
    nothing added the same step integrates 0.05 (by hand)."""
    frozen, free = PI(1.0, 1.0, 0.1, 1.0), PI(1.0, 1.0, 0.1, 1.0)
    assert frozen.step_within(0.5, 0.8) == 0.5 and frozen.integ == 0.0
    assert free.step(0.5) == 0.5 and free.integ == pytest.approx(0.05)
    # an error pulling back out of the limit still integrates
    assert frozen.step_within(-0.5, 2.0) == -0.5 and frozen.integ == pytest.approx(-0.05)


def speed_loop(stop: str) -> SpeedLoop:
    cfg = load_machine(moves.LD386, overrides={"controller": {"speed_antiwindup": stop}})
    sec = load_controller(cfg)
    mo = cfg.motor
    return SpeedLoop(sec, 1.0 / mo.pwm_frequency_hz, cfg.machine.kind,
                     mo.force_constant_n_per_a, mo.current_max_a)


@pytest.mark.parametrize("stop", ["conditional", "torque_setpoint"])
def test_feed_forward_at_the_current_limit(stop):
    """With the current feed-forward alone at I_max and a small speed error pushing further,
    the current setpoint sits at I_max either way; the integrator grows by K_p T / T_n e
    per cycle when only the PI's output counts (by hand), and stays at 0 when the whole
    torque setpoint does (SINAMICS)."""
    loop = speed_loop(stop)
    err, n = 0.01, 50
    for _ in range(n):
        assert loop.step(err, 0.0, loop.i_max) == loop.i_max
    expected = n * loop.pi.ki_t * err if stop == "conditional" else 0.0
    assert loop.pi.integ == pytest.approx(expected, abs=1e-12)


def test_ld386_overshoot_is_not_removed_by_freezing_at_the_torque_limit():
    """The validate row's finding: the integrator charges after the force has left its
    limit, so the SINAMICS freeze gives the same peak as conditional integration, above the
    paper's 2.5 m/s, while the integrator held at the cruise force agrees with it."""
    cfg = load_machine(moves.LD386)
    frozen = moves.linear_move(load_machine(moves.LD386, overrides={
        "controller": {"speed_antiwindup": "torque_setpoint"}}))
    as_is = moves.linear_move(cfg)
    held = moves.linear_move(cfg, moves.cruise_force(cfg))
    assert frozen.peak_velocity == pytest.approx(as_is.peak_velocity, abs=1e-3)
    assert frozen.peak_velocity > moves.PAPER_PEAK_VELOCITY + moves.PAPER_PEAK_VELOCITY_PM
    assert abs(held.peak_velocity - moves.PAPER_PEAK_VELOCITY) <= moves.PAPER_PEAK_VELOCITY_PM
