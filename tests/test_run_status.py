"""``hil run``'s status line (hil/runtime/run_status.py): what it says of hand-made rows,
checked against the rows counted here, and a real ``hil run`` whose stderr ends with it."""

import io
import subprocess

import numpy as np

from hil.cia402 import ModeOfOperation, State
from hil.runtime.run_status import PLAIN_EVERY_S, SILENT_S, RunStatus
from tests.conftest import ROOT
from tests.runtime_helpers import ARROW, ENV, EXIT_S, python_module

PERIOD_NS = 125_000


def _rows(ticks: range, sp_new: np.ndarray, late_ticks=(), state=State.OPERATION_ENABLED,
          prefix: str = "", position_m: float = 0.0125) -> dict[str, np.ndarray]:
    n = len(ticks)
    lateness = np.full(n, 5_000, np.int64)
    lateness[list(late_ticks)] = 200_000
    return {"tick": np.arange(ticks.start, ticks.stop, dtype=np.int64),
            "sp_new": sp_new.astype(np.uint8), "lateness_ns": lateness,
            "compute_ns": np.full(n, 20_000, np.int64),
            f"{prefix}drive_state": np.full(n, int(state), np.uint8),
            f"{prefix}sp_mode": np.full(n, int(ModeOfOperation.CSP), np.int8),
            f"{prefix}fb_fault": np.zeros(n, np.uint16),
            f"{prefix}plant_table_pos": np.full(n, position_m)}


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_the_line_counts_what_the_rows_hold():
    """Ticks without a setpoint from the first setpoint on, overruns (lateness + compute
    beyond the period, after the loop's grace period), the latest state, mode and position in mm, and the controller
    silent once no setpoint came for longer than SILENT_S."""
    status = RunStatus(PERIOD_NS, {"drive_state": "-", "plant_table_pos": "m"}, io.StringIO())
    assert status.line() == "hil run: waiting for the first tick"
    sp = np.zeros(100, bool)
    sp[[40, 41, 43, 47, 99]] = True  # from tick 40 on: 60 ticks, 5 with a setpoint
    status.add(_rows(range(0, 100), sp, late_ticks=(3, 50, 51)))
    line = status.line()
    assert "controller: setpoint 0.0 ms ago, 55 ticks without one" in line, line
    assert "axis Operation enabled CSP 12.500 mm" in line, line
    assert "overruns 3, lateness max 200 µs" in line, line
    after_grace = RunStatus(PERIOD_NS, {"drive_state": "-"}, io.StringIO(), grace_ticks=10)
    after_grace.add(_rows(range(0, 100), sp, late_ticks=(3, 50, 51)))
    assert "overruns 2," in after_grace.line()  # tick 3 is in the loop's grace period
    silent_ticks = round(2 * SILENT_S / (PERIOD_NS * 1e-9))
    status.add(_rows(range(100, 100 + silent_ticks), np.zeros(silent_ticks, bool),
                     state=State.FAULT))
    line = status.line()
    assert f"controller: SILENT for {2 * SILENT_S:.2f} s, {55 + silent_ticks} ticks" in line
    assert "axis Fault CSP" in line, line


def test_axes_by_letter_and_no_setpoint_yet():
    """Several axes each by its letter; a run whose controller never sent says so."""
    columns = {**_rows(range(0, 10), np.zeros(10, bool), prefix="X_"),
               **_rows(range(0, 10), np.zeros(10, bool), prefix="C_", position_m=np.pi / 2)}
    status = RunStatus(PERIOD_NS, {"X_drive_state": "-", "X_plant_table_pos": "m",
                                   "C_drive_state": "-", "C_plant_table_pos": "rad"}, io.StringIO())
    status.add(columns)
    line = status.line()
    assert "controller: no setpoint yet" in line, line
    assert "X Operation enabled CSP 12.500 mm" in line and "C Operation enabled CSP 90.000 deg" in line


def test_piped_lines_are_plain_and_spaced_a_terminal_line_is_rewritten():
    """When piped: a plain line at most every PLAIN_EVERY_S and one at the end; on a
    terminal the line starts with a carriage return and ends with a newline only at the
    end."""
    clock, out = _Clock(), io.StringIO()
    status = RunStatus(PERIOD_NS, {"drive_state": "-", "plant_table_pos": "m"}, out, clock)
    status.add(_rows(range(0, 10), np.ones(10, bool)))
    for t in np.arange(0.0, 2.5 * PLAIN_EVERY_S, 0.25):
        clock.t = t
        status.show()
    status.show(final=True)
    assert len(out.getvalue().splitlines()) == 3 + 1 and "\r" not in out.getvalue()

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    status = RunStatus(PERIOD_NS, {"drive_state": "-", "plant_table_pos": "m"}, term, clock)
    status.add(_rows(range(0, 10), np.ones(10, bool)))
    status.show()
    clock.t += 1.0
    status.show(final=True)
    assert term.getvalue().count("\r") == 2 and term.getvalue().count("\n") == 1
    assert term.getvalue().endswith("\x1b[K\n")


def test_hil_run_ends_its_stderr_with_the_status_line(tmp_path):
    """A real ``hil run`` of 0.5 s with no controller, stderr piped: its last status line
    says no setpoint came and the axis's state; ``--no-status`` leaves it out."""
    def run(*extra: str) -> str:
        done = subprocess.run(python_module(
            "hil.runtime.emulator", ARROW, "--adapter", "udp://127.0.0.1:0", "--duration",
            "0.5", "--no-rt", "--record", tmp_path / f"run{len(extra)}", *extra),
            cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=EXIT_S + 120)
        assert done.returncode == 0, done.stderr
        return done.stderr

    lines = [line for line in run().splitlines() if line.startswith("hil run: ")
             and "controller:" in line]
    assert lines and "controller: no setpoint yet" in lines[-1], lines
    assert "X Switch on disabled" in lines[-1] and " mm | overruns " in lines[-1], lines
    assert "controller:" not in run("--no-status")
