"""Backlash beside a declared compliance, on a record whose load stands between moves.

Reference: the bench generator's truth (its own solver, never the plant's kernel): a
10 um gap and the declared coupling stiffness.  The position domain's joint refit must
give back both: at rest friction holds the load with any force up to the breakaway and
the motor rests anywhere in the gap, so samples at rest say nothing about either.
"""

import math

import pytest

from hil.bench.identify_gen.cases import (
    ADC_BITS,
    LEAD,
    PREROLL_S,
    RECORD_EVERY,
    SCREW,
    SINUMERIK_STYLE,
    TWO_MASS,
    merged,
)
from hil.bench.identify_gen.generate import simulate, write
from hil.bench.identify_gen.trajectory import moves
from hil.identify.config_out import patch_config
from hil.identify.effects import POSITION, Context
from hil.identify.effects.drivetrain import Backlash
from hil.identify.model import Model
from hil.identify.motion import Drive, motion
from hil.identify.record import load_record
from plant.config import load_machine

GAP_M = 1e-5


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    """(record, start file): 8 s of moves in both directions with dwells of 0.5 s, on
    the bench screw with a two-mass train and a 10 um gap."""
    folder = tmp_path_factory.mktemp("backlash_rest")
    text = SCREW.read_text()
    truth = folder / "truth.toml"
    gap = {"coupling": {"backlash_rad": GAP_M / (LEAD / (2 * math.pi))}}
    truth.write_text(patch_config(text, merged(SINUMERIK_STYLE, TWO_MASS, gap), "test"))
    start = folder / "start.toml"
    start.write_text(patch_config(text, TWO_MASS, "test"))
    traj = moves(0.1, [(0.05, 0.1), (0.0, 0.5), (-0.05, 0.05), (0.0, 0.5), (0.03, 0.02),
                       (0.0, 0.5), (-0.03, 0.1)])
    rec = simulate(truth, traj, record_every=RECORD_EVERY, preroll_s=PREROLL_S,
                   adc_bits=ADC_BITS, seed=5)
    return load_record(write(rec, folder / "trace.csv", "test")), start


def test_gap_and_declared_compliance_from_the_motion_alone(record):
    """The gap within 1 % and the declared compliance within 3 % of the truth's after the
    joint refit (with the samples at rest it moved the compliance by 60 % on the bench)."""
    rec, start = record
    cfg = load_machine(start)
    drive = Drive.of(cfg)
    ctx = Context.of(cfg, drive, rec, motion(rec, drive, None))
    model = Model(ctx, start)
    declared = float(model.term("compliance").coef[0])
    model.add(Backlash().propose(ctx, model.residual(POSITION), model))
    model.refit(POSITION)
    assert model.term("backlash").coef[0] == pytest.approx(GAP_M, rel=0.01)
    assert model.term("compliance").coef[0] == pytest.approx(declared, rel=0.03)
    assert not Backlash().mask(ctx)[~ctx.moving].any()
