"""Compliance in the screw model (issue 30, item 3, cause 6): a soft coupling and a soft nut
at once, on a trace of our own controller and plant.

The outside trace's identification knew compliance only as the two-mass form, which holds
one spring between motor and load: it cannot hold coupling and nut together, and took the
table mass 12 % down instead; a screw-model machine file was refused outright.  Here the
truth is tests/test_identify_effects.py's axis with a lumped screw (one segment) whose
coupling is 2.5 times and whose nut 3.3 times softer than the file identify starts from
declares.  Identification from the declared file must name compliance in the screw
model first, with both stiffnesses, and bring the replay to the noise floor without
moving the mass beyond its tolerance; the declared stiffnesses are held within their
tolerance like every declared coefficient.
"""

import copy

import pytest

from hil.identify.changes import declared_changes
from hil.identify.effects import POSITION, Context
from hil.identify.fit import Identification
from hil.identify.model import Model
from hil.identify.motion import Drive, motion
from hil.identify.record import load_record
from hil.identify.refine import parameters
from plant.config import load_machine
from tests.test_identify_effects import (
    BASE,
    check_floor,
    make_trace,
    noise_floor,
    write_config,
)

#: the declared file: tests/test_identify_effects.py's axis on a 0.4 m screw of 16 mm root
#: diameter, one segment (a lumped screw), damped joints
DECLARED = {
    "mechanics": {"model": "screw", "solver": "lumped"},
    "coupling": {"stiffness_nm_per_rad": 500.0, "damping_nms_per_rad": 0.05,
                 "inertia_kgm2": 2e-5},
    "screw": {"length_m": 0.4, "diameter_m": 0.016, "segments": 1, "nut_offset_m": 0.05,
              "thrust_bearing_stiffness_n_per_m": 2e8, "nut_stiffness_n_per_m": 2e8,
              "torsional_damping_nms_per_rad": 0.05, "axial_damping_ns_per_m": 2000.0,
              "nut_damping_ns_per_m": 3000.0, "thrust_bearing_damping_ns_per_m": 3000.0}}
COUPLING_NM_PER_RAD = 200.0
NUT_N_PER_M = 6e7
#: the tolerance the doubted stiffnesses are declared with: the truth's are 60 % and 70 %
#: below the file's
TOLERANCE = {"screw_model_compliance": 0.8}


def truth_overrides() -> dict:
    out = copy.deepcopy(DECLARED)
    out["coupling"]["stiffness_nm_per_rad"] = COUPLING_NM_PER_RAD
    out["screw"]["nut_stiffness_n_per_m"] = NUT_N_PER_M
    return out


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """(declared file, record, noise floor) of the soft coupling and nut."""
    d = tmp_path_factory.mktemp("screw_compliance")
    truth = write_config(d / "truth.toml", truth_overrides())
    start = write_config(d / "start.toml", DECLARED)
    trace = make_trace(truth, d / "trace.csv")
    return start, load_record(trace), noise_floor(truth, trace)


def test_coupling_and_nut_compliance_are_named_in_the_screw_model(case):
    """Named first and ranked first in round 1 (ahead of backlash, which mimics a spring
    in the position residual), both stiffnesses within 20 % of the truth's, every replay
    channel within 1.5x its noise floor, the mass unchanged (its 10 % tolerance not
    asked beyond); the two-mass form is left out on a screw-model file, saying why."""
    start, rec, floor = case
    ident = Identification(start, rec, refine_nfev=0, tolerance=TOLERANCE).fit()
    assert ident.steps and ident.steps[0].effect == "screw_model_compliance", ident.rounds[0]
    ranking = ident.rounds[0]["ranking"]
    assert ranking[0]["effect"] == "screw_model_compliance", ranking
    params = ident.steps[0].params
    assert params["coupling_stiffness_nm_per_rad"] == pytest.approx(COUPLING_NM_PER_RAD,
                                                                    rel=0.2)
    assert params["nut_stiffness_n_per_m"] == pytest.approx(NUT_N_PER_M, rel=0.2)
    check_floor(ident, floor)
    rows = {r["parameter"]: r for r in ident.declared_changes}
    assert not rows["mass_kg"]["beyond_tolerance"] and abs(rows["mass_kg"]["change_pct"]) <= 10
    for key in ("coupling_stiffness_nm_per_rad", "nut_stiffness_n_per_m"):
        assert not rows[key]["beyond_tolerance"], rows[key]
    assert "screw_model_compliance" in ident.skipped["compliance"]
    written = ident.model.overrides()
    assert written["coupling"]["stiffness_nm_per_rad"] == pytest.approx(
        params["coupling_stiffness_nm_per_rad"])
    assert written["screw"]["nut_stiffness_n_per_m"] == pytest.approx(
        params["nut_stiffness_n_per_m"])


def test_declared_stiffnesses_are_held_within_the_default_tolerance(case):
    """Proposed with the default 10 % tolerance: both stiffnesses stop at -10 % of the
    declared ones, what the position residual asks for (60 % and more softer) is the
    finding, named by its machine-file key."""
    start, rec, _ = case
    cfg = load_machine(start)
    drive = Drive.of(cfg)
    ctx = Context.of(cfg, drive, rec, motion(rec, drive, None))
    model = Model(ctx, start)
    effect = model.term("screw_model_compliance").effect
    model.add(effect.propose(ctx, model.residual(POSITION), model))
    rows = {r["parameter"]: r for r in declared_changes(model)}
    for key in ("coupling_stiffness_nm_per_rad", "nut_stiffness_n_per_m"):
        row = rows[key]
        assert row["identified"] == pytest.approx(0.9 * row["declared"], rel=1e-9), row
        assert row["beyond_tolerance"] and row["wanted_by"] == "its proposal", row
        assert row["wanted_change_pct"] < -50.0, row


def test_the_closed_loop_refinement_frees_both_stiffnesses_in_log_space(case):
    """The refinement (hil.identify.refine) adjusts the coupling's and the nut's
    compliance as two parameters, each in log space, within the stiffness box: with the
    default tolerance a compliance may reach 1/0.9 of the declared one (the stiffness
    -10 %), not 1.1 times."""
    start, rec, _ = case
    cfg = load_machine(start)
    drive = Drive.of(cfg)
    ctx = Context.of(cfg, drive, rec, motion(rec, drive, None))
    model = Model(ctx, start)
    mine = [p for p in parameters(model) if p.effect == "screw_model_compliance"]
    assert [(p.label, p.log, p.index) for p in mine] == [
        ("screw_model_compliance[0]", True, 0), ("screw_model_compliance[1]", True, 1)]
    term = model.term("screw_model_compliance")
    lo, hi = model.box(term)
    assert hi == pytest.approx(term.coef / 0.9, rel=1e-12)
    assert lo == pytest.approx(term.coef / 1.1, rel=1e-12)


@pytest.mark.parametrize("table_pos", [0.0, 0.1, 0.25])
def test_held_motor_compliance_is_the_lumped_series_of_the_train(table_pos):
    """The train's compliance the fit keeps as declared comes from the plant's linearised
    mechanics: with the rotor held it is the series of coupling, screw torsion and stretch
    up to the lumped nut place, thrust bearing and nut (the validation's analytic
    formula), to 1e-9."""
    from hil.identify.effects.screw_compliance import held_motor_compliance
    from hil.validate.experiments.mechanics import (
        lumped_nut_distance,
        series_compliance,
    )
    cfg = load_machine(BASE, DECLARED)
    expected = series_compliance(cfg, lumped_nut_distance(cfg, table_pos))
    assert held_motor_compliance(cfg, table_pos) == pytest.approx(expected, rel=1e-9)
