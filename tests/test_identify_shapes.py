"""The effect library's shapes as wide as real machines (issue 30, item 3): each cause
seen on outside traces, on a trace of our own controller and plant
(tests/test_identify_effects.py's axis and program) whose truth has it.

* cause 4: presliding not proposed.  The inverse model's fit, on the low-passed motion,
  ran to x1 = 3 nm (k1 = 1.2e9 N/m) on a trace whose spring has x1 = 0.1 um, and the
  spring was dropped as shorter than two scale counts; the replay stayed 6.4x the scale's
  floor.  The fit now looks over x1 from 0.1 to 50 um and the replay judges.
* cause 5: Coulomb's friction and a Stribeck dip both undeclared.  Coulomb alone took
  the dip's average (35 N against the truth's 30 N) and the joint refit of the force
  domain cut the declared viscous friction to 0 (-100 %); the dip, proposed beside that
  level, came out at 45 N instead of 60 N.  Coulomb with the dip is a candidate of its
  own wherever Coulomb is one, ranked by the same held-out criterion.
* cause 6's refinement: declared coefficients pushed to absorb what was left (table mass
  +3 to +9 %, viscous friction +12 to +17 %, -74 % once).  A declared coefficient moves
  only within its tolerance; what the data ask for beyond it is a finding in the log
  and report.md, not taken into the model or its machine file.
* the declared shapes (the Stribeck velocity, the presliding spring's k1, x1 and
  exponent) the same way: before, the refinement moved a declared Stribeck velocity of
  4 mm/s to the truth's 7.8 mm/s (+96 %) without a word; now it is held within 10 % and
  the +97 % asked for is the finding, by the same box and the same ``wanted``.
"""

import dataclasses

import pytest

from hil.identify.changes import declared_changes
from hil.identify.effects import Context
from hil.identify.fit import Identification
from hil.identify.model import Model
from hil.identify.motion import Drive, motion
from hil.identify.record import load_record
from hil.identify.report import markdown, summary
from plant.config import load_machine
from tests.test_identify_effects import check_floor, make_trace, run_case, write_config

#: a wide dip: 60 N above Coulomb's 30 N at rest, over 15 mm/s (the program moves at 1
#: to 100 mm/s, so the dip covers most of its slow moves)
COULOMB_STRIBECK = {"friction": {"coulomb_n": 30.0, "breakaway_n": 90.0,
                                 "stribeck_velocity_m_s": 0.015}}
#: a Stribeck dip of 30 N over 8 mm/s above the base file's Coulomb 30 N, and a constant
#: force the file identification starts from lacks (so that the search adds something and
#: the closed-loop refinement runs)
DIP_AND_FORCE = {"friction": {"breakaway_n": 60.0, "stribeck_velocity_m_s": 0.008},
                 "table": {"external_force_n": -150.0}}


@pytest.fixture(scope="module")
def coulomb_stribeck(tmp_path_factory):
    """The identification of the Coulomb + Stribeck trace from a file with neither."""
    d = tmp_path_factory.mktemp("shapes_stribeck")
    truth = write_config(d / "truth.toml", COULOMB_STRIBECK)
    start = write_config(d / "start.toml", {"friction": {"coulomb_n": 0.0}})
    rec = load_record(make_trace(truth, d / "trace.csv"))
    return Identification(start, rec, refine_nfev=0).fit()


def test_stribeck_is_proposed_with_coulomb_and_ranked_beside_it(coulomb_stribeck):
    """Round 1 ranks Coulomb alone and Coulomb with the dip by the same criterion; the
    pair wins and both are added with the truth's friction within 5 % (the dip's width
    within 10 %), the declared viscous friction within its 10 % tolerance."""
    ident = coulomb_stribeck
    added = {s.effect: s.params for s in ident.steps}
    assert list(added)[:2] == ["coulomb_friction", "stribeck"]
    assert added["coulomb_friction"]["coulomb_n"] == pytest.approx(30.0, rel=0.05)
    assert added["stribeck"]["static_minus_coulomb"] == pytest.approx(60.0, rel=0.05)
    assert added["stribeck"]["stribeck_velocity_m_s"] == pytest.approx(0.015, rel=0.1)
    viscous = next(c for c in ident.declared_changes if c["parameter"] == "viscous_ns_per_m")
    assert not viscous["beyond_tolerance"], viscous
    ranking = {r["effect"]: r for r in ident.rounds[0]["ranking"]}
    assert {"coulomb_friction", "stribeck", "coulomb_friction+stribeck"} <= set(ranking)
    first = ident.rounds[0]["ranking"][0]
    assert first["effect"] == "coulomb_friction+stribeck"
    assert first["heldout_delta_bic"] < ranking["coulomb_friction"]["heldout_delta_bic"]
    assert ident.proposals[0]["effect"] == "coulomb_friction+stribeck"


def test_a_move_beyond_the_tolerance_is_a_finding_not_taken(tmp_path):
    """The base file's truth (reflected mass 138.96 kg: the table's 60 kg and the rotor's
    78.96 kg) identified from a file that lacks Coulomb's friction and declares the table
    at 48.5 kg, 8.3 % light in the reflected mass, with a tolerance of 5 % on the mass:
    after the closed-loop refinement the mass sits at the tolerance's edge (+5 %), in the
    model and in the machine file it writes, and the +9 % the replay asks for (within 2 %
    of the truth) is a finding in the log and in report.md."""
    truth = write_config(tmp_path / "truth.toml", {})
    start = write_config(tmp_path / "start.toml", {"friction": {"coulomb_n": 0.0},
                                                   "table": {"mass_kg": 48.5}})
    rec = load_record(make_trace(truth, tmp_path / "trace.csv"))
    said = []
    ident = Identification(start, rec, tolerance={"inertia": 0.05}, log=said.append).fit()
    mass = next(c for c in ident.declared_changes if c["parameter"] == "mass_kg")
    assert mass["identified"] == pytest.approx(1.05 * mass["declared"], rel=1e-6), mass
    assert ident.model.overrides()["table"]["mass_kg"] == pytest.approx(
        1.05 * mass["declared"] - (mass["declared"] - 48.5), rel=1e-6)
    assert mass["wanted"] == pytest.approx(60.0 + mass["declared"] - 48.5, rel=0.02), mass
    assert mass["wanted_by"] == "the closed-loop refinement"
    assert mass["beyond_tolerance"]
    text = (f"mass_kg would move {mass['wanted_change_pct']:+.3g} % (tolerance 5 %, asked "
            "for by the closed-loop refinement): a finding, not taken; taken: +5 %")
    assert any(text in line for line in said), said
    md = markdown(summary(ident, None, 0.0))
    assert "### Findings" in md and text in md


@pytest.mark.parametrize("k1, x1", [(3e8, 1e-7), (1.5e6, 4e-5)], ids=["0.1um", "40um"])
def test_presliding_is_found_across_0_1_to_50_um(tmp_path, k1, x1):
    """A presliding spring (exponent 1) at either end of the range: named first, its x1
    within 10 % (0.1 um, the range's end: at it) or 25 % (40 um), and the replay within
    1.5x the noise floor on every channel."""
    ident, floor = run_case(tmp_path, {"presliding": {
        "enabled": True, "stiffness_n_per_m": k1, "x1_m": x1, "exponent": 1.0}}, {})
    assert ident.steps and ident.steps[0].effect == "presliding_hysteresis", ident.rounds[0]
    assert ident.steps[0].params["x1_m"] == pytest.approx(x1, rel=0.1 if x1 < 1e-6 else 0.25)
    check_floor(ident, floor)


@pytest.fixture(scope="module")
def dip_trace(tmp_path_factory):
    d = tmp_path_factory.mktemp("shapes_declared")
    return d, make_trace(write_config(d / "truth.toml", DIP_AND_FORCE), d / "trace.csv")


@pytest.mark.parametrize("vs", [0.004, 0.0076], ids=["-50%", "-5%"])
def test_a_declared_stribeck_velocity_is_held_to_its_tolerance(dip_trace, vs):
    """The dip declared with its level right and its width at 4 mm/s (the truth's 8 mm/s
    is +100 %): the closed-loop refinement asks for the truth's width (within 5 %), a
    finding, and the width taken stays within the 10 % tolerance on the side asked for,
    in the model and in the machine file.  Declared at 7.6 mm/s (-5 %) it moves freely,
    to within 2 % of the truth, and nothing is a finding."""
    d, trace = dip_trace
    start = write_config(d / f"start_{vs:g}.toml", {"friction": {
        "breakaway_n": 60.0, "stribeck_velocity_m_s": vs}})
    said = []
    ident = Identification(start, load_record(trace), log=said.append).fit()
    assert [s.effect for s in ident.steps][:1] == ["gravity_offset"], ident.steps
    row = next(c for c in ident.declared_changes
               if c["parameter"] == "stribeck_velocity_m_s")
    taken = ident.model.overrides()["friction"]["stribeck_velocity_m_s"]
    assert row["declared"] == vs and row["identified"] == pytest.approx(taken, rel=1e-12)
    if vs < 0.005:
        assert row["beyond_tolerance"] and row["wanted_by"] == "the closed-loop refinement"
        assert row["wanted"] == pytest.approx(0.008, rel=0.05), row
        assert vs < taken <= 1.1 * vs * (1 + 1e-9), row
        assert any(f"declared stribeck_velocity_m_s would move {row['wanted_change_pct']:+.3g}"
                   in line for line in said), said
    else:
        assert taken == pytest.approx(0.008, rel=0.02), row
        assert not any(c["beyond_tolerance"] for c in ident.declared_changes), \
            ident.declared_changes


def test_a_declared_presliding_shape_is_held_by_the_same_box(dip_trace):
    """A declared presliding spring (k1 3e7 N/m, x1 1 um, exponent 1) and proposals of it:
    x1 five times the declared one is held at the tolerance's edge (+10 %), in the model
    and its machine file, and the proposal's 5 um is the finding on the row ``x1_m``; a
    proposal 5 % off is taken as it is.  The same box and rows as a coefficient's."""
    d, trace = dip_trace
    start = write_config(d / "start_presliding.toml", {"presliding": {
        "enabled": True, "stiffness_n_per_m": 3e7, "x1_m": 1e-6, "exponent": 1.0}})
    cfg = load_machine(start)
    rec = load_record(trace)
    drive = Drive.of(cfg)
    model = Model(Context.of(cfg, drive, rec, motion(rec, drive, None)), start)
    declared = model.term("presliding_hysteresis")
    for x1, held in ((5e-6, 1.1e-6), (1.05e-6, 1.05e-6)):
        proposal = dataclasses.replace(declared, shape={**declared.shape, "x1": x1},
                                       coef=declared.coef.copy(), added=False)
        model.add(proposal)
        assert model.overrides()["presliding"]["x1_m"] == pytest.approx(held, rel=1e-12)
        row = next(c for c in declared_changes(model) if c["parameter"] == "x1_m")
        assert row["identified"] == pytest.approx(held, rel=1e-12)
        assert row["beyond_tolerance"] == (x1 > held), row
        assert row["wanted"] == (pytest.approx(x1) if x1 > held else None), row
        assert row["wanted_by"] == ("its proposal" if x1 > held else ""), row
    rows = {c["parameter"] for c in declared_changes(model)
            if c["effect"] == "presliding_hysteresis"}
    assert rows == {"stiffness_n_per_m", "x1_m", "exponent"}
