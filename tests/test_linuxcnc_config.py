"""What ``hil linuxcnc`` rests on that needs no LinuxCNC: the shipped LinuxCNC configuration
agrees with the machine it drives, the drive's 60C2h key, the session's files and the
verdict's rules (the sessions themselves: tests/test_linuxcnc.py)."""

import math
import re

import pytest

from hil.controller.config import axis_limits, load_controller
from hil.drive.config import load_drive
from hil.linuxcnc.command import index_above_switch
from hil.linuxcnc.session import (
    LinuxCNCConfigError,
    Processes,
    _ini,
    linuxcnc_ferror,
    read_config,
    read_samples,
    sampler_hal,
    servo_timing,
    set_key,
)
from hil.linuxcnc.verdict import Homing, judge
from hil.replay import ReplayError
from plant.config import load_machine
from plant.errors import ConfigError
from plant.machines import load_machine_set
from tests.conftest import CONFIGS, ROOT

INI = CONFIGS / "linuxcnc" / "arrow500_xyz.ini"


def test_the_ini_fits_the_machine_it_drives():
    """One joint per axis; SCALE is the encoder's increments per mm; HOME_OFFSET is where
    the index above the home switch lies; no speed or acceleration beyond the machine's
    [controller] limits; the soft limits inside the travel; the drives interpolate over
    the servo period."""
    cfg = read_config(INI)
    ini = _ini(INI)
    machine = load_machine_set(cfg.machine)
    assert cfg.joints == len(machine.axes) == 3 and ini["KINS"]["KINEMATICS"].endswith("XYZ")
    servo_s = int(ini["EMCMOT"]["SERVO_PERIOD"]) * 1e-9
    for j, axis_cfg in enumerate(machine.configs):
        joint = ini[f"JOINT_{j}"]
        counts_per_mm = (axis_cfg.sensors.encoder_counts_per_rev
                         / (axis_cfg.mechanics.lead_m * 1e3))
        assert float(joint["SCALE"]) == pytest.approx(counts_per_mm, rel=1e-12)
        assert float(joint["HOME_OFFSET"]) == pytest.approx(
            index_above_switch(axis_cfg) / counts_per_mm, abs=1e-9)
        limits = axis_limits(axis_cfg, load_controller(axis_cfg))
        assert float(joint["MAX_VELOCITY"]) <= limits.velocity * 1e3 + 1e-9
        assert float(joint["MAX_ACCELERATION"]) <= limits.acceleration * 1e3 + 1e-9
        assert 0.0 < float(joint["MIN_LIMIT"]) < float(joint["MAX_LIMIT"]) \
            < axis_cfg.table.travel_m * 1e3
        assert float(joint["MIN_FERROR"]) < float(joint["FERROR"])
        assert float(joint["HOME_SEARCH_VEL"]) < 0.0 < float(joint["HOME_LATCH_VEL"])
        drive = load_drive(axis_cfg, load_controller(axis_cfg))
        assert drive.interpolation_period_s == pytest.approx(servo_s)
        assert (drive.interpolation_value, drive.interpolation_index) == (1, -3)


def test_the_interpolation_period_is_checked(tmp_path):
    """60C2h from the machine file: 0 by default; a time that is no whole number of PWM
    periods is refused naming the key."""
    arrow = CONFIGS / "arrow500_x.toml"
    assert load_drive(load_machine(arrow), None).interpolation_value == 0
    bad = tmp_path / "bad.toml"
    bad.write_text(arrow.read_text() + "\n[drive]\ninterpolation_time_period_s = 0.0001\n")
    with pytest.raises(ConfigError, match=r"\[drive\] interpolation_time_period_s = 0.0001 s "
                                          r"must be a whole number of PWM periods"):
        load_drive(load_machine(bad), None)


def test_a_bad_ini_is_refused_naming_the_key(tmp_path):
    manifest = CONFIGS / "machines" / "arrow500_xyz_2khz.toml"
    text = INI.read_text().replace("MACHINE = ../machines/arrow500_xyz_2khz.toml",
                                   f"MACHINE = {manifest}")
    bad = tmp_path / "bad.ini"
    for old, new, match in [(f"MACHINE = {manifest}", "", r"\[FEEDDRIVE\] MACHINE is missing"),
                            (f"MACHINE = {manifest}", "MACHINE = none.toml",
                             "MACHINE = .*none.toml: no such file"),
                            ("SCALE = 419430.4", "SCALE = 0", "SCALE = .*finite and not 0"),
                            ("JOINTS = 3", "JOINTS = three", "is not a number"),
                            ("SERVO_PERIOD = 1000000", "SERVO_PERIOD = 1e6",
                             r"\[EMCMOT\] SERVO_PERIOD = 1e6: expected a whole number of ns")]:
        bad.write_text(text.replace(old, new, 1))
        with pytest.raises(LinuxCNCConfigError, match=match):
            read_config(bad)
    bad.write_text(text)
    assert read_config(bad).machine == manifest


def test_set_key_replaces_in_its_section_only_or_adds():
    text = "[A]\nX = 1\n[B]\nX = 2\nY = 3\n"
    assert set_key(text, "B", "X", "9") == "[A]\nX = 1\n[B]\nX = 9\nY = 3\n"
    assert set_key(text, "A", "Z", "5") == "[A]\nZ = 5\nX = 1\n[B]\nX = 2\nY = 3\n"
    assert set_key(text, "C", "K", "v").endswith("[C]\nK = v\n")


def test_the_sampler_file_is_read_back_per_joint(tmp_path):
    """halsampler's lines (f-error and its limit per joint, the machine's enable, the
    servo period as it ran, the stale periods and frames received): the largest error
    while enabled and in the period that disabled it, with its limit; a line cut short and
    samples while disabled are left out."""
    hal = sampler_hal(3)
    assert "cfg=ffffffbuuu" in hal and "feeddrive.period-ns => sampler.0.pin.7" in hal
    path = tmp_path / "ferror.txt"
    path.write_text("9.0 9.0 0.5 0.5 0 0 0 0\n"      # disabled: not judged
                    "0.1 -0.2 0.5 0.5 1 1000000 0 2\n"
                    "-0.3 0.1 0.6 0.5 1 1000000 0 4\n"
                    "0.7 0.0 0.6 0.5 0 1000000 0 6\n"      # the period LinuxCNC tripped in
                    "5.0 5.0 0.5 0.5 0 1000000 0 8\n"
                    "1.0 1.0 0.5\n")                       # cut short
    assert linuxcnc_ferror(read_samples(path, 2), 2) == [(0.7, 0.6), (0.2, 0.5)]
    assert linuxcnc_ferror(read_samples(tmp_path / "none.txt", 2), 2) == []


def test_the_servo_threads_timing_is_judged_while_the_machine_is_on(tmp_path):
    """The periods as the component measured them while the machine was on, against a
    hand-made file of one joint: a wake-up 300 µs late makes one period 1300 µs and the
    next 700 µs (jitter 300 µs both); the stale periods and the frames received are
    counted only while on; per second over the periods' own sum."""
    path = tmp_path / "ferror.txt"
    rows = ["0 1 0 0 0 5"]                                   # off, first read: not judged
    rows += [f"0 1 1 1000000 0 {7 + 2 * k}" for k in range(6)]
    rows += ["0 1 1 1300000 0 20", "0 1 1 700000 1 21", "0 1 1 1000000 1 23",
             "0 1 0 5000000 9 99"]                           # off again: not judged
    path.write_text("\n".join(rows) + "\n")
    t = servo_timing(read_samples(path, 1), 1, 1_000_000)
    assert (t.nominal_us, t.periods) == (1000.0, 9)
    assert t.span_s == pytest.approx(9e-3)
    assert (t.period_us.p50, t.period_us.max) == (1000.0, 1300.0)
    assert (t.jitter_us.p50, t.jitter_us.max) == (0.0, 300.0)
    assert (t.stale_periods, t.feedback_frames) == (1, 18)
    assert t.setpoints_per_s == pytest.approx(1000.0)
    assert t.feedback_per_s == pytest.approx(2000.0)
    assert "jitter p50 0.0, p99.9 300.0, max 300.0 µs; 1 periods" in t.line()
    assert servo_timing(read_samples(tmp_path / "none.txt", 1), 1, 1_000_000) is None


def _result(**changes) -> dict:
    result = {"phases": {"ready": 0.1, "reset": 0.1, "on": 0.0, "homed": 2.0, "started": 0.0,
                         "program": 4.0}, "errors": [], "joints": [], "completed": True,
              "failed": None}
    result.update(changes)
    return result


REPORT = {"exit_status": 0, "stopped": "SIGTERM", "watchdog": {"events": []},
          "faults": {"X": {"events": []}}}
RAN = Processes(0, 0, "udp://127.0.0.1:5005?wire=fixed", None)
HOMED = [Homing("X", True, 4194304.0, 4194304.0)]


class _Replay:
    matches = True


@pytest.mark.parametrize("processes, result, homing, report, reasons", [
    (RAN, _result(), HOMED, REPORT, []),
    (RAN, _result(errors=[{"kind": 11, "text": "joint 0 following error", "t_s": 3.0}],
                  failed="program: LinuxCNC reported an error", completed=False),
     HOMED, REPORT, ["LinuxCNC: joint 0 following error"]),
    (RAN, _result(), [Homing("X", True, 4194306.0, 4194304.0)], REPORT,
     ["joint X homed at increment 4194306.0, not at the index mark above the home switch "
      "(4194304)"]),
    (RAN, _result(), [Homing("X", False, None, 4194304.0)], REPORT, ["joint X was not homed"]),
    (RAN, _result(completed=False), HOMED, REPORT, ["the program did not complete"]),
    (RAN, _result(failed="homed: not done in 60 s", phases={"on": 0.0}), [], REPORT,
     ["homed: not done in 60 s"]),
    (RAN, None, [], REPORT, ["LinuxCNC's display wrote no result (LinuxCNC exited with 0; "
                             "see linuxcnc.log)"]),
    (RAN, _result(), HOMED, {**REPORT, "faults": {"X": {"events": [
        {"kind": "fault", "code": 0x8611, "cycle": 7, "text": "following error"}]}}},
     ["axis X: drive fault 8611h at drive cycle 7 (following error)"]),
    (Processes(2, None, None, "the emulator exited with 2 before it was ready"), None, [],
     None, ["the emulator exited with 2 before it was ready"]),
])
def test_the_verdict_names_each_reason(processes, result, homing, report, reasons):
    v = judge(processes, result, homing, True, report, _Replay())
    assert v.reasons == reasons
    assert v.line() == ("PASS" if not reasons else "FAIL: " + "; ".join(reasons))


def test_a_replay_that_could_not_be_made_fails_the_verdict():
    v = judge(RAN, _result(), HOMED, True, REPORT, str(ReplayError("no recording")))
    assert v.reasons == ["the run could not be replayed: no recording"]


def test_the_home_is_the_index_above_the_switch_not_the_switch():
    """The index mark LinuxCNC must home to is a whole motor revolution (10 mm, one mark)
    in, above the switch's edge at half a revolution."""
    cfg = load_machine(CONFIGS / "arrow500_x.toml")
    mark = index_above_switch(cfg)
    assert mark == cfg.sensors.encoder_counts_per_rev and math.isfinite(mark)
    assert re.search(r"HOME_OFFSET = 10.0", INI.read_text())
    assert (ROOT / "programs" / "linuxcnc_square.ngc").exists()
