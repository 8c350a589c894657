"""Reading a run's recording: ``recording.arrows`` and ``events.arrows`` of a run folder.

::

    rec = Recording(RUN_DIR)
    rec.meta["period_ns"], rec.units["plant_table_pos"]
    cols = rec.read(["tick", "plant_table_pos"])      # name -> numpy array
    for batch in rec.batches(["lateness_ns"]): ...   # one flush at a time, bounded memory
    rec.events()                                     # name -> array, one row per event

A stream cut short (SIGKILL, a full disk) reads up to its last complete batch; then
:attr:`Recording.truncated` is True after reading, and :meth:`Recording.closed_cleanly`
says whether the writer wrote the end-of-stream marker.  Any other problem is a
:class:`RecordingError` naming the file.  The format: :mod:`hil.runtime.record_writer`.
"""

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from hil.runtime.arrow import pa
from hil.runtime.run_folder import EVENTS, RECORDING
from hil.runtime.stream_file import END_OF_STREAM, FORMAT, META_KEY


class RecordingError(ValueError):
    """A recording that cannot be read; the message names the file and why."""


def _field_meta(field: pa.Field, key: bytes) -> str:
    return (field.metadata or {}).get(key, b"").decode()


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
        truncated: set once a read met the cut-off end of a stream.
    """

    def __init__(self, folder: Path | str):
        self.folder = Path(folder)
        self.path = self.folder / RECORDING
        self.events_path = self.folder / EVENTS
        schema = self._open(self.path).schema
        blob = (schema.metadata or {}).get(META_KEY)
        try:
            self.meta = json.loads(blob)
        except (TypeError, ValueError) as e:
            raise RecordingError(f"{self.path}: no run metadata in the schema "
                                 f"({META_KEY.decode()}); not written by hil run") from e
        if self.meta.get("format") != FORMAT:
            raise RecordingError(f"{self.path}: format {self.meta.get('format')!r}, this "
                                 f"version reads {FORMAT!r}")
        self.schema = schema
        self.names = schema.names
        self.units = {f.name: _field_meta(f, b"unit") for f in schema}
        self.docs = {f.name: _field_meta(f, b"doc") for f in schema}
        self.truncated = False

    @property
    def period_ns(self) -> int:
        """The loop's period, ns."""
        return int(self.meta["period_ns"])

    @staticmethod
    def _open(path: Path) -> pa.RecordBatchStreamReader:
        try:
            return pa.ipc.open_stream(pa.OSFile(str(path)))
        except (OSError, pa.ArrowInvalid) as e:
            raise RecordingError(f"{path}: cannot read the recording: {e}") from e

    def _batches(self, path: Path) -> Iterator[pa.RecordBatch]:
        reader = self._open(path)
        while True:
            try:
                batch = reader.read_next_batch()
            except StopIteration:
                return
            except (OSError, pa.ArrowInvalid):
                self.truncated = True  # the rest was cut off
                return
            if batch.num_rows:
                yield batch

    def batches(self, columns: list[str] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """The rows as written, one flush at a time: name -> array for ``columns`` (all
        by default)."""
        names = self._check(columns)
        for batch in self._batches(self.path):
            yield {n: batch.column(n).to_numpy(zero_copy_only=False) for n in names}

    def read(self, columns: list[str] | None = None) -> dict[str, np.ndarray]:
        """Every row of ``columns`` (all by default): name -> array."""
        names = self._check(columns)
        parts = {n: [] for n in names}
        for batch in self.batches(names):
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

    def events(self) -> dict[str, np.ndarray]:
        """Every event: name -> array (:data:`hil.runtime.run_events.EVENT_COLUMNS`)."""
        schema = self._open(self.events_path).schema
        parts = {f.name: [] for f in schema}
        for batch in self._batches(self.events_path):
            for name in parts:
                parts[name].append(batch.column(name).to_numpy(zero_copy_only=False))
        return {n: np.concatenate(p) if p else np.empty(0, dtype=object)
                for n, p in parts.items()}

    def closed_cleanly(self) -> bool:
        """True when the recording ends with the end-of-stream marker (the writer closed
        it; after a failed write it is written too, after the last complete batch)."""
        with open(self.path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - len(END_OF_STREAM)))
            return f.read() == END_OF_STREAM
