"""``hil identify``'s words say what happened: no bare "no fault found" after effects were
added, no negative zero, no "None %", no "+0" difference.

References: made-up report.json contents rendered by :func:`hil.identify.report.markdown`
(the values a real run gave: a cogging coefficient declared and identified as -0.0, a
change from a declared 0 that report.json holds as None), the command's summary lines,
and the inertia effect's evidence on a made-up motion whose residual is a known multiple
of the acceleration.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from hil.identify.changes import change_text
from hil.identify.diagnosis import summary_lines
from hil.identify.effects.base import Term
from hil.identify.effects.force import Inertia
from hil.identify.report import markdown

EFFECTS = ["coulomb_friction", "cogging", "backlash", "external_force"]


def _report(**changed) -> dict:
    """A report.json content with the declared-change rows ``changed`` and no fault."""
    err = {"pos_rms_um": 1.5, "pos_relerr_pct": 0.01, "force_rms_n": 2.0,
           "force_relerr_pct": None}
    rows = [{"parameter": "cogging[1]", "effect": "cogging", "declared": -0.0,
             "identified": -0.0, "sigma": None, "change_pct": None, "tolerance_pct": 20.0,
             "beyond_tolerance": False, "significant": None},
            {"parameter": "cogging[2]", "effect": "cogging", "declared": 0.0,
             "identified": 0.25, "sigma": 0.01, "change_pct": None, "tolerance_pct": 20.0,
             "beyond_tolerance": True, "significant": True},
            {"parameter": "mass_kg", "effect": "inertia", "declared": 40.0,
             "identified": 41.0, "sigma": 0.1, "change_pct": 2.5, "tolerance_pct": 20.0,
             "beyond_tolerance": False, "significant": True}]
    return {"trace": "runs/trace.csv", "config": "configs/x.toml", "method": "m",
            "samples": 1000, "sample_time_s": 1e-3, "filter_cutoff_hz": 50.0,
            "elapsed_s": 3.0, "effects_added": EFFECTS, "faults": [], "steps": [],
            "error_before": err, "error_after": err, "refinement": {},
            "declared_changes": changed.get("rows", rows),
            "replay_noise_floor": {"pos_rms_um": 0.5},
            "error_before_over_floor": {}, "error_after_over_floor": {}, "rounds": [],
            "proposals": [], "unexplained": {}, "not_looked_for": {}}


def test_no_fault_after_added_effects_says_beyond_them():
    """With effects added and no fault named, the summary line and report.md name the
    effects instead of a bare "no fault found"; with none added it stays the plain phrase."""
    line, = summary_lines([], EFFECTS)
    assert line != "no fault found" and "beyond the effects added" in line
    assert all(e in line for e in EFFECTS)
    md = markdown(_report())
    assert "No fault found." not in md
    assert ("No fault of the catalog found beyond the effects added to the model "
            "(coulomb_friction, cogging, backlash, external_force).") in md
    assert summary_lines([], []) == ["no fault found"]


def test_the_declared_changes_table_has_no_negative_zero_and_no_none():
    """cogging[1] declared and identified -0.0 reads "| 0 | 0 | unchanged |"; a change from
    a declared 0 reads "n/a (declared 0)", an unknown sigma "n/a", an error report.json
    could not hold "n/a"; none of "-0 |", "None" is left."""
    md = markdown(_report())
    assert "| cogging[1] | 0 | 0 | unchanged | n/a |" in md
    assert "| cogging[2] | 0 | 0.25 | n/a (declared 0) |" in md
    assert "| mass_kg | 40 | 41 | +2.5 % |" in md
    assert "-0 |" not in md and "| -0" not in md and "None" not in md


@pytest.mark.parametrize("declared, identified, said", [
    (40.0, 40.0, "unchanged"), (-0.0, 0.0, "unchanged"), (0.0, 1e-3, "n/a (declared 0)"),
    (40.0, 40.0 + 4e-6, "+1e-05 %"), (40.0, 30.0, "-25 %")])
def test_a_change_is_unchanged_or_enough_digits_never_plus_zero(declared, identified, said):
    """change_text: equal values are "unchanged"; a tiny change keeps its digits."""
    assert change_text({"declared": declared, "identified": identified}) == said


def _ctx(mass: float) -> SimpleNamespace:
    a = np.sin(np.linspace(0.0, 20.0, 400))
    return SimpleNamespace(moving=np.ones(a.size, bool), m=SimpleNamespace(a=a),
                           drive=SimpleNamespace(mass=mass, kind="screw"))


def test_the_moved_mass_evidence_says_unchanged_or_the_change_with_its_unit():
    """A residual of -2 a (the fit adds mass only, so it finds none) reads "unchanged at
    40 kg", not "off by +0"; a residual of +0.5 a reads "off by +0.5 kg (+1.25 % of 40)"."""
    effect = Inertia()
    ctx = _ctx(40.0)
    model = SimpleNamespace(term=lambda name: Term(effect, {}, np.array([40.0])))
    text = effect.propose(ctx, -2.0 * ctx.m.a, model).evidence["text"]
    assert "+0" not in text and "moved mass unchanged at 40 kg" in text
    text = effect.propose(ctx, 0.5 * ctx.m.a, model).evidence["text"]
    assert "moved mass off by +0.5 kg (+1.25 % of 40)" in text
