"""Every run ends with its timing quality, and ``hil report`` gives a verdict.

The counts are the loops' and endpoints' own (``report.json``, ``summary.json``); the
limits are :mod:`hil.runtime.timing_quality`'s (0.1 % of the ticks each, no stall).  The
processes' case is the issue's: a run whose timing went wrong (here the emulator stopped
by SIGSTOP for 0.1 s while the controller went on: a stall of the emulator's loop, the
controller's ticks without feedback) must say so when it ends, on both sides, and ``hil
report`` must fail it naming why, though both processes exit 0.
"""

import json
import os
import signal
import time

import pytest

from hil.report.run_verdict import judge_timing_counts
from hil.runtime.demo_verdict import Verdict
from hil.runtime.timing_quality import MAX_SHARE, TimingQuality
from tests.runtime_helpers import (
    EXIT_S,
    READY_S,
    SLOW_2KHZ,
    Children,
    machine_variant,
    python_module,
    terminate,
    wait_for_enabled,
)

#: 8 mm at 0.12 m/min: about 4 s, long enough that the stop falls inside it, slow enough
#: that the axis stays within contour monitoring (0.2 mm in 0.1 s against 1 mm)
PROGRAM = "G1 X8 F120\nM30\n"
#: when the emulator is stopped: this long after its recording first shows the drive in
#: OPERATION ENABLED (the program then runs)
STOP_AFTER_ENABLE_S = 1.0
STOP_S = 0.1
#: the emulator's watchdog (50 ms at 2 kHz): a stop of that length or more is a stall
WATCHDOG_CYCLES = 100
#: the controller's patience without feedback (0.5 s at 2 kHz), beyond the stop
FEEDBACK_TIMEOUT = 1000


def _loop(ticks: int, overruns: int, worst_us: float, stalls: int = 0) -> dict:
    return {"ticks": ticks, "overruns": overruns, "stalls": stalls, "skipped": 0,
            "lateness_us": {"p50": 1.0, "p99": 2.0, "p999": 3.0, "max": worst_us}}


def test_the_issues_run_is_beyond_the_limits_and_says_why():
    """The run the issue met: 18 700 overruns in 311 739 ticks, the worst 152.6 ms late."""
    q = TimingQuality.of_controller({
        "loop": _loop(311_739, 18_700, 152_621.2),
        "feedback": {"ticks_without_new": 120, "lag_ticks": {"0": 0, "1": 0, "2+": 400}}})
    assert not q.within
    assert q.reasons() == [
        "controller: 18700 overruns in 311739 ticks (6 %, limit 0.1 %), the worst "
        "152621.2 µs late",
        "controller: 400 feedback late in 311739 ticks (0.128 %, limit 0.1 %)"]
    assert "BEYOND the limits" in q.line() and q.as_dict()["within"] is False


def test_counts_at_the_limit_are_within_it_and_a_stall_never_is():
    ticks = 100_000
    at_limit = round(MAX_SHARE * ticks)
    q = TimingQuality.of_emulator({
        "loop": _loop(ticks, at_limit, 80.0),
        "adapter": {"stats": {"drained": at_limit, "lost": at_limit}}})
    assert q.within and q.line().endswith("within the limits")
    assert (q.late, q.missed, q.messages) == (at_limit, at_limit, "setpoints")
    stalled = TimingQuality.of_emulator({
        "loop": _loop(ticks, 0, 60_000.0, stalls=1),
        "adapter": {"stats": {"drained": 0, "lost": 0}}})
    assert stalled.reasons() == ["emulator: 1 stall(s) (ticks several periods late; the "
                                 "worst 60000.0 µs): the process was not running"]


def test_a_priced_run_fails_on_a_stall_alone_an_unpriced_one_on_every_count():
    """judge_timing_counts, the rule hil report and hil demo share: with a lock-step
    reference (priced) 5 % overruns are the timing cost's to judge and only a stall fails;
    without one the overruns fail too."""
    report = {"loop": _loop(10_000, 500, 900.0), "adapter": {"stats": {"drained": 0,
                                                                        "lost": 0}}}
    priced, unpriced = Verdict(), Verdict()
    judge_timing_counts(priced, report, None, priced=True)
    judge_timing_counts(unpriced, report, None, priced=False)
    assert priced.passed and unpriced.reasons == [
        "emulator: 500 overruns in 10000 ticks (5 %, limit 0.1 %), the worst 900.0 µs late"]
    stalled = {**report, "loop": _loop(10_000, 500, 90_000.0, stalls=1)}
    judge_timing_counts(priced, stalled, None, priced=True)
    assert [r.split(" (")[0] for r in priced.reasons] == ["emulator: 1 stall(s)"]


@pytest.fixture(scope="module")
def stalled_run(tmp_path_factory):
    """``hil run`` and ``hil controller`` on the Arrow at 2 kHz, the emulator stopped for
    STOP_S inside the program (STOP_AFTER_ENABLE_S after its recording, read while it is
    written, shows the drive enabled): (folder, the controller's stdout, the emulator's
    stdout)."""
    folder = tmp_path_factory.mktemp("stalled")
    config = machine_variant(folder / "arrow_2khz.toml", SLOW_2KHZ)
    program = folder / "out_and_back.nc"
    program.write_text(PROGRAM)
    cpus = sorted(os.sched_getaffinity(0))
    pin = ["--cpu", cpus[0]] if len(cpus) > 1 else []
    with Children(folder) as children:
        emulator, served = children.emulator(config, "udp://127.0.0.1:0", folder / "emulator",
                                             "--cpu", cpus[-1], "--watchdog-cycles",
                                             WATCHDOG_CYCLES)
        ctl = children.start("controller", python_module(
            "hil.runtime.controller_proc", config, "--adapter", served, "--program", program,
            "--out", folder / "controller", "--feedback-timeout", FEEDBACK_TIMEOUT, *pin))
        wait_for_enabled(folder / "emulator", ctl)
        time.sleep(STOP_AFTER_ENABLE_S)
        emulator.send_signal(signal.SIGSTOP)
        time.sleep(STOP_S)
        emulator.send_signal(signal.SIGCONT)
        assert ctl.wait(timeout=EXIT_S) == 0, children.log("controller")
        assert terminate(emulator) == 0
        emulator_out = emulator.stdout.read()
    return folder, children.log("controller"), emulator_out


def test_both_tools_end_saying_the_timing_was_beyond_the_limits(stalled_run):
    folder, controller_out, emulator_out = stalled_run
    summary = json.loads((folder / "controller" / "summary.json").read_text())
    report = json.loads((folder / "emulator" / "report.json").read_text())
    assert summary["result"] == "completed"
    assert "hil run: timing: " in emulator_out and "BEYOND the limits" in emulator_out
    assert report["timing_quality"]["stalls"] >= 1 and not report["timing_quality"]["within"]
    missed = summary["timing_quality"]["missed"]
    assert missed >= 0.5 * STOP_S * 2000, summary["timing_quality"]  # 2 kHz ticks, no answer
    assert "hil controller: timing: " in controller_out
    assert "BEYOND the limits" in controller_out


def test_hil_report_fails_the_run_naming_the_stall(stalled_run):
    """Without the controller's folder there is no lock-step reference: the counts are
    judged against their limits, and the emulator's stall fails the run."""
    import subprocess

    from tests.runtime_helpers import ENV
    folder = stalled_run[0]
    done = subprocess.run(python_module("hil.cli", "report", folder / "emulator"), env=ENV,
                          capture_output=True, text=True, timeout=READY_S)
    assert done.returncode == 1, done.stdout + done.stderr
    last = done.stdout.strip().splitlines()[-1]
    assert last.startswith("FAIL: ") and "emulator: " in last and "stall(s)" in last, last
    assert "no lock-step reference (no --controller folder)" in done.stdout
    verdict = json.loads((folder / "emulator" / "verdict.json").read_text())
    assert verdict["verdict"] == last


def test_hil_report_with_the_controller_prices_the_timing_and_still_fails_the_stall(
        stalled_run):
    """With the controller's folder (one axis, no injection) the reference exists: the
    timing's cost against the lock-step simulation is shown and judged (within the
    tolerance the stall's own lateness allows), the counts are shown but priced by it,
    as hil demo judges, and the emulator's stall still fails the run."""
    import subprocess

    from tests.runtime_helpers import ENV
    folder = stalled_run[0]
    done = subprocess.run(python_module("hil.cli", "report", folder / "emulator",
                                        "--controller", folder / "controller"),
                          env=ENV, capture_output=True, text=True, timeout=READY_S)
    last = done.stdout.strip().splitlines()[-1]
    assert "timing cost against the lock-step simulation: max " in done.stdout, done.stdout
    assert "recording = replay: " in done.stdout
    assert done.returncode == 1 and last.startswith("FAIL: "), (done.returncode, last)
    # the counts are not reasons (a loaded machine may add a stall of the controller's)
    assert "emulator: " in last and "stall(s)" in last, last
    assert "feedback missed" not in last and "overruns in" not in last, last
    assert "controller: timing: " in done.stdout and "feedback late" in done.stdout
    assert (folder / "emulator" / "verdict_lockstep" / "trace.csv").exists()


def test_the_traces_state_their_runs_timing_and_identify_warns_on_them(stalled_run):
    """The controller's trace.csv and ``hil export --to csv`` of the run carry their side's
    timing in the header; ``hil identify``'s reader finds it beyond the limits and says
    what to do instead (on a trace within the limits it says nothing)."""
    import subprocess

    from hil.identify.record import load_record, timing_warning
    from tests.runtime_helpers import ENV
    folder = stalled_run[0]
    ctl = load_record(folder / "controller" / "trace.csv")
    assert ctl.meta["timing_side"] == "controller"
    assert ctl.meta["timing_within_limits"] == "no"
    assert int(ctl.meta["timing_feedback_missed"]) >= 0.5 * STOP_S * 2000
    why = timing_warning(ctl)
    assert why is not None and "beyond the limits" in why and "hil identify RUN" in why
    done = subprocess.run(python_module("hil.cli", "export", folder / "emulator", "--to", "csv",
                                        "--out", folder / "export"), env=ENV,
                          capture_output=True, text=True, timeout=EXIT_S)
    assert done.returncode == 0, done.stderr
    header = {}  # (the export of a CST run has no position setpoint to load as a record)
    for line in (folder / "export" / "trace.csv").read_text().splitlines():
        if not line.startswith("# "):
            break
        key, _, value = line[2:].partition(": ")
        header[key] = value
    assert header["timing_side"] == "emulator" and header["timing_within_limits"] == "no"
    assert int(header["timing_stalls"]) >= 1
    assert header["modes"] == "CST" and "the position setpoint stays in the controller" in \
        header["pos_set_note"]  # (hil controller drives the Arrow's current: CST)
    ctl.meta["timing_within_limits"] = "yes"
    assert timing_warning(ctl) is None
