"""hil.progress: silent for a short phase, one rewritten line on a terminal, plain lines
(one per tenth of the work) when piped.  Time is a clock the test sets, never the wall."""

import io
import time

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
