"""The machine-file keys for another simulator's conventions (issue 30 item 4), each against
an analytic case: encoder rounding and zero at the start, the current ADC's full scale.  Each key's default is
today's behaviour, which the other plant tests hold bit for bit."""

import math

import numpy as np
import pytest

from plant import Plant
from plant import layout as L
from plant.effects.sensors import counts, measure_current
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
#: the Arrow without measurement delay or noise: its counts are those of the true positions
QUIET = {"sensors": {"delay_s": 0.0, "current_noise_a": 0.0}}


def _sensors(**keys) -> dict:
    return {"sensors": {**QUIET["sensors"], **keys}}


def test_count_rounding_against_floor_and_nearest():
    """Definition: floor(x) and floor(x + 1/2) of the position in counts x, on either side
    of zero (-0.25 counts: -1 by floor, 0 rounded; 2.5: 2 and 3)."""
    per = 4.0
    for x, floor, nearest in ((-0.25, -1.0, 0.0), (2.5, 2.0, 3.0), (2.49, 2.0, 2.0),
                              (-1.75, -2.0, -2.0)):
        assert counts(x / per, per, 0.0) == floor
        assert counts(x / per, per, 1.0) == nearest
    assert counts(1.0, 0.0, 1.0) == 0.0  # no such encoder


@pytest.mark.parametrize("rounding", ["floor", "round"])
def test_encoder_and_scale_count_a_known_position(rounding):
    """Analytic: the Arrow's table at rest at x shows the motor-encoder count of
    x / (lead/2pi) * counts/rev / 2pi and the scale count of x / resolution, floored or
    rounded; x is chosen 3/4 of a count past a whole motor count, where the two differ by
    one (and 0.3 of a scale count: the same scale count either way, by arithmetic)."""
    plant = Plant.from_file(ARROW, overrides=_sensors(encoder_rounding=rounding))
    se, ratio = plant.config.sensors, plant.built.ratio
    per_rad = se.encoder_counts_per_rev / (2.0 * math.pi)
    x = (1234567.75 / per_rad) * ratio
    plant.reset(x)
    whole = {"floor": math.floor, "round": lambda c: math.floor(c + 0.5)}[rounding]
    assert plant.output("encoder_counts") == whole(x / ratio * per_rad)
    assert plant.output("encoder_counts") == 1234567 + (rounding == "round")
    assert plant.output("scale_counts") == whole(x / se.scale_resolution_m)


def test_encoders_count_from_the_start_position():
    """Analytic: with encoder_zero_at_start the first counts are 0 at any start position
    (also through a measurement delay), and after a move the counts are those of the
    travel since the start, q((theta - theta_0) per rad) and q((x - x_0) / resolution);
    without it the first counts are those of the position itself."""
    x0 = 0.123456789
    for rounding in ("floor", "round"):
        plant = Plant.from_file(ARROW, x0, _sensors(encoder_zero_at_start=True,
                                                    encoder_rounding=rounding))
        assert plant.output("encoder_counts") == 0.0
        assert plant.output("scale_counts") == 0.0
    delayed = Plant.from_file(ARROW, x0, {"sensors": {"encoder_zero_at_start": True,
                                                      "delay_s": 0.000375}})
    delayed.set_input(iq_ref_a=5.0)
    first = delayed.run(3, delayed.sub_per_pwm)
    assert np.all(first["encoder_counts"] == 0.0) and np.all(first["scale_counts"] == 0.0)
    plant = Plant.from_file(ARROW, x0, _sensors(encoder_zero_at_start=True))
    theta0 = plant.output("motor_pos")
    plant.set_input(iq_ref_a=5.0)
    plant.run(200, plant.sub_per_pwm)
    se = plant.config.sensors
    per_rad = se.encoder_counts_per_rev / (2.0 * math.pi)
    travel = plant.output("motor_pos") - theta0
    assert travel * per_rad > 1000.0  # it moved
    assert plant.output("encoder_counts") == math.floor(travel * per_rad)
    assert plant.output("scale_counts") == math.floor(
        (plant.output("table_pos") - x0) / se.scale_resolution_m)
    absolute = Plant.from_file(ARROW, x0, QUIET)
    assert absolute.output("encoder_counts") == math.floor(theta0 * per_rad)


def test_current_adc_clips_at_full_scale():
    """Definition: after noise and quantization the reading is limited to +-full scale: 5 A
    and -5 A read +-2 A, 1.5 A reads 1.5 A; 0 (the default) never clips."""
    p = np.zeros(L.P_COUNT)
    s = np.zeros(L.S_COUNT)
    assert measure_current(p, s, 5000.0) == 5000.0
    p[L.P_I_FULL_SCALE] = 2.0
    assert [measure_current(p, s, i) for i in (5.0, -5.0, 1.5)] == [2.0, -2.0, 1.5]


def test_plant_measures_no_current_beyond_full_scale():
    """Analytic: the Arrow's current loop asked for 6 A with a 4 A full scale drives the
    true current past 4 A, and the measured current is at most 4 A, reaching it exactly."""
    plant = Plant.from_file(ARROW, overrides=_sensors(current_full_scale_a=4.0,
                                                      current_lsb_a=0.0))
    plant.set_input(iq_ref_a=6.0)
    run = plant.run(40, plant.sub_per_pwm)
    assert run["iq_a"].max() > 4.5
    assert np.abs(run["iq_meas_a"]).max() == 4.0
