"""Progress of a long phase (compile, warm-up, run, comparison) on stderr.

A phase that ends within :data:`QUIET_S` prints nothing; a longer one shows one line that
is rewritten in place (``\\r``) on a terminal, and plain lines -- one per
:data:`STEP_FRACTION` of the work, or per :data:`PLAIN_EVERY_S` when the amount of work is
not known -- when the stream is a pipe or a file, so a log stays readable.  The line
names the phase, how far it is (a percentage, or the count done) and the time since it
started; :meth:`Progress.close` ends it with the phase's duration.

::

    with Progress("replay", total=n_ticks) as p:
        for k in range(n_ticks):
            ...
            p.update(k + 1)

A phase that blocks in one call (numba compiling, a child process running) passes
``ticking=True``: a thread then updates the line with the time alone until the phase
ends.  A phase whose process must not wake a thread meanwhile (a measured real-time loop:
the thread would take the GIL from it) and whose length is known calls
:meth:`Progress.expect` instead: the line, with that length in its label, shows at once
and ends with the phase.
"""

import sys
import threading
import time
from collections.abc import Callable
from typing import Self, TextIO

#: a phase shorter than this shows no progress, s
QUIET_S = 2.0
#: on a terminal the line is rewritten at most this often, s
TERMINAL_EVERY_S = 0.1
#: when piped, a line per this share of the work done
STEP_FRACTION = 0.1
#: when piped and the work is not counted, a line this often, s
PLAIN_EVERY_S = 5.0
#: how long one process takes to compile its kernels into a cold numba cache and warm them
#: up, s: hil demo's emulator took 54.5 s on the 2-vCPU VM, hil sim 26 s
#: (docs/benchmarks.md, 2026-11-29); every message about that wait quotes this figure
COLD_START_S = 55.0
#: the estimate as the messages give it
COLD_START = f"up to {COLD_START_S:.0f} s on a cold cache"
#: the phase that loads the compiled kernels
COMPILING = f"loading the compiled kernels ({COLD_START})"


class Progress:
    """The progress of one phase (see the module docstring).

    Args:
        label: the phase, as the line starts ("compiling the plant").
        total: the amount of work (ticks, rows); None when it is not known (a compile).
        unit: what ``total`` counts, shown with counts ("ticks").
        stream: where to write (stderr by default); a terminal when its ``isatty()`` says so.
        clock: seconds, monotonic (time.monotonic by default).
        ticking: update the line from a thread of its own until :meth:`close` (a phase
            that blocks in one call).
    """

    def __init__(self, label: str, total: int | None = None, unit: str = "",
                 stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic,
                 ticking: bool = False):
        self.label = label
        self.total = total
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = bool(getattr(self.stream, "isatty", lambda: False)())
        self.clock = clock
        self.t0 = clock()
        self.shown = False
        self._last_t = -float("inf")
        self._last_step = 0
        self._open_line = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ticker = None
        if ticking:
            self._ticker = threading.Thread(target=self._tick, name=f"progress: {label}",
                                            daemon=True)
            self._ticker.start()

    def _tick(self) -> None:
        while not self._stop.wait(TERMINAL_EVERY_S):
            self.update()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _text(self, done: int | None, elapsed: float) -> str:
        if done is None:
            return f"{self.label}: {elapsed:.0f} s"
        if self.total:
            return f"{self.label}: {100.0 * done / self.total:3.0f} % ({elapsed:.0f} s)"
        return f"{self.label}: {done} {self.unit} ({elapsed:.0f} s)".replace("  ", " ")

    def update(self, done: int | None = None) -> None:
        """``done`` of the work is done (None: only the time goes on)."""
        with self._lock:
            self._update(done)

    def expect(self, seconds: float) -> None:
        """The phase will take ``seconds`` and cannot update its line meanwhile: when that
        is :data:`QUIET_S` or more, show the line now (:meth:`close` ends it)."""
        if seconds >= QUIET_S:
            with self._lock:
                self._update(None, now=True)

    def _update(self, done: int | None, now: bool = False) -> None:
        """Show the line when it is due (``now``: at once)."""
        t = self.clock()
        elapsed = t - self.t0
        if elapsed < QUIET_S and not now:
            return
        if self.terminal:
            if t - self._last_t < TERMINAL_EVERY_S and not now:
                return
            self.stream.write("\r" + self._text(done, elapsed) + "\033[K")
            self._open_line = True
        else:
            if self.total and done is not None:
                step = int(done / self.total / STEP_FRACTION)
                if step <= self._last_step and self.shown:
                    return
                self._last_step = step
            elif t - self._last_t < PLAIN_EVERY_S and not now:
                return
            self.stream.write(self._text(done, elapsed) + "\n")
        self.stream.flush()
        self._last_t = t
        self.shown = True

    def close(self, note: str = "") -> None:
        """End the phase: a last line with its duration (and ``note``) if any was shown."""
        if self._ticker is not None:
            self._stop.set()
            self._ticker.join()
            self._ticker = None
        if not self.shown:
            return
        elapsed = self.clock() - self.t0
        end = f"{self.label}: done in {elapsed:.1f} s" + (f", {note}" if note else "")
        self.stream.write(("\r" + end + "\033[K" if self._open_line else end) + "\n")
        self.stream.flush()
        self.shown = False
        self._open_line = False
