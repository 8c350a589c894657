"""``hil run``'s status line while the run goes on: time, the controller's link, each
axis's state, mode, fault and position, overruns and lateness so far.

It is made in the recording's writer process (:mod:`hil.runtime.record_process`) from the
rows it writes anyway, every flush (0.25 s), so the loop's process does nothing for it.  On
a terminal it is one line rewritten in place; when stderr is a pipe or a file it is a plain
line every :data:`PLAIN_EVERY_S`, so a log stays readable.  The figures lag the loop by
one flush at most.

::

    hil run: 12.3 s | controller: setpoint 0.1 ms ago, 2 ticks without one | X Operation enabled CSP 12.500 mm | overruns 0, lateness max 31 µs
"""

import sys
import time
from collections.abc import Callable
from typing import TextIO

import numpy as np

from hil.cia402 import ModeOfOperation, State

#: when stderr is not a terminal, a plain line this often, s
PLAIN_EVERY_S = 10.0
#: a terminal's line is rewritten at most this often, s
TERMINAL_EVERY_S = 0.5
#: the controller counts as silent after this long without a setpoint, s
SILENT_S = 0.1
#: a position column's unit -> (scale to the CNC's unit, that unit)
_CNC_UNIT = {"m": (1e3, "mm"), "rad": (180.0 / np.pi, "deg")}


class RunStatus:
    """The run's state as the recording's rows show it, and its status line.

    Args:
        period_ns: the loop's period, ns.
        units: column -> unit, of the recording's columns (every axis's ``drive_state``
            column names an axis: ``drive_state`` alone for one axis, ``X_drive_state``...).
        stream: where the line goes (stderr by default); a terminal when ``isatty()``.
        clock: monotonic seconds (time.monotonic by default).
        single_axis: the letter of a run's one axis, whose columns carry no prefix.
        grace_ticks: the first ticks, whose overruns the loop counts apart (the line
            counts as the run's report does).
    """

    def __init__(self, period_ns: int, units: dict[str, str], stream: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic, single_axis: str = "axis",
                 grace_ticks: int = 0):
        self.period_ns = period_ns
        self.period_s = period_ns * 1e-9
        self.grace_ticks = grace_ticks
        self.prefixes = [name[:-len("drive_state")] for name in units
                         if name.endswith("drive_state")]
        self.position_unit = {p: _CNC_UNIT.get(units.get(f"{p}plant_table_pos", ""), (1.0, ""))
                              for p in self.prefixes}
        self.label = {p: p.rstrip("_") or single_axis for p in self.prefixes}
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = bool(getattr(self.stream, "isatty", lambda: False)())
        self.clock = clock
        self.shown_at = -np.inf
        self.last_tick = -1
        self.last_setpoint_tick = -1
        self.ticks_without = 0
        self.overruns = 0
        self.lateness_max_ns = 0
        self.axes: dict[str, tuple[int, int, int, float]] = {}

    def add(self, columns: dict[str, np.ndarray]) -> None:
        """Take a chunk of rows (the writer's columns, in tick order)."""
        ticks = columns["tick"]
        if len(ticks) == 0:
            return
        self.last_tick = int(ticks[-1])
        new = np.flatnonzero(columns["sp_new"])
        if len(new):
            # ticks without a new setpoint count from the first setpoint on: before it the
            # controller has not started, which the line says
            first = 0 if self.last_setpoint_tick >= 0 else new[0]
            self.ticks_without += int(len(ticks) - first - len(new))
            self.last_setpoint_tick = int(ticks[new[-1]])
        elif self.last_setpoint_tick >= 0:
            self.ticks_without += len(ticks)
        # an overrun as the loop counts it: the tick ended after the next deadline
        late = ((columns["lateness_ns"] + columns["compute_ns"] > self.period_ns)
                & (ticks >= self.grace_ticks))
        self.overruns += int(np.count_nonzero(late))
        self.lateness_max_ns = max(self.lateness_max_ns, int(columns["lateness_ns"].max()))
        for p in self.prefixes:
            self.axes[p] = (int(columns[f"{p}drive_state"][-1]), int(columns[f"{p}sp_mode"][-1]),
                            int(columns[f"{p}fb_fault"][-1]),
                            float(columns[f"{p}plant_table_pos"][-1]))

    def line(self) -> str:
        """The status line (no newline)."""
        if self.last_tick < 0:
            return "hil run: waiting for the first tick"
        now_s = self.last_tick * self.period_s
        if self.last_setpoint_tick < 0:
            link = "controller: no setpoint yet"
        else:
            ago_s = (self.last_tick - self.last_setpoint_tick) * self.period_s
            link = (f"controller: SILENT for {ago_s:.2f} s" if ago_s > SILENT_S
                    else f"controller: setpoint {ago_s * 1e3:.1f} ms ago")
            link += f", {self.ticks_without} ticks without one"
        parts = [f"hil run: {now_s:.1f} s", link]
        for p, (state, mode, fault, pos) in self.axes.items():
            scale, unit = self.position_unit[p]
            text = f"{self.label[p]} {_state_text(state)} {_mode_text(mode)}"
            if fault:
                text += f" fault 0x{fault:04X}"
            parts.append(f"{text} {pos * scale:.3f} {unit}".rstrip())
        parts.append(f"overruns {self.overruns}, lateness max "
                     f"{self.lateness_max_ns / 1e3:.0f} µs")
        return " | ".join(parts)

    def show(self, final: bool = False) -> None:
        """Write the line if it is due (``final``: now, and end a terminal's line)."""
        now = self.clock()
        every = TERMINAL_EVERY_S if self.terminal else PLAIN_EVERY_S
        if not final and now - self.shown_at < every:
            return
        self.shown_at = now
        try:
            if self.terminal:
                self.stream.write("\r" + self.line() + "\x1b[K" + ("\n" if final else ""))
            else:
                self.stream.write(self.line() + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # the terminal or the pipe is gone: nobody to tell
            pass


def _state_text(value: int) -> str:
    """A CiA 402 state's name as a sentence ("Operation enabled"), or the raw number."""
    try:
        return State(value).name.replace("_", " ").capitalize()
    except ValueError:
        return f"state {value}"


def _mode_text(value: int) -> str:
    """6060h's mode by its short name (CSP), "no mode" for 0, or the raw number."""
    if value == 0:
        return "no mode"
    try:
        return ModeOfOperation(value).name
    except ValueError:
        return f"mode {value}"
