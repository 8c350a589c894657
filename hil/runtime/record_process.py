"""The recording's writer process: drains the shared ring into Arrow IPC streams.

Started by :class:`hil.runtime.record_writer.RecordingWriter` as ``python -m
hil.runtime.record_process`` with three descriptors (``pass_fds``): the ring's memfd
(:mod:`hil.runtime.ring`) and the two files of the run folder, created by the emulator
(``O_EXCL | O_NOFOLLOW``).  Why a process and not a thread: pyarrow's conversions and the
Python around them hold the interpreter lock for hundreds of µs at a time, and a loop
waking up behind them waits (measured with a writer thread: the loop's compute p99.9 rose
from 150-180 to 290-350 µs on one Arrow 500 X axis at 8 kHz).  This process has its own
interpreter, runs at normal priority off the loop's CPU, and touches the loop only
through the ring's memory.

Protocol: JSON lines.  On stdin, first the set-up (:func:`main`), then any of
``{"avoid_cpu": N}``, ``{"events": [...]}`` (events of the emulator's process, written
with the next flush), ``{"flush": true}`` (flush now, answered ``{"flushed": ok}``),
``{"stop": true, "events": [...]}`` (last flush, the streams ended and closed, answered
``{"summary": {...}}``).  With ``"status": {"grace_ticks": N}`` in the set-up it writes ``hil run``'s
status line on stderr from the rows it writes (:mod:`hil.runtime.run_status`).  On
stdout: ``{"ready": true}`` once the streams' schemas are on
disk and pyarrow is warm (or ``{"error": "..."}`` and exit 1), and ``{"failed": "..."}``
as soon as a write fails.  The end of stdin (the emulator gone, even by SIGKILL) counts
as a stop: what the ring still holds is written and the streams closed.  SIGINT and
SIGTERM are ignored: a Ctrl-C at the terminal reaches the whole process group, and the
emulator's shutdown still needs this process to end the recording.
"""

import json
import os
import selectors
import signal
import sys
import time

import numpy as np

from hil.runtime.arrow import pa
from hil.runtime.log_histogram import LogHistogram
from hil.runtime.ring import RingLayout, SharedRing
from hil.runtime.run_events import EVENT_COLUMNS, Overruns, RunEvent
from hil.runtime.run_status import RunStatus
from hil.runtime.stream_file import COMPRESSION, ArrowStream, schema_of


class StreamWriter:
    """Writes the ring's committed rows to ``recording.arrows`` and the events to
    ``events.arrows`` (the module docstring says where the descriptors come from).

    Args:
        ring: the emulator's ring, mapped here.
        samples, event_stream: the two streams, their schemas already written.
        period_ns: the loop's period (overruns, event times).
        status: the run's status line, fed every chunk written; None: no line.
    """

    def __init__(self, ring: SharedRing, samples: ArrowStream, event_stream: ArrowStream,
                 period_ns: int, status: RunStatus | None = None):
        self.ring, self.samples, self.event_stream = ring, samples, event_stream
        self.period_s = period_ns * 1e-9
        self.overruns = Overruns(period_ns)
        self.lateness = LogHistogram()
        self.compute = LogHistogram()
        self.rows = 0
        self.n_events = 0
        self.failed: str | None = None
        self.pending_events: list[RunEvent] = []
        self.status = status

    def warm_up(self) -> None:
        """Convert and compress a batch of each schema into memory: pyarrow's first use
        takes a quarter of a second."""
        for stream, batch in ((self.samples, self._batch(self.ring.columns(0, 1))),
                              (self.event_stream, self._event_batch([]))):
            sink = pa.BufferOutputStream()
            with pa.ipc.new_stream(sink, stream.schema, options=pa.ipc.IpcWriteOptions(
                    compression=COMPRESSION)) as w:
                w.write_batch(batch)

    def _batch(self, columns: dict[str, np.ndarray]) -> pa.RecordBatch:
        schema = self.samples.schema
        return pa.RecordBatch.from_arrays([pa.array(columns[f.name]) for f in schema],
                                          schema=schema)

    def _event_batch(self, events: list[RunEvent]) -> pa.RecordBatch:
        rows = [{"tick": e.tick, "t_s": e.tick * self.period_s if e.tick >= 0 else None,
                 "axis": e.axis, "source": e.source, "kind": e.kind, "code": e.code,
                 "cycle": e.cycle, "count": e.count, "reason": e.reason} for e in events]
        return pa.RecordBatch.from_pylist(rows, schema=self.event_stream.schema)

    def flush(self) -> bool:
        """Write the rows committed so far, the overruns in them and the events received;
        False once a write has failed (:attr:`failed` says which)."""
        if self.failed:
            return False
        ring = self.ring
        try:
            start, stop = ring.pending()
            while start < stop:
                end = min(stop, start + ring.layout.slots - start % ring.layout.slots)
                columns = ring.columns(start, end)
                self.samples.write(self._batch(columns))
                self.lateness.add(columns["lateness_ns"])
                self.compute.add(columns["compute_ns"])
                found: list[RunEvent] = []
                self.overruns.scan(columns["tick"], columns["lateness_ns"],
                                   columns["compute_ns"], found)
                self._write_events(found)
                self._status(columns)
                ring.release(end)
                self.rows += end - start
                start = end
            self._write_events([])
            self.samples.sync()
            self.event_stream.sync()
        except OSError as e:  # the stream's write names its file
            self.failed = (f"writing {e.filename} failed: {e.strerror or e}; the recording "
                           f"holds the {self.rows} ticks written before")
            return False
        return True

    def _status(self, columns: dict[str, np.ndarray]) -> None:
        """Feed the status line; a fault of it ends the line, never the recording."""
        if self.status is None:
            return
        try:
            self.status.add(columns)
        except Exception as e:  # noqa: BLE001 -- the line is a view; the rows must go on
            self.status = None
            print(f"hil run: the status line stopped ({type(e).__name__}: {e}); the "
                  "recording goes on", file=sys.stderr, flush=True)

    def _write_events(self, events: list[RunEvent]) -> None:
        events, self.pending_events = events + self.pending_events, []
        if events:
            self.event_stream.write(self._event_batch(events))
            self.n_events += len(events)

    def finish(self, final_events: list[RunEvent]) -> dict:
        """The last flush, the overruns still open, ``final_events``; both streams ended
        and closed whatever happened before (after a failed write the recording is cut
        back to its last complete batch first, which frees room for the events).
        Returns the summary (JSON-ready)."""
        self.pending_events.extend(final_events)
        self.flush()
        if self.status is not None:
            self.status.show(final=True)
        streams = [self.samples, self.event_stream]
        try:
            if self.failed is not None:
                streams.remove(self.samples)
                self.samples.close()
            if not self.event_stream.broken:
                self._write_events(self.overruns.finish())
        except OSError as e:
            self.failed = self.failed or f"writing {e.filename} failed: {e.strerror or e}"
        finally:
            for stream in streams:
                try:
                    stream.close()
                except OSError as e:
                    self.failed = self.failed or f"closing {stream.path} failed: {e}"
        return {"rows": self.rows, "events": self.n_events,
                "bytes": self.samples.good + self.event_stream.good, "failed": self.failed,
                "lateness_us": self.lateness.percentiles_us().as_dict(),
                "compute_us": self.compute.percentiles_us().as_dict()}


def _setup(msg: dict) -> StreamWriter:
    ring = SharedRing(RingLayout.from_dict(msg["layout"]), fd=msg["ring_fd"])
    blob = json.dumps(msg["meta"]).encode()
    event_specs = [(name, dtype, unit, doc) for name, (dtype, unit, doc)
                   in EVENT_COLUMNS.items()]
    samples = ArrowStream(msg["samples_fd"], msg["samples_path"],
                          schema_of(msg["specs"], blob))
    events = ArrowStream(msg["events_fd"], msg["events_path"], schema_of(event_specs, blob))
    names = [axis["name"] for axis in msg["meta"].get("axes", [])]
    status = (RunStatus(msg["period_ns"], {name: unit for name, _, unit, _ in msg["specs"]},
                        single_axis=names[0] if len(names) == 1 else "axis",
                        grace_ticks=msg["status"]["grace_ticks"])
              if msg.get("status") else None)
    writer = StreamWriter(ring, samples, events, msg["period_ns"], status)
    writer.warm_up()
    return writer


class _Channel:
    """JSON lines on this process's stdin and stdout."""

    def __init__(self):
        self.fd = sys.stdin.fileno()
        self.buffer = b""
        self.selector = selectors.DefaultSelector()
        self.selector.register(self.fd, selectors.EVENT_READ)

    def send(self, msg: dict) -> None:
        try:
            sys.stdout.write(json.dumps(msg) + "\n")
            sys.stdout.flush()
        except (BrokenPipeError, ValueError):  # the emulator is gone: nobody to tell
            pass

    def receive(self, timeout_s: float) -> list[dict] | None:
        """The messages arrived within ``timeout_s`` (maybe none); None at the end of
        stdin."""
        if not self.selector.select(max(0.0, timeout_s)):
            return []
        data = os.read(self.fd, 1 << 16)
        if not data:
            return None
        self.buffer += data
        *lines, self.buffer = self.buffer.split(b"\n")
        return [json.loads(line) for line in lines if line.strip()]


def serve(channel: _Channel, writer: StreamWriter, flush_s: float) -> None:
    """Flush every ``flush_s`` and answer the emulator until it says stop or is gone."""
    reported = False
    due = time.monotonic() + flush_s
    while True:
        messages = channel.receive(due - time.monotonic())
        if messages is None:
            writer.finish([])
            return
        for msg in messages:
            if "avoid_cpu" in msg:
                others = os.sched_getaffinity(0) - {msg["avoid_cpu"]}
                if others:
                    os.sched_setaffinity(0, others)
            if "events" in msg:
                writer.pending_events.extend(RunEvent(**e) for e in msg["events"])
            if msg.get("flush"):
                channel.send({"flushed": writer.flush()})
            if msg.get("stop"):
                channel.send({"summary": writer.finish([])})
                return
        if time.monotonic() >= due:
            writer.flush()
            due = time.monotonic() + flush_s
            if writer.status is not None:
                writer.status.show()
        if writer.failed and not reported:
            channel.send({"failed": writer.failed})
            reported = True


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    channel = _Channel()
    messages: list[dict] = []
    while not messages:
        messages = channel.receive(60.0)
        if messages is None:
            return 1
    setup = messages[0]
    try:
        writer = _setup(setup)
    except Exception as e:  # refused set-up: the emulator says why and exits 2
        channel.send({"error": f"{type(e).__name__}: {e}"})
        return 1
    channel.send({"ready": True})
    serve(channel, writer, setup["flush_s"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
