"""The recording's writer, seen from the emulator: a process that drains the shared ring
into Arrow IPC streams on disk, and a thread that hands it the run's events.

Two streams per run folder (:mod:`hil.runtime.run_folder`, format:
:mod:`hil.runtime.stream_file`): ``recording.arrows``, one row per tick
(:mod:`hil.runtime.recording`), and ``events.arrows``, one row per event
(:mod:`hil.runtime.run_events`).  Both carry the run's metadata (machine files, runtime
settings, adapter URL, period) in their schema, which is written before the loop starts.

The rows go through shared memory (:mod:`hil.runtime.ring`) to the writer process
(:mod:`hil.runtime.record_process`, which says why a process): nothing of the writing runs
in the emulator's interpreter.  What stays here is an *event thread*: every
:data:`FLUSH_S` it gathers the events the drives and the watchdog logged
(:class:`~hil.runtime.run_events.EventCollector`, a few µs when nothing happened) and
sends them on; like an adapter's receive thread it is given real-time priority below the
loop on the loop's CPU (:func:`hil.rt.scheduling.helper_threads_realtime`), so it
runs while the loop sleeps and cannot hold the interpreter lock against it from another
CPU.  A second thread only waits for the writer's messages.

Bounds: the writer takes the committed rows every :data:`FLUSH_S`; the ring holds
:data:`RING_S` of rows, so at most that much of the run is in memory.  A SIGKILL of the
emulator loses nothing the ring held: the writer sees its stdin close, writes the rest
and ends the streams.  A SIGKILL of both (the process group, the OOM killer) loses the
rows since the last flush -- :data:`FLUSH_S` plus the time of one write, at most
:data:`RING_S`.  A writer that falls behind by more than the ring makes the loop skip
recording (counted, an event) rather than wait.

A write that fails (``ENOSPC``, ``EFBIG``, an I/O error) ends the recording cleanly: the
run folder's reserve is given back (:meth:`~hil.runtime.run_folder.RunFolder.hold_reserve`),
the failure reported through ``on_failure`` (the emulator then stops its loop and takes
the axes to their safe state), and at the stop the file is cut back to its last complete
batch and the end-of-stream marker written.
"""

import json
import os
import queue
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import asdict

from hil.rt.loop import Percentiles
from hil.runtime.recording import Recorder
from hil.runtime.run_events import EventCollector, RunEvent
from hil.runtime.run_folder import EVENTS, RECORDING, RunFolder
from hil.runtime.stream_file import COMPRESSION, FORMAT

#: the writer takes the committed rows this often, s
FLUSH_S = 0.25
#: the ring holds this long of rows, s: the most of a run in memory
RING_S = 1.0
#: compressed size over raw size of the recording of moving axes, for the space check:
#: measured 0.33 on one Arrow 500 X axis at 8 kHz, 0.42 on five at 2 kHz (docs/benchmarks.md), at
#: rest 0.14-0.16
ESTIMATED_SHARE = 0.45
#: longest wait for the writer process to start (imports, pyarrow warmed), for an
#: answer to a flush, and for its end, s
ANSWER_TIMEOUT_S = 60.0


class RecordingWriter:
    """Starts the writer process on ``folder``'s two new files and ``recorder``'s ring,
    and feeds it ``events``' events (see the module docstring).  Raises OSError when a
    file cannot be made or the process does not start.

    Args:
        folder: the open run folder.
        recorder: the ring the loop writes.
        events: collects the run's events in this process.
        meta: the run's metadata (JSON-ready), kept in both streams' schemas.
        period_ns: the loop's period (event times, overruns).
        on_failure: called once, from a helper thread, with the message when a write
            fails or the writer process ends early; it must only set flags (the
            emulator's stops the loop).
        flush_s: how often the rows are taken, s.
        status_grace_ticks: the writer process shows ``hil run``'s status line on this
            process's stderr (:mod:`hil.runtime.run_status`), not counting the overruns
            of this many first ticks (the loop's grace period); None: no line.
    """

    def __init__(self, folder: RunFolder, recorder: Recorder, events: EventCollector,
                 meta: dict, period_ns: int, on_failure: Callable[[str], None],
                 flush_s: float = FLUSH_S, status_grace_ticks: int | None = None):
        self.folder, self.recorder, self.events = folder, recorder, events
        self.on_failure = on_failure
        self.flush_s = flush_s
        self.failed: str | None = None
        self.summary: dict | None = None
        self._answers: queue.Queue[dict] = queue.Queue()
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._live = False  # the writer has said ready: its end is a failure from now on
        self._stopping = False
        self._event_thread: threading.Thread | None = None
        fds = [folder.create(RECORDING)]
        try:
            fds.append(folder.create(EVENTS))
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "hil.runtime.record_process"], stdin=subprocess.PIPE,
                stdout=subprocess.PIPE, pass_fds=(recorder.ring.fd, *fds))
        finally:
            for fd in fds:
                os.close(fd)
        self._reader = threading.Thread(target=self._read, name="hil-recording-answers",
                                        daemon=True)
        self._reader.start()
        self._send({"layout": recorder.ring.layout.as_dict(), "ring_fd": recorder.ring.fd,
                    "samples_fd": fds[0], "samples_path": str(folder.path / RECORDING),
                    "events_fd": fds[1], "events_path": str(folder.path / EVENTS),
                    "specs": [[c.name, c.dtype, c.unit, c.doc] for c in recorder.specs],
                    "meta": {"format": FORMAT, **meta}, "period_ns": period_ns,
                    "flush_s": flush_s,
                    "status": None if status_grace_ticks is None
                    else {"grace_ticks": status_grace_ticks}})
        answer = self._answer("ready")
        self._live = "ready" in answer
        if not self._live:
            self._reap()
            raise OSError(f"the recording's writer process refused to start: "
                          f"{answer['error']}")

    def _send(self, msg: dict) -> bool:
        """Send ``msg``; False when the writer process is gone."""
        line = (json.dumps(msg) + "\n").encode()
        with self._send_lock:
            try:
                self.proc.stdin.write(line)
                self.proc.stdin.flush()
            except (BrokenPipeError, ValueError):
                return False
        return True

    def _read(self) -> None:
        """The writer's messages: a failure reported at once, answers queued; its end
        before the stop is a failure."""
        for line in self.proc.stdout:
            msg = json.loads(line)
            if "failed" in msg:
                self._fail(msg["failed"])
            else:
                self._answers.put(msg)
        if self._live and not self._stopping:
            self._fail(f"the recording's writer process ended early (exit status "
                       f"{self.proc.wait()}); the recording holds what it wrote before")
        self._answers.put({"error": "the writer process has ended"})

    def _answer(self, key: str) -> dict:
        """The writer's next answer (``{key: ...}`` or ``{"error": ...}``)."""
        try:
            answer = self._answers.get(timeout=ANSWER_TIMEOUT_S)
        except queue.Empty:
            return {"error": f"no answer ({key}) within {ANSWER_TIMEOUT_S:g} s"}
        return answer if key in answer or "error" in answer else {"error": str(answer)}

    def _fail(self, message: str) -> None:
        self.folder.release_reserve()  # room for the last batch's cut, events, report.json
        if self.failed is None:
            self.failed = message
            self.on_failure(message)

    def start(self, loop_cpu: int | None) -> None:
        """Keep the writer process off ``loop_cpu`` (where another CPU is allowed) and
        start the event thread."""
        if loop_cpu is not None:
            self._send({"avoid_cpu": loop_cpu})
        self._event_thread = threading.Thread(target=self._run, name="hil-recording-events",
                                              daemon=True)
        self._event_thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.flush_s):
            self._send_events()

    def _send_events(self, **msg) -> bool:
        """Send the events logged since the last call, with ``msg``'s keys; nothing when
        there is neither."""
        events = [asdict(e) for e in self.events.collect()]
        return self._send({**msg, "events": events}) if events or msg else True

    def add_events(self, events: list[RunEvent]) -> None:
        """Events from outside the loop, written with the next flush."""
        self._send({"events": [asdict(e) for e in events]})

    def flush(self) -> bool:
        """Have the writer write the rows committed so far and the events gathered now;
        False once a write has failed."""
        if not self._send_events(flush=True):
            return False
        return bool(self._answer("flushed").get("flushed"))

    def stop(self, final_events: list[RunEvent]) -> None:
        """Stop the event thread, send the last events (what the collector still holds,
        ``final_events``) and have the writer write what is left and close both streams;
        wait for it to end."""
        self._stop.set()
        if self._event_thread is not None:
            self._event_thread.join()
        self._stopping = True
        if self._send({"stop": True, "events": [asdict(e) for e in
                                                self.events.finish() + final_events]}):
            answer = self._answer("summary")
            if "summary" in answer:
                self.summary = answer["summary"]
                if self.summary["failed"] and self.failed is None:
                    self._fail(self.summary["failed"])
            elif self.failed is None:
                self._fail(f"the recording's writer did not finish: {answer['error']}")
        self._reap()

    def _reap(self) -> None:
        self._stopping = True
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(ANSWER_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._reader.join()

    def loop_percentiles(self) -> tuple[Percentiles, Percentiles]:
        """The lateness and compute time of every tick written (µs; see
        :mod:`hil.runtime.log_histogram` for the precision); NaN without a summary."""
        s = self.summary or {}
        nan = {k: float("nan") for k in ("p50", "p99", "p999", "max")}
        return (Percentiles(**s.get("lateness_us", nan)),
                Percentiles(**s.get("compute_us", nan)))

    def as_dict(self) -> dict:
        """What the writer did, JSON-ready."""
        s = self.summary or {}
        return {"files": [RECORDING, EVENTS],
                "format": f"{FORMAT}: Arrow IPC stream, {COMPRESSION}, CRC-32 per batch",
                "writer": "separate process", "rows": s.get("rows"),
                "events": s.get("events"), "bytes": s.get("bytes"),
                "ring_rows": self.recorder.slots, "flush_s": self.flush_s,
                "ticks_not_recorded": self.recorder.lost, "failed": self.failed}
