"""``hil sim`` and ``hil measure`` through the command line's entry point (hil.cli.main).

Independent references: the part program's programmed end position (parsed here) and
the exact-stop fine window of a SINUMERIK axis (MD36010, 0.01 mm) for where the axis ends;
the controller's position cycle from the machine file for the trace's sample time; the
servo-trace format (../shared/docs/trace-format.md) for the file; and, for the current
loop's bandwidth, the exact discrete q-axis loop of the plant's drive built here from the
machine file (ZOH of R-L, PI on the current sampled at the PWM event, the voltage applied
one period late, back-EMF cancelled by the drive's precontrol).
"""

import json
import math
from fractions import Fraction

import numpy as np
import pytest

from hil.cli import main
from hil.controller.config import load_controller
from hil.controller.program import read_program
from hil.measure.frequency_response import read_csv
from hil.trace_file import IDENTIFICATION, read_trace, write_trace
from plant.config import load_machine
from tests.conftest import CONFIGS, ROOT
from tests.runtime_helpers import machine_variant

ARROW = CONFIGS / "arrow500_x.toml"
PROGRAM = ROOT / "programs" / "seed000_moves.nc"
#: SINUMERIK exact stop fine (MD36010 default), mm
EXACT_STOP_FINE_MM = 0.01


@pytest.fixture(scope="module")
def sim_out(tmp_path_factory):
    """`hil sim` of the seed-000 program on the Arrow 500 X: (exit status, output folder)."""
    out = tmp_path_factory.mktemp("sim")
    status = main(["sim", str(ARROW), "--program", str(PROGRAM), "--out", str(out)])
    return status, out


def test_sim_writes_trace_and_plot(sim_out):
    status, out = sim_out
    assert status == 0
    assert (out / "trace.csv").stat().st_size > 0
    assert (out / "sim.png").stat().st_size > 0


def test_sim_trace_is_an_identification_trace(sim_out):
    """The trace reads with the identification columns, samples at the position cycle
    (16 PWM periods of 125 us = 2 ms) and ends where the program does, within the exact-stop
    window."""
    _, out = sim_out
    trace = read_trace(out / "trace.csv", require=IDENTIFICATION)
    cfg = load_machine(ARROW)
    cycle = load_controller(cfg).position_cycle_ratio / cfg.motor.pwm_frequency_hz
    assert trace.sample_time_s == pytest.approx(cycle, rel=1e-9)
    end_mm = read_program(PROGRAM).end * 1e3
    assert end_mm == pytest.approx(480.0)
    assert trace.column("pos_mm")[-1] == pytest.approx(end_mm, abs=EXACT_STOP_FINE_MM)
    assert trace.column("pos_set_mm")[-1] == pytest.approx(end_mm, abs=1e-9)
    assert trace.metadata["program"] == str(PROGRAM)
    # vel_set_mm_min is the speed feed-forward (trace-format.md), and the header says so:
    # the setpoint's own rate, within its central difference's error at the 2 ms samples
    # (6.4 mm/min here); the whole speed command adds K_v times the following error to it
    # (up to 107 mm/min on this program)
    assert trace.metadata["vel_set_column"] == "feedforward"
    t, x, v = trace.column("t_s"), trace.column("pos_set_mm"), trace.column("vel_set_mm_min")
    rate = np.gradient(x, t) * 60.0
    assert np.abs(v - rate)[1:-1].max() < 20.0


def test_sim_trace_ends_with_the_currents_means_over_the_position_cycle(sim_out):
    """trace.csv keeps the servo-trace columns in their order and adds iq_set_mean_a and
    iq_mean_a last, with a comment that says what they are.  Reference: the first
    acceleration (0.02 .. 0.1 s), where the rows, one per 2 ms position cycle, all see the
    same phase of the currents' 500 Hz ripple: there iq_set_a and iq_a differ by more than
    1 A on average (3.96 against 2.12 A), while the setpoint and the measured current,
    averaged over the cycle, agree within 0.05 A, as a current loop with a bandwidth far
    above 500 Hz makes them."""
    _, out = sim_out
    trace = read_trace(out / "trace.csv")
    assert trace.names == ("t_s", "pos_set_mm", "pos_mm", "vel_set_mm_min", "vel_mm_min",
                           "iq_set_a", "iq_a", "motor_pos_mm", "iq_set_mean_a", "iq_mean_a")
    assert any("iq_mean_a" in c and "500 Hz" in c for c in trace.comments)
    t = trace.column("t_s")
    accel = (t >= 0.02) & (t <= 0.1)
    raw = trace.column("iq_set_a")[accel].mean() - trace.column("iq_a")[accel].mean()
    mean = (trace.column("iq_set_mean_a")[accel].mean()
            - trace.column("iq_mean_a")[accel].mean())
    assert raw > 1.0
    assert abs(mean) < 0.05


def test_sim_trace_round_trips(sim_out, tmp_path):
    """Writing the columns read back and reading again gives identical arrays, names and
    metadata (values are written with repr)."""
    _, out = sim_out
    first = read_trace(out / "trace.csv")
    again = read_trace(write_trace(tmp_path / "again.csv", first.data, first.metadata))
    assert again.names == first.names
    assert again.metadata == first.metadata
    for name in first.names:
        np.testing.assert_array_equal(again.column(name), first.column(name), err_msg=name)


def test_sim_trace_prints_times_and_scale_positions_as_their_exact_decimals(sim_out):
    """Rows one position cycle (2 ms) apart and the NC's position from the 0.1 um scale:
    row i's t_s is the exact decimal i * 0.002 (not 0.0020000000000000018), and every
    pos_mm a whole number of 0.0001 mm (reference: Python's exact fractions of the text)."""
    _, out = sim_out
    cfg = load_machine(ARROW)
    cycle_s = Fraction(load_controller(cfg).position_cycle_ratio,
                       round(cfg.motor.pwm_frequency_hz))
    resolution_mm = Fraction(repr(cfg.sensors.scale_resolution_m)) * 1000
    lines = (out / "trace.csv").read_text().splitlines()
    assert "# sample_time_s: 0.002" in lines
    header = next(line for line in lines if line.startswith("t_s,")).split(",")
    rows = [line.split(",") for line in lines if line[0] not in "#t"]
    t_col, pos_col = header.index("t_s"), header.index("pos_mm")
    late = [row[t_col] for i, row in enumerate(rows) if Fraction(row[t_col]) != i * cycle_s]
    off_grid = [row[pos_col] for row in rows
                if (Fraction(row[pos_col]) / resolution_mm).denominator != 1]
    assert late == [] and off_grid == [], (late[:5], off_grid[:5])


def run_json(capsys, argv: list[str]) -> dict:
    """main(argv + --json): exit status 0 and the summary it printed."""
    capsys.readouterr()
    assert main(argv + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("loop, amplitude, final, tol", [
    ("current", 5.0, 5.0, 0.1),       # A: noise and 13.7 mA quantization in the mean
    ("speed", 600.0, 600.0, 12.0),    # mm/min: the PI has not fully settled after 50 ms
    ("position", 0.1, 250.1, 1e-3),   # mm: the table position, 0.1 um scale
])
def test_measure_step(capsys, tmp_path, loop, amplitude, final, tol):
    """Each step measurement writes its plot and CSV, and its summary reports a finite rise
    time and a final value at the commanded one."""
    summary = run_json(capsys, ["measure", str(ARROW), "step", loop, "--amplitude",
                                str(amplitude), "--at", "250", "--out", str(tmp_path)])
    assert (tmp_path / f"step_{loop}.png").is_file()
    assert (tmp_path / f"step_{loop}.csv").is_file()
    assert summary["loop"] == loop and summary["step"] == amplitude
    assert 0.0 < summary["rise_time_ms"] < 100.0
    assert summary["final"] == pytest.approx(final, abs=tol)


def current_loop_bandwidth_hz(cfg) -> float:
    """-3 dB frequency of iq_set -> iq_meas of the plant's q current loop, linear analysis.

    Per PWM period T: i' = e i + (1 - e)/R u_applied (e = exp(-R T/L), EMF cancelled),
    u_applied' = kp (r - i) + I, I' = I + kp T / Ti (r - i); the measurement is the current
    sampled at the start of the period the setpoint r is applied in.
    """
    mo, cl = cfg.motor, cfg.current_loop
    T = 1.0 / mo.pwm_frequency_hz
    e = math.exp(-mo.resistance_ohm * T / mo.inductance_q_h)
    kp, ki = cl.kp_v_per_a, cl.kp_v_per_a * T / cl.ti_s
    A = np.array([[e, (1.0 - e) / mo.resistance_ohm, 0.0], [-kp, 0.0, 1.0], [-ki, 0.0, 1.0]])
    B = np.array([0.0, kp, ki])
    f = np.linspace(1.0, 0.49 / T, 20000)
    z = np.exp(2j * np.pi * f * T)
    h = np.array([np.linalg.solve(zk * np.eye(3) - A, B)[0] for zk in z])
    mag = np.abs(h)
    return float(f[np.argmax(mag < mag[0] * 10 ** (-3 / 20))])


def test_measure_bode_current_bandwidth(capsys, tmp_path):
    """The current loop's frequency response (PRBS order 9) has the bandwidth the linear
    analysis of the drive's current loop predicts (about 980 Hz on the Arrow 500 X) within
    5 %; its CSV carries the coherence, above 0.9 through the pass band of this nearly
    linear loop, and a phase that starts within (-180, 180] deg."""
    summary = run_json(capsys, ["measure", str(ARROW), "bode", "current", "--amplitude", "2",
                                "--order", "9", "--at", "250", "--out", str(tmp_path)])
    assert (tmp_path / "bode_current.png").is_file()
    expected = current_loop_bandwidth_hz(load_machine(ARROW))
    assert expected > 500.0
    assert summary["bandwidth_hz"] == pytest.approx(expected, rel=0.05)
    fr = read_csv(tmp_path / "bode_current.csv")
    assert np.all(fr.coherence[fr.freq_hz < summary["bandwidth_hz"]] > 0.9)
    assert -180.0 < fr.phase_deg[0] <= 180.0


def test_sim_reports_no_alarm_on_the_seed_program(capsys, tmp_path):
    """The text summary says there was no alarm (exit 0 is test_sim_writes_trace_and_plot's)."""
    program = tmp_path / "short.nc"
    program.write_text("G0 X250\nG1 X250.5 F200\nM30\n")
    assert main(["sim", str(ARROW), "--program", str(program), "--out", str(tmp_path)]) == 0
    assert "alarms: none" in capsys.readouterr().out.splitlines()


def test_sim_exits_1_and_reports_the_alarm(tmp_path, capsys):
    """``hil sim`` of a blocked axis (the machine file's friction at 1 MN, more than the
    motor's 23.75 kN): exit status 1, the alarm in the JSON summary (number, axis, text,
    tick, time) and on stderr."""
    machine = machine_variant(tmp_path / "blocked.toml", {"coulomb_n": "1.0e6",
                                                          "breakaway_n": "1.0e6"})
    program = tmp_path / "move.nc"
    program.write_text("G0 X250\nG1 X260 F3000\nM30\n")
    status = main(["sim", str(machine), "--program", str(program), "--out",
                   str(tmp_path / "out"), "--json"])
    out, err = capsys.readouterr()
    summary = json.loads(out)
    assert status == 1
    alarm = summary["alarms"][0]
    assert (alarm["number"], alarm["axis"], alarm["text"]) == (25050, "X",
                                                               "Axis X contour monitoring")
    assert alarm["tick"] > 0 and alarm["t_s"] > 0.0 and alarm["count"] == 1
    assert f"hil sim: alarm 25050 axis X contour monitoring at t = {alarm['t_s']:.3f} s" in err


def test_sim_without_controller_section_exits_2(capsys, tmp_path):
    """A machine file without [controller]: exit 2, the message names file and section."""
    text = ARROW.read_text()
    machine = tmp_path / "bare.toml"
    machine.write_text(text[:text.index("[controller]")])
    status = main(["sim", str(machine), "--program", str(PROGRAM), "--out",
                   str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 2
    assert str(machine) in err and "[controller]" in err
    assert not (tmp_path / "out").exists()


def test_sim_with_unknown_word_exits_2(capsys, tmp_path):
    """A program with a word outside the subset: exit 2, the message names the program, the
    line and the word, and nothing is simulated."""
    program = tmp_path / "bad.nc"
    program.write_text("G90 G71\nG1 X10 F1000\nG1 X20 Q5\nM30\n")
    status = main(["sim", str(ARROW), "--program", str(program), "--out",
                   str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 2
    assert f"{program} line 3" in err and "Q5" in err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()
