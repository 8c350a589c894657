"""LinuxCNC drives the emulated machine (``hil linuxcnc``): LinuxCNC 2.9, headless, in
POSIX non-real-time mode, with the feeddrive HAL component in its servo thread, against
``hil run`` on configs/machines/arrow500_xyz_2khz.toml over the fixed binary wire.

Two sessions, each a separate ``hil linuxcnc`` process: one homes and runs a program (the
module's fixture, checked several ways), one with a fault injected on X.  Where LinuxCNC
cannot be run (not unpacked by .ci/test-deps nor installed, not root, no mount namespace)
they skip saying why.
"""

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from hil.bench.linuxcnc import figures
from hil.linuxcnc import install
from hil.linuxcnc.command import COMPONENT_CACHE
from tests.conftest import CONFIGS, ROOT
from tests.runtime_helpers import ENV

INI = CONFIGS / "linuxcnc" / "arrow500_xyz.ini"
PROGRAM = ROOT / "programs" / "linuxcnc_square.ngc"
#: the longest a whole session may take (a cold numba cache compiles the plant and the
#: replay's kernels; LinuxCNC starts, homes, runs 8 s of program and stops)
SESSION_S = 600
#: the fault: the motor loses 90 % of its magnet flux on an axis whose guides' friction
#: grew eleven-fold: it cannot follow LinuxCNC's accelerations any more
FAULT = ["--inject", "X/torque_constant_loss:loss_pct=90",
         "--inject", "X/friction_growth:growth_pct=1000"]


def _linuxcnc_or_skip() -> None:
    try:
        install.build_component(install.find(), COMPONENT_CACHE)
    except install.LinuxCNCUnavailable as e:
        pytest.skip(f"LinuxCNC cannot be run here: {e}")


def _session(out, *extra) -> tuple[subprocess.CompletedProcess, dict]:
    # the emulator's loop on the first CPU: other test processes' hil run loops (SCHED_FIFO
    # on the last CPU by default) would hold it off theirs
    done = subprocess.run([sys.executable, "-m", "hil.linuxcnc.command", str(INI),
                           "--program", str(PROGRAM), "--out", str(out), "--cpu", "0", *extra],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=SESSION_S)
    summary = out / "linuxcnc.json"
    assert summary.exists(), f"no linuxcnc.json:\n{done.stdout}\n{done.stderr}"
    return done, json.loads(summary.read_text())


#: sessions the program fixture may take: LinuxCNC's servo thread is an ordinary thread
#: here (POSIX non-real-time, no PREEMPT_RT), and a stall of it of several milliseconds on
#: a VM trips its own following-error check now and then (once in a quiet suite's run of
#: this VM, 2026-11-28), which docs/benchmarks.md says; a second session judges the product again
ATTEMPTS = 2


@dataclass
class Session:
    """A session of the program: how the command ended, its linuxcnc.json, its folder."""
    done: subprocess.CompletedProcess
    summary: dict
    out: Path


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Session:
    _linuxcnc_or_skip()
    failed = []
    for attempt in range(1, ATTEMPTS + 1):
        out = tmp_path_factory.mktemp(f"linuxcnc{attempt}")
        done, summary = _session(out)
        if summary["verdict"] == "PASS" or attempt == ATTEMPTS:
            break
        failed.append(done.stdout)
    done.stdout = "".join(f"attempt {k}:\n{text}\n" for k, text in enumerate(failed, 1)) \
        + done.stdout
    return Session(done, summary, out)


def test_the_program_completes_and_the_verdict_passes(session):
    done, summary = session.done, session.summary
    lines = done.stdout.strip().splitlines()
    assert done.returncode == 0 and lines[-1] == "PASS", done.stdout + done.stderr
    assert summary["verdict"] == "PASS" and summary["linuxcnc_errors"] == []
    assert {"on", "homed", "program"} <= set(summary["phases"])
    assert summary["replay"]["matches"]


def test_homing_finds_the_emulated_switch_and_index(session):
    """LinuxCNC's own homing (search the switch, latch its edge, on to the index) reset
    every joint's feedback at the emulated encoder's first index mark above the switch,
    to the count: not at the switch's edge, half a mark lower."""
    summary = session.summary
    assert len(summary["homing"]) == 3
    for h in summary["homing"]:
        assert h["homed"], h
        assert abs(h["index_counts"] - h["expected_counts"]) <= 1.0, h


def test_linuxcnc_following_error_is_reported_beside_the_drives(session):
    """LinuxCNC's following error, every servo period, stays inside its FERROR/MIN_FERROR
    limit (0.12-0.18 mm of 1.0 mm on a quiet VM; a stall of its non-real-time servo thread
    takes it higher, so no tighter margin is asserted); it is not zero (the feedback is at
    least a PWM period, 0.5 ms, older than the command: 12.5 µm at the homing search's 25
    mm/s); the drive's own is recorded beside it."""
    for name, e in session.summary["following_error"].items():
        assert 0.0125 < e["linuxcnc_max"] < e["linuxcnc_limit"], (name, e)
        assert e["drive_max"] > 0.0125 and e["unit"] == "mm", (name, e)


def test_the_servo_threads_periods_and_the_frames_are_reported(session):
    """The feeddrive component timed every servo period while the machine was on: the
    INI's 1 ms at the median (the unit from ns right), one setpoint datagram per period,
    and about two feedbacks per period (the emulator answers every PWM period, 2 kHz);
    the emulator received the setpoints in order, none lost.  hil bench linuxcnc puts them
    beside cyclictest at the same period on the CPU LinuxCNC's threads ran on."""
    t = session.summary["servo_thread"]
    assert t["nominal_us"] == 1000.0 and t["periods"] > 1000, t
    assert t["period_us"]["p50"] == pytest.approx(1000.0, rel=0.2), t
    assert t["setpoints_per_s"] == pytest.approx(1000.0, rel=0.2), t
    assert t["feedback_per_s"] == pytest.approx(2000.0, rel=0.2), t
    bench = figures(INI, session.out, realtime=True, cyclictest_s=1.0)
    if isinstance(bench["cyclictest"], str):
        pytest.skip(f"no cyclictest baseline: {bench['cyclictest']}")
    assert bench["servo_thread"] == t and bench["program"] == str(PROGRAM)
    assert bench["cyclictest"]["interval_us"] == 1000
    assert bench["cyclictest"]["cpu"] in session.summary["rt_cpus"]
    assert set(bench["jitter_over_cyclictest"]) == {"p99", "p999", "max"}
    e = bench["emulator"]
    assert e["received"] > t["periods"] and e["lost"] == e["out_of_order"] == 0, e


def test_an_injected_fault_shows_in_linuxcncs_following_error_and_fails_the_run(tmp_path):
    """With X's motor weakened and its guides seizing, X cannot follow LinuxCNC: its
    following error in LinuxCNC grows to several times the healthy joints' of the same run
    (LinuxCNC's own check trips when it passes the limit; or, as the weak axis overshoots
    the home switch, LinuxCNC's homing gives up on joint 0), and the verdict says so in
    LinuxCNC's words; the other joints stay inside their limits.  (Against the healthy
    joints of the same run, not another run's: a stall of LinuxCNC's non-real-time thread
    in either would blur the comparison.)"""
    _linuxcnc_or_skip()
    done, summary = _session(tmp_path, *FAULT)
    assert done.returncode == 1, done.stdout + done.stderr
    last = done.stdout.strip().splitlines()[-1]
    assert last.startswith("FAIL: LinuxCNC: ") and ("joint 0" in last or "j=0" in last), last
    e = summary["following_error"]
    healthy = max(e["Y"]["linuxcnc_max"], e["Z"]["linuxcnc_max"])
    assert e["X"]["linuxcnc_max"] > 3.0 * healthy, e
    assert all(e[n]["linuxcnc_max"] < e[n]["linuxcnc_limit"] for n in ("Y", "Z"))
