"""``hil export RUN --to mdf4|csv``: a run's recording where engineers look at traces.

::

    hil export runs/r1 --to mdf4            # runs/r1/recording.mf4
    hil export runs/r1 --to mdf4 --bus out/bus.asc   # and the CAN frames (CANape, asammdf)
    hil export runs/r1 --to csv [--axis X]  # runs/r1/trace.csv (trace_X.csv, ... per axis)
                                            # and runs/r1/events.csv

* **MDF4** (ASAM MDF 4.10 through asammdf; what ControlDesk, CANape and asammdf's GUI
  open; compressed): one channel group ``recording`` with every column of the recording,
  its unit and its meaning as the channel comment, on the master time ``t = tick *
  period``: the CiA 402 state, mode, 603Fh code and statusword bits read as text, counts
  as integers with a twin in table units (:mod:`hil.runtime.mdf_channels`); a
  channel group ``events`` (time, axis, source, kind, 603Fh code, drive cycle, reason);
  the machine file(s) attached, the run's metadata in the file comment; the file's start
  time is the wall-clock time of tick 0.  With ``--bus LOG`` (a CAN run's ``log=``:
  ``.asc``, ``.blf`` or ``.mf4``) the bus frames too, as MDF4 bus logging (python-can's
  MF4 writer: ``CAN_DataFrame`` with its ID, DLC, data bytes and direction), placed on the
  run's time by their wall-clock stamps: a DBC then decodes them beside the recording
  (``MDF.extract_bus_logging``, with ``hil eds``'s ``nodes.dbc``).
* **CSV**: the servo-trace format of ``../shared/docs/trace-format.md`` per axis
  (:mod:`hil.runtime.record_trace` says which recording column makes which trace
  column), one row per tick on a uniform time base (a tick without a row -- dropped by
  the ``skip`` overrun policy, or not recorded -- is a row of NaN), every number in the
  shortest text that reads back exactly (times and counts computed as the float nearest
  their exact value, so that they show its decimal: :mod:`hil.decimal_grid`); the header says the modes the setpoints were in
  (no position setpoint outside CSP: it stays in the controller, and ``--controller DIR``
  takes it from ``hil controller``'s folder of the same run) and the run's timing;
  the run's events go to ``events.csv`` beside the traces, one row each.

Both are written batch by batch as the recording was (bounded memory, whatever its
length).  An existing output file is refused unless ``--force``; a run folder whose
recording was cut short (SIGKILL) exports what it holds, with a warning.  Every batch's
CRC-32 is checked as it is read (:mod:`hil.runtime.record_reader`): at a corrupt batch of
either stream the export stops, writes what precedes it, names the batch on stderr and
exits 1.  A recording of the format before the checksums exports with a warning that
nothing could be checked.
"""

import argparse
import csv
import json
import math
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

from hil.cia402 import mode_name
from hil.decimal_grid import on_grid
from hil.runtime import mdf_channels
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, eprint
from hil.runtime.record_reader import Recording, RecordingError
from hil.runtime.record_trace import AxisTrace, ControllerSetpoints, axis_trace
from hil.runtime.stream_file import FORMAT

MDF_NAME = "recording.mf4"
#: the MDF4 file's data blocks: transposed deflate (asammdf's 2), the smallest that MDF 4.10
#: allows (zstd and lz4 need 4.30, which fewer tools read); a recording's slowly changing
#: columns shrink to a fraction
COMPRESSION = 2


class ExportError(ValueError):
    """An export that cannot be made; the message names the file and why."""


def _fresh(path: Path, force: bool) -> Path:
    if path.exists() and not force:
        raise ExportError(f"{path} exists; give --force to replace it")
    return path


#: the events file ``hil export --to csv`` writes beside the traces
EVENTS_CSV = "events.csv"
EVENT_COLUMNS = ("t_s", "tick", "axis", "source", "kind", "code", "drive_cycle", "reason")


def export_events_csv(rec: Recording, out: Path, force: bool = False) -> tuple[Path, int]:
    """``out``: the run's events, one row each (up to a corrupt batch): the time (empty
    after the loop), tick (-1 after the loop), axis, source, kind, 603Fh code as hex (empty
    when none), drive cycle (empty when none) and reason.  Returns (the path, the count)."""
    ev = rec.events(stop_at_corrupt=True)
    # from the tick rather than the stored tick * period: the exact decimal of the time
    t_s = on_grid(ev["tick"], Fraction(rec.period_ns, 1_000_000_000))
    with open(_fresh(out, force), "w", encoding="utf-8", newline="") as f:
        w = csv.writer(f)
        w.writerow(EVENT_COLUMNS)
        for i in range(ev["tick"].size):
            w.writerow((repr(float(t_s[i])) if ev["tick"][i] >= 0 else "",
                        int(ev["tick"][i]), ev["axis"][i], ev["source"][i], ev["kind"][i],
                        f"{ev['code'][i]:04X}" if ev["code"][i] else "",
                        int(ev["cycle"][i]) if ev["cycle"][i] >= 0 else "", ev["reason"][i]))
    return out, int(ev["tick"].size)


def _modes(rec: Recording, trace: AxisTrace) -> str:
    """Which modes of operation the axis's setpoints were in, by name (``sp_mode``)."""
    seen = set()
    for rows in rec.batches(["tick", trace.prefix + "sp_mode"], stop_at_corrupt=True):
        seen.update(np.unique(rows[trace.prefix + "sp_mode"]).tolist())
    return ", ".join(mode_name(m) for m in sorted(seen))


def export_csv(rec: Recording, out: Path, trace: AxisTrace, force: bool = False,
               controller: ControllerSetpoints | None = None) -> Path:
    """``out``: the servo trace of one axis (see the module docstring); the setpoints the
    recording lacks (outside CSP) from ``controller``, where given."""
    names = trace.names()
    modes = _modes(rec, trace)
    header = {**trace.metadata(rec, stop_at_corrupt=True), "modes": modes,
              "events": f"{EVENTS_CSV} beside this file"}
    if controller is not None:
        header["pos_set_note"] = (f"outside CSP from the controller's {controller.source}, "
                                  "the setpoint each tick applied found by its sequence "
                                  "number; empty where the controller recorded none")
    elif "CSP" not in modes:
        header["pos_set_note"] = (f"empty: the drive ran in {modes or 'no mode'}, where the "
                                  "position setpoint stays in the controller (hil export "
                                  "--controller DIR takes it from hil controller's folder)")
    pos_set, vel_set = names[1], names[3]
    sources = [*trace.sources(), "sp_seq"]
    with open(_fresh(out, force), "w", encoding="utf-8") as f:
        for key, value in header.items():
            f.write(f"# {key}: {value}".replace("\n", " ") + "\n")
        f.write(",".join(names) + "\n")
        next_tick = 0
        for rows in rec.batches(sources, stop_at_corrupt=True):
            converted = trace.convert(rows)
            if controller is not None:
                x_set, v_set = controller.at(rows["sp_seq"])
                for name, values in ((pos_set, x_set * trace.k),
                                     (vel_set, v_set * trace.k * 60.0)):
                    converted[name] = np.where(np.isnan(converted[name]), values,
                                               converted[name])
            columns = _every_tick(converted, rows["tick"], next_tick, trace)
            # repr: the shortest text that reads back to the same float
            lists = [columns[n].tolist() for n in names]
            f.writelines(",".join(map(repr, row)) + "\n" for row in zip(*lists))
            next_tick = int(rows["tick"][-1]) + 1
    return out


def _every_tick(columns: dict[str, np.ndarray], tick: np.ndarray, first: int,
                trace: AxisTrace) -> dict[str, np.ndarray]:
    """``columns`` on every tick from ``first`` to the last of ``tick``: a tick without a
    row (dropped by the ``skip`` overrun policy, or not recorded) gets NaN, so that the
    trace keeps its uniform time base."""
    if tick.size and tick[0] == first and tick[-1] - first + 1 == tick.size:
        return columns
    every = np.arange(first, tick[-1] + 1)
    out = {}
    for name, values in columns.items():
        out[name] = np.full(every.size, np.nan)
        out[name][tick - first] = values
    out["t_s"] = trace.t_s(every)
    return out


#: bus logs python-can reads with wall-clock time stamps
BUS_LOGS = (".asc", ".blf", ".mf4")


def tick0_unix_ns(rec: Recording, rows: dict) -> int | None:
    """The wall-clock time of tick 0's deadline, ns, from the recording's clock pair and
    the first row of ``rows`` that started on a new setpoint (its wake-up less its
    lateness, less its ticks); None when the run recorded no clock pair or no such row."""
    clock = rec.meta.get("clock")
    if not clock:
        return None
    started = np.flatnonzero(rows["tick_start_ns"] > 0)
    if not started.size:
        return None
    i = started[0]
    deadline = int(rows["tick_start_ns"][i]) - int(rows["lateness_ns"][i])
    t0_monotonic = deadline - int(rows["tick"][i]) * rec.period_ns
    return clock["unix_ns"] + t0_monotonic - clock["monotonic_ns"]


def bus_mdf(path: Path, tmp: Path):
    """The frames of the CAN log ``path`` as an MDF4 bus-logging file (python-can's MF4
    writer) written to ``tmp``, opened; its start time the writer's, its frames at their
    wall-clock stamps from it (so :meth:`MDF.stack` with ``sync`` places them)."""
    import can
    from asammdf import MDF

    from io_adapters.can_tap import mf4_writer_ready

    if path.suffix.lower() not in BUS_LOGS:
        raise ExportError(f"--bus {path}: a CAN log with wall-clock stamps is one of "
                          f"{', '.join(BUS_LOGS)}")
    options = {"relative_timestamp": False} if path.suffix.lower() == ".asc" else {}
    mf4_writer_ready()
    try:
        writer = can.Logger(str(tmp))
        for msg in can.LogReader(str(path), **options):
            writer.on_message_received(msg)
        writer.stop()
    except (OSError, ValueError, can.CanError) as e:
        raise ExportError(f"--bus {path}: cannot read it: {e}") from e
    return MDF(tmp)


def export_mdf4(rec: Recording, out: Path, force: bool = False,
                bus: tuple[Path, ...] = ()) -> Path:
    """``out``: the whole recording and its events as MDF4, up to a corrupt batch, with the
    frames of the CAN logs ``bus`` (see the module docstring)."""
    from datetime import datetime, timezone

    from asammdf import MDF, Signal  # only this export needs asammdf

    period_s = rec.period_ns * 1e-9
    mdf = MDF(version="4.10")
    meta = {k: v for k, v in rec.meta.items() if k != "machine_files"}
    mdf.header.comment = json.dumps(meta)
    for path, text in rec.meta.get("machine_files", {}).items():
        mdf.attach(text.encode(), file_name=Path(path).name, comment=f"machine file {path}",
                   embedded=True)
    channels = mdf_channels.channels(rec)
    group, t0_ns = None, None
    for rows in rec.batches(stop_at_corrupt=True):
        t = rows["tick"] * period_s
        if t0_ns is None:
            t0_ns = tick0_unix_ns(rec, rows)
            if t0_ns is not None:
                mdf.header.start_time = datetime.fromtimestamp(t0_ns / 1e9, timezone.utc)
        samples = [rows[c.source].astype(c.dtype, copy=False) for c in channels]
        if group is None:
            group = mdf.append([Signal(x, t, name=c.name, unit=c.unit, comment=c.comment,
                                       conversion=c.conversion)
                                for c, x in zip(channels, samples)],
                               acq_name="recording", comment="hil run, one row per tick")
        else:
            mdf.extend(group, [(t, None), *((x, None) for x in samples)])
    ev = rec.events(stop_at_corrupt=True)
    if ev["tick"].size:
        end = (rows["tick"][-1] + 1) * period_s if group is not None else 0.0
        t = np.where(ev["tick"] >= 0, ev["t_s"], end)
        order = np.argsort(t, kind="stable")  # a channel group's time only goes forward
        t, ev = t[order], {name: values[order] for name, values in ev.items()}

        def text(name: str, comment: str) -> Signal:
            return Signal(np.array([s.encode() for s in ev[name]]), t, name=name,
                          comment=comment, encoding="utf-8")

        mdf.append([text("axis", "axis letter (empty: all)"),
                    text("source", "who logged it"), text("kind", "what happened"),
                    Signal(ev["code"].astype(np.uint16), t, name="code",
                           unit=mdf_channels.NO_UNIT,
                           comment="the drive's error code 603Fh (0: none)",
                           conversion=mdf_channels.value_to_text(mdf_channels.fault_names())),
                    Signal(ev["cycle"], t, name="cycle", unit=mdf_channels.NO_UNIT,
                           comment="drive cycle (-1: none)"),
                    text("reason", "why")],
                   acq_name="events", comment="events of the run; after the loop: at the end")
    if bus:
        if t0_ns is None:
            raise ExportError(f"{rec.path}: the run recorded no wall clock beside its own "
                              "(hil run before it did, or no setpoint ever came): the bus "
                              "frames cannot be placed on its time")
        with tempfile.TemporaryDirectory(prefix="hil-export-bus-") as tmp:
            logs = [bus_mdf(path, Path(tmp) / f"bus{i}.mf4") for i, path in enumerate(bus)]
            stacked = MDF.stack([mdf, *logs], sync=True)
            stacked.header.comment, stacked.header.start_time = mdf.header.comment, \
                mdf.header.start_time
            for attachment in mdf.attachments:
                stacked.attach(attachment.extract(), file_name=attachment.file_name,
                               comment=attachment.comment, embedded=True)
            mdf.close()
            for log in logs:
                log.close()
            stacked.save(_fresh(out, force), overwrite=True, compression=COMPRESSION)
            stacked.close()
        return out
    mdf.save(_fresh(out, force), overwrite=True, compression=COMPRESSION)
    mdf.close()
    return out


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil export``."""
    p.add_argument("run", help="run folder of hil run (recording.arrows, events.arrows)")
    p.add_argument("--to", required=True, choices=("mdf4", "csv"), help="mdf4: the whole "
                   "recording (ControlDesk, CANape, asammdf); csv: the servo trace per axis")
    p.add_argument("--axis", help="csv: only this axis (default: every axis)")
    p.add_argument("--out", metavar="PATH", help=f"mdf4: the file (default RUN/{MDF_NAME}); "
                   "csv: the folder (default RUN)")
    p.add_argument("--bus", action="append", default=[], metavar="LOG",
                   help="mdf4: add a CAN run's bus log (hil run's log=FILE: .asc, .blf or "
                   ".mf4) as MDF4 bus logging on the run's time (repeatable)")
    p.add_argument("--controller", metavar="DIR",
                   help="csv: hil controller's folder of the same run; the position "
                   "setpoint of a CST or CSV run (and the velocity setpoint of a CST run), "
                   "which stay in the controller, come from its controller.npz")
    p.add_argument("--force", action="store_true", help="replace existing output files")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil export``: returns the exit status."""
    run = Path(args.run)
    try:
        rec = Recording(run)
        if args.controller and args.to != "csv":
            raise ExportError("--controller is for --to csv: an MDF4 file holds the "
                              "recording as the drive saw it")
        if args.to == "mdf4":
            outputs = [export_mdf4(rec, Path(args.out or run / MDF_NAME), args.force,
                                   tuple(Path(b) for b in args.bus))]
        else:
            names = [args.axis] if args.axis else [a["name"] for a in rec.meta["axes"]]
            folder = Path(args.out or run)
            folder.mkdir(parents=True, exist_ok=True)
            outputs = [export_csv(rec, folder / ("trace.csv" if len(rec.meta["axes"]) == 1
                                                 else f"trace_{name}.csv"),
                                  axis_trace(rec, name), args.force,
                                  ControllerSetpoints.load(Path(args.controller), name)
                                  if args.controller else None) for name in names]
            outputs.append(export_events_csv(rec, folder / EVENTS_CSV, args.force)[0])
    except (RecordingError, ExportError, OSError) as e:
        eprint(f"hil export: {e}")
        return EXIT_BAD_INPUT
    if rec.truncated:
        eprint(f"hil export: {rec.path} was cut short (the run did not end cleanly); "
               "exported what it holds")
    if not rec.checksums:
        eprint(f"hil export: {rec.path} carries no checksums (written before the format "
               f"{FORMAT!r}): a corrupt batch could not be told")
    for path in outputs:
        print(f"hil export: {path} ({math.ceil(path.stat().st_size / 1e3)} kB)")
    for error in rec.corrupt.values():
        eprint(f"hil export: {error}; exported what precedes it")
    return EXIT_FAILED if rec.corrupt else EXIT_OK
