"""Study files refused before any work starts, distributions and designs, and the figures
a study computes, each against an independent reference (analytic responses, closed-form
margins, the published Ishigami indices).  No cluster here: tests/test_study_dask.py."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import scipy.optimize
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import truncnorm

from hil.controller.config import load_controller
from hil.measure.frequency_response import FrequencyResponse
from hil.measure.runs import position_step
from hil.study import report
from hil.study.analytic import ishigami, ishigami_indices
from hil.study.circularity import CircularityExperiment
from hil.study.distributions import Distribution
from hil.study.evaluate import evaluate_chunk
from hil.study.experiments import axis_config
from hil.study.keys import StudySpecError, _range, declared_field, overrides_of
from hil.study.outputs import margins, step_metrics
from hil.study.run import job_of, study_design
from hil.study.sampling import design, monte_carlo, sobol_sequence
from hil.study.spec import load_study
from hil.study.store import Results, ResultStore
from hil.study.tuning import robust_values
from plant.config import load_machine
from plant.errors import ConfigError
from plant.schema import in_range, range_text

ROOT = Path(__file__).resolve().parents[1]
ARROW = ROOT / "configs" / "arrow500_x.toml"
ARROW_XY = ROOT / "configs" / "machines" / "arrow500_xy.toml"

GOOD = f"""
[study]
name = "test"
machine = "{ARROW}"
method = "tolerance"
samples = 4
[experiment]
kind = "step"
at_mm = 250.0
duration_s = 0.1
[vary.table]
mass_kg = {{ tolerance_pct = 10.0 }}
"""


def write(tmp_path: Path, text: str, name: str = "study.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(tmp_path: Path, text: str) -> str:
    with pytest.raises(StudySpecError) as exc:
        load_study(write(tmp_path, text))
    return str(exc.value)


def test_good_spec_loads_with_the_machine_files_values(tmp_path):
    study = load_study(write(tmp_path, GOOD))
    (ref,), (dist,) = study.varied, study.distributions
    assert (ref.name, ref.unit, ref.nominal) == ("table.mass_kg", "kg", 350.0)
    assert dist.support() == pytest.approx((315.0, 385.0))
    assert study.outputs == ("rise_time_s", "lag_50pct_s", "overshoot_pct", "settling_time_s")


@pytest.mark.parametrize("change, words", [
    (("[study]", "[study]\ncolour = 3"), ["unknown key [study] colour"]),
    (("[experiment]", "[experiment]\namplitude_m = 0.5"), ["unknown key [experiment] amplitude_m",
                                                          "amplitude_mm"]),
    (("[vary.table]", "[vary.tabel]"), ["[tabel]"]),
    (("mass_kg =", "mass_kilo ="), ["unknown key [table] mass_kilo"]),
    (("[vary.table]", "[colours]\n[vary.table]"), ["unknown section [colours]"]),
    (("kind = \"step\"", "kind = \"step\"\noutputs = [\"bandwidth_hz\"]"),
     ["no output 'bandwidth_hz'"]),
    (("method = \"tolerance\"", "method = \"tuning\""), ["minimize"]),
    (("samples = 4", "samples = 6\ndesign = \"sobol\""), ["samples = 6", "power of 2"]),
])
def test_bad_spec_is_refused_naming_the_key(tmp_path, change, words):
    message = refused(tmp_path, GOOD.replace(*change))
    assert str(tmp_path / "study.toml") in message
    for w in words:
        assert w in message


@pytest.mark.parametrize("line, end", [
    # a tolerance reaching below 0 kg
    ("[vary.table]\nmass_kg = { tolerance_pct = 150.0 }", ("table", "mass_kg", -175.0)),
    # truncated normal 350 +- 3 x 150 kg reaches -100 kg
    ("[vary.table]\nmass_kg = { normal = [350.0, 150.0] }", ("table", "mass_kg", -100.0)),
    # no stiffness of 0 N*m/rad
    ("[vary.coupling]\nstiffness_nm_per_rad = { uniform = [0.0, 4000.0] }",
     ("coupling", "stiffness_nm_per_rad", 0.0)),
    ("[vary.controller]\nspeed_ff_weight = { uniform = [0.5, 2.5] }",
     ("controller", "speed_ff_weight", 2.5)),
])
def test_distribution_outside_the_keys_physical_range_is_refused(tmp_path, line, end):
    """Refused naming the parameter, the value and the range; the reference is the
    machine-file loader, which refuses that value in the file itself."""
    section, key, value = end
    text = GOOD.replace("[vary.table]\nmass_kg = { tolerance_pct = 10.0 }", line)
    message = refused(tmp_path, text)
    assert f"parameter '{section}.{key}'" in message
    assert f"reaches {value:g} " in message and "outside the physical range" in message
    with pytest.raises(ConfigError, match=key):
        load_controller(load_machine(ARROW, {section: {key: value}}))


@pytest.mark.parametrize("line, words", [
    ("[vary.screw]\nsegments = { tolerance_pct = 10.0 }", ["screw.segments", "whole numbers"]),
    ("[vary.mechanics]\nmodel = { values = [1, 2] }", ["mechanics.model", "numbers only"]),
    ("[vary.table]\nmass_kg = { tolerance_pct = 10.0, sd = 3 }", ["table.mass_kg", "unknown: sd"]),
    ("[vary.table]\nmass_kg = { uniform = [400.0, 300.0] }", ["table.mass_kg", "empty range"]),
])
def test_malformed_distribution_is_refused(tmp_path, line, words):
    message = refused(tmp_path, GOOD.replace("[vary.table]\nmass_kg = { tolerance_pct = 10.0 }",
                                             line))
    for w in words:
        assert w in message


def test_a_range_end_the_machine_file_rules_refuse_is_refused(tmp_path):
    # breakaway_n (160 N) must stay >= coulomb_n: 120 N + 50 % = 180 N breaks that rule
    message = refused(tmp_path, GOOD + "[vary.friction]\ncoulomb_n = { tolerance_pct = 50.0 }\n")
    assert "friction.coulomb_n' = 180 N" in message
    assert "breakaway_n" in message


def test_manifest_keys_name_their_axis(tmp_path):
    text = GOOD.replace(str(ARROW), str(ARROW_XY))
    assert "AXIS.section.key" in refused(tmp_path, text)
    study = load_study(write(tmp_path, text.replace("[vary.table]", "[vary.Y.table]")))
    assert study.varied[0].name == "Y.table.mass_kg"
    assert study.varied[0].nominal == 550.0  # the manifest's override of Y


def test_a_samples_keys_do_not_stay_in_the_next_samples_machine(tmp_path):
    """The worker parses the machine's text once and builds every sample from a copy: a
    sample's keys, and the manifest's overrides, apply to that sample only."""
    study = load_study(write(tmp_path, GOOD.replace(str(ARROW), str(ARROW_XY))
                             .replace("[vary.table]", "[vary.Y.table]")))
    source = study.machine
    changed = source.build({"Y": {"table": {"mass_kg": 700.0}}, "X": {"friction":
                                                                      {"coulomb_n": 90.0}}})
    assert changed.axes[1].config.table.mass_kg == 700.0
    plain = source.build()
    assert plain.axes[1].config.table.mass_kg == 550.0  # the manifest's Y override
    assert plain.axes[0].config.friction.coulomb_n == load_machine(ARROW).friction.coulomb_n
    assert plain.axes[0].config.table.mass_kg == load_machine(ARROW).table.mass_kg


def test_bad_spec_stops_hil_study_before_any_work(tmp_path):
    spec = write(tmp_path, GOOD.replace("tolerance_pct = 10.0", "tolerance_pct = 150.0"))
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "hil.study", str(spec), "--out", str(out)],
                         capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 2
    assert "table.mass_kg" in res.stderr and "outside the physical range" in res.stderr
    assert not out.exists()  # no store, no cluster: nothing started


@settings(max_examples=50, deadline=None)
@given(st.floats(-1e3, 1e3), st.floats(1e-3, 1e3), st.floats(0.5, 5.0),
       st.lists(st.floats(0.0, 1.0), min_size=1, max_size=20))
def test_normal_values_stay_within_the_truncation(mean, sd, k, u):
    values = Distribution("normal", mean, sd, truncate_sd=k).ppf(np.array(u))
    assert np.all(values >= mean - k * sd - 1e-9 * (abs(mean) + sd))
    assert np.all(values <= mean + k * sd + 1e-9 * (abs(mean) + sd))


def test_truncated_normal_matches_scipy_truncnorm():
    u = np.linspace(0.01, 0.99, 25)
    ours = Distribution("normal", 10.0, 2.0, truncate_sd=3.0).ppf(u)
    assert ours == pytest.approx(truncnorm.ppf(u, -3.0, 3.0, loc=10.0, scale=2.0), rel=1e-9)


def test_log_uniform_and_values():
    u = np.array([0.0, 0.5, 1.0])
    assert Distribution("uniform", 1.0, 100.0, log=True).ppf(u) == pytest.approx([1, 10, 100])
    assert list(Distribution("values", values=(5.0, 7.0, 9.0)).ppf(u)) == [5.0, 7.0, 9.0]


def test_a_samples_values_depend_on_the_seed_and_its_index_only():
    assert np.array_equal(monte_carlo(3, 10, seed=4)[:6], monte_carlo(3, 6, seed=4))
    assert np.array_equal(sobol_sequence(3, 16, seed=4)[:8], sobol_sequence(3, 8, seed=4))
    assert not np.array_equal(monte_carlo(3, 6, seed=4), monte_carlo(3, 6, seed=5))
    saltelli = design("saltelli", ("a", "b"), 8, seed=1)
    assert saltelli.shape == (8 * 4, 2)
    # each base row: A, AB_1 (A with B's first column), AB_2, B
    a, ab1, ab2, b = saltelli[:4]
    assert (ab1[0], ab1[1]) == (b[0], a[1]) and (ab2[0], ab2[1]) == (a[0], b[1])


def second_order_step(zeta: float, wn: float, t: np.ndarray) -> np.ndarray:
    """Unit step response of wn^2 / (s^2 + 2 zeta wn s + wn^2), zeta < 1 (closed form)."""
    wd = wn * math.sqrt(1.0 - zeta * zeta)
    phi = math.acos(zeta)
    return 1.0 - np.exp(-zeta * wn * t) * np.sin(wd * t + phi) / math.sqrt(1.0 - zeta * zeta)


@pytest.mark.parametrize("zeta", [0.3, 0.6, 0.9])
def test_step_metrics_against_the_second_order_system(zeta):
    wn, y0, step = 2 * math.pi * 20.0, 0.25, 0.0005
    t = np.arange(0.0, 0.6, 125e-6)
    y = y0 + step * second_order_step(zeta, wn, t)
    m = step_metrics(t, y, y0, step, band_pct=2.0)

    def reach(level):  # first crossing, by root finding on the closed form
        grid = np.linspace(0, 0.6, 200001)
        i = int(np.argmax(second_order_step(zeta, wn, grid) >= level))
        return scipy.optimize.brentq(lambda s: second_order_step(zeta, wn, np.array([s]))[0]
                                     - level, grid[i - 1], grid[i])

    # analytic overshoot exp(-zeta pi / sqrt(1 - zeta^2)); the sampled peak is within a tick
    assert m.overshoot_pct == pytest.approx(100 * math.exp(-zeta * math.pi / math.sqrt(
        1 - zeta * zeta)), abs=0.01)
    assert m.rise_time_s == pytest.approx(reach(0.9) - reach(0.1), abs=2e-6)
    assert m.lag_50pct_s == pytest.approx(reach(0.5), abs=2e-6)
    # settling into +-2 %: the last time |y - 1| = 0.02, found on the closed form
    fine = np.linspace(0, 0.6, 600001)
    err = np.abs(second_order_step(zeta, wn, fine) - 1.0)
    assert m.settling_time_s == pytest.approx(fine[np.flatnonzero(err > 0.02)[-1]], abs=2e-6)


def test_margins_against_the_closed_form_loop():
    # L = K e^(-T s) / (s (tau s + 1)): crossover and phase crossover found by root finding
    k, tau, delay = 40.0, 0.02, 0.004
    f = np.geomspace(0.1, 2000.0, 4000)

    def loop(w):
        return k * np.exp(-1j * w * delay) / (1j * w * (1j * w * tau + 1.0))

    h = loop(2 * np.pi * f) / (1.0 + loop(2 * np.pi * f))
    got = margins(FrequencyResponse.from_h(f, h, np.ones_like(f)))
    wc = scipy.optimize.brentq(lambda w: abs(loop(w)) - 1.0, 1.0, 1e4)
    pm = 180.0 + math.degrees(-math.pi / 2 - math.atan(wc * tau) - wc * delay)
    wp = scipy.optimize.brentq(lambda w: -math.pi / 2 - math.atan(w * tau) - w * delay + math.pi,
                               1.0, 1e4)
    gm = -20.0 * math.log10(abs(loop(wp)))
    assert got["phase_margin_deg"] == pytest.approx(pm, abs=0.05)
    assert got["gain_margin_db"] == pytest.approx(gm, abs=0.05)


def test_margins_of_a_loop_with_a_resonance_take_the_worst_crossing():
    """A PI speed loop on a two-mass drive: |L| passes 1 three times (the resonance lifts
    it above 1 again); the reference finds every crossing on the closed form."""
    kp, tn, j, delay = 4.0, 0.01, 3.2e-3, 2e-4
    wz, wp, zeta = 2 * np.pi * 300.0, 2 * np.pi * 420.0, 0.03

    def loop(w):
        s = 1j * w
        two_mass = ((s * s / wz ** 2 + 2 * zeta * s / wz + 1)
                    / (s * s / wp ** 2 + 2 * zeta * s / wp + 1))
        return kp * (1 + 1 / (tn * s)) / (j * s) * two_mass * np.exp(-s * delay)

    f = np.geomspace(2.0, 4000.0, 20000)
    h = loop(2 * np.pi * f) / (1 + loop(2 * np.pi * f))
    got = margins(FrequencyResponse.from_h(f, h, np.ones_like(f)))
    w = 2 * np.pi * np.geomspace(2.0, 4000.0, 400001)
    lw = loop(w)
    roots = [scipy.optimize.brentq(lambda x: abs(loop(x)) - 1.0, w[i], w[i + 1])
             for i in np.flatnonzero(np.diff(np.sign(np.abs(lw) - 1.0)))]
    assert len(roots) == 3
    pm = min(180.0 - abs(math.degrees(np.angle(loop(r)))) for r in roots)
    turns = [scipy.optimize.brentq(lambda x: loop(x).imag, w[i], w[i + 1])
             for i in np.flatnonzero(np.diff(np.sign(lw.imag)))
             if w[i] > roots[0] and lw.real[i] < 0]
    gm = min(-20 * math.log10(abs(loop(t))) for t in turns)
    assert got["phase_margin_deg"] == pytest.approx(pm, abs=0.1)
    assert got["gain_margin_db"] == pytest.approx(gm, abs=0.05)
    first = 180.0 - abs(math.degrees(np.angle(loop(roots[0]))))
    assert pm < first - 10.0  # the worst crossing is the resonance's, not the first


def test_ishigami_indices_are_the_published_ones():
    first, total = ishigami_indices()
    # Saltelli et al., Global Sensitivity Analysis: The Primer (2008), for a = 7, b = 0.1
    assert first == pytest.approx([0.3139, 0.4424, 0.0], abs=1e-4)
    assert total == pytest.approx([0.5576, 0.4424, 0.2437], abs=1e-4)
    # and the function's variance by brute force against the closed form
    x = np.random.default_rng(0).uniform(-np.pi, np.pi, (200000, 3))
    y = np.sin(x[:, 0]) + 7 * np.sin(x[:, 1]) ** 2 + 0.1 * x[:, 2] ** 4 * np.sin(x[:, 0])
    assert ishigami(*x[0]) == pytest.approx(y[0])
    assert y.var() == pytest.approx(7 ** 2 / 8 + 0.1 * np.pi ** 4 / 5 + 0.01 * np.pi ** 8 / 18
                                    + 0.5, rel=0.02)


def test_circle_path_is_on_the_circle_with_consistent_derivatives(tmp_path):
    text = (GOOD.replace(str(ARROW), str(ARROW_XY)).replace("[vary.table]", "[vary.X.table]")
            .replace('kind = "step"\nat_mm = 250.0\nduration_s = 0.1',
                     'kind = "circularity"\nradius_mm = 20.0\nfeed_mm_min = 3000.0\n'
                     'center_mm = [200.0, 300.0]\ndirection = "cw"'))
    exp = load_study(write(tmp_path, text)).experiments[0]
    assert isinstance(exp, CircularityExperiment)
    x, y = exp._path(0.0002)
    r = np.hypot(x.pos - 0.2, y.pos - 0.3)
    assert r == pytest.approx(0.02, abs=1e-12)
    # velocities and accelerations against central differences of the positions
    dt = x.t[1] - x.t[0]
    for p in (x, y):
        assert p.vel[1:-1] == pytest.approx(np.gradient(p.pos, dt)[1:-1], abs=1e-5)
        assert p.acc[1:-1] == pytest.approx(np.gradient(p.vel, dt)[1:-1], abs=0.01)
    speed = np.hypot(x.vel, y.vel)
    assert speed.max() == pytest.approx(0.05, rel=1e-9)  # 3000 mm/min
    # clockwise: the angle falls; the arc at the feed covers more than one turn
    angle = np.unwrap(np.arctan2(y.pos - 0.3, x.pos - 0.2))
    assert angle[-1] < -2 * np.pi


def test_store_keeps_whole_files_records_refusals_and_refuses_another_study(tmp_path):
    study = load_study(write(tmp_path, GOOD))
    store = ResultStore(tmp_path / "out", study)
    job = job_of(study, store)
    # sample 1's mass is one the machine-file loader refuses: a row with its reason
    table = evaluate_chunk(job, np.array([0, 1]), np.array([[350.0], [-1.0]]))
    store.write(table)
    # what a kill during the next write leaves: the file under its temporary name
    cut_short = store.dir / ".part-00000002-00000002.parquet.tmp"
    cut_short.write_bytes(b"cut short by a kill")
    assert store.done_ids() == {0, 1}
    # the results folder stays one Parquet dataset any reader opens
    assert sorted(pq.read_table(store.dir)["sample_id"].to_pylist()) == [0, 1]
    results = store.read()
    assert results.status[0] == "ok" and results.status[1].startswith("ConfigError")
    assert "mass_kg" in results.status[1]
    assert np.isnan(results.outputs["lag_50pct_s"][1])
    assert results.outputs["lag_50pct_s"][0] > 0.0
    # the study resumed: the leftover goes, the whole files stay
    assert ResultStore(tmp_path / "out", study).done_ids() == {0, 1}
    assert not cut_short.exists()
    written = store.write(evaluate_chunk(job, np.array([2]), np.array([[360.0]])))
    assert written.name == "part-00000002-00000002.parquet"
    assert [f.name for f in store.dir.iterdir() if f.name.startswith(".")] == []
    other = load_study(write(tmp_path, GOOD.replace("samples = 4", "samples = 8"), "b.toml"))
    with pytest.raises(StudySpecError, match="another study"):
        ResultStore(tmp_path / "out", other)


@pytest.mark.parametrize("section, key", [("motor", "resistance_ohm"), ("table", "mass_kg"),
                                          ("coupling", "stiffness_nm_per_rad")])
def test_a_keys_study_range_is_the_loaders_range(section, key):
    """The study's range of a key admits exactly what the machine-file loader admits
    (reference: plant.schema.in_range and range_text on the same declaration), 0 included
    where the declaration says what 0 means ("not used" for a resistance)."""
    meta = declared_field(section, key, "test").metadata
    ref = _range(meta)
    for value in (-1.0, 0.0, 1e-9, 1e-5, 1e-3, 1.0, 1e3, 1e6, 1e9, 1e15, 1e300):
        assert ref.contains(value) == in_range(meta, value), value
    assert ref.describe("UNIT").replace(" UNIT", "") == range_text(meta)


def test_a_study_file_that_is_no_file_or_no_toml_is_refused_in_one_line(tmp_path):
    """The machine-file reader's refusals (plant.config.read_toml) for a study file: a
    directory, bytes that are not UTF-8, TOML with its line and column."""
    with pytest.raises(StudySpecError, match="is a directory, not a study file"):
        load_study(tmp_path)
    bad = tmp_path / "latin1.toml"
    bad.write_bytes(b"[study]\nname = \"K\xfchlung\"\n")
    with pytest.raises(StudySpecError, match="not UTF-8"):
        load_study(bad)
    bad.write_text("[study]\nmethod = \n")
    with pytest.raises(StudySpecError, match="line 2"):
        load_study(bad)


STUDIES = ROOT / "configs" / "studies"


@pytest.mark.parametrize("path", sorted(STUDIES.glob("*.toml")), ids=lambda p: p.stem)
def test_every_shipped_study_file_loads(path):
    study = load_study(path)
    assert study.parameters and study.outputs


def test_the_speed_tuning_reference_runs_on_the_tunings_own_machines():
    """docs/study.md: the machine file's own speed-loop settings are measured on the machines the
    tuning runs every trial on (arrow500_speed_as_written.toml's samples are
    arrow500_speed_tuning.toml's robust sample)."""
    tuning = load_study(STUDIES / "arrow500_speed_tuning.toml")
    reference = load_study(STUDIES / "arrow500_speed_as_written.toml")
    assert [r.name for r in reference.varied] == [r.name for r in tuning.varied]
    machines = robust_values(tuning)
    assert machines.shape == (4, 2)
    np.testing.assert_array_equal(study_design(reference).values, machines)
    # the same measurement (its options), keeping the outputs the tuning is judged by
    assert reference.experiments[0].opts == tuning.experiments[0].opts
    assert set(reference.outputs) <= set(tuning.outputs)


#: experiment kinds whose run is, by construction, what they measure: whole PRBS periods
#: (frequency_response), the program or the circle and their settle_s after it (program,
#: circularity), no time at all (analytic)
WINDOW_BY_CONSTRUCTION = ("frequency_response", "program", "circularity", "analytic")


def slowest_kv_per_s(study) -> float:
    """The smallest position-loop gain K_v (1/s) of the study's axes, on the nominal
    machine and with each parameter at either end of its range (a study may vary or tune
    K_v itself)."""
    corners = [{}] + [overrides_of((ref,), (value,))
                      for ref, dist in zip(study.parameters, study.spaces + study.distributions)
                      for value in dist.support()]
    return min(load_controller(axis.config).kv_m_min_per_mm * 1e3 / 60.0
               for overrides in corners for axis in study.machine.build(overrides).axes)


@pytest.mark.parametrize("path", sorted(STUDIES.glob("*.toml")), ids=lambda p: p.stem)
def test_every_shipped_study_window_holds_the_step_and_its_settling(path):
    """A step experiment's window (duration_s, from the step at t = 0) holds its settling
    twice over: the position loop, K_v with the inner loops much faster, approaches the
    target as a first-order lag exp(-K_v t), which enters the settling band b at
    ln(1/b) / K_v; by 2 ln(1/b) / K_v it lies within b^2 of the target (0.04 % for a 2 %
    band), so overshoot_pct is the response's peak, not its shortfall at the window's end
    (ci_small.toml's 0.15 s gave -0.82 % on every sample).  The slowest K_v over the
    study's parameter ranges counts.  Kinds in WINDOW_BY_CONSTRUCTION run what they
    measure; any other window needs a rule here."""
    study = load_study(path)
    for exp in study.experiments:
        if exp.kind in WINDOW_BY_CONSTRUCTION:
            continue
        assert exp.kind == "step" and exp.opts.loop == "position", (
            f"{path.name}: no window rule for kind = '{exp.kind}', loop = "
            f"'{getattr(exp.opts, 'loop', '')}': add one to this test")
        band = exp.opts.settling_band_pct / 100.0
        needed_s = 2.0 * math.log(1.0 / band) / slowest_kv_per_s(study)
        assert exp.opts.duration_s >= needed_s, (
            f"{path.name}: duration_s = {exp.opts.duration_s} s ends before the step has "
            f"settled twice over ({needed_s:.3f} s)")


def test_shipped_step_windows_end_after_the_responses_peak_and_settling():
    """The rule above on the simulated machine: for every shipped position-step study, the
    nominal machine's overshoot_pct and settling_time_s over the study's window equal
    those over a window twice as long (one run of twice the window; the lock-step is
    deterministic, so the window's run is its beginning).  At 0.15 s ci_small.toml's
    overshoot read -0.82 % against 0 % over 0.3 s."""
    steps = [(path, study, exp) for path in sorted(STUDIES.glob("*.toml"))
             for study in [load_study(path)] for exp in study.experiments
             if exp.kind == "step"]
    assert steps, "no shipped step study left to check"
    for path, study, exp in steps:
        o = exp.opts
        x0, step = o.at_mm * 1e-3, o.amplitude_mm * 1e-3
        res = position_step(axis_config(study.machine.build(), o.axis), x0, step,
                            2.0 * o.duration_s)

        def metrics(window_s, res=res, o=o, x0=x0, step=step):
            kept = (res.t_s >= 0.0) & (res.t_s <= window_s)
            return step_metrics(res.t_s[kept], res.response[kept], x0, step,
                                o.settling_band_pct)
        inside, longer = metrics(o.duration_s), metrics(2.0 * o.duration_s)
        assert inside.overshoot_pct == pytest.approx(longer.overshoot_pct, abs=1e-9), path.name
        assert inside.settling_time_s == pytest.approx(longer.settling_time_s), path.name


def drawn_figures(monkeypatch) -> list:
    """The figures hil.study.report saves from now on, after their drawing."""
    figures = []
    save = report._save

    def keep(fig, path):
        figures.append(fig)
        return save(fig, path)
    monkeypatch.setattr(report, "_save", keep)
    return figures


def test_study_figures_draw_times_in_ms_without_offset_notation(tmp_path, monkeypatch):
    """Settling times 122.000 .. 122.001 ms (a spread of 1 µs, as a tolerance study of a
    well-damped loop gives) and a step-response curve over 0 .. 0.3 s: the histogram's
    axis and the curve's time axis are in ms with plain tick labels (matplotlib's default
    would read '+1.22e2' or '+1.22e-1' beside ticks of a few digits), the values scaled,
    not only the label."""
    study = load_study(STUDIES / "ci_small.toml")
    n = 16
    outputs = {name: np.linspace(0.122, 0.122001, n) for name in study.outputs}
    outputs["overshoot_pct"] = np.linspace(-0.01, 0.0, n)
    results = Results(np.arange(n), ["ok"] * n, {}, outputs, {}, None)
    figures = drawn_figures(monkeypatch)
    report.histograms(study, results, np.ones(n, dtype=bool), tmp_path / "h.png")
    grid = np.linspace(0.0, 0.3, 50)
    info = {"name": "position from the start", "unit": "mm", "grid": grid.tolist(),
            "grid_name": "time", "grid_unit": "s", "log_grid": False}
    curves = 0.5 * (1.0 - np.exp(-grid / 0.03)) + np.linspace(0, 1e-6, n)[:, None]
    report.curve_bands(study, info, curves, tmp_path / "c.png")
    hist, curve = figures
    settling = hist.axes[study.outputs.index("settling_time_s")]
    assert settling.get_xlabel() == "settling_time_s, shown in ms"
    assert 121.9 < settling.get_xlim()[0] < settling.get_xlim()[1] < 122.1
    assert curve.axes[1].get_xlabel() == "time (ms)"
    assert curve.axes[1].get_xlim()[1] == pytest.approx(315.0)  # 300 ms and a margin
    for ax in hist.axes + curve.axes:
        for axis in (ax.xaxis, ax.yaxis):
            assert axis.get_offset_text().get_text() == "", ax.get_xlabel()
