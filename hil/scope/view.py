"""What the scope page shows, without the page: a run folder followed as it grows, its status
(:class:`~hil.runtime.run_status.RunStatus`), its events, the last seconds of the chosen
channels, and the curve for a time span at the screen's resolution (min/max per pixel).

One :class:`ScopeView` per browser tab; :meth:`ScopeView.update` is its whole work, done
about once a second and bounded: at most :data:`~hil.runtime.record_follow.MAX_BATCHES`
new batches are read per update, the buffer holds at most :data:`KEEP_S` s of the chosen
channels, and a span beyond the buffer (the whole of a finished run, a zoom into it) is read
batch by batch into an :class:`~hil.scope.envelope.Envelope` of one bin per pixel.
"""

import io
import os
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from hil.runtime.record_follow import Follower
from hil.runtime.record_reader import Recording
from hil.runtime.record_trace import axis_trace
from hil.runtime.run_status import RunStatus
from hil.scope.envelope import Envelope
from hil.scope.trigger import Trigger

#: the shortest and longest time window, s
WINDOW_MIN_S, WINDOW_MAX_S = 0.1, 60.0
#: the chosen channels' rows kept, s of run: a capture of the longest window around a trigger
#: found up to a window ago
KEEP_S = 2 * WINDOW_MAX_S + 1.0
#: a recording without its end marker that has not grown for this long counts as stopped
#: (a run cut short), s
STOPPED_AFTER_S = 3.0
#: events listed on the page (the newest)
MAX_EVENTS = 200


@dataclass(frozen=True)
class EventRow:
    """One event as the page lists it."""
    t_s: float
    axis: str
    source: str
    kind: str
    code: int
    reason: str


@dataclass
class Curve:
    """The curve to draw: times (s) and name -> values, two points per pixel."""
    t_s: np.ndarray
    values: dict[str, np.ndarray]
    t0_s: float
    t1_s: float


class KeptRows(Mapping):
    """The last rows of some channels (name -> the kept rows' values; ``"tick"`` among
    them), appended in place: each channel's array has room for twice the rows kept, the
    rows that age out are dropped by moving a start index, and the kept rows move to the
    front only when the end is reached -- about once per kept span -- so an update copies
    its new rows, not the whole buffer (121 s of a channel at 8 kHz is 7.7 MB).

    Args:
        columns: the rows to start with (copied), equal lengths.
    """

    def __init__(self, columns: Mapping[str, np.ndarray]):
        self._data = {n: np.array(v) for n, v in columns.items()}
        self._lo = 0
        self._hi = len(self._data["tick"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self._data[name][self._lo:self._hi]

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def extend(self, rows: Mapping[str, np.ndarray], keep_from_tick: float) -> None:
        """Append ``rows`` (every kept channel, ticks after the last kept one) and drop the
        rows before ``keep_from_tick``."""
        self._lo += np.searchsorted(self["tick"], keep_from_tick)
        new = rows["tick"]
        first = np.searchsorted(new, keep_from_tick) if self._lo == self._hi else 0
        old, count = self._hi - self._lo, new.size - first
        room = len(self._data["tick"])
        if self._lo + old + count > room:
            room = max(room, 2 * (old + count))
            for n, v in self._data.items():
                dtype = v.dtype if v.size else rows[n].dtype
                moved = np.empty(room, dtype=dtype) if room > v.size else v
                moved[:old] = v[self._lo:self._hi]
                self._data[n] = moved
            self._lo, self._hi = 0, old
        for n, v in self._data.items():
            v[self._hi:self._hi + count] = rows[n][first:]
        self._hi += count


class ScopeView:
    """A run folder as the page shows it (module docstring).

    Args:
        folder: the run folder (``hil run --record DIR``, ``hil soak``'s run).
        pixels: the plot's width, bins of the curve.
        clock: monotonic seconds (tells a recording that stopped growing).
    """

    def __init__(self, folder, pixels: int = 1200,
                 clock: Callable[[], float] = time.monotonic):
        self.rec = Recording(folder)
        self.period_s = self.rec.period_ns * 1e-9
        self.pixels = pixels
        self.clock = clock
        axes = self.rec.meta.get("axes", [])
        traces = {a["prefix"]: axis_trace(self.rec, a["name"]) for a in axes
                  if "table_per_count" in a}
        self.status = RunStatus(self.rec.period_ns, self.rec.units, stream=io.StringIO(),
                                single_axis=axes[0]["name"] if len(axes) == 1 else "axis",
                                traces=traces)
        self.samples = Follower(self.rec)
        self.event_stream = Follower(self.rec, self.rec.events_path)
        self.events: deque[EventRow] = deque(maxlen=MAX_EVENTS)
        #: events read so far (the list keeps the last MAX_EVENTS of them)
        self.events_read = 0
        self.channels: list[str] = []
        self.trigger: Trigger | None = None
        self.buffer: Mapping[str, np.ndarray] = KeptRows({"tick": np.empty(0, np.int64)})
        self.size = -1
        self.grew_at = clock()
        self.catching_up = False

    # -- what is read -------------------------------------------------------------------

    def watched(self) -> list[str]:
        """The channels whose rows are kept: the chosen ones and the trigger's."""
        names = list(self.channels)
        if self.trigger is not None and self.trigger.channel not in names:
            names.append(self.trigger.channel)
        return names

    def choose(self, channels: list[str], trigger: Trigger | None) -> None:
        """Show ``channels`` (recording columns) and trigger on ``trigger`` (None: free
        running); a channel not kept so far is read back for the last :data:`KEEP_S` s."""
        unknown = [c for c in [*channels, *([trigger.channel] if trigger else [])]
                   if c not in self.rec.names]
        if unknown:
            raise ValueError(f"no column {', '.join(unknown)} in {self.rec.path}")
        self.channels, self.trigger = list(channels), trigger
        kept = {"tick", *self.watched()}
        self.buffer = KeptRows({n: v for n, v in self.buffer.items() if n in kept})
        if kept - self.buffer.keys():
            self._refill()

    def _refill(self) -> None:
        """The buffer read again from the recording: the last :data:`KEEP_S` s of the
        watched channels."""
        names = ["tick", *self.watched()]
        last = self.buffer["tick"][-1] if self.buffer["tick"].size else (
            self.samples.spans[-1].last_tick if self.samples.spans else 0)
        spans = self.samples.spans_between(int(last - KEEP_S / self.period_s), int(last))
        parts = list(self.samples.read(spans, names))
        self.buffer = KeptRows({n: np.concatenate([p[n] for p in parts]) if parts
                                else np.empty(0) for n in names})

    def update(self) -> bool:
        """Read what the run wrote since the last update (bounded); True when rows came."""
        rows = self.samples.poll(list(dict.fromkeys(
            [*self.status.columns(), *self.watched()])))
        self._events()
        size = os.path.getsize(self.rec.path)
        if size != self.size:
            self.size, self.grew_at = size, self.clock()
        self.catching_up = self.samples.full
        if rows is None:
            return False
        self.status.add(rows)
        self.buffer.extend(rows, rows["tick"][-1] - KEEP_S / self.period_s)
        return True

    def _events(self) -> None:
        rows = self.event_stream.poll(["tick", "t_s", "axis", "source", "kind", "code",
                                       "reason"])
        if rows is None:
            return
        for i in range(rows["tick"].size):
            self.events.append(EventRow(float(rows["t_s"][i]), str(rows["axis"][i]),
                                        str(rows["source"][i]), str(rows["kind"][i]),
                                        int(rows["code"][i]), str(rows["reason"][i])))
        self.events_read += rows["tick"].size

    # -- where the run is ---------------------------------------------------------------

    @property
    def end_s(self) -> float:
        """Run time of the last row read, s (0 before any)."""
        return max(self.status.last_tick, 0) * self.period_s

    def state(self) -> str:
        """``live``, ``ended`` (the writer closed the recording) or ``stopped`` (no end
        marker, and no growth for :data:`STOPPED_AFTER_S`: a run cut short, or stalled)."""
        if self.samples.ended:
            return "ended"
        if self.clock() - self.grew_at > STOPPED_AFTER_S and not self.catching_up:
            return "stopped"
        return "live"

    # -- curves -------------------------------------------------------------------------

    def curve(self, t0_s: float, t1_s: float) -> Curve:
        """The chosen channels over [t0_s, t1_s) at one bin per pixel: from the buffer when
        it holds the span, else read from the recording batch by batch."""
        env = Envelope(t0_s, t1_s, self.pixels, self.channels)
        ticks = self.buffer["tick"]
        first = int(t0_s / self.period_s)
        if ticks.size and ticks[0] <= max(first, 0) and all(c in self.buffer
                                                              for c in self.channels):
            # the rows of the span (and a tick either side; the envelope keeps the span's
            # own), not the whole buffer: a 2 s window of a 121 s buffer every second
            lo = np.searchsorted(ticks, first)
            hi = np.searchsorted(ticks, int(np.ceil(t1_s / self.period_s)), side="right")
            env.add(ticks[lo:hi] * self.period_s,
                    {c: self.buffer[c][lo:hi] for c in self.channels})
        else:
            spans = self.samples.spans_between(first, int(np.ceil(t1_s / self.period_s)))
            for rows in self.samples.read(spans, ["tick", *self.channels]):
                env.add(rows["tick"] * self.period_s, rows)
        t_s, _, values = env.curve()
        return Curve(t_s, values, t0_s, t1_s)

    def whole(self) -> Curve:
        """The whole recording read so far (at least a window's length)."""
        return self.curve(0.0, max(self.end_s + self.period_s, WINDOW_MIN_S))

    def trigger_at(self, after_s: float, window_s: float) -> float | None:
        """The first trigger later than ``after_s`` whose capture of ``window_s`` the
        buffer holds whole; None when there is none yet."""
        if self.trigger is None or not self.buffer["tick"].size:
            return None
        # from the last row at or before after_s on (a crossing needs the row before it)
        ticks = self.buffer["tick"]
        lo = max(int(np.searchsorted(ticks, after_s / self.period_s, side="right")) - 1, 0)
        t_s = ticks[lo:] * self.period_s
        at = self.trigger.first(t_s, self.buffer[self.trigger.channel][lo:], after_s)
        if at is None or self.trigger.window(at, window_s)[1] > t_s[-1]:
            return None
        return at
