"""The wait for an emulator's ready line (hil/runtime/demo.py's wait_ready): past its
limit it waits on only while the child works, as a numba compile slowed by other busy
processes does (over 120 s on the 2-vCPU VM beside two busy processes), and gives up on
a child that sits idle.  Real child processes: a busy loop and a sleep."""

import subprocess
import sys
import time

import pytest

from hil.runtime.demo import DemoError, wait_ready


def _child(code: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)


BUSY_THEN_READY = ("import time\nend = time.monotonic() + 2.5\nwhile time.monotonic() < end: "
                   "pass\nprint('ready: udp://127.0.0.1:1', flush=True)\ntime.sleep(5)")


def test_a_child_still_working_at_the_limit_is_waited_for():
    """Busy for 2.5 s, then ready: a 1 s limit waits on (before, it gave up at 1 s)."""
    proc = _child(BUSY_THEN_READY)
    try:
        assert wait_ready(proc, 1.0) == "udp://127.0.0.1:1"
    finally:
        proc.kill()
        proc.wait()


def test_an_idle_child_is_given_up_at_the_limit_and_a_busy_one_at_the_longest():
    """A child that sleeps (after its interpreter's start) fails the 1 s limit saying how
    little CPU it used; a busy one fails at the longest wait, 1.5 s here."""
    proc = _child("import time; time.sleep(30)")
    try:
        t0 = time.monotonic()
        with pytest.raises(DemoError, match=r"not ready within 1 s \(it used \d+ % of a CPU"
                           ) as err:
            wait_ready(proc, 1.0)
        assert int(str(err.value).split("it used ")[1].split(" %")[0]) < 20
        assert time.monotonic() - t0 < 5.0
    finally:
        proc.kill()
        proc.wait()
    proc = _child(BUSY_THEN_READY)
    try:
        with pytest.raises(DemoError, match=r"only while it works, up to 1.5 s"):
            wait_ready(proc, 1.0, busy_max_s=1.5)
    finally:
        proc.kill()
        proc.wait()
