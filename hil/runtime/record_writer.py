"""The recording's writer: a thread that drains the ring into Arrow IPC streams on disk.

Why the Arrow IPC *stream* format (``.arrows``, pyarrow): it is made for appending --
each flush is one self-contained record batch after the schema, nothing earlier in the
file is ever rewritten, and no footer or index is needed to read it -- so a file cut
short by SIGKILL, the OOM killer or a full disk reads up to its last complete batch
(:mod:`hil.runtime.record_reader`).  It is columnar with exact dtypes (int64 ns stamps,
uint16 CiA words), its buffers are zstd-compressed (a moving axis at 8 kHz: about
87 bytes per tick instead of 262), and pyarrow, pandas and polars read it as it is.
(The Arrow *file* format would need its footer, written at close; HDF5 in SWMR mode needs
its library's cooperation to be readable after a crash.)

Two streams per run folder (:mod:`hil.runtime.run_folder`): ``recording.arrows``, one row
per tick (:mod:`hil.runtime.recording`), and ``events.arrows``, one row per event
(:mod:`hil.runtime.run_events`).  Both carry the run's metadata (machine files, runtime
settings, adapter URL, period) in their schema, which is written before the loop starts.

Bounds: the writer takes the committed rows every :data:`FLUSH_S`; the ring holds
:data:`RING_S` of rows, so at most that much of the run is in memory, and a SIGKILL loses
the rows since the last flush -- :data:`FLUSH_S` plus the time of one write, at most
:data:`RING_S`.  A writer that falls behind by more than the ring makes the loop skip
recording (counted, an event) rather than wait.

The thread runs at normal priority on every CPU but the loop's, started and warmed (the
first pyarrow conversion takes a quarter of a second with the GIL held) before the loop
and its real-time scheduling start.  A write that fails (``ENOSPC``, ``EFBIG``, an I/O
error) ends the recording cleanly: the run folder's reserve is given back
(:meth:`~hil.runtime.run_folder.RunFolder.hold_reserve`), the file is cut back to its last
complete batch, the end-of-stream marker written, the failure reported through
``on_failure`` (the emulator then stops its loop and takes the axes to their safe state).
"""

import json
import os
import threading
from collections.abc import Callable

import numpy as np

from hil.rt.loop import Percentiles
from hil.runtime.arrow import pa
from hil.runtime.log_histogram import LogHistogram
from hil.runtime.recording import Recorder
from hil.runtime.run_events import EVENT_COLUMNS, EventCollector, RunEvent
from hil.runtime.run_folder import EVENTS, RECORDING, RunFolder

#: the writer takes the committed rows this often, s
FLUSH_S = 0.25
#: the ring holds this long of rows, s: the most of a run in memory
RING_S = 1.0
#: the streams' buffers are compressed with this codec
COMPRESSION = "zstd"
#: compressed size over raw size of the recording of moving axes, for the space check:
#: measured 0.33 on one Arrow 500 X axis at 8 kHz, 0.42 on five at 2 kHz (README), at
#: rest 0.14-0.16
ESTIMATED_SHARE = 0.45
#: schema metadata key holding the run's metadata (JSON)
META_KEY = b"hil.recording"
FORMAT = "hil-recording 1"
#: an Arrow IPC stream ends with this marker (continuation token, zero length)
END_OF_STREAM = b"\xff\xff\xff\xff\x00\x00\x00\x00"


class _FdSink:
    """A file-like object over a descriptor, for pyarrow's stream writer: every write
    goes to the file at once (no buffer to lose), and the offset is known."""

    def __init__(self, fd: int):
        self.fd = fd
        self.offset = 0
        self.closed = False

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        while view:
            n = os.write(self.fd, view)
            self.offset += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self.offset

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def _schema(specs, meta: bytes) -> pa.Schema:
    return pa.schema([pa.field(name, pa.from_numpy_dtype(np.dtype(dtype)) if dtype != "string"
                               else pa.string(), metadata={"unit": unit, "doc": doc})
                      for name, dtype, unit, doc in specs], metadata={META_KEY: meta})


class _Stream:
    """One Arrow IPC stream being written to a file of the run folder."""

    def __init__(self, folder: RunFolder, name: str, schema: pa.Schema):
        self.path = folder.path / name
        self.schema = schema
        self.sink = _FdSink(folder.create(name))
        self.writer = pa.ipc.new_stream(
            self.sink, schema, options=pa.ipc.IpcWriteOptions(compression=COMPRESSION))
        self.good = 0  # the offset after the last complete batch
        self.broken = False
        self.write(pa.RecordBatch.from_pylist([], schema=schema))  # the schema, on disk now

    def write(self, batch: pa.RecordBatch) -> None:
        """Append ``batch``; an OSError names this file."""
        try:
            self.writer.write_batch(batch)
        except OSError as e:
            self.broken = True
            raise OSError(e.errno, e.strerror, str(self.path)) from e
        self.good = self.sink.offset

    def sync(self) -> None:
        os.fdatasync(self.sink.fd)

    def close(self) -> None:
        """End the stream and close the file.  After a failed write, cut the file back to
        its last complete batch and write the end marker by hand (the pyarrow writer is
        in an error state)."""
        try:
            if self.broken:
                os.ftruncate(self.sink.fd, self.good)
                os.lseek(self.sink.fd, self.good, os.SEEK_SET)
                os.write(self.sink.fd, END_OF_STREAM)
            else:
                self.writer.close()
            os.fsync(self.sink.fd)
        finally:
            if self.sink.fd >= 0:
                os.close(self.sink.fd)
                self.sink.fd = -1


class RecordingWriter:
    """Drains ``recorder`` into ``recording.arrows`` and ``events``' events into
    ``events.arrows`` of ``folder`` (see the module docstring).

    Args:
        folder: the open run folder.
        recorder: the ring the loop writes.
        events: collects the run's events.
        meta: the run's metadata (JSON-ready), kept in both streams' schemas.
        period_ns: the loop's period (event times).
        on_failure: called once, from the writer thread, with the message when a write
            fails; it must only set flags (the emulator's stops the loop).
        flush_s: how often the rows are taken, s.
    """

    def __init__(self, folder: RunFolder, recorder: Recorder, events: EventCollector,
                 meta: dict, period_ns: int, on_failure: Callable[[str], None],
                 flush_s: float = FLUSH_S):
        self.folder, self.recorder, self.events = folder, recorder, events
        self.period_s = period_ns * 1e-9
        self.on_failure = on_failure
        self.flush_s = flush_s
        self.lateness = LogHistogram()
        self.compute = LogHistogram()
        self.rows = 0
        self.n_events = 0
        self.failed: str | None = None
        self._pending_events: list[RunEvent] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        blob = json.dumps({"format": FORMAT, **meta}).encode()
        specs = [(c.name, c.dtype, c.unit, c.doc) for c in recorder.specs]
        event_specs = [(name, dtype, unit, doc) for name, (dtype, unit, doc)
                       in EVENT_COLUMNS.items()]
        self.samples = _Stream(folder, RECORDING, _schema(specs, blob))
        try:
            self.event_stream = _Stream(folder, EVENTS, _schema(event_specs, blob))
        except BaseException:
            self.samples.close()
            raise
        self._warm_up()

    @property
    def thread(self) -> threading.Thread | None:
        """The writer thread once started."""
        return self._thread

    def _warm_up(self) -> None:
        """Convert and compress a batch of each schema into memory: pyarrow's first use
        holds the GIL for a long time, which must happen before the loop runs."""
        for stream, batch in ((self.samples, self._batch(self.recorder.columns(0, 1))),
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

    def start(self, loop_cpu: int | None) -> None:
        """Start the thread, kept off ``loop_cpu`` where another CPU is allowed."""
        self._thread = threading.Thread(target=self._run, args=(loop_cpu,),
                                        name="hil-recording-writer", daemon=True)
        self._thread.start()

    def add_events(self, events: list[RunEvent]) -> None:
        """Events from outside the loop (the safe state, why the run stopped), written
        with the next flush."""
        with self._lock:
            self._pending_events.extend(events)

    def _run(self, loop_cpu: int | None) -> None:
        others = os.sched_getaffinity(0) - {loop_cpu}
        if others:
            os.sched_setaffinity(0, others)
        while not self._stop.wait(self.flush_s):
            if not self.flush():
                return

    def flush(self) -> bool:
        """Write the rows committed so far and the events up to them; False once a write
        has failed (the failure reported)."""
        if self.failed:
            return False
        rec = self.recorder
        try:
            start, stop = rec.pending()
            while start < stop:
                end = min(stop, start + rec.slots - start % rec.slots)
                columns = rec.columns(start, end)
                self.samples.write(self._batch(columns))
                self.lateness.add(columns["lateness_ns"])
                self.compute.add(columns["compute_ns"])
                self._write_events(self.events.collect(columns))
                rec.release(end)
                self.rows += end - start
                start = end
            self._write_events([])
            self.samples.sync()
            self.event_stream.sync()
        except OSError as e:  # the stream's write names its file

            self._fail(e)
            return False
        return True

    def _write_events(self, events: list[RunEvent]) -> None:
        with self._lock:
            events, self._pending_events = events + self._pending_events, []
        if events:
            self.event_stream.write(self._event_batch(events))
            self.n_events += len(events)

    def _fail(self, err: OSError) -> None:
        self.folder.release_reserve()  # room for the last batch's cut, events, report.json
        if self.failed is None:
            self.failed = (f"writing {err.filename} failed: {err.strerror or err}; the "
                           f"recording holds the {self.rows} ticks written before")
            self.on_failure(self.failed)

    def stop(self, final_events: list[RunEvent]) -> None:
        """Stop the thread, write what is left (rows, the collector's last events,
        ``final_events``) and close both streams, whatever happened before: after a
        failed write the recording is cut back to its last complete batch first (which
        frees the room the events may need)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.add_events(final_events)
        self.flush()
        streams = [self.samples, self.event_stream]
        try:
            if self.failed is not None:
                streams.remove(self.samples)
                self.samples.close()
            if not self.event_stream.broken:
                self._write_events(self.events.finish())
        except OSError as e:
            self._fail(e)
        finally:
            for stream in streams:
                try:
                    stream.close()
                except OSError as e:
                    self._fail(e)

    def loop_percentiles(self) -> tuple[Percentiles, Percentiles]:
        """The lateness and compute time of every tick written (µs; see
        :mod:`hil.runtime.log_histogram` for the precision)."""
        return self.lateness.percentiles_us(), self.compute.percentiles_us()

    def as_dict(self) -> dict:
        """What the writer did, JSON-ready."""
        return {"files": [RECORDING, EVENTS], "format": f"Arrow IPC stream, {COMPRESSION}",
                "rows": self.rows, "events": self.n_events,
                "bytes": self.samples.good + self.event_stream.good,
                "ring_rows": self.recorder.slots, "flush_s": self.flush_s,
                "ticks_not_recorded": self.recorder.lost, "failed": self.failed}
