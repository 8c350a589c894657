"""``hil run``'s status line while the run goes on: time, the controller's link, each
axis's state, mode, fault and position, overruns and lateness so far.

It is made in the recording's writer process (:mod:`hil.runtime.record_process`) from the
rows it writes anyway, every flush (0.25 s), so the loop's process does nothing for it.  On
a terminal it is one line rewritten in place; when stderr is a pipe or a file it is a plain
line every :data:`PLAIN_EVERY_S`, so a log stays readable.  The figures lag the loop by
one flush at most.

::

    hil run: 12.3 s | controller: setpoint 0.1 ms ago, 2 ticks without one | X Operation enabled CSP 12.500 mm | overruns 0, lateness max 31 µs

``hil scope``'s status panel is made from the same figures, and a few the line leaves out
(each axis's statusword and following error, the setpoints never applied), which
:class:`RunStatus` counts when it is given the axes' :class:`~hil.runtime.record_trace.
AxisTrace` (``traces``); :meth:`RunStatus.panel` gives them all.
"""

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TextIO

import numpy as np

from hil.cia402 import ModeOfOperation, State

if TYPE_CHECKING:  # the writer process makes the line without the traces
    from hil.runtime.record_trace import AxisTrace

#: when stderr is not a terminal, a plain line this often, s
PLAIN_EVERY_S = 10.0
#: a terminal's line is rewritten at most this often, s
TERMINAL_EVERY_S = 0.5
#: the controller counts as silent after this long without a setpoint, s
SILENT_S = 0.1
#: a position column's unit -> (scale to the CNC's unit, that unit)
_CNC_UNIT = {"m": (1e3, "mm"), "rad": (180.0 / np.pi, "deg")}


@dataclass
class AxisNow:
    """One axis as the latest row shows it (SI; the following error in the trace's unit).

    Attributes:
        state, mode, fault: ``drive_state``, ``sp_mode`` and ``fb_fault`` (603Fh).
        position: ``plant_table_pos``, m or rad.
        statusword: ``fb_statusword`` (6041h); -1 where not counted (no ``traces``).
        following_error, following_error_max: the CSP target 607Ah less the position,
            now and its largest magnitude so far, mm or deg (NaN: not in CSP yet, or not
            counted).
    """
    state: int
    mode: int
    fault: int
    position: float
    statusword: int = -1
    following_error: float = np.nan
    following_error_max: float = np.nan


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
        traces: column prefix -> that axis's servo-trace view: the statusword, the
            following error and the setpoints never applied are counted too (their
            columns: :meth:`columns`).
    """

    def __init__(self, period_ns: int, units: dict[str, str], stream: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic, single_axis: str = "axis",
                 grace_ticks: int = 0, traces: "dict[str, AxisTrace] | None" = None):
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
        self.traces = traces
        self.skipped_setpoints = 0
        self.last_seq = -1
        self.axes: dict[str, AxisNow] = {}

    def columns(self) -> list[str]:
        """The recording columns :meth:`add` reads."""
        names = ["tick", "sp_new", "lateness_ns", "compute_ns"]
        for p in self.prefixes:
            names += [f"{p}drive_state", f"{p}sp_mode", f"{p}fb_fault", f"{p}plant_table_pos"]
        if self.traces is not None:
            names.append("sp_seq")
            for p, trace in self.traces.items():
                names += [f"{p}fb_statusword", *trace.sources()]
        return list(dict.fromkeys(names))

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
            now = AxisNow(int(columns[f"{p}drive_state"][-1]), int(columns[f"{p}sp_mode"][-1]),
                          int(columns[f"{p}fb_fault"][-1]),
                          float(columns[f"{p}plant_table_pos"][-1]))
            if self.traces is not None and p in self.traces:
                self._following(p, now, columns)
            self.axes[p] = now
        if self.traces is not None:
            self._skipped(columns["sp_seq"][new])

    def _following(self, p: str, now: AxisNow, columns: dict[str, np.ndarray]) -> None:
        """``now``'s statusword and following error (CSP target less position, the
        trace's units), the largest so far carried from the axis's last row."""
        trace = self.traces[p]
        rows = trace.convert(columns)
        error = rows[f"pos_set_{trace.unit}"] - rows[f"pos_{trace.unit}"]
        before = self.axes.get(p)
        largest = before.following_error_max if before is not None else np.nan
        finite = np.abs(error[np.isfinite(error)])
        if finite.size:
            largest = float(np.fmax(largest, finite.max()))
        now.statusword = int(columns[f"{p}fb_statusword"][-1])
        now.following_error = float(error[-1])
        now.following_error_max = largest

    def _skipped(self, seqs: np.ndarray) -> None:
        """Count the sequence numbers the applied setpoints skipped (32-bit, wrapping):
        setpoints that came too late and were superseded by a newer one, or never came."""
        if seqs.size == 0:
            return
        seqs = seqs.astype(np.int64)
        chain = np.concatenate(([self.last_seq], seqs)) if self.last_seq >= 0 else seqs
        steps = np.diff(chain) % (1 << 32)
        self.skipped_setpoints += int(np.sum(np.clip(steps - 1, 0, None)))
        self.last_seq = int(seqs[-1])

    def since_setpoint_s(self) -> float:
        """Run time since the last new setpoint, s (inf: none yet)."""
        if self.last_setpoint_tick < 0:
            return np.inf
        return (self.last_tick - self.last_setpoint_tick) * self.period_s

    def panel(self) -> dict:
        """Every figure of the status: ``t_s``; ``link``: ``started``, ``silent`` (no
        setpoint for longer than :data:`SILENT_S`), ``since_setpoint_s``,
        ``ticks_without``, ``skipped_setpoints``; ``axes``: label -> (:class:`AxisNow`,
        its position in the CNC's unit, that unit); ``overruns``; ``lateness_max_us``."""
        ago = self.since_setpoint_s()
        return {"t_s": max(self.last_tick, 0) * self.period_s,
                "link": {"started": self.last_setpoint_tick >= 0, "silent": ago > SILENT_S,
                         "since_setpoint_s": ago, "ticks_without": self.ticks_without,
                         "skipped_setpoints": self.skipped_setpoints},
                "axes": {self.label[p]: (now, now.position * self.position_unit[p][0],
                                         self.position_unit[p][1])
                         for p, now in self.axes.items()},
                "overruns": self.overruns, "lateness_max_us": self.lateness_max_ns / 1e3}

    def line(self) -> str:
        """The status line (no newline)."""
        if self.last_tick < 0:
            return "hil run: waiting for the first tick"
        now_s = self.last_tick * self.period_s
        if self.last_setpoint_tick < 0:
            link = "controller: no setpoint yet"
        else:
            ago_s = self.since_setpoint_s()
            link = (f"controller: SILENT for {ago_s:.2f} s" if ago_s > SILENT_S
                    else f"controller: setpoint {ago_s * 1e3:.1f} ms ago")
            link += f", {self.ticks_without} ticks without one"
        parts = [f"hil run: {now_s:.1f} s", link]
        for p, now in self.axes.items():
            scale, unit = self.position_unit[p]
            text = f"{self.label[p]} {state_text(now.state)} {mode_text(now.mode)}"
            if now.fault:
                text += f" fault 0x{now.fault:04X}"
            parts.append(f"{text} {now.position * scale:.3f} {unit}".rstrip())
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


def state_text(value: int) -> str:
    """A CiA 402 state's name as a sentence ("Operation enabled"), or the raw number."""
    try:
        return State(value).name.replace("_", " ").capitalize()
    except ValueError:
        return f"state {value}"


def mode_text(value: int) -> str:
    """6060h's mode by its short name (CSP), "no mode" for 0, or the raw number."""
    if value == 0:
        return "no mode"
    try:
        return ModeOfOperation(value).name
    except ValueError:
        return f"mode {value}"
