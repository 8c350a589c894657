"""The emulator's recording: one row per tick in a preallocated ring, drained to disk.

The loop must neither allocate nor block, and a run may last a day, so nothing here grows
with the run: :class:`Recorder` holds :attr:`Recorder.slots` rows (about one second, see
:data:`hil.runtime.record_writer.RING_S`) in shared memory allocated and touched before
the clock starts (:mod:`hil.runtime.ring`).  The tick writes its row
(:meth:`Recorder.record`, from the emulator's step; then :meth:`Recorder.end_tick` with
the loop's own measurements, from :class:`~hil.runtime.streaming_loop.StreamingLoop`), and
the writer process (:mod:`hil.runtime.record_process`) takes the committed rows out of
the same memory.  A row the
writer has not taken yet is never overwritten: when the ring is full the tick is not
recorded but counted (:attr:`Recorder.lost`), and the loop keeps its period.

One row per tick that ran, tick k carrying ``tick = k`` (a deadline the ``skip`` overrun
policy dropped has no row).  Columns (:func:`column_specs`: dtype, unit, meaning):

* ``tick``, ``lateness_ns``, ``compute_ns``: the loop's deadline index and measurements;
* the round-trip stamps of :mod:`hil.report.latency` -- ``tick_start_ns``, ``sp_t_ns``,
  ``sp_rx_ns``, ``fb_t_ns`` -- only on ticks that used a newly received setpoint, 0
  elsewhere (the controller's receive stamp is in its own ``controller.npz``: ``hil
  report RUN --controller DIR`` pairs it in);
* ``sp_refused`` (bit ``a`` set when the adapter refused axis ``a``'s setpoint in the
  tick: the drive latched a fault for it; :mod:`hil.replay` needs it);
* ``sp_new`` (1 on a tick that received a setpoint) and the setpoint the drive applied:
  ``sp_seq``, ``sp_controlword``, ``sp_mode``, ``sp_iq_ref_a``, ``sp_id_ref_a``,
  ``sp_ud_v``, ``sp_uq_v``, ``sp_target_position_counts``, ``sp_target_velocity_counts_s``,
  ``sp_velocity_offset_counts_s``;
* the drive: ``fb_statusword``, ``fb_fault`` (603Fh), ``drive_state``
  (:class:`hil.cia402.State`), ``drive_enable`` (the plant's power stage, 0 = torque off);
* the plant after the tick: ``plant_<name>`` for every name of :data:`plant.OUTPUTS`
  (float64, but currents, voltages, forces and torques in float32: see
  :data:`_PLANT_FLOAT32`).

On a machine of several axes (:class:`hil.drive.DriveSet`) the loop's columns, the stamps,
``sp_new`` and ``sp_seq`` are common, and every other column is there once per axis with
the axis letter in front: ``X_sp_iq_ref_a``, ``Y_plant_table_pos``, ``Y_drive_state``
(:func:`column_specs`).  A single-axis recording keeps the names above.  Each column's
unit is its axis's: ``plant_table_pos`` is in m on a screw or linear axis, in rad on a
rotary table.

Each tick a drive's fault log grows (:class:`hil.drive.faults.FaultLog`) is noted in
:attr:`Recorder.fault_marks`, so the events in the recording carry the tick they
happened in (:mod:`hil.runtime.run_events`).
"""

from collections import deque
from dataclasses import dataclass
from operator import attrgetter

import numpy as np

from hil.drive import DriveSet, EmulatedDrive, compiled
from hil.runtime.ring import RingLayout, SharedRing
from io_adapters.messages import axis_records
from plant import OUTPUTS
from plant import layout as L
from plant.sections import KINDS


@dataclass(frozen=True)
class ColumnSpec:
    """One column of the recording.

    Attributes:
        name: its name in the file.
        dtype: numpy dtype on disk.
        unit: its unit ("1" for dimensionless, a CiA object for words).
        doc: what it is (the channel comment of an MDF4 export).
    """
    name: str
    dtype: str
    unit: str
    doc: str


#: the setpoint's float columns, in the ring's order (the compiled drive cycle writes them)
SP_FLOATS = compiled.SP_FLOATS
#: the loop's columns, written by :meth:`Recorder.end_tick`
LOOP = ("tick", "lateness_ns", "compute_ns")
STAMPS = ("tick_start_ns", "sp_t_ns", "sp_rx_ns", "fb_t_ns")
#: per-axis integer columns
AXIS_INTS = compiled.RING_INTS
#: a plant output's unit by the axis's kind (:data:`plant.sections.KINDS` order: screw,
#: linear, rotary), or one unit for all, and its meaning
_PLANT = {"status": ("1", "kernel status of the last call (plant.layout STATUS_*)"),
          "time_s": ("s", "plant time at the end of the tick"),
          "motor_pos": (("rad", "m", "rad"), "motor angle (linear motor: position)"),
          "motor_vel": (("rad/s", "m/s", "rad/s"), "motor speed"),
          "table_pos": (("m", "m", "rad"), "table position (true)"),
          "table_vel": (("m/s", "m/s", "rad/s"), "table velocity (true)"),
          "encoder_counts": ("counts", "motor encoder as measured"),
          "scale_counts": ("counts", "linear scale as measured (0 without a scale)"),
          "id_a": ("A", "d current (true)"), "iq_a": ("A", "q current (true)"),
          "id_meas_a": ("A", "d current as measured"),
          "iq_meas_a": ("A", "q current as measured"),
          "torque": (("N*m", "N", "N*m"), "motor torque (linear motor: force)"),
          "ud_v": ("V", "d voltage applied"), "uq_v": ("V", "q voltage applied"),
          "nut_force_n": ("N", "axial force in the nut"),
          "friction": (("N", "N", "N*m"), "table friction"),
          "limit_neg": ("1", "negative limit switch (1: beyond it)"),
          "limit_pos": ("1", "positive limit switch (1: beyond it)"),
          "end_stop_force_n": ("N", "end-stop contact force, + toward +x"),
          "home_switch": ("1", "home switch (1: on the cam)"),
          "index_marks": ("1", "encoder index marks below its position (a whole number)")}
#: plant outputs kept as float32: currents, voltages, forces and torques, whose 24-bit
#: mantissa (a relative 6e-8) is far below their physical resolution (a current ADC's step
#: is 1e-3 of full scale), which saves a quarter of the file.  Positions, velocities,
#: counts and time stay float64: a 22-bit encoder's count at 100 rad is below float32's
#: step there.
_PLANT_FLOAT32 = frozenset({"id_a", "iq_a", "id_meas_a", "iq_meas_a", "torque", "ud_v", "uq_v",
                            "nut_force_n", "friction", "end_stop_force_n"})
#: common columns, in file order
_COMMON = [
    ColumnSpec("tick", "int64", "1", "deadline index of the tick (t = tick * period)"),
    ColumnSpec("lateness_ns", "int64", "ns", "wake-up time - deadline"),
    ColumnSpec("compute_ns", "int64", "ns", "end of the step - wake-up time"),
    ColumnSpec("tick_start_ns", "int64", "ns", "drive clock at the start of a tick that "
               "used a new setpoint (0: none)"),
    ColumnSpec("sp_t_ns", "int64", "ns", "controller clock when that setpoint was sent"),
    ColumnSpec("sp_rx_ns", "int64", "ns", "drive clock when that setpoint arrived"),
    ColumnSpec("fb_t_ns", "int64", "ns", "drive clock when the tick's feedback was sent"),
    ColumnSpec("sp_new", "uint8", "1", "1 on a tick that received a new setpoint"),
    ColumnSpec("sp_seq", "uint32", "1", "sequence number of the setpoint applied"),
    ColumnSpec("sp_refused", "uint32", "1", "bit a: the adapter refused axis a's setpoint "
               "in the tick (0: none)"),
]
#: per-axis columns (without the axis prefix), in file order
_AXIS = [
    ColumnSpec("sp_controlword", "uint16", "-", "controlword 6040h applied"),
    ColumnSpec("sp_mode", "int8", "-", "mode of operation 6060h applied (8 CSP, 9 CSV, "
               "10 CST, -1 voltage)"),
    ColumnSpec("fb_statusword", "uint16", "-", "statusword 6041h answered"),
    ColumnSpec("fb_fault", "uint16", "-", "error code 603Fh answered (0: no fault)"),
    ColumnSpec("drive_state", "uint8", "-", "CiA 402 state after the tick "
               "(hil.cia402.State)"),
    ColumnSpec("drive_enable", "uint8", "1", "power stage on (0: torque off)"),
    ColumnSpec("sp_iq_ref_a", "float64", "A", "q-current setpoint (CST; feed-forward in "
               "CSP/CSV)"),
    ColumnSpec("sp_id_ref_a", "float64", "A", "d-current setpoint"),
    ColumnSpec("sp_ud_v", "float64", "V", "d-voltage setpoint (voltage mode)"),
    ColumnSpec("sp_uq_v", "float64", "V", "q-voltage setpoint (voltage mode)"),
    ColumnSpec("sp_target_position_counts", "float64", "counts", "CSP target 607Ah"),
    ColumnSpec("sp_target_velocity_counts_s", "float64", "counts/s", "CSV target 60FFh"),
    ColumnSpec("sp_velocity_offset_counts_s", "float64", "counts/s",
               "speed feed-forward 60B1h"),
    *(ColumnSpec(f"plant_{n}", "float32" if n in _PLANT_FLOAT32 else "float64",
                 *_PLANT.get(n, ("", "plant output")))
      for n in OUTPUTS),
]
_KIND_INDEX = {kind: i for i, kind in enumerate(KINDS)}
#: the plant outputs the recording documents (a new output without an entry in _PLANT is
#: recorded with an empty unit; tests/test_recording.py asks for one)
PLANT_DOCUMENTED = tuple(_PLANT)


def column_specs(kinds: tuple[str, ...],
                 axis_names: tuple[str, ...] | None = None) -> list[ColumnSpec]:
    """The recording's columns in file order for axes of ``kinds`` (``[machine] kind``
    each, which sets the plant outputs' units): one axis (``axis_names`` None: no
    prefix), or the common columns and each per-axis column per axis letter."""
    prefixes = ("",) if axis_names is None else tuple(f"{a}_" for a in axis_names)
    if len(prefixes) != len(kinds):
        raise ValueError(f"{len(kinds)} kinds for {len(prefixes)} axes")
    return [*_COMMON, *(ColumnSpec(prefix + c.name, c.dtype, _unit(c.unit, kind), c.doc)
                        for prefix, kind in zip(prefixes, kinds) for c in _AXIS)]


def _unit(unit: str | tuple[str, ...], kind: str) -> str:
    return unit if isinstance(unit, str) else unit[_KIND_INDEX[kind]]


def units(kinds: tuple[str, ...], axis_names: tuple[str, ...] | None = None) -> dict[str, str]:
    """Column -> unit (see :func:`column_specs`)."""
    return {c.name: c.unit for c in column_specs(kinds, axis_names)}


def row_bytes(n_axes: int) -> int:
    """Bytes of one row of ``n_axes`` axes, uncompressed."""
    return (sum(np.dtype(c.dtype).itemsize for c in _COMMON)
            + n_axes * sum(np.dtype(c.dtype).itemsize for c in _AXIS))


class Recorder:
    """The ring of rows (see the module docstring) for axes of ``kinds`` (``[machine]
    kind`` each): one axis (``axis_names`` None: the single-axis column names) or each
    axis named.

    Attributes:
        slots: rows the ring holds.
        ring: its memory, shared with the writer process
            (:class:`~hil.runtime.ring.SharedRing`).
        committed: rows finished so far (by :meth:`end_tick`).
        drained: rows the writer has taken (:meth:`release`).
        lost: ticks not recorded because the ring was full.
        last_lost_tick: the last of them (-1: none).
        fault_marks: (tick, axis, fault events logged so far) each tick a drive's fault
            log grew; the writer's event thread takes them out (a deque: one thread
            appends, the other pops).
    """

    def __init__(self, slots: int, kinds: tuple[str, ...],
                 axis_names: tuple[str, ...] | None = None):
        self.slots = slots
        self.axis_names = axis_names
        self.specs = column_specs(kinds, axis_names)
        # column-major: a run of rows of one column is contiguous, so the writer hands
        # slices to the file without copying them
        self.ring = SharedRing(_layout(slots, len(kinds), axis_names))
        self.common, self.ints, self.floats = self.ring.common, self.ring.ints, self.ring.floats
        self._counters = self.ring.counters
        self.fault_marks: deque[tuple[int, int, int]] = deque()
        self._faults_seen = [0] * len(kinds)
        self._skip = False
        self._sp_floats = attrgetter(*SP_FLOATS)
        self._n_sp = len(SP_FLOATS)
        self._compiled = ()
        self._row = -1

    @property
    def committed(self) -> int:
        return self.ring.committed

    @property
    def drained(self) -> int:
        return self.ring.drained

    @property
    def lost(self) -> int:
        return self.ring.lost

    @property
    def last_lost_tick(self) -> int:
        return self.ring.last_lost_tick

    def attach(self, drives: EmulatedDrive | DriveSet) -> None:
        """Let the drives' compiled paths write their axis's row themselves (in the same
        compiled call as the cycle, :mod:`hil.drive.compiled`); :meth:`begin_tick` then
        tells them where."""
        each = drives.drives if isinstance(drives, DriveSet) else (drives,)
        self._compiled = tuple(d.compiled for d in each)
        for i, path in enumerate(self._compiled):
            if path is not None:
                path.bind_ring(self.floats[i], self.ints[i])

    def _next_column(self) -> int:
        """The ring's column for the next row, or -1 when the ring is full."""
        counters = self._counters
        committed = counters[0]
        return -1 if committed - counters[1] >= self.slots else committed % self.slots

    def begin_tick(self) -> None:
        """Before the drive cycles of a tick: the row the attached compiled paths write
        (none when the ring is full)."""
        self._row = self._next_column()
        for path in self._compiled:
            if path is not None:
                path.set_row(self._row)

    def wrote_row(self, j: int) -> None:
        """A tick wrote its whole row in compiled code (:mod:`hil.runtime.steady_tick`:
        the axis's part and the common part that :meth:`record` writes; no drive's fault
        log grows in such a tick) at column ``j``, or none (-1: the ring was full;
        :meth:`end_tick` then counts the tick lost)."""
        self._skip = j < 0

    def record(self, k: int, heard: bool, tick_start_ns: int, sp, fb,
               drives: EmulatedDrive | DriveSet, refused: int = 0) -> None:
        """Tick ``k``'s row: the setpoint applied, the drives' answer and the plants'
        outputs (``sp``/``fb`` plain records or groups, ``drives`` one drive or a
        DriveSet), ``refused`` the adapter's refused axes (bit mask).  Not recorded
        (counted by :meth:`end_tick`) when the ring is full."""
        each = drives.drives if isinstance(drives, DriveSet) else (drives,)
        for i, drive in enumerate(each):
            n = drive.faults.n_events
            if n != self._faults_seen[i]:
                self._faults_seen[i] = n
                self.fault_marks.append((k, i, n))
        j, n_sp = self._next_column(), self._n_sp
        self._skip = j < 0
        if self._skip:
            return
        floats, ints = self.floats, self.ints
        for i, (s, f, drive) in enumerate(zip(axis_records(sp), axis_records(fb), each)):
            path = drive.compiled
            if path is not None:
                written = path.row_written and j == self._row
                path.set_row(-1)  # a cycle outside the tick (the safe state) writes none
                if written:
                    continue  # the compiled cycle wrote this axis's row
            floats[i, :n_sp, j] = self._sp_floats(s)
            floats[i, n_sp:, j] = drive.plant.out
            ints[i, :, j] = (s.controlword, s.mode, f.statusword, f.fault, drive.sm.state,
                             drive.plant.inp[L.I_ENABLE])
        self.common[3:, j] = ((tick_start_ns, sp.t_ns, sp.rx_ns, fb.t_ns, 1, sp.seq, refused)
                              if heard else (0, 0, 0, 0, 0, sp.seq, refused))

    def end_tick(self, k: int, lateness_ns: int, compute_ns: int) -> None:
        """Finish tick ``k``'s row with the loop's measurements (the loop calls this after
        the step)."""
        counters = self._counters
        if self._skip:
            counters[2] += 1
            counters[3] = k
            return
        j, common = counters[0] % self.slots, self.common
        common[0, j] = k  # three scalar stores take half the time of a slice from a tuple
        common[1, j] = lateness_ns
        common[2, j] = compute_ns
        counters[0] += 1  # after the row: the writer reads rows below this count

    def pending(self) -> tuple[int, int]:
        """(first, end) of the rows committed and not yet taken, as row numbers."""
        return self.ring.pending()

    def columns(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Name -> rows ``start`` .. ``stop`` - 1 of each column (see
        :meth:`hil.runtime.ring.SharedRing.columns`)."""
        return self.ring.columns(start, stop)

    def release(self, stop: int) -> None:
        """Every row before ``stop`` has been taken: their slots may be reused."""
        self.ring.release(stop)


def _layout(slots: int, n_axes: int, axis_names: tuple[str, ...] | None) -> RingLayout:
    """Where each column of :func:`column_specs` lives in the ring."""
    prefixes = ("",) if axis_names is None else tuple(f"{x}_" for x in axis_names)
    n_ints = len(AXIS_INTS)
    columns = [(c.name, c.dtype, "common", 0, row) for row, c in enumerate(_COMMON)]
    for axis, prefix in enumerate(prefixes):
        columns += [(prefix + c.name, c.dtype, "ints", axis, row)
                    for row, c in enumerate(_AXIS[:n_ints])]
        columns += [(prefix + c.name, c.dtype, "floats", axis, row)
                    for row, c in enumerate(_AXIS[n_ints:])]
    return RingLayout(slots, n_axes, len(_COMMON), n_ints, len(_AXIS) - n_ints,
                      tuple(columns))
