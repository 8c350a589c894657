"""Mechanical validation experiments (hil.validate.experiments.mechanics) and their helpers."""

import math

import numpy as np
import pytest
import scipy.linalg

from hil.validate.core import REGISTRY
from hil.validate.experiments import mechanics as mech
from hil.validate.experiments import variants
from plant.assemble import mechanics_matrices
from plant.config import load_machine
from tests.helpers import assert_rows_ok


def test_experiments_registered():
    """The six mechanical experiments are in the registry under their seed papers."""
    seeds = {"rigid_acceleration": "000", "two_mass_resonance": "000", "screw_modes": "000",
             "moving_nut_stiffness": "003", "energy_conservation": "000",
             "lumped_vs_tlm": "003"}
    for name, seed in seeds.items():
        assert REGISTRY[name].seed == seed


def test_rigid_acceleration(experiment_rows):
    """Rigid Arrow axis vs the analytic acceleration T / (J_m + J_load + m (lead/2pi)^2)."""
    assert_rows_ok(experiment_rows("rigid_acceleration"))


def test_two_mass_resonance(experiment_rows):
    """Two-mass free vibration vs the analytic sqrt(k (J1+J2)/(J1 J2)) and sqrt(k/J2)."""
    assert_rows_ok(experiment_rows("two_mass_resonance"))


def test_screw_modes(experiment_rows):
    """Lumped screw vs the continuous fixed-free rod (1/N^2 convergence) and the kernel's
    modal free vibration vs the eigenvalues of mechanics_matrices."""
    assert_rows_ok(experiment_rows("screw_modes"))


def test_rod_convergence_is_second_order():
    """Each doubling of N cuts the rod-frequency error about four times (analytic rod);
    the lumped rod is too soft-massed, so its frequency is below the rod's."""
    _, err = mech.rod_convergence((4, 8, 16))["torsional"]
    assert np.all(err < 0.0)
    assert err[0] / err[1] == pytest.approx(4.0, rel=0.02)
    assert err[1] / err[2] == pytest.approx(4.0, rel=0.02)


def test_moving_nut_stiffness(experiment_rows):
    """Kernel static stiffness at the table vs the analytic series formula, 7 positions."""
    assert_rows_ok(experiment_rows("moving_nut_stiffness"))


@pytest.mark.parametrize("table_pos", [0.0, 0.147, 0.3, 0.5])
def test_series_formula_matches_linearisation(table_pos):
    """The analytic lumped series compliance equals the table's static compliance from
    mechanics_matrices' K with the rotor clamped (independent matrix assembly)."""
    cfg = load_machine(mech.ARROW)
    _, _, k_mat = mechanics_matrices(cfg, table_pos)
    k_held = k_mat[1:, 1:]  # clamp the motor coordinate
    load = np.zeros(k_held.shape[0])
    load[-1] = 1.0
    compliance = scipy.linalg.solve(k_held, load)[-1]
    analytic = mech.series_compliance(cfg, mech.lumped_nut_distance(cfg, table_pos))
    assert compliance == pytest.approx(analytic, rel=1e-9)


def test_lumped_nut_distance_at_nodes_and_between():
    """At a node the lumped nut distance is the true one; between nodes it is shorter by
    w (1 - w) seg (linear interpolation of the nut)."""
    cfg = load_machine(mech.ARROW)
    seg = cfg.screw.length_m / cfg.screw.segments
    at_node = 3 * seg - cfg.screw.nut_offset_m
    assert mech.lumped_nut_distance(cfg, at_node) == pytest.approx(3 * seg, rel=1e-12)
    mid = at_node + 0.5 * seg
    assert mech.lumped_nut_distance(cfg, mid) == pytest.approx(3.25 * seg, rel=1e-12)


def test_energy_conservation(experiment_rows):
    """Undamped Arrow screw model: bounded energy, no drift; trajectory vs solve_ivp DOP853."""
    assert_rows_ok(experiment_rows("energy_conservation"))


def test_energy_function_matches_matrices():
    """screw_energy of a displaced state at rest equals 1/2 dq^T K dq of mechanics_matrices
    (the nut term and both chains' springs, assembled independently)."""
    plant = variants.plant_of(variants.undamped(variants.torque_free(variants.machine_raw())), "arrow", 0.25)
    st = variants.ScrewState(plant)
    dq = np.random.default_rng(3).normal(size=st.q0.size) * 1e-6
    st.displace(dq)
    _, _, k_mat = mechanics_matrices(plant.config, 0.25)
    # the displaced table moves the nut's interpolation weight by ~1e-5: not exactly linear
    assert variants.screw_energy(plant) == pytest.approx(0.5 * dq @ k_mat @ dq, rel=1e-6)


def test_lumped_vs_tlm(experiment_rows):
    """TLM solver vs the lumped solver: first natural frequency and static stiffness."""
    assert_rows_ok(experiment_rows("lumped_vs_tlm"))


def test_crossing_frequency_of_a_sine():
    """The zero-crossing frequency estimate on an exact sine (analytic)."""
    t = np.linspace(0.0, 0.1, 20001)
    assert variants.crossing_frequency(t, np.sin(2 * np.pi * 123.4 * t + 0.3)) == pytest.approx(
        123.4, rel=1e-6)


def test_variants_are_checked_machine_files():
    """The rigid and two-mass variants load through the strict parser, drop the screw and
    keep the total inertia (analytic: J_m + J_coupling + J_screw + m r^2)."""
    raw = variants.machine_raw()
    rigid = variants.plant_of(variants.lumped_variant(raw, "rigid"), "rigid")
    two = variants.plant_of(variants.lumped_variant(raw, "two_mass"), "two-mass")
    cfg = load_machine(mech.ARROW)
    r = cfg.mechanics.lead_m / (2 * math.pi)
    total = (cfg.motor.inertia_kgm2 + cfg.coupling.inertia_kgm2 + variants.screw_inertia()
             + cfg.table.mass_kg * r * r)
    assert rigid.config.screw is None and two.config.screw is None
    assert rigid.built.rot.m.sum() == pytest.approx(total, rel=1e-12)
    assert two.built.rot.m.sum() == pytest.approx(total, rel=1e-12)
    assert "cogging" not in variants.with_keys(raw, {"cogging": None})
    assert raw["cogging"]  # with_keys copies


def test_undamped_model_runs_finite():
    """Kernel status 0 and finite outputs over 1000 PWM periods of the undamped model."""
    plant, _, _ = mech.conservative_arrow()
    tr = plant.run(1000, plant.sub_per_pwm)
    assert tr["status"].max() == 0
    for name in ("motor_pos", "table_pos", "nut_force_n"):
        assert np.all(np.isfinite(tr[name]))
