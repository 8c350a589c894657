"""The closed-loop refinement finds the friction of a stick-slip record, not a point near it.

Reference: the bench generator's truth (hil/bench/identify_gen/: scipy's solve_ivp on the
documented stick-slip law, never the plant's kernel) for screw_stribeck -- moved mass
139 kg (60 kg table and the motor's 2e-4 kg m^2 through a 10 mm lead), viscous 300 N s/m,
Coulomb 30 N, breakaway 60 N, Stribeck velocity 8 mm/s.  The least-squares passes alone
stopped at 141.3 kg, 304.7 N s/m and 7.93 mm/s, 1.58x the scale's floor, where the truth
replays at 1.27x.
"""

import math

import pytest

from hil.bench.identify import FLOOR_GOAL, prepare, ratios
from hil.bench.identify_gen.cases import case
from hil.identify.fit import Identification
from hil.identify.record import load_record

TRUTH = {"inertia": 60.0 + 2e-4 / (0.01 / (2 * math.pi)) ** 2, "viscous_friction": 300.0,
         "coulomb_friction": 30.0, "stribeck": 30.0, "stribeck.vs": 0.008}


def test_stribeck_record_refined_to_the_truths_friction_and_the_floor(tmp_path):
    # the trace alone: the generator's repeat deviation is the bench's, not this test's
    files = prepare(case("screw_stribeck"), tmp_path, repeat=False)
    ident = Identification(files["start"], load_record(files["trace"])).fit()
    # Stribeck named first; Coulomb's declared level, fitted beside the dip (the joint
    # candidate of issue 30 item 3), may come with it as a correction
    added = [s.effect for s in ident.steps]
    assert added[0] == "stribeck" and set(added) <= {"stribeck", "coulomb_friction"}, added
    after = ident.refinement["after"]
    for label, value in TRUTH.items():
        # within 1 % of the truth (the passes alone: the mass 1.7 %, the viscous 1.6 % off)
        assert after[label] == pytest.approx(value, rel=0.01), label
    over = ratios(ident.error_after, files["floor"])
    assert max(over.values()) <= FLOOR_GOAL, over
