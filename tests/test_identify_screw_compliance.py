"""Compliance in the screw model (issue 30, item 3, cause 6): a soft coupling and a soft nut
at once, a soft screw torsion, and the same candidate on a rigid file that declares its
screw, on traces of our own controller and plant.

The outside trace's identification knew compliance only as the two-mass form, which holds
one spring between motor and load: it cannot hold coupling and nut together, and took the
table mass 12 % down instead; a screw-model file was refused outright, and a rigid file
had no screw to place the springs in.  Here the truth is tests/test_identify_effects.py's
axis with a lumped screw (one segment): its coupling 2.5 times and its nut 3.3 times
softer than the file identify starts from declares, or its screw's torsion 4 times softer
(shear modulus 20 GPa for steel's 81), or the soft coupling and nut behind a rigid file
with ``[identify.screw]``.  Identification must name compliance in the screw model first,
with the stiffnesses, and bring the replay to the noise floor without moving the mass
beyond its tolerance; the declared stiffnesses are held within their tolerance like every
declared coefficient.  The independent checks are the analytic series formula of the
rotor-held screw (hil.validate's, written from the textbook chain: coupling, screw torsion
and stretch up to the nut, thrust bearing, nut) and, for the screw's inertia, the lumped
chain's closed forms worked out by hand below.
"""

import copy
import math

import numpy as np
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
def soft_trace(tmp_path_factory):
    """(folder, record, noise floor) of the soft coupling and nut, simulated once for the
    screw-model, rigid and two-mass files that declare them."""
    d = tmp_path_factory.mktemp("screw_compliance")
    truth = write_config(d / "truth.toml", truth_overrides())
    trace = make_trace(truth, d / "trace.csv")
    return d, load_record(trace), noise_floor(truth, trace)


@pytest.fixture(scope="module")
def case(soft_trace):
    """(declared file, record, noise floor) of the soft coupling and nut."""
    d, record, floor = soft_trace
    return write_config(d / "start.toml", DECLARED), record, floor


def test_coupling_and_nut_compliance_are_named_in_the_screw_model(case):
    """Named first and ranked first in round 1 (ahead of backlash, which mimics a spring
    in the position residual), both stiffnesses within 20 % of the truth's, every replay
    channel within 1.5x its noise floor, the mass unchanged (its 10 % tolerance not
    asked beyond); the screw's torsion, which this record does not determine within its
    tolerance (the nut stays within 0.11 m of the thrust bearing, where the torsion is a
    few per cent of the train's compliance), held as declared; the two-mass form is left
    out on a screw-model file, saying why."""
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
    assert ident.model.term("screw_model_compliance").shape["torsion_held"]
    assert "shear_modulus_pa" not in rows and "as declared" in ident.steps[0].evidence["text"]
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


def test_the_closed_loop_refinement_frees_the_three_stiffnesses_in_log_space(case):
    """The refinement (hil.identify.refine) adjusts the coupling's, the nut's and the
    screw torsion's compliance as three parameters, each in log space, within the
    stiffness box: with the default tolerance a compliance may reach 1/0.9 of the declared
    one (the stiffness -10 %), not 1.1 times."""
    start, rec, _ = case
    cfg = load_machine(start)
    drive = Drive.of(cfg)
    ctx = Context.of(cfg, drive, rec, motion(rec, drive, None))
    model = Model(ctx, start)
    mine = [p for p in parameters(model) if p.effect == "screw_model_compliance"]
    assert [(p.label, p.log, p.index) for p in mine] == [
        (f"screw_model_compliance[{j}]", True, j) for j in range(3)]
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


def _torsion_share(cfg, table_pos: float):
    """The screw torsion's share of (h_n, h_a, h_v) at ``table_pos`` (m), as the candidate
    takes it: twice the change when the torsion is made twice as stiff."""
    from hil.identify.effects.screw_compliance import influence, stiffer
    at = np.array([table_pos])
    return 2.0 * (influence(cfg, at) - influence(stiffer(cfg, "torsion", 2.0), at))[:, 0]


@pytest.mark.parametrize("table_pos", [0.0, 0.1, 0.25])
def test_the_torsion_column_is_the_lumped_screws_torsion_by_hand(table_pos):
    """The screw torsion's column, from the plant's rotor-held mechanics, against the
    lumped chain worked out by hand.  One segment of k_s = G J_p / l between node 1 (the
    motor end) and node 2, the nut at w = (nut_offset + x) / l between them: a force F
    through the nut twists the segment by r w F / k_s, which the nut reads with weight w,
    r² w² F / k_s at the table -- hil.validate's series formula r² s / (G J_p) at its
    lumped nut distance s = w² l; the rigid motion's acceleration a loads node 2 with
    its half of the screw's inertia, m_2 = rho J_p l / 2: a torque m_2 a / r that twists
    the segment by m_2 a / (r k_s), w m_2 a / k_s at the table.  To 1e-9."""
    from hil.validate.experiments.mechanics import lumped_nut_distance
    cfg = load_machine(BASE, DECLARED)
    sc = cfg.screw
    r = cfg.mechanics.lead_m / (2.0 * math.pi)
    jp = math.pi * sc.diameter_m ** 4 / 32.0
    k_s = sc.shear_modulus_pa * jp / sc.length_m
    w = (sc.nut_offset_m + table_pos) / sc.length_m
    share = _torsion_share(cfg, table_pos)
    assert share[0] == pytest.approx(r * r * w * w / k_s, rel=1e-9)
    assert share[0] == pytest.approx(
        r * r * lumped_nut_distance(cfg, table_pos) / (sc.shear_modulus_pa * jp), rel=1e-9)
    assert share[1] == pytest.approx(w * 0.5 * sc.density_kg_m3 * jp * sc.length_m / k_s,
                                     rel=1e-9)


#: the torsion case: a longer, thinner screw (0.6 m of 12 mm root diameter) with the nut
#: 0.25 m from the thrust bearing, where steel's torsion is 8 % of the train's compliance
#: at the nut and the truth's, four times softer, a quarter
TORSION_DECLARED = copy.deepcopy(DECLARED)
TORSION_DECLARED["screw"].update(length_m=0.6, diameter_m=0.012, nut_offset_m=0.25)
SHEAR_PA = 2.0e10


@pytest.fixture(scope="module")
def torsion_case(tmp_path_factory):
    """(declared file, truth file, record, noise floor) of the soft screw torsion."""
    d = tmp_path_factory.mktemp("screw_torsion")
    over = copy.deepcopy(TORSION_DECLARED)
    over["screw"]["shear_modulus_pa"] = SHEAR_PA
    truth = write_config(d / "truth.toml", over)
    start = write_config(d / "start.toml", TORSION_DECLARED)
    trace = make_trace(truth, d / "trace.csv")
    return start, truth, load_record(trace), noise_floor(truth, trace)


def test_a_soft_screw_torsion_is_named_and_fitted(torsion_case):
    """A screw whose torsion is 4 times softer than declared: compliance in the screw
    model is named first and ranked first, its shear modulus within 10 % of the truth's
    (before, only coupling and nut were fitted, and they took it: the coupling -48 %, the
    nut -24 %), every replay channel within 1.5x its noise floor, no declared stiffness
    asked beyond its tolerance, the mass unchanged.  Independent check: the fitted file's
    compliance at the table with the rotor held, by the analytic series formula at both
    ends of the record's travel, within 5 % of the truth's."""
    from hil.validate.experiments.mechanics import (
        lumped_nut_distance,
        series_compliance,
    )
    start, truth, rec, floor = torsion_case
    ident = Identification(start, rec, refine_nfev=0, tolerance=TOLERANCE).fit()
    assert ident.steps and ident.steps[0].effect == "screw_model_compliance", ident.rounds[0]
    assert ident.rounds[0]["ranking"][0]["effect"] == "screw_model_compliance"
    assert not ident.model.term("screw_model_compliance").shape.get("torsion_held")
    params = ident.steps[0].params
    assert params["shear_modulus_pa"] == pytest.approx(SHEAR_PA, rel=0.1), params
    check_floor(ident, floor)
    rows = {r["parameter"]: r for r in ident.declared_changes}
    assert not rows["mass_kg"]["beyond_tolerance"] and abs(rows["mass_kg"]["change_pct"]) <= 10
    for key in ("coupling_stiffness_nm_per_rad", "nut_stiffness_n_per_m", "shear_modulus_pa"):
        assert not rows[key]["beyond_tolerance"], rows[key]
    fitted = load_machine(start, ident.model.overrides())
    true = load_machine(truth)
    for x in (0.0, 0.06):
        assert series_compliance(fitted, lumped_nut_distance(fitted, x)) == pytest.approx(
            series_compliance(true, lumped_nut_distance(true, x)), rel=0.05)


#: the screw of DECLARED as [identify.screw] declares it: everything but the nut's
#: stiffness, which the fit gives
GEOMETRY = {k: v for k, v in DECLARED["screw"].items() if k != "nut_stiffness_n_per_m"}
#: the screw's inertia rho pi d^4 l / 32 (kg m^2), by hand; a rigid file holds it in
#: load_inertia_kgm2 with the coupling's
SCREW_INERTIA = 7850.0 * math.pi * 0.016 ** 4 / 32.0 * 0.4
COUPLING_INERTIA = DECLARED["coupling"]["inertia_kgm2"]
RIGID = {"mechanics": {"load_inertia_kgm2": SCREW_INERTIA + COUPLING_INERTIA},
         "identify.screw": GEOMETRY}


@pytest.fixture(scope="module")
def rigid_case(soft_trace):
    """(rigid declared file, record, noise floor) of the soft coupling and nut."""
    d, record, floor = soft_trace
    return write_config(d / "rigid.toml", RIGID), record, floor


def test_a_rigid_file_that_declares_its_screw_gets_the_screw_model(rigid_case):
    """The soft coupling and nut behind a rigid file that declares its screw
    ([identify.screw]): compliance in the screw model is offered beside the two-mass form,
    ranked ahead of it by the same held-out criterion and named first, coupling and nut
    within 25 % of the truth's (the rigid file lumps the coupling's inertia behind its
    spring, the truth splits it), every replay channel within 1.5x its noise floor, the
    mass unchanged.  Before, the rigid file's only compliance was the two-mass form, and
    it ended 3.6x the floor on the scale.  Independent check: the screw model written
    keeps the rigid file's moved inertia, J_motor + J_load + m r² by hand, and its load
    inertia is the declared one less the screw's rho pi d^4 l / 32."""
    from hil.identify.config_out import patch_config
    from plant.assemble import reflected_inertia
    start, rec, floor = rigid_case
    ident = Identification(start, rec, refine_nfev=0).fit()
    assert ident.steps and ident.steps[0].effect == "screw_model_compliance", ident.rounds[0]
    ranking = [c["effect"] for c in ident.rounds[0]["ranking"]]
    assert ranking.index("screw_model_compliance") < ranking.index("compliance"), ranking
    params = ident.steps[0].params
    assert params["coupling_stiffness_nm_per_rad"] == pytest.approx(COUPLING_NM_PER_RAD,
                                                                    rel=0.25)
    assert params["nut_stiffness_n_per_m"] == pytest.approx(NUT_N_PER_M, rel=0.25)
    check_floor(ident, floor)
    rows = {r["parameter"]: r for r in ident.declared_changes}
    assert not rows["mass_kg"]["beyond_tolerance"] and abs(rows["mass_kg"]["change_pct"]) <= 10
    written = start.parent / "identified.toml"
    written.write_text(patch_config(start.read_text(), ident.model.overrides(), "test"))
    cfg = load_machine(written)
    assert cfg.mechanics.model == "screw" and cfg.screw.length_m == GEOMETRY["length_m"]
    declared = load_machine(start)
    r = declared.mechanics.lead_m / (2.0 * math.pi)
    by_hand = (declared.motor.inertia_kgm2 + declared.mechanics.load_inertia_kgm2
               + declared.table.mass_kg * r * r)
    # the identified file's mass is the declared one, up to the refit within tolerance
    moved = cfg.table.mass_kg - declared.table.mass_kg
    assert reflected_inertia(cfg) - moved * r * r == pytest.approx(by_hand, rel=1e-6)
    assert cfg.mechanics.load_inertia_kgm2 == pytest.approx(COUPLING_INERTIA, rel=1e-5)


def test_without_its_screw_a_rigid_file_is_not_offered_the_screw_model(case, tmp_path):
    """Where a rigid file does not declare its screw the candidate is not looked for, and
    why names the keys [identify.screw] lacks (the log's and report's "not looked for");
    a screw heavier than the file's load inertia is not the file's; a key the section
    cannot hold is refused naming it."""
    from hil.identify.effects.screw_compliance import ScrewModelCompliance
    from hil.identify.screw_geometry import check
    from plant.errors import ConfigError
    _, rec, _ = case

    def why(over: dict) -> str | None:
        cfg = load_machine(write_config(tmp_path / "f.toml", over))
        drive = Drive.of(cfg)
        ctx = Context.of(cfg, drive, rec, motion(rec, drive, None))
        return ScrewModelCompliance().unavailable(ctx)

    bare = why({})
    assert "[identify.screw] length_m, diameter_m, nut_offset_m, " \
           "thrust_bearing_stiffness_n_per_m missing" in bare, bare
    partial = {k: v for k, v in GEOMETRY.items() if k != "thrust_bearing_stiffness_n_per_m"}
    lacks = why({**RIGID, "identify.screw": partial})
    assert "[identify.screw] thrust_bearing_stiffness_n_per_m missing" in lacks, lacks
    heavy = why({"identify.screw": GEOMETRY})
    assert "more than [mechanics] load_inertia_kgm2 = 0 kg*m^2" in heavy, heavy
    assert why(RIGID) is None
    for key, words in (("nut_stiffness_n_per_m", "fitted by hil identify"),
                       ("nut_coulomb_nm", "declared elsewhere"), ("lenght_m", "not a")):
        bad = load_machine(write_config(tmp_path / "bad.toml",
                                        {"identify.screw": {**GEOMETRY, key: 1e6}}))
        with pytest.raises(ConfigError, match=rf"\[identify.screw\] {key}: .*{words}"):
            check(bad)


def test_a_two_mass_file_that_declares_its_screw_gets_the_screw_model(rigid_case, tmp_path):
    """The same trace behind a two-mass file (its one spring 60 N*m/rad, the train's in
    series; its load inertia the screw's, the coupling's its own) that declares its
    screw: compliance in the screw model is named first and takes the two-mass
    compliance's place (that term leaves the model, and is not offered after it), every
    replay channel within 1.5x its noise floor."""
    _, rec, floor = rigid_case
    start = write_config(tmp_path / "two_mass.toml", {
        "mechanics": {"model": "two_mass", "load_inertia_kgm2": SCREW_INERTIA},
        "coupling": {"stiffness_nm_per_rad": 60.0, "inertia_kgm2": COUPLING_INERTIA,
                     "damping_nms_per_rad": 0.03},
        "identify.screw": GEOMETRY})
    ident = Identification(start, rec, refine_nfev=0).fit()
    assert ident.steps and ident.steps[0].effect == "screw_model_compliance", ident.rounds[0]
    assert ident.model.term("compliance") is None
    assert ident.model.overrides()["mechanics"]["model"] == "screw"
    check_floor(ident, floor)
