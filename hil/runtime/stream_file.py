"""One Arrow IPC stream written to a file of the run folder, batch by batch.

Why the Arrow IPC *stream* format (``.arrows``, pyarrow): it is made for appending --
each flush is one self-contained record batch after the schema, nothing earlier in the
file is ever rewritten, and no footer or index is needed to read it -- so a file cut
short by SIGKILL, the OOM killer or a full disk reads up to its last complete batch
(:mod:`hil.runtime.record_reader`).  It is columnar with exact dtypes (int64 ns stamps,
uint16 CiA words), its buffers are zstd-compressed (a moving axis at 8 kHz: about
87 bytes per tick instead of 262), and pyarrow, pandas and polars read it as it is.
(The Arrow *file* format would need its footer, written at close; HDF5 in SWMR mode needs
its library's cooperation to be readable after a crash.)
"""

import os

import numpy as np

from hil.runtime.arrow import pa

#: the streams' buffers are compressed with this codec
COMPRESSION = "zstd"
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


def schema_of(specs, meta: bytes) -> pa.Schema:
    """The schema of columns ``specs`` ((name, numpy dtype or "string", unit, doc) each),
    the run's metadata ``meta`` (JSON) under :data:`META_KEY`."""
    return pa.schema([pa.field(name, pa.from_numpy_dtype(np.dtype(dtype)) if dtype != "string"
                               else pa.string(), metadata={"unit": unit, "doc": doc})
                      for name, dtype, unit, doc in specs], metadata={META_KEY: meta})


class ArrowStream:
    """One Arrow IPC stream written to the open file ``fd`` (``path`` names it in
    errors); the schema is on disk when this returns.

    Attributes:
        good: the offset after the last complete batch.
        broken: a write has failed.
    """

    def __init__(self, fd: int, path: str, schema: pa.Schema):
        self.path = path
        self.schema = schema
        self.sink = _FdSink(fd)
        self.writer = pa.ipc.new_stream(
            self.sink, schema, options=pa.ipc.IpcWriteOptions(compression=COMPRESSION))
        self.good = 0
        self.broken = False
        self.write(pa.RecordBatch.from_pylist([], schema=schema))

    def write(self, batch: pa.RecordBatch) -> None:
        """Append ``batch``; an OSError names this file."""
        try:
            self.writer.write_batch(batch)
        except OSError as e:
            self.broken = True
            raise OSError(e.errno, e.strerror, self.path) from e
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
