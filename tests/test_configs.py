"""Machine files: every shipped config runs, the strict loader refuses what is wrong, and the
seed configs hold the numbers their papers print.

Broken variants are written from configs/arrow500_x.toml into ``tmp_path`` with a small TOML
writer for flat sections (round-trip checked below, so a refusal cannot come from the writer).
"""

import json
import math
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
import tomllib

from hil.validate.experiments.electrical import SeedOneDrive
from plant import ConfigError, Plant, load_machine
from plant import layout as L
from plant.assemble import mechanics_matrices, natural_frequencies, transmission_ratio
from plant.config import schema_rows
from plant.effects.cogging import cogging_torque
from plant.effects.friction import sliding_friction
from plant.sections import KINDS, SECTIONS, MotorSection

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
CONFIGS = sorted(CONFIG_DIR.glob("*.toml"))
ARROW = CONFIG_DIR / "arrow500_x.toml"


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def _dump(raw: dict) -> str:
    """TOML text of ``{section: {key: value}}`` (flat sections only)."""
    blocks = []
    for sec, values in raw.items():
        lines = [f"[{sec}]"] + [f"{k} = {_toml_value(v)}" for k, v in values.items()]
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks) + "\n"


def _variant(tmp_path: Path, edit) -> Path:
    """configs/arrow500_x.toml changed by ``edit(raw)``, written to tmp_path."""
    raw = tomllib.loads(ARROW.read_text())
    edit(raw)
    path = tmp_path / "machine.toml"
    path.write_text(_dump(raw))
    return path


def _set(sec, key, value):
    def edit(raw):
        raw.setdefault(sec, {})[key] = value
    return edit


def _delete(sec, key):
    def edit(raw):
        del raw[sec][key]
    return edit


def _rename_section(old, new):
    def edit(raw):
        raw[new] = raw.pop(old)
    return edit


@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_every_config_runs(path):
    """Each machine file loads, keeps the automatic sub-step within the rule of
    plant.assemble (omega_max*dt <= max_omega_dt, and no absurd stiffness forcing more than
    64 sub-steps per PWM period), and 300 PWM periods at 5 % of I_max end with status 0,
    finite outputs and the motor turned the way its torque pushes."""
    plant = Plant.from_file(path)
    assert plant.built.omega_max * plant.dt <= plant.config.simulation.max_omega_dt + 1e-12
    assert plant.sub_per_pwm <= 64, f"{path.name}: {plant.sub_per_pwm} sub-steps per PWM"
    plant.set_input(iq_ref_a=0.05 * plant.config.motor.current_max_a)
    trace = plant.run(300, plant.sub_per_pwm)
    assert np.all(trace["status"] == L.STATUS_OK)
    for name, values in trace.signals.items():
        assert np.all(np.isfinite(values)), f"{path.name}: {name} not finite"
    assert trace["motor_pos"][-1] > 0.0
    assert trace["time_s"][-1] == pytest.approx(300 * plant.pwm_period, rel=1e-9)


def test_writer_round_trip(tmp_path):
    """The test's TOML writer reproduces arrow500_x.toml exactly (reference: the loader on
    the original file), so the refusals below come from the edits, not from the writer."""
    path = _variant(tmp_path, lambda raw: None)
    assert load_machine(path) == replace(load_machine(ARROW), path=str(path))


REFUSALS = {
    "unknown key": (_set("motor", "resistance_mohm", 360.0),
                    ["[motor] resistance_mohm", "did you mean 'resistance_ohm'", "unit ohm"]),
    "missing key": (_delete("table", "mass_kg"), ["missing key [table] mass_kg", "unit kg"]),
    "key of another kind": (_set("motor", "pole_pitch_m", 0.03),
                            ["[motor] pole_pitch_m", "kind=linear only", "kind = 'screw'"]),
    "key of another model": (_set("current_loop", "time_constant_s", 1e-3),
                             ["[current_loop] time_constant_s", "model=first_order only"]),
    "text for a number": (_set("motor", "resistance_ohm", "0.36"),
                          ["[motor] resistance_ohm", "expected a number in ohm"]),
    "fraction for a count": (_set("screw", "segments", 7.5),
                             ["[screw] segments", "expected a whole number"]),
    "unknown choice": (_set("mechanics", "model", "flexible"),
                       ["[mechanics] model", "expected one of rigid, two_mass, screw"]),
    "negative mass": (_set("table", "mass_kg", -350.0),
                      ["[table] mass_kg", "must be 0 (none) or >= 0.001 and <= 100000 kg"]),
    "above range": (_set("motor", "pwm_frequency_hz", 2e6),
                    ["[motor] pwm_frequency_hz", "must be >= 500 and <= 100000 Hz"]),
    "breakaway below coulomb": (_set("friction", "breakaway_n", 100.0),
                                ["[friction] breakaway_n = 100 N", "coulomb_n = 120 N"]),
    "nut beyond the screw": (_set("screw", "nut_offset_m", 0.3),
                             ["[screw] nut_offset_m", "[table] travel_m", "0.81 m",
                              "[screw] length_m = 0.75 m"]),
    "unknown section": (_set("gearbox", "ratio", 3.0), ["unknown section [gearbox]"]),
    "misspelt section": (_rename_section("friction", "frictions"),
                         ["unknown section [frictions]", "did you mean 'friction'"]),
}


@pytest.mark.parametrize("edit, fragments", REFUSALS.values(), ids=REFUSALS.keys())
def test_loader_refuses(tmp_path, edit, fragments):
    """A broken variant of arrow500_x.toml raises ConfigError (also a ValueError) whose
    message names the file, the section and key, and the unit or range (reference: the
    contract in plant.config's docstring)."""
    path = _variant(tmp_path, edit)
    with pytest.raises(ConfigError) as err:
        Plant.from_file(path)
    message = str(err.value)
    assert isinstance(err.value, ValueError)
    assert message.startswith(str(path))
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in {message!r}"


def test_loader_refuses_unreadable_files(tmp_path):
    """A missing file and a file that is not TOML are refused with the path in the message."""
    missing = tmp_path / "nothing.toml"
    with pytest.raises(ConfigError, match="no such machine file"):
        load_machine(missing)
    bad = tmp_path / "bad.toml"
    bad.write_text("[motor\nmodel = 'dq'\n")
    with pytest.raises(ConfigError, match="not valid TOML") as err:
        load_machine(bad)
    assert str(bad) in str(err.value)


def test_overrides_change_the_machine_and_are_checked():
    """Overrides replace file values (reference: the linearised mass matrix and the first
    elastic mode, which must drop for a heavier table), add optional sections, leave the
    file alone and are refused like file values."""
    base = Plant.from_file(ARROW, table_pos=0.25)
    heavy = Plant.from_file(ARROW, table_pos=0.25, overrides={"table": {"mass_kg": 700.0}})
    assert heavy.config.table.mass_kg == 700.0
    assert mechanics_matrices(heavy.config, 0.25)[0][-1, -1] == 700.0
    f_base = natural_frequencies(base.config, 0.25)[1]
    f_heavy = natural_frequencies(heavy.config, 0.25)[1]
    assert f_heavy < f_base
    assert load_machine(ARROW).table.mass_kg == 350.0
    fine = Plant.from_file(ARROW, overrides={"simulation": {"substep_s": 1.0 / 8000.0 / 52}})
    assert fine.sub_per_pwm == 52
    with pytest.raises(ConfigError, match=r"\[table\] mass_kg = -1.0: must be 0 \(none\) or "
                                          r">= 0.001 and <= 100000 kg"):
        Plant.from_file(ARROW, overrides={"table": {"mass_kg": -1.0}})
    with pytest.raises(ConfigError, match="did you mean 'motor'"):
        Plant.from_file(ARROW, overrides={"motr": {"pole_pairs": 4}})


def test_every_key_is_documented():
    """Every field of every section class has a non-empty unit and doc in schema_rows() (the
    rows `hil config-keys` prints), and every `only=` condition names a real kind or motor
    model (a typo there would silently make a key apply nowhere)."""
    rows = schema_rows()
    documented = {(r["section"], r["key"]) for r in rows}
    declared = {(sec, f.name) for sec, cls in SECTIONS.items() for f in fields(cls)}
    assert documented == declared
    models = MotorSection.__dataclass_fields__["model"].metadata["choices"]
    allowed = {"kind": set(KINDS), "model": set(models)}
    for row in rows:
        where = f"[{row['section']}] {row['key']}"
        assert row["unit"].strip(), f"{where} has no unit"
        assert row["doc"].strip(), f"{where} has no doc"
        if row["only"]:
            name, values = row["only"].split("=")
            assert set(values.split("|")) <= allowed[name], f"{where}: only={row['only']}"


def test_config_keys_tables_hold_together():
    """`hil config-keys --markdown` read by a Markdown parser (markdown-it-py with GitHub's
    tables): one table, its header the seven columns, one row of seven cells for each key
    of the plain listing, in its order, the key's meaning from the schema in its last cell
    (a | inside a cell -- the choice list "screw | linear | rotary" -- is escaped: it
    neither ends the cell nor pushes the meaning out of the table); and the plain listing
    has the range column docs/machine-files.md promises."""
    import subprocess
    import sys

    from markdown_it import MarkdownIt

    def run(*args):
        return subprocess.run([sys.executable, "-m", "hil.cli", "config-keys", *args],
                              capture_output=True, text=True, check=True, timeout=120).stdout

    tokens = MarkdownIt("commonmark").enable("table").parse(run("--markdown"))
    assert [t.type for t in tokens].count("table_open") == 1
    rows, row = [], None
    for token in tokens:
        if token.type == "tr_open":
            row = []
        elif token.type == "inline" and row is not None:
            row.append(token.content)
        elif token.type == "tr_close":
            rows.append(row)
            row = None
    header, body = rows[0], rows[1:]
    assert header == ["section", "key", "unit", "range", "default", "applies to", "meaning"]
    assert {len(cells) for cells in body} == {len(header)}
    plain = run().splitlines()
    assert plain[0].split()[:5] == ["[section]", "key", "unit", "range", "default"]
    keys = [tuple(line.split()[:2]) for line in plain[1:]]
    assert len(keys) > 100
    assert [(f"[{cells[0]}]", cells[1].strip("`")) for cells in body] == keys
    docs = {(r["section"], r["key"]): r["doc"] for r in schema_rows()}
    wrong = [cells for cells in body if docs.get((cells[0], cells[1].strip("`")),
                                                  cells[6]) != cells[6]]
    assert wrong == [] and len(docs) > 100
    kind = next(cells for cells in body if cells[:2] == ["machine", "`kind`"])
    assert kind[3] == "screw | linear | rotary"
    assert any(line.startswith("[machine] kind") and "screw | linear | rotary" in line
               for line in plain)


def test_config_keys_into_a_pipe_closed_early_exits_quietly():
    """`hil config-keys | head -1`: the reader takes one line and closes the pipe while hil
    still writes (the pipe made one page long, so that the 34 kB listing cannot all sit
    in it); hil stops without a traceback on stderr, with the status a tool ended by
    SIGPIPE has (128 + 13)."""
    import fcntl
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "hil.cli", "config-keys"], bufsize=0,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    fcntl.fcntl(proc.stdout.fileno(), fcntl.F_SETPIPE_SZ, 4096)
    first = proc.stdout.readline()
    proc.stdout.close()
    stderr = proc.stderr.read()
    assert proc.wait(timeout=120) == 141, stderr.decode()
    assert first.startswith(b"[section] key")
    assert stderr == b""


def _config(name):
    return Plant.from_file(CONFIG_DIR / name)


def test_emps_mass_force_and_step_response():
    """EMPS starting model against SOURCE.md: translational mass M = 95.1089 kg and force
    gtau = 35.15065 N per unit of iq (= vir in V); a held vir = 1 V then follows the analytic
    step response v(t) = gtau/Fv (1 - exp(-t Fv/M)) of the rigid mass with viscous friction."""
    plant = _config("emps.toml")
    ratio = transmission_ratio(plant.config)
    m_total = plant.built.rot.m.sum() / ratio ** 2
    assert m_total == pytest.approx(95.1089, rel=1e-7)
    gtau = plant.config.motor.torque_constant_nm_per_a / ratio
    assert gtau == pytest.approx(35.15065188248547, rel=1e-6)
    fv = 203.5034
    plant.set_input(iq_ref_a=1.0)
    trace = plant.run(5000, plant.sub_per_pwm)
    t = trace["time_s"]
    v_ref = gtau / fv * (1.0 - np.exp(-t * fv / m_total))
    assert np.max(np.abs(trace["table_vel"] - v_ref)) < 1e-3 * v_ref[-1]


def test_ld386_friction_and_cogging_spectrum():
    """LD386 against seed 002 §5: sliding friction at the 2000 mm/min test feed is the
    18.76 N DC component, and a numpy FFT of the cogging force over one electrical
    revolution (two pole pitches) gives 1.39, 2.62 and 1.52 N at 1, 2 and 4 cycles (Fig. 9)."""
    plant = _config("ld386_linear.toml")
    p = plant.params
    assert -sliding_friction(p, 2.0 / 60.0) == pytest.approx(18.76, abs=1e-9)
    n = 256
    x = np.arange(n) * 2.0 * plant.config.motor.pole_pitch_m / n
    force = np.array([cogging_torque(p, p[L.P_POLE_PAIRS] * xi) for xi in x])
    spectrum = 2.0 * np.abs(np.fft.rfft(force)) / n
    assert spectrum[[1, 2, 4]] == pytest.approx([1.39, 2.62, 1.52], abs=1e-9)
    assert np.max(np.delete(spectrum, [1, 2, 4])) < 1e-9


def test_xy_table_presliding_and_encoder():
    """xy_table_004 against seed 004: presliding stiffness at the motor T1 = 1.14 N·m/rad
    (1140 N·mm/rad, §3.2), theta1 = x1/(lead/2pi) = 5.03e-3 rad as printed, and one encoder
    count is 38 nm at the table (§2.1)."""
    plant = _config("xy_table_004.toml")
    p, ratio = plant.params, plant.built.ratio
    assert p[L.P_PRE_K1] * ratio ** 2 == pytest.approx(1.14, rel=1e-4)
    assert p[L.P_PRE_X1] / ratio == pytest.approx(5.03e-3, rel=1e-3)
    assert 2.0 * math.pi * ratio / plant.config.sensors.encoder_counts_per_rev == pytest.approx(
        38e-9, rel=0.01)


def test_tlm_rig_karnopp_levels():
    """tlm_rig against seed 003 §4.1: F_C = 9.81 * 0.003 * 850 N and F_H = 1.5 F_C in the
    kernel's params, solved by TLM with the nut moving along the screw."""
    plant = _config("tlm_rig.toml")
    f_c = 9.81 * 0.003 * 850.0
    assert plant.params[L.P_FR_COULOMB] == pytest.approx(f_c, rel=1e-12)
    assert plant.params[L.P_FR_STATIC] == pytest.approx(1.5 * f_c, rel=1e-12)
    assert plant.params[L.P_SOLVER] == L.SOLVER_TLM
    assert plant.config.table.mass_kg == 850.0


def test_geiss_field_weakening_speed():
    """geiss_c_axis at full current from rest: below the corner speed the torque holds
    M_max = K_M I_max less the PI current loop's lag behind the ramping back-EMF (analytic:
    I_err = K_M alpha T_i / K_p at the acceleration alpha), within the cogging amplitude;
    above it the torque falls under M_max.  The corner (analytic): the speed where the
    voltage the current needs, sqrt((K omega + R I)^2 + (p L I omega)^2) with the
    omega_e L cross term, reaches U_Z -- below seed 001 eq. 8's omega_Mmax = U_Z/K -
    M_max R/K^2, which leaves the cross term out."""
    plant = _config("geiss_c_axis.toml")
    mo, fw = plant.config.motor, plant.config.field_weakening
    k, m_max = mo.torque_constant_nm_per_a, fw.max_torque_nm
    drive = SeedOneDrive.from_config(plant.config)
    i, r, uz = mo.current_max_a, mo.resistance_ohm, mo.dc_link_v
    x = drive.pole_pairs * drive.inductance * i
    a, b, c = k * k + x * x, 2.0 * k * r * i, (r * i) ** 2 - uz ** 2
    corner = (-b + math.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    omega_mmax = mo.dc_link_v / k - m_max * mo.resistance_ohm / k ** 2
    assert 0.0 < corner < omega_mmax < mo.dc_link_v / k
    plant.set_input(iq_ref_a=mo.current_max_a)
    trace = plant.run(4000, plant.sub_per_pwm)
    assert np.all(trace["status"] == L.STATUS_OK)
    w, torque = trace["motor_vel"], trace["torque"]
    cog = plant.config.cogging.amplitudes_nm[0]
    below = (trace["time_s"] > 0.02) & (w < 0.95 * corner)
    above = w > 1.1 * corner
    assert below.sum() > 100 and above.sum() > 100
    cl = plant.config.current_loop
    alpha = np.gradient(w, trace["time_s"])
    i_err = k * alpha * cl.ti_s / cl.kp_v_per_a
    expected = k * (mo.current_max_a - i_err)
    assert np.all(np.abs(torque[below] - expected[below]) < cog + 0.005 * m_max)
    assert np.all(torque[above] < m_max - cog)
