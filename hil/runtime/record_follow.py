"""Following a recording while it grows: the batches the writer has flushed since the last
look, each read once, with the checks of :mod:`hil.runtime.record_reader`.

``hil scope`` reads a run this way, live or finished: every poll reads only the messages
whose bytes are all on disk (:func:`~hil.runtime.record_reader._message_end` tells where
each ends), at most ``max_batches`` of them, so a poll's work is bounded however far
behind it starts.  Each batch read is remembered as a :class:`Span` (its bytes and its
ticks), so a part of the run can be read again later (:meth:`Follower.read`: the last
seconds of a channel chosen late, the rows of a zoomed view) without reading the rest.

::

    follow = Follower(Recording(RUN_DIR))
    rows = follow.poll(["tick", "plant_table_pos"])   # None: nothing new
    follow.ended                                      # the end-of-stream marker was met
    for rows in follow.read(follow.spans_between(t0_tick, t1_tick), ["plant_table_pos"]): ...

The events stream follows the same way: ``Follower(rec, rec.events_path)``.
"""

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.runtime.arrow import pa
from hil.runtime.record_reader import (
    CorruptBatchError,
    Recording,
    _crc_mismatch,
    _message_end,
)
from hil.runtime.stream_file import END_OF_STREAM

#: batches one poll reads at most (0.25 s of run each: 50 s of run per poll)
MAX_BATCHES = 200


@dataclass(frozen=True, slots=True)
class Span:
    """One record batch of the stream.

    Attributes:
        offset: its first byte in the file.
        first_tick, last_tick: the ticks of its first and last rows (the events
            stream's may be -1: events outside the loop).
        rows: its rows.
    """
    offset: int
    first_tick: int
    last_tick: int
    rows: int


class Follower:
    """The batches of one stream of a recording, read as they appear (module docstring).

    Args:
        rec: the recording (its schema, checked when it was opened).
        path: the stream to follow (default: the recording's samples; ``rec.events_path``
            for the events).

    Attributes:
        spans: every non-empty batch read so far, in file order.
        ended: the stream's end-of-stream marker was met (the writer closed it).
        full: the last poll stopped at ``max_batches``: more complete batches wait.
    """

    def __init__(self, rec: Recording, path: Path | None = None):
        self.rec = rec
        self.path = rec.path if path is None else Path(path)
        source, reader, self.checked = rec._open(self.path)
        self.names = reader.schema.names
        self.offset = source.tell()  # the first batch's, after the schema
        source.close()
        self.spans: list[Span] = []
        self.ended = False
        self.full = False
        self._index = 0

    def behind_bytes(self) -> int:
        """Bytes on disk not read yet (a whole or a partly written message)."""
        return max(0, os.path.getsize(self.path) - self.offset)

    def poll(self, columns: list[str], max_batches: int = MAX_BATCHES
             ) -> dict[str, np.ndarray] | None:
        """The rows of ``columns`` in the batches completed since the last poll (at most
        ``max_batches``), name -> array; None when there are none.

        Raises:
            CorruptBatchError: a batch fails its check (those before it were returned
                by earlier polls or are dropped with the error).
        """
        if self.ended:
            return None
        parts: list[dict[str, np.ndarray]] = []
        size = os.path.getsize(self.path)
        source, reader, _ = self.rec._open(self.path)
        try:
            while len(parts) < max_batches:
                end = _message_end(self.path, self.offset)
                if end is None and self._at_marker(size):
                    self.ended = True
                    break
                if end is not None and end > size:
                    break  # the writer has not flushed all of it yet
                start = self.offset
                batch = self._read_at(source, reader, start, end)
                self.offset = end
                self._index += 1
                if batch.num_rows == 0:
                    continue
                ticks = batch.column("tick")
                self.spans.append(Span(start, int(ticks[0].as_py()),
                                       int(ticks[-1].as_py()), batch.num_rows))
                parts.append({n: batch.column(n).to_numpy(zero_copy_only=False)
                              for n in columns})
        finally:
            source.close()
        self.full = len(parts) == max_batches
        if not parts:
            return None
        return {n: np.concatenate([p[n] for p in parts]) for n in columns}

    def _at_marker(self, size: int) -> bool:
        if size - self.offset < len(END_OF_STREAM):
            return False
        with open(self.path, "rb") as f:
            f.seek(self.offset)
            return f.read(len(END_OF_STREAM)) == END_OF_STREAM

    def _read_at(self, source, reader, offset: int, end: int | None) -> pa.RecordBatch:
        """The checked batch at ``offset`` (its message ends at ``end``)."""
        before = [s for s in self.spans if s.offset < offset]
        rows_before = sum(s.rows for s in before)
        after = self.rec.ticks_before(before[-1].last_tick if before and
                                      self.path == self.rec.path else None)
        if end is None:
            raise CorruptBatchError(self.path, self._index, offset, rows_before,
                                    "it is no Arrow message", after)
        source.seek(offset)
        try:
            batch, custom = reader.read_next_batch_with_custom_metadata()
            batch.validate(full=True)
        except (OSError, pa.ArrowException, StopIteration) as e:
            raise CorruptBatchError(self.path, self._index, offset, rows_before,
                                    f"it cannot be decoded ({e})", after) from e
        reason = _crc_mismatch(batch, custom) if self.checked else None
        if reason is not None:
            raise CorruptBatchError(self.path, self._index, offset, rows_before, reason, after)
        return batch

    def spans_between(self, first_tick: int, last_tick: int) -> list[Span]:
        """The spans read so far that hold a row with a tick in [first_tick, last_tick]."""
        return [s for s in self.spans if s.last_tick >= first_tick and s.first_tick <= last_tick]

    def read(self, spans: list[Span], columns: list[str]) -> Iterator[dict[str, np.ndarray]]:
        """The rows of ``columns`` in ``spans`` (read before by :meth:`poll`), one batch
        at a time, checked again."""
        source, reader, _ = self.rec._open(self.path)
        try:
            for s in spans:
                batch = self._read_at(source, reader, s.offset,
                                      _message_end(self.path, s.offset))
                yield {n: batch.column(n).to_numpy(zero_copy_only=False) for n in columns}
        finally:
            source.close()
