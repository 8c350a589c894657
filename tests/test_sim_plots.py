"""hil sim's figure and the position-cycle mean of its currents.

References: hand-made signals whose mean over a window is known in closed form (a ramp's
mean is its value at the window's centre; a ripple whose period is the window averages to
its own mean), and matplotlib's own tick formatter for what a reader sees on the axes.
"""

import io

import numpy as np
import pytest

from hil.figures import sim_figure
from hil.measure.runs import position_step
from hil.sim import position_cycle_mean, ripple_hz
from plant.config import load_machine
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"


def test_a_ripple_at_the_position_cycle_averages_out_exactly():
    """i_q = ramp + a saw-tooth of one position cycle's period (16 ticks, the shape a held
    feed-forward step leaves): the mean is the ramp at the window's centre (16 samples,
    8 before the sample: centre half a tick earlier) plus the saw-tooth's mean, to
    rounding, everywhere a whole window fits."""
    n, ticks = 400, 16
    k = np.arange(n)
    saw = np.array([2.0, 1.9, 1.1, 0.4, 0.1, 0.0, 0.2, 0.3, 0.5, 0.6, 0.9, 1.0, 1.2, 1.3,
                    1.5, 1.8])
    x = 0.01 * k + saw[k % ticks]
    got = position_cycle_mean(x, ticks)
    inner = slice(ticks // 2, n - ticks // 2 + 1)
    np.testing.assert_allclose(got[inner], (0.01 * (k - 0.5) + saw.mean())[inner],
                               rtol=0, atol=1e-12)
    # at the ends the mean is over the samples there are: a constant stays that constant
    np.testing.assert_allclose(position_cycle_mean(np.full(40, 3.5), ticks), 3.5, atol=1e-12)
    np.testing.assert_array_equal(position_cycle_mean(x, 1), x)
    with pytest.raises(ValueError, match="ticks must be >= 1"):
        position_cycle_mean(x, 0)


def test_a_nan_spoils_only_the_windows_that_hold_it():
    """Sample i's window is i - 8 .. i + 7: a NaN at 50 reaches the means of 43 .. 58."""
    x = np.ones(100)
    x[50] = np.nan
    got = position_cycle_mean(x, 16)
    assert np.isnan(got[43:59]).all()
    np.testing.assert_array_equal(np.delete(got, np.arange(43, 59)), 1.0)


@pytest.fixture(scope="module")
def micro_step():
    """A 1 µm position step at 250 mm: every value on the position axis shares 250.000, the
    case where matplotlib's default ticks would read '+2.5e2' with tiny labels."""
    return position_step(load_machine(ARROW), 0.25, 1e-6, 0.02).sim


def test_sim_figure_has_units_on_every_axis_and_no_offset_notation(micro_step):
    fig = sim_figure(micro_step, "1 µm step")
    fig.savefig(io.BytesIO(), format="png")  # drawn: the ticks and offsets are set
    axes = fig.axes
    assert [a.get_ylabel() for a in axes] == [
        "position (mm)", "velocity (mm/min)", "following error (µm)", "current i_q (A)"]
    assert axes[-1].get_xlabel() == "time (s)"
    for a in axes:
        assert a.yaxis.get_offset_text().get_text() == "", a.get_ylabel()
        assert a.xaxis.get_offset_text().get_text() == "", a.get_ylabel()
    # the position axis reads 250.000x mm, not an offset from 250
    assert all(abs(t - 250.0) < 0.01 for t in axes[0].get_yticks())


def test_the_current_panel_shows_each_tick_and_the_position_cycle_mean(micro_step):
    """Light lines: iq_set and iq_meas as recorded; bold: their position_cycle_mean over
    the recording's own position cycle (16 ticks of 125 µs on the Arrow 500 X); the title
    names the ripple's frequency, 1 / 2 ms."""
    assert micro_step.position_cycle_ticks == 16
    assert ripple_hz(micro_step) == pytest.approx(500.0)
    ax = sim_figure(micro_step, "step").axes[3]
    labels = [line.get_label() for line in ax.get_lines()]
    assert labels == ["setpoint, each 125 µs tick", "measured, each 125 µs tick",
                      "setpoint, 2 ms position-cycle mean",
                      "measured, 2 ms position-cycle mean"]
    lines = ax.get_lines()
    np.testing.assert_array_equal(lines[0].get_ydata(), micro_step["iq_set"])
    np.testing.assert_array_equal(lines[3].get_ydata(),
                                  position_cycle_mean(micro_step["iq_meas"], 16))
    assert lines[0].get_alpha() < 1.0 and lines[2].get_alpha() is None
    assert "500 Hz ripple" in ax.get_title() and "2 ms position cycle" in ax.get_title()
