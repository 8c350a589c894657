"""hil.progress: silent for a short phase, one rewritten line on a terminal, plain lines
(one per tenth of the work) when piped.  Time is a clock the test sets, never the wall."""

import io
import json
import time

import pytest

from hil.progress import QUIET_S, Progress


class Clock:
    """Seconds the test sets."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_phase_shorter_than_two_seconds_prints_nothing():
    out, clock = io.StringIO(), Clock()
    with Progress("replay", total=10, stream=out, clock=clock) as p:
        for i in range(10):
            clock.t += 0.19
            p.update(i + 1)
    assert out.getvalue() == ""


def test_piped_progress_is_plain_lines_one_per_tenth():
    out, clock = io.StringIO(), Clock()
    with Progress("replay", total=1000, stream=out, clock=clock) as p:
        for i in range(1000):
            clock.t += 0.01  # 10 s in all
            p.update(i + 1)
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    # from 2 s on (20 %): one line per tenth reached, then the end
    assert lines[0] == "replay:  20 % (2 s)"
    assert [line.split("%")[0].split(":")[1].strip() for line in lines[:-1]] == [
        str(p) for p in range(20, 101, 10)]
    assert lines[-1] == "replay: done in 10.0 s"


def test_terminal_progress_rewrites_one_line_and_ends_it():
    out, clock = Terminal(), Clock()
    with Progress("compiling", stream=out, clock=clock) as p:
        clock.t += QUIET_S + 0.5
        p.update()
        clock.t += 1.0
        p.update()
    text = out.getvalue()
    assert text.count("\n") == 1 and text.endswith("\n")
    assert text.startswith("\rcompiling: 2 s\033[K\rcompiling: 4 s\033[K")
    assert "\rcompiling: done in 3.5 s\033[K\n" in text


def test_piped_progress_without_a_total_prints_every_five_seconds():
    out, clock = io.StringIO(), Clock()
    with Progress("waiting", stream=out, clock=clock) as p:
        for _ in range(48):
            clock.t += 0.25  # 12 s, in steps a float holds exactly
            p.update()
    assert out.getvalue().splitlines() == ["waiting: 2 s", "waiting: 7 s", "waiting: 12 s",
                                           "waiting: done in 12.0 s"]


def test_a_ticking_phase_shows_its_time_while_the_caller_blocks():
    out, clock = io.StringIO(), Clock()
    p = Progress("compiling", stream=out, clock=clock, ticking=True)
    clock.t += QUIET_S + 1.0  # the caller is busy: only the thread updates
    deadline = time.monotonic() + 10.0
    while not out.getvalue() and time.monotonic() < deadline:
        time.sleep(0.01)
    p.close()
    assert out.getvalue().splitlines() == ["compiling: 3 s", "compiling: done in 3.0 s"]


def test_hil_controller_says_it_waits_for_a_drive_that_does_not_answer():
    """hil controller at a UDP port nobody serves, --connect-timeout 3: a wait over two
    seconds shows as a progress line naming the drive's address and the limit, then the
    refusal names the drive (a real process, stderr piped)."""
    import socket
    import subprocess

    from tests.conftest import CONFIGS, ROOT
    from tests.runtime_helpers import ENV, python_module

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))  # a port of our own that nothing answers on
        port = s.getsockname()[1]
        done = subprocess.run(python_module(
            "hil.cli", "controller", CONFIGS / "arrow500_x.toml", "--adapter",
            f"udp://127.0.0.1:{port}", "--program", ROOT / "programs" / "demo_moves.nc",
            "--out", ROOT / "out" / "test-progress-ctl", "--no-rt", "--connect-timeout", "3"),
            cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=180)
    assert done.returncode == 1, done.stderr  # the run failed (no drive), not bad input
    waiting = f"waiting for the drive at udp://127.0.0.1:{port} (up to 3 s)"
    assert f"{waiting}: 2 s" in done.stderr and f"{waiting}: done in 3.0 s" in done.stderr
    assert f"drive 127.0.0.1:{port}> within 3 s" in done.stderr.splitlines()[-1]


def test_a_phase_of_known_length_shows_its_line_at_once_and_ends_it():
    """expect(): a phase that cannot update its line (a measured loop) shows it at its
    start when it will take QUIET_S or more, and nothing when shorter; close() ends it, in
    place on a terminal."""
    out, clock = io.StringIO(), Clock()
    with Progress("the loop measured for 5 s", stream=out, clock=clock) as p:
        p.expect(5.0)
        clock.t += 5.0
    assert out.getvalue().splitlines() == ["the loop measured for 5 s: 0 s",
                                           "the loop measured for 5 s: done in 5.0 s"]
    term = Terminal()
    with Progress("loop", stream=term, clock=clock) as p:
        p.expect(QUIET_S)
        clock.t += 3.0
    assert term.getvalue() == "\rloop: 0 s\033[K\rloop: done in 3.0 s\033[K\n"
    short = io.StringIO()
    with Progress("loop", stream=short, clock=clock) as p:
        p.expect(QUIET_S - 0.5)
        clock.t += QUIET_S - 0.5
    assert short.getvalue() == ""


def test_every_compile_estimate_is_the_measured_cold_start():
    """The progress lines' compile estimate is one figure, at or above the cold start
    docs/benchmarks.md measured, and the README and docs/benchmarks.md quote it."""
    import re

    from hil.progress import COLD_START, COLD_START_S, COMPILING
    from tests.conftest import ROOT

    benchmarks = (ROOT / "docs" / "benchmarks.md").read_text()
    measured = re.search(r"compiling and\s+warming up ([\d.]+) s", benchmarks)
    assert measured and float(measured.group(1)) <= COLD_START_S
    quoted = f"up to {COLD_START_S:.0f} s"
    assert quoted in COLD_START and COLD_START in COMPILING
    assert quoted in benchmarks and quoted in (ROOT / "README.md").read_text()


def _run(*argv, timeout: float = 300.0):
    """``hil ARGV`` as a child process, stdout and stderr piped (plain progress lines)."""
    import subprocess

    from tests.conftest import ROOT
    from tests.runtime_helpers import ENV, python_module

    return subprocess.run(python_module("hil.cli", *argv), cwd=ROOT, env=ENV,
                          capture_output=True, text=True, timeout=timeout, check=False)


def test_hil_soak_shows_how_far_its_run_is_and_keeps_stdout_for_its_summary(tmp_path):
    """A 3.6 s soak (--no-rt): stderr has the run's progress, its share of the 3.6 s in
    steps of a tenth, and its end; stdout has the summary alone."""
    done = _run("soak", "--minutes", "0.06", "--no-rt", "--rss-every", "0.5", "--out",
                tmp_path, timeout=400)
    assert done.returncode == 0, done.stderr
    label = "hil soak: the master drives the emulator for 3.6 s"
    # "LABEL:  60 % (2 s)": the shares shown, each once and rising
    shares = [int(line.removeprefix(f"{label}:").split("%")[0])
              for line in done.stderr.splitlines() if line.startswith(f"{label}:") and "%" in line]
    assert shares and shares == sorted(set(shares)), done.stderr
    assert f"{label}: done in" in done.stderr
    assert label not in done.stdout
    assert done.stdout.splitlines()[0] == "hil soak: 0.06 min at 4000 Hz, --no-rt"
    assert done.stdout.splitlines()[-1] == f"files in {tmp_path}/"


def test_hil_validate_shows_the_experiment_it_runs_and_keeps_the_json_clean(experiment_rows,
                                                                           tmp_path):
    """On an empty numba cache (a compile of 30 s on the 2-vCPU VM) stderr names the
    experiment while it compiles, with the compile's estimate, once QUIET_S has passed
    (the run is stopped there); on the warm cache stdout is the JSON of its rows, as
    run_all gives them, and nothing else, and stderr holds at most its progress lines and
    the summary (an experiment done within QUIET_S shows none)."""
    import subprocess

    from hil.progress import COMPILING
    from tests.conftest import ROOT
    from tests.runtime_helpers import ENV, EXIT_S, python_module

    argv = python_module("hil.cli", "validate", "--json", "--no-plots", "--only",
                         "seed003_trapezoid")
    label = f"hil validate: seed003_trapezoid (1 of 1), {COMPILING}"
    cold = subprocess.Popen(argv, cwd=ROOT, text=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE,
                            env={**ENV, "NUMBA_CACHE_DIR": str(tmp_path / "cold-cache")})
    try:
        first = cold.stderr.readline()
    finally:
        cold.kill()
        cold.wait(EXIT_S)
        cold.stderr.close()
    assert first.startswith(f"{label}: ") and first.rstrip().endswith(" s"), first
    done = _run("validate", "--json", "--no-plots", "--only", "seed003_trapezoid")
    assert done.returncode == 0, done.stderr
    rows = [r.as_dict() for r in experiment_rows("seed003_trapezoid")]
    assert done.stdout == json.dumps(rows, indent=1) + "\n"
    *lines, summary = done.stderr.splitlines()
    assert all(line.startswith(f"{label}: ") for line in lines), done.stderr
    assert summary.startswith("10 rows: 10 verification"), done.stderr


def test_hil_report_shows_cyclictest_running_and_keeps_stdout_for_the_report(tmp_path):
    """hil report --cyclictest on a one-second run of hil run: stderr shows cyclictest's
    3 s at the run's period while it runs; stdout is the report and its verdict alone."""
    import shutil

    from tests.runtime_helpers import ARROW

    if shutil.which("cyclictest") is None:
        pytest.skip("cyclictest is not installed (apt-get install rt-tests)")
    run = tmp_path / "run"
    made = _run("run", ARROW, "--adapter", "udp://127.0.0.1:0", "--record", run,
                "--duration", "1", "--no-rt")
    assert made.returncode == 0, made.stderr
    done = _run("report", run, "--cyclictest", "--cyclictest-seconds", "3")
    if "cyclictest failed" in done.stderr:
        pytest.skip(f"cyclictest does not run here: {done.stderr.strip()}")
    label = "hil report: cyclictest, 125 µs for 3 s"
    assert f"{label}: 2 s" in done.stderr and f"{label}: done in" in done.stderr
    assert "cyclictest" not in done.stderr.replace(label, "")
    assert done.stdout.startswith("# Latency report: run\n"), done.stdout[:200]
    assert label not in done.stdout and "## Verdict" in done.stdout
