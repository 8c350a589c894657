"""The recording ring's memory, shared between the emulator and its writer process.

The emulator's loop writes rows into three preallocated blocks -- ``common`` (int64, one
row per common column), ``ints`` and ``floats`` (per axis) -- each column-major, ``slots``
rows long, and four counters; the writer process (:mod:`hil.runtime.record_process`)
maps the same memory and takes the committed rows out.  The memory is an anonymous
``memfd`` (Linux): no name to clean up, handed to the writer as a descriptor
(``subprocess``'s ``pass_fds``), freed when both have closed it.

Counters (:data:`COUNTERS`): ``committed`` (rows finished by the loop, which alone
writes it), ``drained`` (rows the writer has taken, which alone writes it), ``lost`` and
``last_lost_tick`` (ticks not recorded because the ring was full; the loop's).  The loop
writes a row's values before it raises ``committed``, and the writer reads ``committed``
before the rows and raises ``drained`` after it has written them: aligned 8-byte stores
are atomic and seen in program order on x86-64 and (with the mmap's coherence) between
processes, so neither side ever sees half a row or reuses a slot still being read.

Nothing here imports the plant or the drives: the writer process imports this module
alone with pyarrow.
"""

import mmap
import os
from dataclasses import dataclass

import numpy as np

#: the counters' order in the shared memory
COUNTERS = ("committed", "drained", "lost", "last_lost_tick")
BLOCKS = ("common", "ints", "floats")


@dataclass(frozen=True)
class RingLayout:
    """Where each column lives in the ring (JSON-ready through :meth:`as_dict`).

    Attributes:
        slots: rows the ring holds.
        n_axes: axes (the ``ints`` and ``floats`` blocks have one plane each).
        n_common: rows of the ``common`` block (int64).
        n_ints: rows per axis of the ``ints`` block (int64).
        n_floats: rows per axis of the ``floats`` block (float64).
        columns: (name, file dtype, block, axis, row) of every column, in file order
            (``axis`` 0 for the common block).
    """
    slots: int
    n_axes: int
    n_common: int
    n_ints: int
    n_floats: int
    columns: tuple[tuple[str, str, str, int, int], ...]

    def shapes(self) -> dict[str, tuple[tuple[int, ...], type]]:
        """Block name -> (shape, dtype), the counters last."""
        return {"common": ((self.n_common, self.slots), np.int64),
                "ints": ((self.n_axes, self.n_ints, self.slots), np.int64),
                "floats": ((self.n_axes, self.n_floats, self.slots), np.float64),
                "counters": ((len(COUNTERS),), np.int64)}

    def nbytes(self) -> int:
        """Bytes of shared memory the ring takes."""
        return sum(int(np.prod(shape)) * np.dtype(dtype).itemsize
                   for shape, dtype in self.shapes().values())

    def as_dict(self) -> dict:
        return {"slots": self.slots, "n_axes": self.n_axes, "n_common": self.n_common,
                "n_ints": self.n_ints, "n_floats": self.n_floats,
                "columns": [list(c) for c in self.columns]}

    @classmethod
    def from_dict(cls, d: dict) -> "RingLayout":
        return cls(d["slots"], d["n_axes"], d["n_common"], d["n_ints"], d["n_floats"],
                   tuple(tuple(c) for c in d["columns"]))


class SharedRing:
    """The ring's blocks and counters over shared memory: new (``fd`` None: a memfd made,
    every page written now so the loop takes no page fault) or the writer's mapping of
    the emulator's ``fd``.

    Attributes:
        layout: where each column lives.
        fd: the memfd (the writer gets it through ``pass_fds``).
        common, ints, floats: the blocks (views of the shared memory).
        counters: int64[4] in :data:`COUNTERS` order.
    """

    def __init__(self, layout: RingLayout, fd: int | None = None):
        if layout.slots < 2:
            raise ValueError(f"the ring needs at least 2 slots, got {layout.slots}")
        self.layout = layout
        size = layout.nbytes()
        new = fd is None
        if new:
            fd = os.memfd_create("hil-recording", os.MFD_CLOEXEC)
            try:
                os.ftruncate(fd, size)  # a file: RLIMIT_FSIZE (ulimit -f) counts it
            except OSError as e:
                os.close(fd)
                raise OSError(e.errno, f"cannot make the recording's ring of "
                              f"{layout.slots} rows ({size / 1e6:.2f} MB of shared memory): "
                              f"{e.strerror}") from e
        self.fd = fd
        self._map = mmap.mmap(fd, size)
        blocks, offset = {}, 0
        for name, (shape, dtype) in layout.shapes().items():
            blocks[name] = np.ndarray(shape, dtype, buffer=self._map, offset=offset)
            offset += blocks[name].nbytes
        self.common, self.ints, self.floats = blocks["common"], blocks["ints"], blocks["floats"]
        self.counters = blocks["counters"]
        if new:
            for block in blocks.values():
                block.fill(0)
            self.counters[COUNTERS.index("last_lost_tick")] = -1

    @property
    def committed(self) -> int:
        return int(self.counters[0])

    @property
    def drained(self) -> int:
        return int(self.counters[1])

    @property
    def lost(self) -> int:
        return int(self.counters[2])

    @property
    def last_lost_tick(self) -> int:
        return int(self.counters[3])

    def pending(self) -> tuple[int, int]:
        """(first, end) of the rows committed and not yet taken, as row numbers."""
        return self.drained, self.committed

    def columns(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Name -> rows ``start`` .. ``stop`` - 1 of each column, in the file's dtypes;
        the rows must not wrap around the ring (``stop - start <= slots - start %
        slots``).  Views into the ring where the dtype is int64 or float64: valid until
        :meth:`release`."""
        slots = self.layout.slots
        a = start % slots
        b = a + stop - start
        if b > slots:
            raise ValueError(f"rows {start}..{stop} wrap around the ring of {slots}")
        blocks = {"common": self.common, "ints": self.ints, "floats": self.floats}
        out = {}
        for name, dtype, block, axis, row in self.layout.columns:
            values = (self.common[row, a:b] if block == "common"
                      else blocks[block][axis, row, a:b])
            out[name] = values.astype(dtype, copy=False)
        return out

    def release(self, stop: int) -> None:
        """The writer has taken every row before ``stop``: their slots may be reused."""
        self.counters[1] = stop

    def close(self) -> None:
        """Unmap and close the descriptor (the arrays must not be used after)."""
        self.common = self.ints = self.floats = self.counters = None
        try:
            self._map.close()
        except BufferError:  # a view still exported somewhere: the GC unmaps it later
            pass
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
