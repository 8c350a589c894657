"""A triggered servo-trace recorder, as a SINUMERIK servo trace or a dSPACE ControlDesk
capture records: fixed signals, a fixed depth, a trigger and samples kept before it.

Definitions (the tests check each):

* The recording holds exactly ``depth`` samples: ``pre_trigger`` samples before the
  trigger sample, the trigger sample, and ``depth - pre_trigger - 1`` samples after it.
* The trigger sample is the first sample, counted from the ``pre_trigger``-th one on
  (the trigger is armed only once the pre-trigger samples are in the buffer), at which
  the condition holds:

  - ``immediate``: always, so the recording is the first ``depth`` samples;
  - ``level``: the trigger signal crosses ``threshold`` from the previous sample to
    this one — rising: previous < threshold <= this; falling: previous > threshold >=
    this; either: one of the two;
  - ``edge``: the trigger signal differs from its previous sample (a control bit or
    status word changing).

``record`` runs once per controller cycle on a preallocated ring buffer and allocates
no array; once ``done``, further samples are ignored until ``reset``.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

KINDS = ("immediate", "level", "edge")
DIRECTIONS = ("rising", "falling", "either")
TIME_COLUMN = "t_s"


class TraceError(Exception):
    """Base class of the recorder's errors."""


class TraceConfigError(TraceError, ValueError):
    """A trigger or recorder set up with impossible values; the message names them."""


class TraceNotDoneError(TraceError, RuntimeError):
    """The result was asked for before the recording was complete."""


@dataclass(frozen=True)
class Trigger:
    """When a recording starts: ``kind`` immediate, level or edge; ``signal`` the trigger
    signal (level, edge); ``threshold`` in the signal's unit and ``direction`` (level)."""

    kind: str = "immediate"
    signal: str | None = None
    threshold: float = 0.0
    direction: str = "rising"

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise TraceConfigError(f"trigger kind {self.kind!r} not one of {KINDS}")
        if self.direction not in DIRECTIONS:
            raise TraceConfigError(f"trigger direction {self.direction!r} not one of {DIRECTIONS}")
        if (self.kind == "immediate") != (self.signal is None):
            verb = "needs" if self.signal is None else "takes no"
            raise TraceConfigError(f"a {self.kind} trigger {verb} trigger signal")
        if not math.isfinite(self.threshold):
            raise TraceConfigError(f"trigger threshold must be finite, got {self.threshold}")

    @classmethod
    def level(cls, signal: str, threshold: float, direction: str = "rising") -> "Trigger":
        """Trigger when ``signal`` crosses ``threshold`` in ``direction``."""
        return cls("level", signal, float(threshold), direction)

    @classmethod
    def edge(cls, signal: str) -> "Trigger":
        """Trigger when ``signal`` changes from one sample to the next."""
        return cls("edge", signal)


@dataclass(frozen=True)
class Recording:
    """A finished recording: ``names`` of the signals, ``t_s`` of shape (depth,) in
    seconds from the first kept sample, ``data`` name -> read-only array of shape (depth,)
    in the signals' own units, ``trigger_index`` the position of the trigger sample."""

    names: tuple[str, ...]
    t_s: np.ndarray
    data: dict[str, np.ndarray]
    trigger_index: int
    dt_s: float

    @property
    def trigger_time_s(self) -> float:
        """Time of the trigger sample on the ``t_s`` axis."""
        return self.trigger_index * self.dt_s


class TraceRecorder:
    """Records ``signal_names`` every cycle of ``dt_s`` seconds into a ring buffer of
    shape (depth, len(signal_names)), float64, per the module's definitions."""

    def __init__(self, signal_names: Sequence[str], depth: int, pre_trigger: int,
                 trigger: Trigger, dt_s: float) -> None:
        names = tuple(signal_names)
        _check_names(names, trigger)
        if not 0 <= pre_trigger < depth:
            raise TraceConfigError(f"need 0 <= pre_trigger < depth, got {pre_trigger}, {depth}")
        if not dt_s > 0.0:
            raise TraceConfigError(f"sample time must be positive, got {dt_s} s")
        self.names = names
        self.depth = depth
        self.pre_trigger = pre_trigger
        self.trigger = trigger
        self.dt_s = float(dt_s)
        self._buffer = np.zeros((depth, len(names)), dtype=np.float64)
        self._column = -1 if trigger.signal is None else names.index(trigger.signal)
        self._rising = trigger.kind == "level" and trigger.direction in ("rising", "either")
        self._falling = trigger.kind == "level" and trigger.direction in ("falling", "either")
        self.reset()

    def reset(self) -> None:
        """Forget everything recorded and arm again (the buffer is reused)."""
        self._write = 0
        self._seen = 0          # samples taken before the trigger
        self._remaining = 0
        self._previous = math.nan
        self.triggered = False
        self.done = False

    def record(self, values: np.ndarray) -> None:
        """Take one cycle's ``values`` (float64, shape (n_signals,), in signal order):
        copied into the ring buffer, trigger checked; nothing allocated, nothing raised."""
        if self.done:
            return
        self._buffer[self._write] = values
        self._write = (self._write + 1) % self.depth
        if not self.triggered:
            if self._seen >= self.pre_trigger and self._fires(values):
                self.triggered = True
                self._remaining = self.depth - self.pre_trigger
            elif self._column >= 0:
                self._previous = values[self._column]
            self._seen += 1
        if self.triggered:
            self._remaining -= 1
            self.done = self._remaining == 0

    def _fires(self, values: np.ndarray) -> bool:
        """The trigger condition between the previous sample and ``values``."""
        if self._column < 0:
            return True
        now = values[self._column]
        before = self._previous
        if self.trigger.kind == "edge":
            return self._seen > 0 and now != before
        level = self.trigger.threshold
        return ((self._rising and before < level <= now)
                or (self._falling and before > level >= now))

    def result(self) -> Recording:
        """The recording, oldest sample first; only once ``done``."""
        if not self.done:
            raise TraceNotDoneError(f"recording not finished: triggered={self.triggered}, "
                                   f"{self._remaining} samples to go")
        ordered = np.roll(self._buffer, -self._write, axis=0)
        data = {}
        for i, name in enumerate(self.names):
            column = ordered[:, i].copy()
            column.flags.writeable = False
            data[name] = column
        t_s = np.arange(self.depth) * self.dt_s
        t_s.flags.writeable = False
        return Recording(names=self.names, t_s=t_s, data=data,
                         trigger_index=self.pre_trigger, dt_s=self.dt_s)


def _check_names(names: tuple[str, ...], trigger: Trigger) -> None:
    """Signal names are unique, not the time column, and include the trigger signal."""
    if not names:
        raise TraceConfigError("a trace needs at least one signal")
    if len(set(names)) != len(names):
        raise TraceConfigError(f"signal names repeat: {names}")
    if TIME_COLUMN in names:
        raise TraceConfigError(f"{TIME_COLUMN!r} is the time axis, not a signal name")
    if trigger.signal is not None and trigger.signal not in names:
        raise TraceConfigError(f"trigger signal {trigger.signal!r} not among {names}")
