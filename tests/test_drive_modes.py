"""The emulated drive's own loops in CiA 402 CSV and CSP modes (what a CANopen master or
an external controller uses), with the Arrow 500 X machine data."""

import math

import pytest

from hil.cia402 import EnableSequencer
from hil.controller.config import kv_si, load_controller
from hil.drive import EmulatedDrive
from io_adapters.messages import MODE_CSP, MODE_CSV, Feedback, Setpoint
from plant import Plant
from plant import layout as L
from plant.config import load_machine
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"


def enabled_drive(cfg, x0=0.25):
    """A drive brought to OPERATION ENABLED by the CiA 402 enable sequence."""
    plant = Plant(cfg, table_pos=x0)
    drive = EmulatedDrive(plant)
    sp, fb = Setpoint(), Feedback()
    seq = EnableSequencer(timeout_cycles=50)
    seq.enable()
    for _ in range(50):
        sp.controlword = seq.next_controlword(fb.statusword)
        drive.cycle(sp, fb)
        if seq.done:
            return plant, drive, sp, fb, seq
    raise AssertionError(f"not enabled: {seq.reason}")


def run(drive, sp, fb, seq, n, update):
    for k in range(n):
        sp.controlword = seq.next_controlword(fb.statusword)
        update(k, sp)
        drive.cycle(sp, fb)


def test_csv_holds_the_commanded_speed():
    """CSV: the drive's speed loop (PI, no steady-state error) makes the measured speed
    equal the target velocity (increments/s) on average."""
    cfg = load_machine(ARROW)
    plant, drive, sp, fb, seq = enabled_drive(cfg)
    target = 50.0 / drive.rad_per_count  # 50 rad/s in increments/s
    sp.mode = MODE_CSV

    def update(k, sp):
        sp.target_velocity_counts_s = target

    run(drive, sp, fb, seq, 4000, update)
    speeds = []
    run(drive, sp, fb, seq, 800, lambda k, s: speeds.append(fb.velocity_counts_s))
    assert sum(speeds) / len(speeds) == pytest.approx(target, rel=2e-3)


def test_csp_ramp_following_error_is_v_over_kv():
    """CSP without a velocity offset: the drive's P position loop lags a ramp by
    v / K_v (K_v of the machine data, analytic), measured in motor increments."""
    cfg = load_machine(ARROW, overrides={"controller": {"speed_ff": False}})
    plant, drive, sp, fb, seq = enabled_drive(cfg)
    w = 20.0  # rad/s
    start = fb.encoder_counts
    sp.mode = MODE_CSP
    per_tick = w * plant.pwm_period / drive.rad_per_count

    def update(k, sp):
        sp.target_position_counts = start + per_tick * k

    n = 8000
    run(drive, sp, fb, seq, n, update)
    lag_rad = (start + per_tick * (n - 1) - fb.encoder_counts) * drive.rad_per_count
    expected = w / kv_si(load_controller(cfg))
    assert lag_rad == pytest.approx(expected, rel=0.02)


def test_csp_position_step_settles_on_target():
    """CSP step: the axis ends on the target position within a few increments."""
    plant, drive, sp, fb, seq = enabled_drive(load_machine(ARROW))
    target = fb.encoder_counts + 0.5e-3 / plant.built.ratio / drive.rad_per_count
    sp.mode = MODE_CSP
    sp.target_position_counts = target
    run(drive, sp, fb, seq, 4000, lambda k, s: None)
    assert abs(fb.encoder_counts - target) < 5
    assert math.isfinite(fb.velocity_counts_s)


def test_without_machine_data_csp_gives_no_torque(tmp_path):
    """A machine file without [controller] has no drive loops: CSP and CSV leave the
    current setpoint at 0 A instead of guessing gains."""
    text = ARROW.read_text().split("[controller]")[0]
    path = tmp_path / "no_controller.toml"
    path.write_text(text)
    plant, drive, sp, fb, seq = enabled_drive(load_machine(path))
    assert drive.loops is None
    sp.mode = MODE_CSP
    sp.target_position_counts = fb.encoder_counts + 1e6
    run(drive, sp, fb, seq, 200, lambda k, s: None)
    assert plant.inp[L.I_IQ_REF] == 0.0
