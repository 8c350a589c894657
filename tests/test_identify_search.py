"""The search's held-out ranking, the refits' priors and uncertainties, the report's
declared-parameter changes (issue 13 parts 3 and 4).

References: the Gaussian linear model's posterior mean and covariance in closed form
(normal equations with the prior's precision added), written out here with numpy; the
traces come from our own controller and plant (tests/test_identify_effects.py's axis)
with known truths.
"""

import math

import numpy as np
import pytest

from hil.identify.candidates import BLOCK_S, holdout_rows
from hil.identify.changes import declared_changes
from hil.identify.command import tolerances
from hil.identify.effects import Context
from hil.identify.fit import Identification
from hil.identify.floor import replay_floor
from hil.identify.model import Model, uncertainty
from hil.identify.motion import Drive, motion
from hil.identify.record import load_record
from hil.identify.refine import refine
from plant.config import load_machine
from tests.test_identify_effects import make_trace, write_config


@pytest.fixture(scope="module")
def coulomb_trace(tmp_path_factory):
    """The test axis with Coulomb friction 30 N and a mass of 60 kg on the table; start
    files without Coulomb friction."""
    d = tmp_path_factory.mktemp("search")
    truth = write_config(d / "truth.toml", {})
    return d, make_trace(truth, d / "trace.csv")


def _model(start, rec, tolerance):
    cfg = load_machine(start)
    drive = Drive.of(cfg)
    ctx = Context.of(cfg, drive, rec, motion(rec, drive, None))
    return Model(ctx, start, tolerance=tolerance)


def test_refit_with_a_prior_is_the_gaussian_posterior(coulomb_trace):
    """The force domain's joint refit (mass, viscous and Coulomb friction; the declared
    mass 20 % low) against the posterior mean of the same weighted linear model written
    out here, (AᵀA + P) c = Aᵀb + P c0 with P = diag(1 / (tol c0)²); a prior as tight as
    1e-6 holds the mass at its declared value, a loose one lets the data move it to the
    truth's 60 kg reflected mass."""
    d, trace = coulomb_trace
    start = write_config(d / "light.toml", {"table": {"mass_kg": 0.8 * 60.0}})
    rec = load_record(trace)
    for tol, check in ((0.1, None), (1e-6, "declared"), (1e3, "truth")):
        model = _model(start, rec, {"inertia": tol, "viscous_friction": tol,
                                    "coulomb_friction": tol})
        c0 = {t.effect.name: float(t.coef[0]) for t in model.terms}
        model.refit("force")
        got = {t.effect.name: float(t.coef[0]) for t in model.terms}
        ctx, m = model.ctx, model.ctx.m
        names = ["inertia", "viscous_friction", "coulomb_friction"]
        a = np.column_stack([m.a, m.v, np.sign(m.v)])[ctx.moving]
        w = math.sqrt(2.0 * m.cutoff_hz * rec.dt) / m.noise_force
        prior = np.array([c0[n] for n in names])
        p = np.diag(1.0 / (tol * prior) ** 2)
        want = np.linalg.solve(w * w * a.T @ a + p, w * w * a.T @ m.force[ctx.moving] + p @ prior)
        np.testing.assert_allclose([got[n] for n in names], want, rtol=1e-6)
        if check == "declared":
            assert got["inertia"] == pytest.approx(c0["inertia"], rel=1e-5)
        if check == "truth":
            truth_mass = c0["inertia"] + 0.2 * 60.0
            assert got["inertia"] == pytest.approx(truth_mass, rel=0.01)


def test_uncertainty_of_a_straight_line_is_the_textbook_one():
    """y = c x + noise of deviation s: the least-squares slope's standard error is
    s / sqrt(sum x²); with rows in noise units (x / s) uncertainty() gives exactly that, and
    a misfit of 3 (a residual three times the floor) triples it."""
    x = np.linspace(-1.0, 2.0, 50)
    s = 0.3
    a_w = (x / s)[:, None]
    assert uncertainty(a_w, 1.0)[0] == pytest.approx(s / math.sqrt(np.sum(x * x)), rel=1e-12)
    assert uncertainty(a_w, 3.0)[0] == pytest.approx(3 * s / math.sqrt(np.sum(x * x)),
                                                     rel=1e-12)


def test_holdout_blocks_alternate_every_block_s(coulomb_trace):
    rec = load_record(coulomb_trace[1])
    rows = holdout_rows(rec)
    block = round(BLOCK_S / rec.dt)
    assert not rows[:block].any() and rows[block:2 * block].all()
    assert abs(rows.mean() - 0.5) < block / rec.n


def test_every_candidate_is_ranked_and_a_wrong_mass_is_flagged(coulomb_trace):
    """Start without Coulomb friction and with the table mass declared 50 % high (18 % of
    the reflected mass with the rotor): round 1 ranks every available effect, Coulomb's
    first; the mass, whose data outweigh its prior, is held at the edge of its 10 %
    tolerance, and what the data ask for, near the truth, is a finding (issue 30, item
    3), not one with a tolerance of 50 %.  Two worker processes rank exactly as the
    calling process does."""
    d, trace = coulomb_trace
    start = write_config(d / "start.toml", {"friction": {"coulomb_n": 0.0},
                                            "table": {"mass_kg": 1.5 * 60.0}})
    rec = load_record(trace)
    ident = Identification(start, rec, refine_nfev=0, workers=2).fit()
    ranking = ident.rounds[0]["ranking"]
    assert ranking[0]["effect"] == "coulomb_friction"
    assert {r["effect"] for r in ranking} >= {"inertia", "viscous_friction", "gravity_offset",
                                               "stribeck", "cogging", "pitch_error",
                                               "compliance", "time_delay"}
    mass = next(c for c in ident.declared_changes if c["parameter"] == "mass_kg")
    truth = mass["declared"] - 0.5 * 60.0
    assert mass["identified"] == pytest.approx(0.9 * mass["declared"], rel=1e-9)
    assert mass["wanted"] == pytest.approx(truth, rel=0.03)
    assert mass["beyond_tolerance"] and mass["significant"]
    assert mass["sigma"] > 0
    serial = Identification(start, rec, refine_nfev=0, workers=1).fit()
    assert [(r["effect"], r["heldout_cost"]) for r in serial.rounds[0]["ranking"]] == [
        (r["effect"], r["heldout_cost"]) for r in ranking]
    serial.model.tolerance = {"inertia": 0.5}
    mass = next(c for c in declared_changes(serial.model) if c["parameter"] == "mass_kg")
    assert not mass["beyond_tolerance"] and mass["tolerance_pct"] == 50.0


def test_tolerance_option_parses_and_refuses_naming_the_item():
    assert tolerances(["inertia=0.05", "coulomb_friction=0.2"]) == {
        "inertia": 0.05, "coulomb_friction": 0.2}
    for bad in ("mass=0.1", "inertia=-1", "inertia=x", "inertia"):
        with pytest.raises(ValueError, match=bad.replace("=", "=")):
            tolerances([bad])


def test_refinement_on_the_replay_recovers_a_declared_coulomb_level(coulomb_trace):
    """Our own plant's trace (Coulomb 30 N) replayed from a file declaring 24 N, with a
    tolerance of 100 % (the prior barely binds): the refinement's least squares on the
    replay brings Coulomb's level to the truth within 2 % and lowers J, with a finite
    uncertainty; a tolerance of 1e-4 holds it at the declared value."""
    d, trace = coulomb_trace
    start = write_config(d / "low_coulomb.toml", {"friction": {"coulomb_n": 24.0}})
    rec = load_record(trace)
    for tol, want in ((1.0, 30.0), (1e-4, 24.0)):
        model = _model(start, rec, {"coulomb_friction": tol})
        n_eff = rec.n * 2.0 * model.ctx.m.cutoff_hz * rec.dt
        out = refine(model, rec, replay_floor(rec), n_eff, 10)
        assert out["after"]["coulomb_friction"] == pytest.approx(want, rel=0.02)
        assert out["cost_after"] <= out["cost_before"]
        assert 0.0 < out["sigma"]["coulomb_friction"] < 1.0


def test_a_fractional_cogging_order_comes_from_the_spectrum(tmp_path):
    """Cogging at 2.5 cycles per electrical revolution (10 per mechanical revolution of the
    4-pole-pair motor: a slot count that is no multiple of the poles) is no whole order;
    the residual's spectrum against the motor angle offers it, and it is what is fitted,
    with its amplitude within 5 % (the force residual's lines at the table: 0.02 N m at the
    motor over lead / 2 pi)."""
    truth = write_config(tmp_path / "truth.toml", {"cogging": {"orders": [2.5],
                                                                "amplitudes_nm": [0.02]}})
    start = write_config(tmp_path / "start.toml", {})
    rec = load_record(make_trace(truth, tmp_path / "trace.csv"))
    ident = Identification(start, rec, refine_nfev=0).fit()
    step = ident.steps[0]
    assert step.effect == "cogging"
    assert step.evidence["spectral_orders"][0] == pytest.approx(2.5, abs=0.01)
    assert step.params["orders"] == [pytest.approx(2.5, abs=0.01)]
    assert step.params["amplitudes_nm"][0] == pytest.approx(0.02, rel=0.05)
