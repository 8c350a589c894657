"""The identification's building blocks, each against an analytic answer."""

import math

import numpy as np
import pytest
import tomllib

from hil.identify.config_out import patch_config, toml_value
from hil.identify.effects.base import quantum
from hil.identify.effects.delay import xcorr_lag
from hil.identify.effects.drivetrain import contact_side
from hil.identify.motion import derivative
from hil.identify.spectrum import position_spectrum


def test_five_point_derivative_of_a_sine_has_the_stencils_analytic_gain():
    """Gain of the stencil at w: (8 sin(w dt) - sin(2 w dt)) / (6 w dt)."""
    dt, f = 1e-3, 50.0
    t = np.arange(2000) * dt
    w = 2 * math.pi * f
    d = derivative(np.sin(w * t), dt)
    gain = (8 * math.sin(w * dt) - math.sin(2 * w * dt)) / (6 * w * dt)
    assert np.allclose(d[2:-2], gain * w * np.cos(w * t[2:-2]), atol=1e-9 * w)
    assert gain > 0.9995 and math.sin(w * dt) / (w * dt) < 0.985  # three-point: 1.6 % low


def test_position_spectrum_finds_a_line_periodic_in_position_whatever_the_speed():
    """A residual A sin(2 pi x / P) recorded over a back-and-forth move at changing speed:
    the line sits at 1/P with amplitude A (the Hann window's gain restored)."""
    t = np.linspace(0, 10, 20001)
    x = 0.05 * (1 - np.cos(2 * math.pi * t / 5)) + 0.002 * np.sin(2 * math.pi * 1.3 * t)
    period, amp = 0.0125, 3.0
    r = amp * np.sin(2 * math.pi * x / period)
    spec = position_spectrum(r, x, np.ones(t.size, bool), 0.0001)
    (f, a), = spec.peaks(1)
    assert 1 / f == pytest.approx(period, rel=0.02)
    assert a == pytest.approx(amp, rel=0.05)


def test_quantum_of_counts_and_of_data_off_a_grid():
    rng = np.random.default_rng(1)
    counts = np.cumsum(rng.integers(-3, 4, 5000))
    assert quantum(counts * 5e-8) == pytest.approx(5e-8, rel=1e-6)
    assert quantum(rng.normal(size=5000)) == 0.0


def test_xcorr_lag_recovers_a_fractional_delay():
    rng = np.random.default_rng(2)
    model = np.cumsum(rng.normal(size=4000))
    lag = 3.0
    measured = np.interp(np.arange(4000) - lag, np.arange(4000), model)
    assert xcorr_lag(measured, model, 10) == pytest.approx(lag, abs=0.2)


def test_contact_side_holds_inside_the_band_and_flips_outside():
    f = np.array([0.0, 5.0, 1.0, -1.0, -5.0, -0.5, 0.5, 3.0])
    assert list(contact_side(f, 2.0)) == [1, 1, 1, 1, -1, -1, -1, 1]


def test_patch_config_replaces_inserts_and_appends_and_reads_back():
    text = ("# header\n[table]\nmass_kg = 60.0   # assumed: why\n\n[friction]\n"
            "viscous_ns_per_m = 300.0\n")
    out = patch_config(text, {"table": {"mass_kg": 61.5, "external_force_n": -3.0},
                              "cogging": {"orders": [2, 4], "amplitudes_nm": [0.02, 0.01]},
                              "presliding": {"enabled": True}}, "fitted")
    data = tomllib.loads(out)
    assert data["table"] == {"mass_kg": 61.5, "external_force_n": -3.0}
    assert data["friction"] == {"viscous_ns_per_m": 300.0}
    assert data["cogging"] == {"orders": [2, 4], "amplitudes_nm": [0.02, 0.01]}
    assert data["presliding"] == {"enabled": True}
    assert "# header" in out and "(was 60.0)" in out
    # the inserted key stays inside its section, before the blank line that ends it
    assert out.index("external_force_n") < out.index("[friction]")


def test_toml_value_refuses_what_a_machine_file_cannot_hold():
    assert toml_value(0.1 + 0.2) == "0.3"
    with pytest.raises(ValueError):
        toml_value(math.inf)
    with pytest.raises(TypeError):
        toml_value({"a": 1})
