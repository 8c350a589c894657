"""Reading a run's recording: ``recording.arrows`` and ``events.arrows`` of a run folder.

::

    rec = Recording(RUN_DIR)
    rec.meta["period_ns"], rec.units["plant_table_pos"]
    cols = rec.read(["tick", "plant_table_pos"])      # name -> numpy array
    for batch in rec.batches(["lateness_ns"]): ...   # one flush at a time, bounded memory
    rec.events()                                     # name -> array, one row per event

A stream cut short (SIGKILL, a full disk) reads up to its last complete batch; then
:attr:`Recording.truncated` is True after reading, and :meth:`Recording.closed_cleanly`
says whether the writer wrote the end-of-stream marker.

Every record batch's CRC-32 is checked as it is read, and the schema's when the file is
opened (:mod:`hil.runtime.stream_file`).  A batch that does not match its CRC, carries
none, or cannot be decoded although the file holds all of its bytes is *corrupt*: the
read stops there with a :class:`CorruptBatchError` naming the file, the batch (its index
in the stream, the schema's message not counted, and its byte offset) and how many rows
before it are intact -- or, given ``stop_at_corrupt``, ends quietly there and keeps the
error in :attr:`Recording.corrupt`.  What tells a cut-off end from a corrupt batch: the
cut-off one is the last message, whose prefix and metadata declare more bytes than the
file holds after it (:func:`_message_end`), in a stream without its end marker (a
length damaged to point past the end of such a stream is taken for the cut: the read
ends there, :attr:`Recording.truncated` set).  A
recording of the format before the checksums
(:data:`~hil.runtime.stream_file.UNCHECKED_FORMAT`) is read without checks
(:attr:`Recording.checksums` False).  Any other problem is a :class:`RecordingError`
naming the file.  The format: :mod:`hil.runtime.record_writer`.
"""

import json
import os
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hil.runtime.arrow import pa
from hil.runtime.run_folder import EVENTS, RECORDING
from hil.runtime.stream_file import (
    CRC_KEY,
    END_OF_STREAM,
    FORMAT,
    META_KEY,
    SCHEMA_CRC_KEY,
    UNCHECKED_FORMAT,
    batch_crc32,
    crc_text,
    schema_crc32,
)
from plant.files import refuse_special

#: an Arrow IPC message starts with this continuation token, then its metadata's length
_CONTINUATION = 0xFFFFFFFF
#: the Message table's field slot holding the body's length (Arrow's Message.fbs: version,
#: header_type, header, bodyLength, custom_metadata)
_BODY_LENGTH_SLOT = 3


class RecordingError(ValueError):
    """A recording that cannot be read; the message names the file and why."""


class CorruptBatchError(RecordingError):
    """A record batch that fails its check (module docstring); the message names the file,
    the batch and what is intact before it.

    Attributes:
        path: the file.
        index: the batch's index in the stream (0: the first after the schema).
        offset: its first byte in the file.
        rows_before: the rows of the batches before it, all intact.
        reason: what is wrong with it, in words.
    """

    def __init__(self, path: Path, index: int, offset: int, rows_before: int, reason: str,
                 after: str = ""):
        self.path, self.index, self.offset = path, index, offset
        self.rows_before, self.reason = rows_before, reason
        super().__init__(f"{path}: batch {index} (at byte {offset}) is corrupt: {reason}; "
                         f"the {rows_before} rows before it{after} are intact, nothing from "
                         f"it on is read")


def _field_meta(field: pa.Field, key: bytes) -> str:
    return (field.metadata or {}).get(key, b"").decode()


def _ends_with_marker(path: Path) -> bool:
    """True when the stream in ``path`` ends with the end-of-stream marker."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        size = f.tell()
        f.seek(max(0, size - len(END_OF_STREAM)))
        return f.read() == END_OF_STREAM


def _message_end(path: Path, offset: int) -> int | None:
    """Where the IPC message at ``offset`` of ``path`` ends as its prefix and metadata
    declare it (continuation token, metadata length, the Message table's ``bodyLength``),
    past the end of the file when that holds fewer bytes; None when what is there is no
    message (no continuation token, a negative length, offsets outside the metadata)."""
    with open(path, "rb") as f:
        f.seek(offset)
        prefix = f.read(8)
        if len(prefix) < 8:
            return offset + 8
        token, length = struct.unpack("<Ii", prefix)
        if token != _CONTINUATION or length < 0:
            return None
        meta = f.read(length)
    start = offset + 8
    if len(meta) < length:
        return start + length
    try:
        table = _unpack("<I", meta, 0)
        vtable = table - _unpack("<i", meta, table)
        slot = 4 + 2 * _BODY_LENGTH_SLOT
        field = _unpack("<H", meta, vtable + slot) if slot + 2 <= _unpack("<H", meta, vtable) \
            else 0
        body = _unpack("<q", meta, table + field) if field else 0
    except struct.error:
        return None
    return start + length + body if body >= 0 else None


def _unpack(fmt: str, data: bytes, pos: int) -> int:
    """The one value of ``fmt`` at ``pos`` of ``data``; struct.error outside it."""
    if pos < 0:
        raise struct.error(f"offset {pos}")
    return struct.unpack_from(fmt, data, pos)[0]


class Recording:
    """A run folder's recording (see the module docstring).

    Args:
        folder: the run folder (``hil run --record DIR``).

    Attributes:
        folder: the folder.
        meta: the run's metadata: ``period_ns``, ``rate_hz``, ``axes``, ``machine_files``,
            ``runtime``, ``adapter`` (see :meth:`hil.runtime.emulator.Emulator.metadata`).
        names: the columns, in file order.
        units: column -> unit; ``docs``: column -> meaning.
        checksums: the batches carry CRC-32s, checked as they are read (False: a
            recording of :data:`~hil.runtime.stream_file.UNCHECKED_FORMAT`).
        truncated: set once a read met the cut-off end of a stream.
        corrupt: file name -> the corrupt batch a read given ``stop_at_corrupt`` stopped
            at.
    """

    def __init__(self, folder: Path | str):
        self.folder = Path(folder)
        self.path = self.folder / RECORDING
        self.events_path = self.folder / EVENTS
        _, reader, self.checksums = self._open(self.path)
        schema = reader.schema
        self.meta = json.loads(schema.metadata[META_KEY])
        self.schema = schema
        self.names = schema.names
        self.units = {f.name: _field_meta(f, b"unit") for f in schema}
        self.docs = {f.name: _field_meta(f, b"doc") for f in schema}
        self.truncated = False
        self.corrupt: dict[str, CorruptBatchError] = {}

    @property
    def period_ns(self) -> int:
        """The loop's period, ns."""
        return int(self.meta["period_ns"])

    @staticmethod
    def _open(path: Path) -> tuple[pa.OSFile, pa.RecordBatchStreamReader, bool]:
        """The file, its stream reader past the schema, and whether its batches carry
        CRC-32s; the run's metadata and (format :data:`FORMAT`) the schema's CRC-32 are
        checked."""
        refuse_special(path, "recording", RecordingError)  # a FIFO would block the open
        try:
            source = pa.OSFile(str(path))
            reader = pa.ipc.open_stream(source)
        except (OSError, pa.ArrowException) as e:
            raise RecordingError(f"{path}: cannot read the recording: {e}") from e
        metadata = reader.schema.metadata or {}
        try:
            meta = json.loads(metadata.get(META_KEY))
        except (TypeError, ValueError) as e:
            raise RecordingError(f"{path}: no readable run metadata in the schema "
                                 f"({META_KEY.decode()}); not written by hil run, or "
                                 f"corrupt") from e
        form = meta.get("format") if isinstance(meta, dict) else None
        if form == UNCHECKED_FORMAT:
            return source, reader, False
        if form != FORMAT:
            raise RecordingError(f"{path}: format {form!r}, this version reads {FORMAT!r} "
                                 f"and {UNCHECKED_FORMAT!r}")
        stored = metadata.get(SCHEMA_CRC_KEY)
        try:
            computed = crc_text(schema_crc32(reader.schema, metadata[META_KEY]))
            why = f"CRC-32 {_shown(stored)} stored, {computed.decode()} computed"
        except UnicodeDecodeError:  # a name, unit or meaning that is no longer UTF-8
            computed, why = None, "a column's name, unit or meaning is not UTF-8"
        if stored != computed:
            raise RecordingError(f"{path}: the schema (the stream's first message: the "
                                 f"columns and the run's metadata) is corrupt: {why}")
        return source, reader, True

    def _batches(self, path: Path, stop_at_corrupt: bool) -> Iterator[pa.RecordBatch]:
        """The non-empty batches of ``path``, each checked (module docstring)."""
        source, reader, checked = self._open(path)
        index = rows = 0
        last_tick = None
        while True:
            offset = source.tell()
            try:
                batch, custom = reader.read_next_batch_with_custom_metadata()
                batch.validate(full=True)
            except StopIteration:
                return
            except (OSError, pa.ArrowException) as e:
                if self._cut_off(path, offset):
                    self.truncated = True
                    return
                reason = f"it cannot be decoded ({e})"
            else:
                reason = _crc_mismatch(batch, custom) if checked else None
            if reason is not None:
                error = CorruptBatchError(path, index, offset, rows, reason,
                                          self.ticks_before(last_tick))
                if not stop_at_corrupt:
                    raise error
                self.corrupt[path.name] = error
                return
            index += 1
            rows += batch.num_rows
            if batch.num_rows:
                if path == self.path and "tick" in self.names:
                    last_tick = batch.column("tick")[-1].as_py()
                yield batch

    def ticks_before(self, last_tick: int | None) -> str:
        """How a corrupt batch's message names the rows before it, whose last tick is
        ``last_tick`` (None: not known)."""
        return "" if last_tick is None else (
            f" (ticks up to {last_tick}, t = {last_tick * self.period_ns * 1e-9:.6f} s)")

    @staticmethod
    def _cut_off(path: Path, offset: int) -> bool:
        """The message at ``offset`` is the cut-off end of the stream: it declares more
        bytes than the file holds, and the file has no end marker."""
        end = _message_end(path, offset)
        return end is not None and end > os.path.getsize(path) and not _ends_with_marker(path)

    def batches(self, columns: list[str] | None = None,
                stop_at_corrupt: bool = False) -> Iterator[dict[str, np.ndarray]]:
        """The rows as written, one flush at a time: name -> array for ``columns`` (all
        by default).  A corrupt batch raises :class:`CorruptBatchError` after the batches
        before it, or with ``stop_at_corrupt`` ends the rows there (:attr:`corrupt`)."""
        names = self._check(columns)
        for batch in self._batches(self.path, stop_at_corrupt):
            yield {n: batch.column(n).to_numpy(zero_copy_only=False) for n in names}

    def read(self, columns: list[str] | None = None,
             stop_at_corrupt: bool = False) -> dict[str, np.ndarray]:
        """Every row of ``columns`` (all by default): name -> array (``stop_at_corrupt``:
        see :meth:`batches`)."""
        names = self._check(columns)
        parts = {n: [] for n in names}
        for batch in self.batches(names, stop_at_corrupt):
            for n in names:
                parts[n].append(batch[n])
        return {n: np.concatenate(p) if p else np.empty(0, dtype=self._dtype(n))
                for n, p in parts.items()}

    def _dtype(self, name: str) -> np.dtype:
        return self.schema.field(name).type.to_pandas_dtype()

    def _check(self, columns: list[str] | None) -> list[str]:
        names = list(self.names) if columns is None else list(columns)
        missing = [n for n in names if n not in self.names]
        if missing:
            raise RecordingError(f"{self.path}: no column {', '.join(missing)} (has "
                                 f"{len(self.names)}: {', '.join(self.names[:12])}, ...)")
        return names

    def events(self, stop_at_corrupt: bool = False) -> dict[str, np.ndarray]:
        """Every event: name -> array (:data:`hil.runtime.run_events.EVENT_COLUMNS`;
        ``stop_at_corrupt``: see :meth:`batches`)."""
        schema = self._open(self.events_path)[1].schema
        parts = {f.name: [] for f in schema}
        for batch in self._batches(self.events_path, stop_at_corrupt):
            for name in parts:
                parts[name].append(batch.column(name).to_numpy(zero_copy_only=False))
        return {n: np.concatenate(p) if p else np.empty(0, dtype=object)
                for n, p in parts.items()}

    def closed_cleanly(self) -> bool:
        """True when the recording ends with the end-of-stream marker (the writer closed
        it; after a failed write it is written too, after the last complete batch)."""
        return _ends_with_marker(self.path)


def _shown(stored: bytes | None) -> str:
    return "none" if stored is None else stored.decode(errors="replace")


def _crc_mismatch(batch: pa.RecordBatch, custom) -> str | None:
    """Why ``batch`` fails its CRC-32 (``custom``: its custom metadata), None when it
    matches."""
    stored = (custom or {}).get(CRC_KEY)
    if stored is None:
        return "it carries no checksum"
    computed = crc_text(batch_crc32(batch))
    if stored != computed:
        return f"its values do not match its CRC-32 ({_shown(stored)} stored, " \
               f"{computed.decode()} computed)"
    return None
