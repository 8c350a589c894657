"""Seed 002's position-domain method on the LD386 linear motor."""

import numpy as np

from hil.validate.experiments.cogging import position_spectrum


def test_position_spectrum_recovers_a_known_signal():
    """Analytic: a force of known harmonics, sampled at unevenly spaced positions (speed
    ripple), comes back with its amplitudes and mean from the resampled FFT."""
    rng = np.random.default_rng(3)
    period = 0.06
    pos = np.sort(rng.uniform(0.0, 4.3 * period, 20000))
    theta = 2 * np.pi * pos / period
    force = 18.0 + 1.39 * np.sin(theta) + 2.62 * np.sin(2 * theta + 0.4) + 1.52 * np.cos(4 * theta)
    sp = position_spectrum(pos, force, period, 4)
    assert abs(sp.amplitudes[0] - 18.0) < 0.01
    for order, amp in ((1, 1.39), (2, 2.62), (4, 1.52)):
        assert abs(sp.amplitudes[4 * order] - amp) < 0.01, order
    assert sp.amplitudes[12] < 0.01


def test_ld386_cogging_and_friction_match_seed_002(experiment_rows):
    """Seed 002 Fig. 9 / §5: at constant velocity under a velocity loop the motor force's
    position spectrum shows 1.39, 2.62, 1.52 N at 1, 2, 4 cycles per electrical revolution
    and a DC part of 18.76 N (friction)."""
    rows = experiment_rows("cogging_spectrum")
    assert len(rows) == 4
    for r in rows:
        assert r.ok, r
