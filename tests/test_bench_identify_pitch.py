"""The bench generator's pitch error moves the table's mass, not only its reading.

Reference: the energy balance of a rigid body on the constraint x = u + e(u) (Lagrange):
the kinetic energy is (M - m_t) u'^2 / 2 + m_t x'^2 / 2 with x' = (1 + e'(u)) u', and the
only work done on a coasting axis is the viscous friction's at the table's velocity,
-B x'^2.  A generator that moved the table's mass with u' (the pitch error a mere offset
of the scale's reading) misses this balance by about 2 e' m_t / M of the energy, here 1 %.
"""

import numpy as np
import pytest

from hil.bench.identify_gen.axis import Axis, axis_params, pitch_position, pitch_slope
from hil.bench.identify_gen.cases import SCREW
from plant.config import load_machine

#: a steep pitch error (slope 2 pi A / P = 0.01 m/m, within the loader's 0.05) makes the
#: table's share of the kinematics large enough to see
PITCH = {"periods_m": [0.025], "amplitudes_m": [4e-5]}


def _coasting(viscous_ns_per_m: float):
    """An axis sliding at 0.2 m/s with no current and no Coulomb friction, stepped for
    0.2 s (eight pitch periods) in 0.1 ms steps; (energies J, dissipated power W, step s,
    the table's share of the moved mass m_t / M)."""
    cfg = load_machine(SCREW, {"pitch_error": PITCH, "friction": {
        "coulomb_n": 0.0, "viscous_ns_per_m": viscous_ns_per_m}})
    p = axis_params(cfg)
    axis = Axis(p, 0.1)
    axis.y[1] = axis.y[3] = 0.2
    dt = 1e-4
    energy, power = [], []
    for _ in range(2001):
        u, v = float(axis.y[2]), float(axis.y[3])
        x_dot = pitch_slope(p, u)[0] * v
        energy.append(0.5 * (p.mass - p.m_table) * v * v + 0.5 * p.m_table * x_dot * x_dot)
        power.append(p.b * x_dot * x_dot)
        axis.step(dt, 0.0)
    return np.array(energy), np.array(power), dt, p.m_table / p.mass


def test_coasting_without_friction_keeps_the_kinetic_energy_of_the_moving_table():
    energy, _, _, share = _coasting(0.0)
    # 2 e' m_t / M is what a pitch error as a mere reading offset would miss
    assert np.ptp(energy) / energy[0] < 1e-3 * 2 * 0.01 * share
    assert energy[0] > 0.0


def test_viscous_friction_does_its_work_at_the_tables_velocity():
    energy, power, dt, _ = _coasting(300.0)
    # trapezoidal integral of B x'^2 against the energy lost
    work = float(np.sum(0.5 * (power[1:] + power[:-1])) * dt)
    lost = float(energy[0] - energy[-1])
    assert lost == pytest.approx(work, rel=1e-4)
    assert lost > 0.3 * energy[0]  # the viscous friction took a good share of it


def test_pitch_slope_against_the_position_by_central_difference():
    cfg = load_machine(SCREW, {"pitch_error": {**PITCH, "linear_ppm": 30.0,
                                               "phases_deg": [25.0]}})
    p = axis_params(cfg)
    h = 1e-6
    for u in (0.05, 0.1234, 0.2):
        g, curv = pitch_slope(p, u)
        x = [pitch_position(p, u + k * h) for k in (-1, 0, 1)]
        assert g == pytest.approx((x[2] - x[0]) / (2 * h), rel=1e-8)
        assert curv == pytest.approx((x[2] - 2 * x[1] + x[0]) / h ** 2, rel=1e-3)
    assert p.m_table == 60.0  # the table's mass, the part that moves with x
