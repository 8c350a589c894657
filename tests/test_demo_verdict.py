"""``hil demo``'s verdict: the last line is ``PASS`` or ``FAIL: <reasons>``, the exit status
follows it, and each reason comes from the file that holds it.

A real demo (the Arrow 500 X at 2 kHz PWM, ``runtime_helpers.SLOW_2KHZ``, a short
program, cyclictest for 1 s) with contour monitoring (MD36400) at 2 µm, which the rapid's
start passes (the lock-step simulation itself raises alarm 25050 there at 2.2 µm): the
demo must fail naming the controller's alarm, and still show the replay matching its
recording, the three traces and the timing report.  (A clean demo's PASS and exit 0:
``tests/test_loopback.py``'s demo test.)  The checks
themselves are tested on report dicts written here, shaped as the processes write them.
"""

import json
from pathlib import Path

import pytest

from hil.replay import ChannelDifference, ReplayResult
from hil.runtime.demo_verdict import Verdict, check_processes, check_replay
from tests.runtime_helpers import SLOW_2KHZ, Children, machine_variant, python_module

PROGRAM = "N10 G90 G71\nN20 G0 X20\nN30 G0 X0\nN40 M30\n"
DEMO_S = 300.0


def emulator_report(**changes) -> dict:
    return {"stopped": "SIGTERM/SIGINT", "watchdog": {"events": []},
            "faults": {"X": {"events": []}}, **changes}


def test_a_clean_run_passes():
    v = Verdict()
    check_processes(v, 0, 0, {"result": "completed", "alarms": []}, emulator_report())
    assert v.line() == "PASS"


def test_a_failed_runs_line_adds_each_loops_worst_overrun_a_passed_one_does_not():
    """The context (each side's worst overrun, what kept it) follows the reasons of a
    FAIL line, so that a failure under load names its stall; PASS stays PASS."""
    v = Verdict(context=["controller's worst overrun: tick 9 ..."])
    assert v.line() == "PASS"
    v.fail("the controller raised alarm 25050")
    assert v.line() == ("FAIL: the controller raised alarm 25050 | controller's worst "
                        "overrun: tick 9 ...")


def test_a_watchdog_trip_and_a_drive_fault_each_fail_the_run():
    v = Verdict()
    report = emulator_report(
        watchdog={"events": [{"kind": "tripped", "t_s": 0.5, "tick": 4000,
                              "silent_ticks": 800}, {"kind": "recovered"}]},
        faults={"X": {"events": [{"kind": "fault", "code": 0x8250, "cycle": 4001,
                                  "text": "8250h no valid setpoint"},
                                 {"kind": "reset", "code": 0, "cycle": 5000, "text": ""}]}})
    check_processes(v, 0, 1, {"result": "alarm", "alarms": [{"message": "alarm 25201"}]},
                    report)
    assert v.reasons == [
        "hil controller exited with 1 (alarm)", "the controller raised alarm 25201",
        ("the emulator's watchdog tripped at t = 0.5000 s (tick 4000, 800 ticks without a "
        "setpoint)"),
        "axis X: drive fault 8250h at drive cycle 4001 (8250h no valid setpoint)"]
    assert v.line().startswith("FAIL: hil controller exited with 1 (alarm); the controller")


def test_a_replay_that_does_not_match_fails_naming_channel_and_tick():
    v = Verdict()
    worst = ChannelDifference("plant_table_pos", 2e-8, 1234, 0.01, 0.0100000002)
    check_replay(v, ReplayResult("run", 5000, 26, 1e-9, worst, False))
    check_replay(v, "recording.arrows: no sp_refused column")
    assert v.reasons == [
        ("the replay does not match the recording: plant_table_pos at tick 1234 differs by "
        "2e-08 relative (tolerance 1e-09)"),
        "the run could not be replayed: recording.arrows: no sp_refused column"]


def demo(folder: Path, config: Path) -> tuple[int, str, dict]:
    program = folder / "short.nc"
    program.write_text(PROGRAM)
    with Children(folder) as children:
        proc = children.start("demo", python_module(
            "hil.runtime.demo", "--config", config, "--program", program, "--out",
            folder / "out", "--cyclictest-seconds", "1"))
        status = proc.wait(timeout=DEMO_S)
        log = children.log("demo")
    return status, log, json.loads((folder / "out" / "demo.json").read_text())


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    return machine_variant(tmp_path_factory.mktemp("cfg") / "arrow_2khz.toml", SLOW_2KHZ)


def test_a_contour_monitoring_alarm_fails_the_demo_naming_it(config, tmp_path):
    tight = tmp_path / "tight.toml"
    tight.write_text(config.read_text().replace("[controller]\n", "[controller]\n"
                                                "contour_tol_mm = 0.002\n", 1))
    status, log, result = demo(tmp_path, tight)
    assert status == 1, log
    last = log.strip().splitlines()[-1]
    assert last.startswith("FAIL: ") and last == result["verdict"]
    assert "hil controller exited with 1" in last
    assert any(r.startswith("the controller raised alarm 25050 axis X contour monitoring")
               for r in result["reasons"]), last
    # the rest of the summary is there all the same: the alarm is physics, not the emulator
    assert result["replay"]["matches"] and result["replay"]["worst"]["rel_diff"] <= 1e-9
    cost = result["timing_cost"]
    assert cost["setpoints"] == (cost["on_time"] + cost["late"] + cost["early"]
                                 + cost["missed"])
    for text in ("recording = replay: replay matches", "lock-step (hil sim)",
                 "replay of the real timing", "timing cost (replay - lock-step FE)",
                 "wake-up latency, loop", "lateness after the spin, loop", "round trip"):
        assert text in log, text
    for name in ("emulator/latency_hist.png", "emulator/latency_time.png",
                 "emulator/report.md"):
        assert (tmp_path / "out" / name).stat().st_size > 0, name
