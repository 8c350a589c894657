"""``hil replay RUN``: re-run a recorded ``hil run`` offline on exactly the setpoints it
applied, and compare every drive word and plant output with the recording.

What makes the replay causal and exact: it does not re-implement the emulator's tick, it
*runs* it.  An :class:`~hil.runtime.emulator.Emulator` is built from the recording's
metadata -- the machine files' text (:func:`~hil.replay.machine_files.machine_files`), the
runtime settings (rate, watchdog limit, start position) -- so its plants, the
:data:`~hil.runtime.emulator.WARMUP_CYCLES` warm-up on the real arrays and the reset after
it, its drives, watchdog and recorder are the run's.  Its adapter is a
:class:`RecordedSetpoints`: each tick's ``recv_setpoint`` writes the setpoint the recording
says the drive applied in that tick (``sp_*`` of the row, every field the drive reads, and
``sp_seq``), says whether it was new (``sp_new``: the watchdog's "heard") and which axes the
adapter refused (``sp_refused``: the drive latches a fault for each).  Then
:meth:`Emulator.step` is called for every recorded ``tick`` in order, and the emulator's own
:class:`~hil.runtime.recording.Recorder` turns the result into rows of the recording's
columns and dtypes, which are compared with the file's.

Compared: per axis ``fb_statusword``, ``fb_fault``, ``drive_state``, ``drive_enable`` and
every ``plant_*`` output.  The relative difference of a value is
``|replay - recorded| / max(|recorded| over the channel)`` -- relative to the channel's
largest magnitude in the run, so that a zero crossing does not divide by zero -- and a
channel that is 0 throughout compares absolutely; NaN equals NaN.  The replay matches when
the largest difference is at most the tolerance (:data:`TOLERANCE`, 1e-9); the worst
channel and tick are reported either way.  Not compared: the loop's measurements and the
round-trip stamps (wall-clock times, which the replay does not have) and the setpoint
columns (the replay's input).

Fault injections (:mod:`hil.inject`) are replayed as they acted: those of the machine
files and the ``--inject`` flags are rebuilt with the emulator, and each request the
adapter handed on is handed on again in the tick the run took it (the recording's
``inject`` events of kind ``request``).

What the replay cannot reproduce, and refuses: a run over ``can://`` (its link conditions
-- heartbeat, NMT -- and SDO writes to the drive's parameters are not in the recording), a
recording without the ``sp_refused`` column (written before it existed), and ticks the
emulator ran but could not record (its ring full: ``tick`` jumps although the overrun
policy was not ``skip``).  A recording cut short (SIGKILL) is replayed up to its last
complete batch.
"""

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from hil.progress import Progress
from hil.replay.machine_files import ReplayError, machine_files
from hil.runtime.common import RuntimeInputError, StopFlag
from hil.runtime.emulator import Emulator
from hil.runtime.emulator_config import RuntimeConfig
from hil.runtime.record_reader import Recording, RecordingError
from hil.runtime.recording import SP_FLOATS
from io_adapters.messages import InjectRequest, axis_records
from plant.errors import ConfigError
from plant.machines import load_machine_set

#: the largest relative difference (see the module docstring) of a matching replay
TOLERANCE = 1e-9
#: per-axis columns compared (without the axis prefix); plant_* are added per run
DRIVE_WORDS = ("fb_statusword", "fb_fault", "drive_state", "drive_enable")
#: the setpoint's integer fields the recording holds, per axis
_SP_INTS = ("controlword", "mode")


@dataclass(frozen=True)
class ChannelDifference:
    """The largest relative difference of one channel.

    Attributes:
        channel: the column.
        rel_diff: its largest relative difference (see the module docstring).
        tick: the tick it is at (-1: none differs).
        recorded, replayed: the two values there.
    """
    channel: str
    rel_diff: float
    tick: int
    recorded: float
    replayed: float


@dataclass
class ReplayResult:
    """How the replay compares with the recording.

    Attributes:
        run: the run folder.
        ticks: rows replayed and compared.
        channels: columns compared.
        tolerance: the largest relative difference of a match.
        worst: the channel with the largest difference.
        truncated: the recording was cut short (replayed up to its last complete batch).
        per_channel: channel -> its largest relative difference.
    """
    run: str
    ticks: int
    channels: int
    tolerance: float
    worst: ChannelDifference
    truncated: bool
    per_channel: dict[str, float] = field(default_factory=dict)

    @property
    def matches(self) -> bool:
        """Every compared value within the tolerance."""
        return self.worst.rel_diff <= self.tolerance

    def line(self) -> str:
        """One line: match or not, the worst channel and tick."""
        w = self.worst
        verdict = "matches" if self.matches else "does NOT match"
        where = ("every value identical" if w.tick < 0 else
                 f"worst {w.channel} at tick {w.tick}: recorded {w.recorded:.17g}, replayed "
                 f"{w.replayed:.17g}")
        return (f"replay {verdict} the recording: max relative difference "
                f"{w.rel_diff:.3g} (tolerance {self.tolerance:g}) over {self.ticks} ticks "
                f"and {self.channels} channels; {where}")

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {**asdict(self), "matches": self.matches}


class RecordedSetpoints:
    """The emulator's adapter during a replay: hands :meth:`Emulator.step` the setpoint
    the recording says row :attr:`row` applied (a device-side endpoint's interface as the
    step uses it; it sends nothing).

    Args:
        cols: the recording's columns (name -> array over the rows).
        prefixes: the per-axis column prefixes ("" on a single axis).
        requests: the fault-injection requests the adapter handed on, by tick
            (:func:`injection_requests`).
    """

    heard_for_s = 0.0  # udp:// and serial://: a setpoint stands for its tick only

    def __init__(self, cols: dict[str, np.ndarray], prefixes: tuple[str, ...],
                 requests: dict[int, list[InjectRequest]] | None = None):
        self.row = 0
        self.refused_axes = 0
        self.injections: list[InjectRequest] = []
        self._requests = requests or {}
        self._tick = cols["tick"]
        self._new = cols["sp_new"]
        self._seq = cols["sp_seq"]
        self._refused = cols["sp_refused"]
        self._floats = [[(name, cols[f"{p}sp_{name}"]) for name in SP_FLOATS] for p in prefixes]
        self._ints = [[(name, cols[f"{p}sp_{name}"]) for name in _SP_INTS] for p in prefixes]

    def recv_setpoint(self, into, timeout_s: float | None) -> bool:
        """Row :attr:`row`'s setpoint into ``into``; True when it was new in that tick."""
        i = self.row
        into.seq = int(self._seq[i])
        for sp, floats, ints in zip(axis_records(into), self._floats, self._ints):
            sp.seq = into.seq
            for name, values in floats:
                setattr(sp, name, float(values[i]))
            for name, values in ints:
                setattr(sp, name, int(values[i]))
        self.refused_axes = int(self._refused[i])
        self.injections.extend(self._requests.get(int(self._tick[i]), ()))
        return bool(self._new[i])

    def send_feedback(self, fb) -> bool:
        """Nothing to send to: the feedback is compared through the recorder."""
        return True

    def link_conditions(self, axis: int) -> int:
        """udp:// and serial:// have none."""
        return 0


def injection_requests(rec: Recording) -> dict[int, list[InjectRequest]]:
    """The run-time fault-injection requests of ``rec`` (its ``inject`` events of kind
    ``request``) by the tick they were taken in, in order."""
    ev = rec.events()
    axes = [a["name"] for a in rec.meta["axes"]]
    out: dict[int, list[InjectRequest]] = {}
    for tick, src, kind, axis, reason in zip(ev["tick"], ev["source"], ev["kind"],
                                             ev["axis"], ev["reason"]):
        if src == "inject" and kind == "request":
            r = json.loads(reason)
            out.setdefault(int(tick), []).append(InjectRequest(axes.index(axis), r["fault"],
                                                               r["settings"]))
    return out


def _runtime(meta: dict, machine_file: Path, where: str) -> RuntimeConfig:
    """The run's runtime settings, with the rebuilt machine file, without scheduling."""
    rt = dict(meta.get("runtime") or {})
    try:
        return RuntimeConfig(**{**rt, "machine_file": machine_file,
                                "run_dir": Path(rt.get("run_dir", ".")), "realtime": False,
                                "cpu": None, "duration_s": None})
    except (TypeError, RuntimeInputError) as e:
        raise ReplayError(f"{where}: the runtime settings in the metadata do not load: "
                          f"{e}") from e


def _check_ticks(ticks: np.ndarray, policy: str, where: str, stalls: set[int]) -> None:
    """Refuse a gap in the ticks that was not a deadline dropped (the ``skip`` policy, or
    after a stall: the ``stalls`` events' ticks)."""
    gaps = [g for g in np.flatnonzero(np.diff(ticks) != 1) if int(ticks[g]) not in stalls]
    if gaps and policy != "skip":
        k = int(ticks[gaps[0]])
        raise ReplayError(f"{where}: ticks {k + 1}..{int(ticks[gaps[0] + 1]) - 1} ran but were "
                          f"not recorded (the recording's ring was full); the setpoints they "
                          f"applied are unknown, so the run cannot be replayed")


class _Comparison:
    """The running maxima of the relative differences, channel by channel."""

    def __init__(self, recorded: dict[str, np.ndarray], names: list[str]):
        self.recorded = recorded
        self.names = names
        self.scale = {n: float(np.nanmax(np.abs(recorded[n].astype(np.float64)), initial=0.0))
                      for n in names}
        self.worst = {n: ChannelDifference(n, 0.0, -1, math.nan, math.nan) for n in names}

    def take(self, start: int, replayed: dict[str, np.ndarray], ticks: np.ndarray) -> None:
        """Rows ``start`` .. of the recording against ``replayed`` (name -> rows)."""
        for n in self.names:
            b = replayed[n].astype(np.float64)
            a = self.recorded[n][start:start + b.size].astype(np.float64)
            diff = np.abs(b - a)
            diff[np.isnan(a) & np.isnan(b)] = 0.0
            diff[np.isnan(diff)] = math.inf
            rel = diff / self.scale[n] if self.scale[n] > 0.0 else diff
            j = int(np.argmax(rel))
            if rel[j] > self.worst[n].rel_diff:
                self.worst[n] = ChannelDifference(n, float(rel[j]), int(ticks[start + j]),
                                                  float(a[j]), float(b[j]))

    def overall(self) -> ChannelDifference:
        return max(self.worst.values(), key=lambda d: d.rel_diff)


def stall_ticks(rec: Recording) -> set[int]:
    """The ticks of ``rec``'s loop stalls (``loop`` events of kind ``stall``), after each
    of which the loop dropped the deadlines it had missed."""
    ev = rec.events()
    return {int(t) for t, src, kind in zip(ev["tick"], ev["source"], ev["kind"])
            if src == "loop" and kind == "stall"}


def replay_run(folder: Path | str, tolerance: float = TOLERANCE) -> ReplayResult:
    """Replay the run in ``folder`` and compare it with its recording (see the module
    docstring); raises :class:`ReplayError` for a run that cannot be replayed."""
    folder = Path(folder)
    try:
        rec = Recording(folder)
        cols = rec.read()
        requests = injection_requests(rec)
    except RecordingError as e:
        raise ReplayError(str(e)) from e
    where, meta = str(rec.path), rec.meta
    if "sp_refused" not in cols:
        raise ReplayError(f"{where}: no sp_refused column (recorded before hil replay "
                          f"existed); the refused setpoints are unknown")
    if str(meta.get("adapter", "")).startswith("can://"):
        raise ReplayError(f"{where}: a can:// run ({meta['adapter']}): its link conditions "
                          f"and SDO writes are not recorded, so it cannot be replayed")
    ticks = cols["tick"]
    prefixes = tuple(a["prefix"] for a in meta["axes"])
    compared = [p + n for p in prefixes for n in DRIVE_WORDS] + [
        n for n in rec.names if any(n.startswith(p + "plant_") for p in prefixes)]
    with machine_files(meta, where) as machine_file:
        rc = _runtime(meta, machine_file, where)
        _check_ticks(ticks, rc.overrun, where, stall_ticks(rec))
        try:
            with Progress("replay: building the plant (a cold cache compiles it)",
                          ticking=True):
                emu = Emulator(rc, load_machine_set(machine_file), StopFlag(), log=lambda m: None)
        except (ConfigError, RuntimeInputError) as e:
            raise ReplayError(f"{where}: the recorded machine files do not load: {e}") from e
    if emu.timing.period_ns != rec.period_ns:
        raise ReplayError(f"{where}: period {emu.timing.period_ns} ns rebuilt, "
                          f"{rec.period_ns} ns recorded")
    endpoint = RecordedSetpoints(cols, prefixes, requests)
    emu.endpoint = endpoint
    recorder, cmp = emu.recorder, _Comparison(cols, compared)
    n = ticks.size
    with Progress("replay", total=n) as shown:
        for i in range(n):
            endpoint.row = i
            emu.step(int(ticks[i]))
            recorder.end_tick(int(ticks[i]), 0, 0)
            if recorder.committed - recorder.drained == recorder.slots or i == n - 1:
                start, stop = recorder.pending()
                cmp.take(start, recorder.columns(start, stop), ticks)
                recorder.release(stop)
            shown.update(i + 1)
    return ReplayResult(str(folder), n, len(compared), tolerance, cmp.overall(),
                        rec.truncated, {k: v.rel_diff for k, v in cmp.worst.items()})
