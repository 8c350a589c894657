"""Progress of a study on stderr: one updating line on a terminal, plain lines when piped."""

import math
import sys
import time


class Progress:
    """Samples done, failures, rate and time left.

    On a terminal one line is rewritten after every finished task; piped (a CI log), a
    line is printed at every tenth of the work and at the end.  :meth:`note` prints a
    message of its own on a line of its own.
    """

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.total = 0
        self.label = ""
        self._t0 = time.perf_counter()
        self._shown = -1
        self._open = False

    def start(self, total: int, label: str) -> None:
        """A new phase of ``total`` samples, named ``label``."""
        self.total, self.label = total, label
        self._t0 = time.perf_counter()
        self._shown = -1

    def __call__(self, done: int, failed: int) -> None:
        """``done`` of the phase's samples are finished, ``failed`` of them failed."""
        tenth = 10 * done // max(self.total, 1)
        if not self.tty and tenth == self._shown and done != self.total:
            return
        self._shown = tenth
        elapsed = time.perf_counter() - self._t0
        rate = done / elapsed if elapsed > 0 else 0.0
        left = (self.total - done) / rate if rate > 0 else float("nan")
        line = (f"{self.label}: {done}/{self.total} samples"
                + (f" ({failed} failed)" if failed else "")
                + f", {rate:.1f} samples/s, {_duration(left)} left")
        if self.tty:
            end = "\n" if done == self.total else ""
            self.stream.write(f"\r{line:<78}{end}")
            self._open = done != self.total
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def note(self, message: str) -> None:
        """A line of its own."""
        if self._open:
            self.stream.write("\n")
            self._open = False
        self.stream.write(message + "\n")
        self.stream.flush()


def _duration(seconds: float) -> str:
    if math.isnan(seconds):  # no rate yet
        return "? s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds // 60:.0f} min {seconds % 60:.0f} s"
