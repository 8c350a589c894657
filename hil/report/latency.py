"""Latency and jitter report of one emulator run: ``hil report RUN [--controller DIR]``.

:func:`load_run` reads a run folder into a :class:`RunData`, pairing its round trips with
the controller's recording when given one; :func:`build_report` reduces it to a JSON-ready
dict; :func:`write_report` writes ``report_latency.json``, ``report.md``,
``latency_hist.png`` (wake-up latency and lateness after the spin, each in its own panel
beside cyclictest's) and, given the run, ``latency_time.png`` (lateness and compute time
over the run) into a folder.  :func:`report_run` does all of it, with an optional
cyclictest baseline at the run's period (:mod:`hil.report.baseline`).  The loop's
wake-up latency and its lateness after the spin are each set beside cyclictest's
(:mod:`hil.report.wakeup`): the recording's lateness is measured after the loop's spin,
cyclictest's latency before any, so they are not compared directly.

Percentiles are nearest rank, as :mod:`hil.rt` computes them
(:meth:`hil.rt.loop.Percentiles.of_ns_in_us`): the p-th percentile of n samples is the
smallest sample with at least p % of them at or below it, i.e. the ``ceil(p/100 * n)``-th
smallest.  Every figure is over the ticks that ran (dropped ticks excluded).

The run folder
--------------
``recording.arrows`` (:mod:`hil.runtime.record_reader`), one row per tick that ran, read
here into one slot per deadline the loop covered (tick k in slot k)::

    tick           int64     the deadline index of the row
    lateness_ns    int64[n]  wake-up time - deadline, ns; NO_VALUE (int64 min) where no
                             row has the tick: dropped by the ``skip`` overrun policy, or
                             not recorded (the recording's writer fell behind)
    compute_ns     int64[n]  end of the step - wake-up time, ns; NO_VALUE likewise

and, when the run had an adapter, four round-trip stamps, all four or none
(``time.monotonic_ns()`` values; 0 = no stamp).  Only the tick that first used a newly
received setpoint carries stamps; every other row is 0 in all four::

    tick_start_ns  device clock at the start of that tick's step (read first thing in it)
    sp_t_ns        Setpoint.t_ns: controller clock when the controller sent the setpoint
    sp_rx_ns       Setpoint.rx_ns: device clock when the setpoint arrived: on UDP the
                   kernel's receive stamp (io_adapters.udp), on serial when the adapter
                   returned it
    fb_t_ns        Feedback.t_ns: device clock when that tick's feedback was sent

The fifth, ``fb_rx_ns`` (Feedback.rx_ns: controller clock when that feedback arrived), is
the controller's: 0 (unknown) until the pairing below fills it.

``report.json``, a JSON object; the keys read here (others are ignored)::

    "loop":       LoopStats.as_dict(); "period_ns", "ticks", "overruns", "skipped" are read
    "scheduling": SchedulingReport.as_dict()
    "adapter":    {"name": str (e.g. the URL), "stats": dataclasses.asdict(AdapterStats)},
                  or null / absent for a run without one
    "recording":  {"ticks_not_recorded": int}; optional (0)
    "host":       hil.report.host.host_fingerprint() taken during the run; optional (the
                  report then takes the fingerprint of the machine it runs on)

``loop.ticks + loop.skipped`` must equal the slots (the last row's tick + 1), and the
empty slots ``loop.skipped + recording.ticks_not_recorded``.

A run folder without ``report.json`` is a run cut short (the emulator killed, or
crashed): the report is made of what the recording holds, and says so (:func:`load_run`);
so is one whose recording is corrupt at a batch, up to that batch.

The controller's folder
-----------------------
``controller.npz`` of ``hil controller --out DIR``
(:data:`hil.runtime.controller_proc.INT_COLUMNS`), int64[m] each, one row per controller
tick it recorded (from the program's start), 0 in all three on a tick without new
feedback::

    fb_sp_t_ns     Feedback.sp_t_ns: the t_ns of the setpoint that feedback answers
    fb_t_ns        Feedback.t_ns: device clock when the drive sent it
    fb_rx_ns       Feedback.rx_ns: controller clock when it arrived

Pairing (``load_run(RUN, controller=DIR)``): a run tick with stamps takes ``fb_rx_ns`` from
the row whose ``fb_sp_t_ns`` is its ``sp_t_ns`` and whose ``fb_t_ns`` is its ``fb_t_ns``:
the very feedback that tick sent (``sp_t_ns`` alone is not enough: each feedback until the
next setpoint arrives echoes the same one; a feedback is accepted once, so one row at
most matches).  A run tick no row matches keeps ``fb_rx_ns`` 0 (its total and
transport stay unknown, left out of their figures) and is counted as an unmatched tick:
the controller recorded no row then (the alignment and enable sequence before its
recording, the disable after it), or it never read that feedback (lost, or superseded by
a newer one before its tick).  A row no tick matches is counted as an unmatched row: the
drive sent that feedback on a tick without a new setpoint.  The recording is not
rewritten.

The round trip and its parts
----------------------------
Per tick k with stamps (all ns; "controller" and "device" clocks may be different
machines, so only differences on one clock are taken)::

    total_ns     = fb_rx_ns - sp_t_ns              controller clock: setpoint sent to
                                                   feedback received
    hold_ns      = fb_t_ns - sp_rx_ns              device clock: how long the drive held it
    transport_ns = total_ns - hold_ns              (= Feedback.round_trip_ns())
    wait_ns      = tick_start_ns - sp_rx_ns        setpoint's arrival to the start of the
                                                   tick that used it
    compute_ns   = compute_ns[k]                   the tick's compute time

so ``total = transport + wait + compute + (fb_t_ns - tick_start_ns - compute_ns[k])``; the
last term is the end of the step to the send, negative when the feedback goes out before
the step ends.  ``total`` and ``transport`` need ``fb_rx_ns``; ``wait`` and ``compute`` do
not.  "Arrival" is ``Setpoint.rx_ns``: on UDP the kernel's stamp, moved to the monotonic
clock never late and at most ``io_adapters.udp.RealtimeToMonotonic.window_ns`` early, so a
setpoint that arrived before its tick has a wait >= 0.  A wait is negative only for a
setpoint that arrived after its tick had started and before the daemon polled for it (at
most the start of the step to the poll: microseconds, more when the step was preempted
there), or where arrival is when the adapter returned the
setpoint (serial; UDP where the kernel gives no stamp): then the time it waited for the
tick counts as transport.
"""

import json
import math
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from hil.progress import Progress
from hil.report.baseline import CyclictestBaseline, run_cyclictest_baseline
from hil.report.host import host_fingerprint
from hil.report.wakeup import (
    lateness_after_spin_us,
    loop_wakeup_known_ns,
    spin_ns,
    wakeup_report,
)
from hil.rt.cyclictest import CyclictestError
from hil.rt.loop import SKIPPED, Percentiles
from hil.rt.scheduling import last_cpu
from hil.runtime.emulator_config import GRACE_S
from hil.runtime.record_reader import Recording, RecordingError
from hil.runtime.run_folder import RECORDING, REPORT
from hil.runtime.stream_file import FORMAT
from plant.files import read_text

CONTROLLER_NPZ = "controller.npz"
#: the controller.npz columns the pairing reads
CONTROLLER_KEYS = ("fb_sp_t_ns", "fb_t_ns", "fb_rx_ns")
REPORT_JSON = "report_latency.json"
REPORT_MD = "report.md"
REPORT_PNG = "latency_hist.png"
TIMELINE_PNG = "latency_time.png"
#: a slot with no value: the loop's marker of a dropped tick, also used for a tick
#: without a round trip
NO_VALUE = SKIPPED
STAMP_KEYS = ("tick_start_ns", "sp_t_ns", "sp_rx_ns", "fb_t_ns", "fb_rx_ns")
#: the stamps a recording holds (``fb_rx_ns`` is the controller's)
RECORDED_STAMPS = STAMP_KEYS[:4]
PERCENTILE_DEFINITION = "nearest rank: the ceil(p/100 * n)-th smallest of n samples"
#: the histograms: log-spaced bins from HIST_LOW_US up, HIST_BINS_PER_DECADE per decade
HIST_LOW_US = 0.1
#: a run's report.json is a few kilobytes; larger is refused unread, bytes
MAX_REPORT_BYTES = 10_000_000
HIST_BINS_PER_DECADE = 20


class ReportError(ValueError):
    """A run folder that cannot be read: a missing file or key, or arrays that disagree.
    The message names the file and the key."""


@dataclass(frozen=True, eq=False)
class RoundTrip:
    """The setpoint-to-feedback round trip, split as the module docstring defines, one
    slot per tick (``NO_VALUE`` where a tick has no round trip or that part is unknown).

    Attributes:
        total_ns: setpoint sent to feedback received, controller clock.
        transport_ns: ``total_ns`` less the time the drive held the setpoint.
        wait_ns: the setpoint's arrival to the start of the tick that used it.
        compute_ns: that tick's compute time.
    """
    total_ns: np.ndarray
    transport_ns: np.ndarray
    wait_ns: np.ndarray
    compute_ns: np.ndarray


@dataclass(frozen=True)
class Pairing:
    """The run's round trips against a controller's rows (module docstring, Pairing).

    Attributes:
        controller: the controller's folder.
        rows: its rows with a new feedback's stamps.
        matched: run ticks with stamps that took their ``fb_rx_ns`` from a row.
        unmatched_ticks: run ticks with stamps no row matched.
        unmatched_rows: rows no run tick matched.
    """
    controller: str
    rows: int
    matched: int
    unmatched_ticks: int
    unmatched_rows: int


@dataclass(frozen=True, eq=False)
class RunData:
    """What a latency report is made from (see the module docstring for the files).

    Attributes:
        period_ns: the loop's period.
        lateness_ns, compute_ns: per tick, ``NO_VALUE`` where the tick was dropped.
        overruns: overruns after the grace period.
        skipped: ticks dropped by the ``"skip"`` overrun policy (missed ticks).
        scheduling: ``SchedulingReport.as_dict()``; empty when not known (a run cut
            short).
        adapter: the adapter's name, or None for a run without one.
        adapter_stats: its ``AdapterStats`` as a dict, or None (no adapter, or a run
            cut short).
        round_trip: the per-tick round trip, or None when the run recorded no stamps.
        host: the host fingerprint taken during the run, or None.
        pairing: how the round trips were paired with a controller's folder, or None
            when they were not.
        notes: what the report cannot vouch for, in words: a run cut short, a corrupt
            batch, a recording without checksums (:func:`load_run`).
        corrupt: the recording's corrupt batch the figures stop at (the error's
            message), or None.
    """
    period_ns: int
    lateness_ns: np.ndarray
    compute_ns: np.ndarray
    overruns: int
    skipped: int
    scheduling: dict
    adapter: str | None = None
    adapter_stats: dict | None = None
    round_trip: RoundTrip | None = None
    host: dict | None = None
    pairing: Pairing | None = None
    notes: tuple[str, ...] = ()
    corrupt: str | None = None


# -- reading a run folder ------------------------------------------------------------------

def _count(section: dict, key: str, where: str, minimum: int = 0) -> int:
    value = section.get(key)
    if type(value) is not int or value < minimum:
        raise ReportError(f"{where}: {key!r} must be an integer >= {minimum}, got {value!r}")
    return value


def _int_array(arrays: dict, key: str, n: int | None, where: Path) -> np.ndarray:
    a = arrays[key]
    if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
        raise ReportError(f"{where}: {key!r} must be a 1-D integer array, got {a.dtype} "
                          f"of shape {a.shape}")
    if n is not None and a.size != n:
        raise ReportError(f"{where}: {key!r} has {a.size} slots, lateness_ns {n}")
    return a.astype(np.int64)


def _stamped(stamps: dict[str, np.ndarray], compute_ns: np.ndarray) -> np.ndarray:
    """Ticks with a round trip: the four device-side stamps and a compute time."""
    return ((stamps["tick_start_ns"] != 0) & (stamps["sp_t_ns"] != 0)
            & (stamps["sp_rx_ns"] != 0) & (stamps["fb_t_ns"] != 0) & (compute_ns != NO_VALUE))


def round_trip_from_stamps(stamps: dict[str, np.ndarray],
                           compute_ns: np.ndarray) -> RoundTrip:
    """The parts of the module docstring from the five stamp arrays (0 = no stamp)."""
    tick, sp_t, sp_rx, fb_t, fb_rx = (stamps[k] for k in STAMP_KEYS)
    has = _stamped(stamps, compute_ns)
    known = has & (fb_rx != 0)
    total = np.where(known, fb_rx - sp_t, NO_VALUE)
    transport = np.where(known, total - (fb_t - sp_rx), NO_VALUE)
    return RoundTrip(total_ns=total, transport_ns=transport,
                     wait_ns=np.where(has, tick - sp_rx, NO_VALUE),
                     compute_ns=np.where(has, compute_ns, NO_VALUE))


def load_controller_stamps(folder: Path | str) -> dict[str, np.ndarray]:
    """The pairing columns of ``controller.npz`` in ``folder`` (module docstring).

    Raises:
        ReportError: the file is missing or unreadable, or a column missing or not 1-D
            integers of one length.
    """
    path = Path(folder) / CONTROLLER_NPZ
    try:
        with np.load(path) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError) as e:
        raise ReportError(f"{path}: cannot read the controller's recording: {e}") from e
    missing = [k for k in CONTROLLER_KEYS if k not in arrays]
    if missing:
        raise ReportError(f"{path}: no {missing} (has {sorted(arrays)}; recorded by an "
                          f"older hil controller?)")
    first = _int_array(arrays, CONTROLLER_KEYS[0], None, path)
    return {k: _int_array(arrays, k, first.size, path) for k in CONTROLLER_KEYS}


def pair_with_controller(stamps: dict[str, np.ndarray], compute_ns: np.ndarray,
                         controller: dict[str, np.ndarray],
                         name: str) -> tuple[np.ndarray, Pairing]:
    """``fb_rx_ns`` of the run with the controller's stamps filled in where a row matches
    (module docstring, Pairing), and the counts; ``controller`` as
    :func:`load_controller_stamps` returns it, ``name`` its folder."""
    rows = controller["fb_sp_t_ns"] != 0
    rx_of = dict(zip(zip(controller["fb_sp_t_ns"][rows].tolist(),
                         controller["fb_t_ns"][rows].tolist()),
                     controller["fb_rx_ns"][rows].tolist()))
    fb_rx = stamps["fb_rx_ns"].copy()
    ticks = np.flatnonzero(_stamped(stamps, compute_ns))
    keys = zip(stamps["sp_t_ns"][ticks].tolist(), stamps["fb_t_ns"][ticks].tolist())
    matched = 0
    for k, key in zip(ticks.tolist(), keys):
        rx = rx_of.pop(key, None)
        if rx is not None:
            fb_rx[k] = rx
            matched += 1
    return fb_rx, Pairing(controller=name, rows=int(rows.sum()), matched=matched,
                          unmatched_ticks=ticks.size - matched, unmatched_rows=len(rx_of))


def _slots(columns: dict[str, np.ndarray], keys, n: int) -> dict[str, np.ndarray]:
    """Each of ``keys`` in one slot per deadline (the row of tick k in slot k); where no
    row has the tick, NO_VALUE for the loop's columns and 0 (no stamp) for the stamps."""
    out = {}
    tick = columns["tick"]
    for key in keys:
        slots = np.full(n, NO_VALUE if key in ("lateness_ns", "compute_ns") else 0, np.int64)
        slots[tick] = columns[key]
        out[key] = slots
    return out


def _read_recording(folder: Path) -> tuple[Recording, dict[str, np.ndarray], bool]:
    """``folder``'s recording, its loop's columns and the stamps (when recorded), up to a
    corrupt batch (:attr:`Recording.corrupt <hil.runtime.record_reader.Recording>` then
    says which), and whether it has the stamps."""
    try:
        rec = Recording(folder)
        present = [k for k in RECORDED_STAMPS if k in rec.names]
        if present and len(present) != len(RECORDED_STAMPS):
            raise ReportError(f"{rec.path}: round-trip stamps need all of "
                              f"{list(RECORDED_STAMPS)}, found only {present}")
        stamped = bool(present)
        columns = rec.read(["tick", "lateness_ns", "compute_ns", *present],
                           stop_at_corrupt=True)
    except RecordingError as e:
        raise ReportError(str(e)) from e
    tick = columns["tick"]
    if tick.size and (tick.min() < 0 or np.any(np.diff(tick) <= 0)):
        raise ReportError(f"{folder / RECORDING}: 'tick' must increase from 0")
    return rec, columns, stamped


def _counts_from_recording(rec: Recording, columns: dict[str, np.ndarray],
                           n: int) -> tuple[int, int]:
    """(overruns, skipped) as the loop would have counted them, from the rows of
    ``columns`` over ``n`` deadlines, for a run without report.json or whose recording
    stops at a corrupt batch: a tick overran when its lateness plus compute time passed the
    period (:mod:`hil.rt.loop`), counted after the first GRACE_S; under the ``skip``
    policy the deadlines without a row are skipped ones, less the ticks the events say
    were not recorded; under the others the ticks the ``loop``/``stall`` events say were
    dropped after a stall."""
    period = rec.period_ns
    late = columns["lateness_ns"] + columns["compute_ns"] > period
    grace = round(GRACE_S * 1e9 / period)
    overruns = int(np.count_nonzero(late & (columns["tick"] >= grace)))
    try:
        ev = rec.events(stop_at_corrupt=True)
    except RecordingError:  # no events stream: every gap counts as skipped
        ev = {"source": np.empty(0), "kind": np.empty(0), "count": np.empty(0)}

    def count(source: str, kind: str) -> int:
        return int(ev["count"][(ev["source"] == source) & (ev["kind"] == kind)].sum())

    if (rec.meta.get("runtime") or {}).get("overrun") != "skip":
        return overruns, count("loop", "stall")
    lost = count("recording", "ticks not recorded")
    return overruns, max(0, n - columns["tick"].size - lost)


def _notes(rec: Recording, cut_short: bool) -> list[str]:
    """What the report cannot vouch for, one sentence or two each."""
    notes = []
    rows = f"the ticks {RECORDING} holds" + (
        " (up to its last complete batch: the stream was cut off)" if rec.truncated else "")
    if cut_short:
        notes.append(f"Cut short: no {REPORT} (the emulator did not end normally).  The "
                     f"figures are of {rows}; the overruns are counted from its rows "
                     f"(lateness + compute time > period, after the first {GRACE_S:g} s); "
                     f"the scheduling granted and the adapter's counters are not known.")
    for name, error in rec.corrupt.items():
        notes.append(f"Corrupt: {error}." + ("  The figures are of the ticks before it; the "
                                             "overruns are counted from their rows."
                                             if name == RECORDING else ""))
    if not rec.checksums:
        notes.append(f"{RECORDING} carries no checksums (written before the format "
                     f"{FORMAT!r}): a corrupt batch could not be told.")
    return notes


def load_run(folder: Path | str, controller: Path | str | None = None) -> RunData:
    """Read ``recording.arrows`` and ``report.json`` of a run folder (keys: module
    docstring), and pair its round trips with ``controller.npz`` in ``controller`` when
    given.

    A run cut short (no ``report.json``: the emulator was killed, or crashed) is read
    from its recording alone: the period from its metadata, the overruns and skipped
    ticks counted from its rows (:func:`_counts_from_recording`), no scheduling, adapter
    counters or host, and :attr:`RunData.notes` says so.  A recording corrupt at a batch
    is read up to it, its counts likewise, :attr:`RunData.corrupt` naming the batch.

    Raises:
        ReportError: a file is unreadable, a key is missing or of the wrong type, the
            files disagree on the number of ticks, or ``controller`` is given for a run
            without round-trip stamps.
    """
    folder = Path(folder)
    rec_path, json_path = folder / RECORDING, folder / REPORT
    meta = None  # cut short: no report.json
    if json_path.exists() or json_path.is_symlink():
        text = read_text(json_path, "run's report", MAX_REPORT_BYTES, ReportError)
        try:
            meta = json.loads(text)
        except json.JSONDecodeError as e:
            raise ReportError(f"{json_path}: cannot read the run's report: {e}") from e
    if meta is not None and not isinstance(meta, dict):
        raise ReportError(f"{json_path}: expected a JSON object")
    rec, columns, stamped = _read_recording(folder)
    corrupt = rec.corrupt.get(RECORDING)
    tick = columns["tick"]
    n = int(tick[-1]) + 1 if tick.size else 0
    if meta is None:
        period_ns, scheduling, host = rec.period_ns, {}, None
        adapter = None if rec.meta.get("adapter") is None else {"name": rec.meta["adapter"],
                                                                 "stats": None}
    else:
        period_ns, scheduling, adapter, host = _report_json(meta, json_path)
    if meta is None or corrupt is not None:
        overruns, skipped = _counts_from_recording(rec, columns, n)
    else:
        overruns, skipped = _check_counts(meta, json_path, rec_path, tick)
    if controller is not None and not stamped:
        raise ReportError(f"{rec_path}: no round-trip stamps to pair with {controller}")
    slots = _slots(columns, ("lateness_ns", "compute_ns",
                             *(RECORDED_STAMPS if stamped else ())), n)
    lateness, compute = slots.pop("lateness_ns"), slots.pop("compute_ns")
    round_trip = pairing = None
    if stamped:
        stamps = {**slots, "fb_rx_ns": np.zeros(n, dtype=np.int64)}
        if controller is not None:
            stamps["fb_rx_ns"], pairing = pair_with_controller(
                stamps, compute, load_controller_stamps(controller), str(controller))
        round_trip = round_trip_from_stamps(stamps, compute)
    return RunData(period_ns=period_ns, lateness_ns=lateness, compute_ns=compute,
                   overruns=overruns, skipped=skipped, scheduling=scheduling,
                   adapter=None if adapter is None else adapter["name"],
                   adapter_stats=None if adapter is None else adapter["stats"],
                   round_trip=round_trip, host=host, pairing=pairing,
                   notes=tuple(_notes(rec, meta is None)),
                   corrupt=None if corrupt is None else str(corrupt))


def _report_json(meta: dict, json_path: Path) -> tuple[int, dict, dict | None, dict | None]:
    """(period_ns, scheduling, adapter, host) of ``report.json``, checked."""
    loop, scheduling = meta.get("loop"), meta.get("scheduling")
    if not isinstance(loop, dict) or not isinstance(scheduling, dict):
        raise ReportError(f"{json_path}: needs the objects 'loop' (LoopStats.as_dict()) and "
                          f"'scheduling' (SchedulingReport.as_dict())")
    period_ns = _count(loop, "period_ns", f"{json_path} 'loop'", minimum=1)
    adapter = meta.get("adapter")
    if adapter is not None and not (isinstance(adapter, dict) and isinstance(
            adapter.get("name"), str) and isinstance(adapter.get("stats"), dict)):
        raise ReportError(f"{json_path}: 'adapter' must be null or "
                          f"{{'name': str, 'stats': {{...}}}}, got {adapter!r:.200}")
    host = meta.get("host")
    if host is not None and not isinstance(host, dict):
        raise ReportError(f"{json_path}: 'host' must be an object, got {host!r:.200}")
    return period_ns, scheduling, adapter, host


def _check_counts(meta: dict, json_path: Path, rec_path: Path,
                  tick: np.ndarray) -> tuple[int, int]:
    """(overruns, skipped) of ``report.json``'s loop, once checked against the rows'
    ``tick``: ``ticks + skipped`` deadlines, ``skipped + ticks_not_recorded`` of them
    without a row."""
    loop = meta["loop"]
    where = f"{json_path} 'loop'"
    ticks, skipped = _count(loop, "ticks", where), _count(loop, "skipped", where)
    recording = meta.get("recording") or {}
    lost = _count(recording, "ticks_not_recorded", f"{json_path} 'recording'") \
        if "ticks_not_recorded" in recording else 0
    n = int(tick[-1]) + 1 if tick.size else 0
    if ticks + skipped != n or n - tick.size != skipped + lost:
        raise ReportError(f"{rec_path}: rows for {tick.size} of {n} deadlines, but {where} "
                          f"says {ticks} ticks + {skipped} skipped and {json_path} "
                          f"{lost} ticks not recorded")
    return _count(loop, "overruns", where), skipped


# -- the report ------------------------------------------------------------------------------

def summary_us(values_ns: np.ndarray) -> dict | None:
    """``{"min", "p50", "p99", "p999", "max"}`` of ``values_ns`` in µs (nearest rank),
    or None for no samples."""
    if values_ns.size == 0:
        return None
    return {"min": float(values_ns.min()) / 1e3, **Percentiles.of_ns_in_us(values_ns).as_dict()}


def _round_trip_summary(run: RunData) -> dict | None:
    rt = run.round_trip
    if rt is None:
        return None
    has = rt.wait_ns != NO_VALUE
    known = rt.total_ns != NO_VALUE
    return {"adapter": run.adapter, "samples": int(has.sum()), "with_transport": int(known.sum()),
            "negative_waits": int((rt.wait_ns[has] < 0).sum()),
            "pairing": None if run.pairing is None else asdict(run.pairing),
            "total_us": summary_us(rt.total_ns[known]),
            "transport_us": summary_us(rt.transport_ns[known]),
            "wait_us": summary_us(rt.wait_ns[has]), "compute_us": summary_us(rt.compute_ns[has])}


def _histogram(lateness_ns: np.ndarray, period_ns: int,
               cyclictest: CyclictestBaseline | None) -> dict:
    """Counts on shared log-spaced bins (µs) of the two quantities both sides have
    (:mod:`hil.report.wakeup`): the wake-up latency (the loop's where known, the count of
    the ticks the spin hides beside it; cyclictest's own) and the lateness after the spin
    (the loop's recording; cyclictest's ``max(0, latency - spin)``).  A cyclictest bin
    counts at its centre (value + 0.5 µs), its overflows not at all; a value below the
    first edge counts in the first bin."""
    spin_us = spin_ns(period_ns) / 1e3
    lateness_us = lateness_ns / 1e3
    wakeup_us = loop_wakeup_known_ns(lateness_ns, period_ns) / 1e3
    top_us = max(float(np.max(wakeup_us, initial=0.0)), float(np.max(lateness_us, initial=0.0)),
                 1.0)
    if cyclictest is not None and cyclictest.counts.any():
        top_us = max(top_us, float(cyclictest.bins_us[cyclictest.counts > 0][-1]) + 1.0)
    n_bins = HIST_BINS_PER_DECADE * max(1, math.ceil(math.log10(top_us / HIST_LOW_US)))
    edges_us = HIST_LOW_US * 10.0 ** (np.arange(n_bins + 1) / HIST_BINS_PER_DECADE)

    def counts(values_us: np.ndarray, weights: np.ndarray | None = None) -> list[int]:
        clipped = np.clip(values_us, edges_us[0], edges_us[-1])
        return np.histogram(clipped, edges_us, weights=weights)[0].astype(np.int64).tolist()

    cyclictest_wakeup = cyclictest_lateness = None
    if cyclictest is not None:
        centre_us = cyclictest.bins_us + 0.5
        cyclictest_wakeup = counts(centre_us, cyclictest.counts)
        cyclictest_lateness = counts(lateness_after_spin_us(centre_us, spin_us),
                                     cyclictest.counts)
    return {"edges_us": edges_us.tolist(), "spin_us": spin_us,
            "lateness_counts": counts(lateness_us), "wakeup_counts": counts(wakeup_us),
            "wakeup_hidden": int(lateness_ns.size - wakeup_us.size),
            "cyclictest_wakeup_counts": cyclictest_wakeup,
            "cyclictest_lateness_counts": cyclictest_lateness}


def build_report(run: RunData, cyclictest: CyclictestBaseline | None = None) -> dict:
    """The report as a JSON-ready dict::

        {"period_us", "ticks", "overruns", "missed_ticks",
         "lateness_us" | "compute_us" | "slack_us": {"min", "p50", "p99", "p999", "max"},
         "round_trip": {"adapter", "samples", "with_transport", "negative_waits",
                        "pairing": {"controller", "rows", "matched", "unmatched_ticks",
                                    "unmatched_rows"} (Pairing) or null, "total_us",
                        "transport_us", "wait_us", "compute_us"} or null,
         "adapter": {"name", "stats"} or null, "scheduling", "host", "host_source",
         "cyclictest": {"interval_us", "samples", "overflows", "latency_us"} or null,
         "wakeup": hil.report.wakeup.wakeup_report(...),
         "histogram": {"edges_us", "spin_us", "lateness_counts", "wakeup_counts",
                       "wakeup_hidden", "cyclictest_wakeup_counts",
                       "cyclictest_lateness_counts"} (:func:`_histogram`; cyclictest's
                       null without a baseline),
         "percentiles", "notes": [str, ...], "corrupt": str or null}

    Slack is ``period - compute - lateness`` per tick: the time from the end of the step to
    the next deadline (negative: an overrun), so its worst case is its ``min``.  ``host`` is
    the run's fingerprint when it recorded one, otherwise this machine's (``host_source``
    says which).  ``negative_waits`` counts the round trips whose wait is below 0 (module
    docstring).  A summary over no samples is null.  ``notes`` and ``corrupt`` are the
    run's (:class:`RunData`).
    """
    ran = run.lateness_ns != NO_VALUE
    lateness, compute = run.lateness_ns[ran], run.compute_ns[ran]
    baseline = None
    if cyclictest is not None:
        baseline = {"interval_us": cyclictest.interval_us, "samples": cyclictest.samples,
                    "overflows": cyclictest.overflows,
                    "latency_us": None if cyclictest.samples == 0 else
                    {"min": cyclictest.min_us, **cyclictest.latency_us.as_dict()}}
    return {
        "period_us": run.period_ns / 1e3,
        "ticks": int(ran.sum()), "overruns": run.overruns, "missed_ticks": run.skipped,
        "lateness_us": summary_us(lateness), "compute_us": summary_us(compute),
        "slack_us": summary_us(run.period_ns - compute - lateness),
        "round_trip": _round_trip_summary(run),
        "adapter": None if run.adapter is None else {"name": run.adapter,
                                                     "stats": run.adapter_stats},
        "scheduling": run.scheduling,
        "host": run.host if run.host is not None else host_fingerprint(),
        "host_source": "run" if run.host is not None else "report",
        "cyclictest": baseline,
        "wakeup": wakeup_report(lateness, run.period_ns, cyclictest),
        "histogram": _histogram(lateness, run.period_ns, cyclictest),
        "percentiles": PERCENTILE_DEFINITION,
        "notes": list(run.notes), "corrupt": run.corrupt,
    }


def write_report(folder: Path | str, report: dict, run: RunData | None = None) -> list[Path]:
    """Write ``report_latency.json``, ``report.md``, ``latency_hist.png`` and, given the
    ``run`` the report was built from, ``latency_time.png`` into ``folder``; returns their
    paths."""
    from hil.report.render import markdown, plot_histogram, plot_timeline

    folder = Path(folder)
    json_path, md_path, png_path = folder / REPORT_JSON, folder / REPORT_MD, folder / REPORT_PNG
    json_path.write_text(json.dumps(report, indent=1, allow_nan=False) + "\n")
    md_path.write_text(markdown(report, title=folder.name, histogram_png=REPORT_PNG,
                                timeline_png=None if run is None else TIMELINE_PNG))
    plot_histogram(report, png_path)
    if run is None:
        return [json_path, md_path, png_path]
    return [json_path, md_path, png_path,
            plot_timeline(run.lateness_ns, run.compute_ns, run.period_ns, folder / TIMELINE_PNG)]


def report_run(folder: Path | str, cyclictest_s: float | None = None,
               note: Callable[[str], None] = lambda message: print(message, file=sys.stderr),
               controller: Path | str | None = None) -> dict:
    """What ``hil report RUN`` does: load the run (paired with the controller's folder
    ``controller`` when given), run cyclictest at its period for ``cyclictest_s`` seconds
    (None: no baseline) on the last CPU at SCHED_FIFO 80, build the report and write it
    into the folder.  ``note`` receives why a baseline is missing.
    """
    run = load_run(folder, controller)
    baseline = None
    if cyclictest_s is not None:
        interval_us = max(1, round(run.period_ns / 1e3))
        if interval_us * 1000 != run.period_ns:
            note(f"cyclictest runs at whole µs: {interval_us} µs for the run's "
                 f"{run.period_ns} ns")
        try:
            with Progress(f"hil report: cyclictest, {interval_us} µs for {cyclictest_s:g} s",
                          ticking=True):
                baseline = run_cyclictest_baseline(interval_us, cyclictest_s, cpu=last_cpu())
        except CyclictestError as err:
            note(f"cyclictest failed, no baseline: {err}")
        else:
            if baseline is None:
                note("cyclictest is not installed (apt-get install rt-tests): no baseline")
    report = build_report(run, baseline)
    write_report(folder, report, run)
    return report
