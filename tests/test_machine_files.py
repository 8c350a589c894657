"""Machine files are refused, never hung on (issue 11, item 6).

* every loader failure is one line naming the file and the key: encoding, a directory, a
  FIFO (never read, so nothing blocks), TOML syntax with line and column, unknown and
  missing keys -- for machine files and manifests alike;
* every number key has a physical range (checked against its own declaration, for every
  key of every shipped machine file), and the absurd values of the issue are refused with
  it;
* a stiffness that needs more sub-steps than the plant takes, or than a real-time tick
  allows, is refused with the largest value that fits (reference: the two-inertia
  formula for the coupling's mode, and the plant built at that value);
* ``hil run`` refuses each of those files before ``ready:`` in bounded time, and a
  SIGTERM or SIGINT during a cold compile or the warm-up ends it at once.
"""

import os
import signal
import subprocess
import threading
from dataclasses import fields
from pathlib import Path

import pytest

from hil.controller.config import ControllerSection, load_controller
from hil.runtime import emulator as emulator_module
from hil.runtime.common import StopFlag
from hil.runtime.emulator import Emulator
from hil.runtime.emulator_config import RuntimeConfig
from plant import ConfigError, Plant, load_machine
from plant.assemble import build_chains, check_substep_count
from plant.config import _applies
from plant.machines import load_machine_set
from plant.schema import range_text
from plant.sections import SECTIONS
from plant.substeps import MAX_SUB_PER_PWM, realtime_limit, realtime_limit_text
from tests.conftest import CONFIGS
from tests.runtime_helpers import ENV, EXIT_S, READY_S, python_module

ARROW = CONFIGS / "arrow500_x.toml"
ARROW_TEXT = ARROW.read_text()
#: line numbers in ARROW_TEXT: [motor], and the machine's name
MOTOR_LINE = ARROW_TEXT.splitlines().index("[motor]") + 1
NAME_LINE = next(i for i, ln in enumerate(ARROW_TEXT.splitlines(), 1) if ln.startswith("name ="))


def _with_line(text: str, section: str, line: str) -> str:
    """``text`` with ``line`` added at the top of ``[section]``."""
    return text.replace(f"[{section}]\n", f"[{section}]\n{line}\n", 1)


def _one_line(err: pytest.ExceptionInfo, path: Path) -> str:
    message = str(err.value)
    assert "\n" not in message and message.startswith(str(path)), message
    return message


# --- loader failures ----------------------------------------------------------------------

def _non_utf8(path: Path) -> Path:
    path.write_bytes(ARROW_TEXT.encode().replace(b'name = "Cincinnati', b'name = "Cin\xe7innati'))
    return path


def _directory(path: Path) -> Path:
    path.mkdir()
    return path


def _fifo(path: Path) -> Path:
    os.mkfifo(path)  # nobody writes it: reading it would block forever
    return path


def _text(text: str):
    def make(path: Path) -> Path:
        path.write_text(text)
        return path
    return make


BAD_FILES = {
    "not UTF-8": (_non_utf8, ["not UTF-8 text", f"byte 0xe7 at line {NAME_LINE}"]),
    "a directory": (_directory, ["is a directory, not a machine file"]),
    "a FIFO": (_fifo, ["not a regular file"]),
    "TOML syntax": (_text(ARROW_TEXT.replace("[motor]\n", "[motor]\nmodel = = 'dq'\n", 1)),
                    ["not valid TOML", f"line {MOTOR_LINE + 1}, column"]),
    "unknown key": (_text(_with_line(ARROW_TEXT, "table", "mass_kgs = 3.0")),
                    ["unknown key [table] mass_kgs", "did you mean 'mass_kg'", "unit kg"]),
    "missing key": (_text(ARROW_TEXT.replace("current_max_a", "#", 1)),
                    ["missing key [motor] current_max_a", "unit A"]),
    "missing file": (lambda path: path, ["no such machine file"]),
}


@pytest.mark.parametrize("make, fragments", BAD_FILES.values(), ids=BAD_FILES.keys())
@pytest.mark.parametrize("loader", [load_machine, load_machine_set],
                         ids=["machine file", "machine or manifest"])
def test_a_bad_file_is_one_line_naming_file_and_key(tmp_path, make, fragments, loader):
    """Each class of broken file: a ConfigError of one line starting with the path and
    saying what is wrong (the TOML one with line and column) -- from both loaders."""
    path = make(tmp_path / "machine.toml")
    with pytest.raises(ConfigError) as err:
        loader(path)
    message = _one_line(err, path)
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in {message!r}"


def test_a_bad_axis_file_in_a_manifest_names_the_manifest_and_the_axis(tmp_path):
    """A manifest whose axis file is not UTF-8: one line naming the manifest, the axis and
    the axis file."""
    axis = _non_utf8(tmp_path / "x.toml")
    manifest = tmp_path / "m.toml"
    manifest.write_text('[machine]\nname = "m"\nsource = "test"\n\n[[axis]]\nname = "X"\n'
                        'file = "x.toml"\n')
    with pytest.raises(ConfigError) as err:
        load_machine_set(manifest)
    message = _one_line(err, manifest)
    assert "axis X" in message and str(axis) in message and "not UTF-8" in message


# --- ranges ---------------------------------------------------------------------------------

ABSURD = {
    "PWM at 1 MHz": ("motor", "pwm_frequency_hz = 1.0e6", "Hz"),
    "a table of 1e300 kg": ("table", "mass_kg = 1.0e300", "kg"),
    "a current limit of 1e300 A": ("motor", "current_max_a = 1.0e300", "A"),
    "a DC link of 1e300 V": ("motor", "dc_link_v = 1.0e300", "V"),
    "a resistance of 1e-300 ohm": ("motor", "resistance_ohm = 1.0e-300", "ohm"),
    "one count per revolution": ("sensors", "encoder_counts_per_rev = 1", "1"),
}


@pytest.mark.parametrize("section, line, unit", ABSURD.values(), ids=ABSURD.keys())
def test_the_absurd_values_of_the_issue_are_refused_with_their_range(tmp_path, section, line,
                                                                     unit):
    """Each value the issue found accepted: refused naming the key, the value and its range
    as declared, with the unit."""
    key = line.split(" = ")[0]
    text = "\n".join(ln for ln in ARROW_TEXT.splitlines() if not ln.startswith(f"{key} ="))
    path = tmp_path / "machine.toml"
    path.write_text(_with_line(text + "\n", section, line))
    with pytest.raises(ConfigError) as err:
        load_machine(path)
    meta = {f.name: f for f in fields(SECTIONS[section])}[key].metadata
    assert f"[{section}] {key} = " in _one_line(err, path)
    assert str(err.value).endswith(f"must be {range_text(meta)} {unit}")


def _applicable_keys():
    """(machine file, section, field) for every number key of every section that applies
    to a shipped machine file, each key once."""
    seen, out = set(), []
    for path in sorted(CONFIGS.glob("*.toml")):
        cfg = load_machine(path)
        context = {"kind": cfg.machine.kind, "model": cfg.motor.model}
        for section, cls in SECTIONS.items():
            if getattr(cfg, section) is None:
                continue
            for f in fields(cls):
                only = f.metadata["only"]
                if (section, f.name) in seen or (only and not _applies(only, context)):
                    continue
                if f.type in ("float", "int", "tuple", float, int, tuple):
                    seen.add((section, f.name))
                    out.append(pytest.param(path, section, f, id=f"{section}.{f.name}"))
    return out


@pytest.mark.parametrize("path, section, field", _applicable_keys())
def test_every_number_key_has_a_range_and_a_value_outside_it_is_refused(path, section, field):
    """Every number key declares an upper bound and a lower one (reference: the
    declaration); ten times the upper bound is refused, and so is a tenth of the lower
    bound where 0 is a special value -- each naming the key and the range."""
    meta = field.metadata
    assert meta["le"] is not None and (meta["ge"] is not None or meta["gt"] is not None), (
        f"[{section}] {field.name} has no range")
    is_int = field.type in ("int", int)
    above = meta["le"] * 10 + 1 if is_int else (abs(meta["le"]) * 10 or 1.0)
    outside = [above]
    low = meta["ge"] if meta["ge"] is not None else meta["gt"]
    if meta["zero"] and low > 0 and not is_int:
        outside.append(low / 10)
    for value in outside:
        given = [value] if field.type in ("tuple", tuple) else value
        with pytest.raises(ConfigError) as err:
            load_machine(path, {section: {field.name: given}})
        message = _one_line(err, path)
        assert f"[{section}] {field.name} = " in message
        assert f"must be {range_text(meta)} {meta['unit']}" in message


def test_every_controller_key_has_a_range_and_a_gain_beyond_it_is_refused():
    """The [controller] section's numbers too (its loader is the same): each declares
    both bounds, and a K_v of 1e6 (m/min)/mm is refused with its range."""
    for f in fields(ControllerSection):
        if f.type in ("float", "int", float, int):
            meta = f.metadata
            assert meta["le"] is not None and (meta["ge"], meta["gt"]) != (None, None), f.name
    with pytest.raises(ConfigError) as err:
        load_controller(load_machine(ARROW, {"controller": {"kv_m_min_per_mm": 1e6}}))
    assert str(err.value).endswith("[controller] kv_m_min_per_mm = 1000000.0: must be > 0 and "
                                   "<= 100 (m/min)/mm")


def test_every_shipped_machine_file_is_within_the_ranges():
    """The ranges are physical: every shipped machine file and manifest loads, [controller]
    sections included."""
    for path in [*CONFIGS.glob("*.toml"), *(CONFIGS / "machines").glob("*.toml")]:
        for cfg in load_machine_set(path).configs:
            if cfg.section("controller"):
                load_controller(cfg)


# --- sub-steps ------------------------------------------------------------------------------

#: the Arrow 500 X with a coupling of 1e9 N*m/rad on a rotor of 5e-6 kg*m^2: its coupling
#: mode needs about 1400 sub-steps, more than MAX_SUB_PER_PWM
STIFF = {"coupling": {"stiffness_nm_per_rad": 1e9}, "motor": {"inertia_kgm2": 5e-6}}


def _largest(message: str) -> float:
    return float(message.split("at most ")[-1].split()[0])


def test_a_stiffness_beyond_the_plants_substeps_is_refused_with_the_largest_that_fits():
    """More than MAX_SUB_PER_PWM sub-steps: refused naming the coupling stiffness and the
    largest that fits.  Reference: the two-inertia mode sqrt(k (1/J1 + 1/J2)) of the
    motor side and the screw's first node, which the coupling's mode is at this
    stiffness: k = (n max_omega_dt / T)^2 / (1/J1 + 1/J2), within 0.5 %; that value
    builds within the bound, 1 % more does not."""
    with pytest.raises(ConfigError) as err:
        Plant(load_machine(ARROW, STIFF))
    message = _one_line(err, ARROW)
    assert f"the plant takes at most {MAX_SUB_PER_PWM}" in message
    assert "[coupling] stiffness_nm_per_rad = 1e+09 N*m/rad: at most" in message
    cfg = load_machine(ARROW, STIFF)
    rot, _ = build_chains(cfg)
    omega = MAX_SUB_PER_PWM * cfg.simulation.max_omega_dt * cfg.motor.pwm_frequency_hz
    two_inertia = omega ** 2 / (1.0 / rot.m[0] + 1.0 / rot.m[1])
    k_max = _largest(message)
    assert k_max == pytest.approx(two_inertia, rel=5e-3)
    fits = {**STIFF, "coupling": {"stiffness_nm_per_rad": k_max}}
    assert Plant(load_machine(ARROW, fits)).sub_per_pwm <= MAX_SUB_PER_PWM
    with pytest.raises(ConfigError, match="too stiff"):
        Plant(load_machine(ARROW, {**STIFF, "coupling": {"stiffness_nm_per_rad": 1.01 * k_max}}))


def test_a_tiny_explicit_substep_is_refused_with_the_least_that_fits():
    """An explicit sub-step of 10 ns (12500 per PWM period) names the shortest allowed."""
    with pytest.raises(ConfigError) as err:
        Plant(load_machine(ARROW, {"simulation": {"substep_s": 1e-8}}))
    assert "substep_s must be >= 1.25e-07 s" in _one_line(err, ARROW)


def test_the_real_time_tick_bound_names_the_largest_stiffness_that_fits():
    """A coupling of 1e7 N*m/rad needs 70 sub-steps, more than a tick at 8 kHz allows
    (62): the value named builds with at most that many."""
    cfg = load_machine(ARROW, {"coupling": {"stiffness_nm_per_rad": 1e7}})
    n_max = realtime_limit(cfg.motor.pwm_frequency_hz)
    assert n_max == 62 and Plant(cfg).sub_per_pwm > n_max
    with pytest.raises(ConfigError) as err:
        check_substep_count(cfg, n_max, realtime_limit_text(cfg))
    assert "a real-time tick allows 62 at 8000 Hz PWM" in _one_line(err, ARROW)
    k_max = _largest(str(err.value))
    fits = load_machine(ARROW, {"coupling": {"stiffness_nm_per_rad": k_max}})
    assert Plant(fits).sub_per_pwm <= n_max
    assert check_substep_count(load_machine(ARROW), n_max, "") == 26


# --- hil run: refused in bounded time, stopped at once while starting ---------------------

def _variant(tmp_path: Path, replace: dict[str, str]) -> Path:
    text = ARROW_TEXT
    for old, new in replace.items():
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "machine.toml"
    path.write_text(text)
    return path


HANGING = {
    "a coupling of 1e30": {"stiffness_nm_per_rad = 3300.0": "stiffness_nm_per_rad = 1.0e30"},
    "beyond the plant's sub-steps": {"stiffness_nm_per_rad = 3300.0":
                                     "stiffness_nm_per_rad = 1.0e9",
                                     "inertia_kgm2 = 0.00150": "inertia_kgm2 = 1.0e-5"},
    "beyond the tick's sub-steps": {"stiffness_nm_per_rad = 3300.0":
                                    "stiffness_nm_per_rad = 1.0e7"},
    "a sub-step of 10 ns": {"[sensors]": "[simulation]\nsubstep_s = 1.0e-8\n\n[sensors]"},
}


@pytest.mark.parametrize("replace", HANGING.values(), ids=HANGING.keys())
def test_hil_run_refuses_the_files_that_hung_it_before_ready(tmp_path, replace):
    """The machine files that hung the daemon (an unbounded number of sub-steps): exit 2
    with one line naming the file, before ``ready:`` and before any run folder is made."""
    path = _variant(tmp_path, replace)
    done = subprocess.run(python_module("hil.runtime.emulator", path, "--adapter",
                                        "udp://127.0.0.1:0", "--record", tmp_path / "run"),
                          env=ENV, capture_output=True, text=True, timeout=READY_S)
    assert done.returncode == 2, done.stderr
    assert "ready:" not in done.stdout and not (tmp_path / "run").exists()
    refusal = [ln for ln in done.stderr.splitlines() if str(path) in ln]
    assert len(refusal) == 1 and ("must be" in refusal[0] or "at most" in refusal[0]), (
        done.stderr)


def _wait_for_line(proc: subprocess.Popen, fragment: str) -> None:
    """Read the child's stderr until a line holds ``fragment`` (bounded by its exit)."""
    for line in proc.stderr:
        if fragment in line:
            return
    raise AssertionError(f"the child ended (status {proc.wait()}) before {fragment!r}")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_during_a_cold_compile_ends_hil_run_at_once(tmp_path, signum):
    """With an empty numba cache (a compile of about 10 s), a signal a second into it ends
    the process by the signal's default action: it neither finishes compiling nor prints
    ``ready:`` -- a Python handler would have waited for numba to return."""
    env = {**ENV, "NUMBA_CACHE_DIR": str(tmp_path / "cold-cache")}
    proc = subprocess.Popen(python_module("hil.runtime.emulator", ARROW, "--adapter",
                                          "udp://127.0.0.1:0", "--record", tmp_path / "run"),
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_line(proc, "loading the plant's compiled kernels")
        threading.Event().wait(1.0)
        proc.send_signal(signum)
        assert proc.wait(timeout=EXIT_S) == -signum
        assert "ready:" not in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.stdout.close()
        proc.stderr.close()


def test_a_stop_request_ends_the_warm_up_at_the_next_cycle(tmp_path, monkeypatch):
    """A warm-up made 10^8 cycles long (hours) ends at the next cycle once the stop flag is
    set from another thread, as a signal handler would: the emulator is built having run
    far fewer cycles."""
    monkeypatch.setattr(emulator_module, "WARMUP_CYCLES", 10 ** 8)
    stop = StopFlag()
    timer = threading.Timer(1.0, stop.request)
    rc = RuntimeConfig(machine_file=ARROW, adapter_url="udp://127.0.0.1:0",
                       run_dir=tmp_path / "run", duration_s=1.0, realtime=False)
    timer.start()
    try:
        emu = Emulator(rc, load_machine(ARROW), stop)
    finally:
        timer.cancel()
    assert stop.requested and 0 < emu.warmup_cycles < 10 ** 8
    assert not (tmp_path / "run").exists()
