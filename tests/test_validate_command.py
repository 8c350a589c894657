"""``hil validate`` as a command (hil.validate.command, through the argparse parser its
``add_arguments`` builds): JSON rows with kind and verdict, the table's columns, the summary,
the exit status with and without --strict, plots, refusal of an unknown experiment; and
the helpers behind the new rows, each against an independent reference."""

import argparse
import json
import math

import numpy as np
import pytest
import scipy.linalg

from hil.controller.blocks import PI
from hil.validate.command import add_arguments, run_from_args
from hil.validate.core import CONFIGS
from hil.validate.experiments.configuration import CLAIMS, screw_modes
from hil.validate.experiments.electrical import SeedOneDrive
from hil.validate.experiments.linear_loops import closed_speed_loop
from hil.validate.experiments.moves import IntegratorCap
from hil.validate.experiments.seed001_envelope import OperatingPoint
from plant.assemble import mechanics_matrices
from plant.config import load_machine


def validate(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="hil validate")
    add_arguments(parser)
    return run_from_args(parser.parse_args(list(argv)))


def test_json_rows_carry_kind_verdict_note_and_source(capsys):
    """A disagreement (a machine-file comment's modal damping) is a finding: exit status 0."""
    assert validate("--json", "--no-plots", "--only", "encoder_resolution",
                    "modal_damping") == 0
    out = capsys.readouterr()
    rows = json.loads(out.out)
    assert {"experiment", "paper", "model", "unit", "ok", "reference", "tolerance", "kind",
            "verdict", "note", "source", "uncertainty"} <= set(rows[0])
    assert {r["kind"] for r in rows} == {"verification"}
    assert {r["verdict"] for r in rows} == {"agrees", "disagrees"}
    counts = next(r for r in rows if r["experiment"] == "encoder counts per revolution")
    assert counts["source"]["seed"] == "004" and counts["source"]["page"] is None
    assert "disagreements:" in out.err  # the summary goes to stderr, the JSON stays clean


def test_strict_exits_1_when_a_verification_fails(capsys):
    assert validate("--strict", "--no-plots", "--only", "modal_damping") == 1
    assert "[verification] arrow500_x.toml: damping of the screw torsion mode" in \
        capsys.readouterr().out


def test_strict_exits_0_when_only_findings_disagree(capsys):
    """Seed 004's predictions disagree; its verifications agree: not a bug."""
    assert validate("--strict", "--no-plots", "--only", "presliding_seed004") == 0
    out = capsys.readouterr().out
    assert "3 prediction (1 agree, 2 disagree)" in out
    assert "- [prediction] presliding: torque amplitude ratio" in out


def test_table_has_kind_and_verdict_columns_and_escapes_pipes(capsys):
    validate("--no-plots", "--only", "current_steps", "modal_damping")
    lines = capsys.readouterr().out.splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    assert header == ["experiment", "kind", "reference value", "model", "unit", "verdict",
                      "reference", "tolerance", "note"]
    body = [line for line in lines[2:] if line.startswith("| ")]
    assert all(line.count(" | ") == len(header) - 1 for line in body)
    assert any("max \\|i_model - i_analytic\\|" in line for line in body)
    assert any("| **disagrees** |" in line for line in body)


def test_summary_line_counts_rows_per_kind(capsys):
    validate("--no-plots", "--only", "modal_damping")
    summary = capsys.readouterr().out.split("\n\n")[-1].splitlines()
    assert summary[0] == ("6 rows: 6 verification (1 agree, 5 disagree), 0 reproduction "
                          "(0 agree, 0 disagree), 0 prediction (0 agree, 0 disagree).")
    assert summary[1] == "disagreements:" and len(summary) == 2 + 5


def test_plots_go_to_out(tmp_path, capsys):
    assert validate("--out", str(tmp_path), "--only", "seed001_voltage_envelope") == 0
    assert (tmp_path / "seed001_voltage_envelope.png").stat().st_size > 0
    assert f"plots in {tmp_path}/" in capsys.readouterr().out


def test_an_unknown_experiment_is_refused_naming_the_known_ones(capsys):
    """The command line refuses it before anything runs (exit 2, the names it takes); the
    API behind it names the known ones too."""
    with pytest.raises(SystemExit) as stopped:
        validate("--no-plots", "--only", "no_such")
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'no_such'" in err and "cogging_spectrum" in err
    from hil.validate.core import run_all
    with pytest.raises(KeyError, match="unknown experiment.*no_such.*known: cogging_spectrum"):
        run_all(None, ["no_such"])


# --- the helpers behind the new rows ------------------------------------------------------

def test_damping_claims_quote_their_machine_files():
    """Each checked comment stands, verbatim, on the line of its key in its file."""
    for claim in CLAIMS:
        section, key = claim.key.strip("[").split("] ")
        lines = (CONFIGS / claim.file).read_text().splitlines()
        start = lines.index(f"[{section}]")
        (line,) = [ln for ln in lines[start:] if ln.startswith(f"{key} ")][:1]
        assert claim.comment in line, (claim.file, claim.key)


def test_voltage_of_the_coil_as_a_synchronous_machine():
    """By hand at gamma = 0: |u| = hypot(R I + K omega, p omega L I); at a lowered
    commutation angle the d current's omega_e L i_d lowers it."""
    cfg = load_machine(CONFIGS / "geiss_c_axis.toml")
    mo = cfg.motor
    drive = SeedOneDrive.from_config(cfg)
    point = OperatingPoint(45.0, 30.0, mo.torque_constant_nm_per_a)
    applied, needed = point.voltages(drive)
    assert applied == pytest.approx(mo.resistance_ohm * 30.0 + 12.0 * 45.0)
    assert needed == pytest.approx(math.hypot(applied, 22 * 45.0 * mo.inductance_d_h * 30.0))
    assert needed == pytest.approx(677.3, abs=0.1)  # the review's figure
    weakened = OperatingPoint(45.0, 30.0, 0.8 * mo.torque_constant_nm_per_a)
    assert weakened.voltages(drive)[1] < needed
    braking = OperatingPoint(45.0, -30.0, 0.8 * mo.torque_constant_nm_per_a)
    assert braking.voltages(drive)[1] < math.hypot(*drive.dq_voltage(45.0, 12.0, -30.0)), \
        "i_d stays demagnetising for a braking current"


def test_closed_speed_loop_has_unity_gain_at_low_frequency_and_refuses_filters():
    """Integral action: |T| -> 1, phase -> 0 as f -> 0; filters it leaves out are refused."""
    cfg = load_machine(CONFIGS / "arrow500_x.toml")
    low = closed_speed_loop(cfg, 0.25, np.array([0.01]))[0]
    assert abs(low) == pytest.approx(1.0, abs=1e-4) and abs(np.angle(low)) < 1e-3
    notched = load_machine(CONFIGS / "arrow500_x.toml",
                           overrides={"controller": {"notch_hz": 400.0,
                                                     "notch_bandwidth_hz": 50.0}})
    with pytest.raises(ValueError, match="notch_hz"):
        closed_speed_loop(notched, 0.25, np.array([10.0]))


def test_modal_damping_matches_the_proportional_estimate():
    """Second method: for light damping the complex eigenvalue's ratio equals
    phi' C phi / (2 omega) of the mass-normalised undamped mode within 2 %, and the strain
    energy shares of every mode add up to 1."""
    cfg = load_machine(CONFIGS / "arrow500_x.toml")
    m_mat, c_mat, k_mat = mechanics_matrices(cfg, 0.25)
    w2, phi = scipy.linalg.eigh(k_mat, m_mat)
    for mode, (w_sq, q) in zip(screw_modes(cfg, 0.25), zip(w2[1:], phi.T[1:])):
        assert sum(mode.shares.values()) == pytest.approx(1.0)
        assert mode.freq_hz == pytest.approx(math.sqrt(w_sq) / (2 * math.pi))
        if mode.freq_hz < 1000.0:
            assert mode.damping == pytest.approx(q @ c_mat @ q / (2 * math.sqrt(w_sq)),
                                                 rel=0.02)


def test_integrator_cap_holds_the_integrator_and_is_the_pi_without_one():
    """Uncapped it gives the drive's PI's outputs step by step; capped its integrator stays
    within the cap and the largest value it reached is recorded."""
    errors = np.sin(np.arange(200) * 0.05) * 3.0 + 1.0
    plain, free = PI(2.0, 0.01, 1e-3, 50.0), IntegratorCap(PI(2.0, 0.01, 1e-3, 50.0), math.inf)
    held = IntegratorCap(PI(2.0, 0.01, 1e-3, 50.0), 1.5)
    largest = 0.0
    for k, e in enumerate(errors):
        assert free.step(e) == plain.step(e), k
        largest = max(largest, abs(plain.integ))
        held.step(e)
        assert abs(held.integ) <= 1.5
    assert free.peak == largest > 1.5
    assert held.peak == 1.5
