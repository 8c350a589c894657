"""The emulator's recording: every tick in preallocated arrays, written once as ``run.npz``.

Why ``.npz`` and not the servo-trace CSV: the emulator records at the PWM rate (8000 rows
a second on the Arrow 500 X) with raw CiA 402 words and integer nanosecond stamps; text
would be large, slow to write at shutdown and lossy for 64-bit stamps.  ``.npz`` keeps
every dtype exactly and is what ``hil report RUN`` (:mod:`hil.report.latency`) reads.  The
controller's servo trace (position-cycle rows, CNC units) is ``hil controller``'s
``trace.csv``.

One slot per deadline the loop covered (slot k = tick k; with the ``skip`` overrun policy
a dropped tick's slot holds NaN, or 0 for integers), so ``lateness_ns``/``compute_ns``
(``LoopStats``) line up with every column.  Columns (units in :data:`UNITS`):

* ``lateness_ns``, ``compute_ns`` -- the loop's own measurements;
* the round-trip stamps of :mod:`hil.report.latency` -- ``tick_start_ns``, ``sp_t_ns``,
  ``sp_rx_ns``, ``fb_t_ns``, ``fb_rx_ns`` -- only on ticks that used a newly received
  setpoint, 0 elsewhere; ``fb_rx_ns`` is always 0 (the controller's receive stamps are
  in its own ``controller.npz``: ``hil report RUN --controller DIR`` pairs them in);
* ``sp_new`` (1 on a tick that received a setpoint) and the setpoint the drive applied:
  ``sp_seq``, ``sp_controlword``, ``sp_mode``, ``sp_iq_ref_a``, ``sp_id_ref_a``,
  ``sp_ud_v``, ``sp_uq_v``, ``sp_target_position_counts``, ``sp_target_velocity_counts_s``,
  ``sp_velocity_offset_counts_s``;
* the drive: ``fb_statusword``, ``fb_fault``, ``drive_state`` (:class:`hil.cia402.State`),
  ``drive_enable`` (the plant's power stage, 0 = torque off);
* the plant after the tick: ``plant_<name>`` for every name of :data:`plant.OUTPUTS`.

On a machine of several axes (:class:`hil.drive.DriveSet`) the loop's columns, the stamps,
``sp_new`` and ``sp_seq`` are common, and every other column is there once per axis with
the axis letter in front: ``X_sp_iq_ref_a``, ``Y_plant_table_pos``, ``Y_drive_state``
(:func:`units`).  A single-axis recording keeps the names above.

Memory: about 300 bytes per tick and axis, touched when allocated (no page faults in the
loop).
"""

import os
from operator import attrgetter
from pathlib import Path

import numpy as np

from hil.drive import DriveSet, EmulatedDrive
from io_adapters.messages import axis_records
from plant import OUTPUTS
from plant import layout as L

SP_FLOATS = ("iq_ref_a", "id_ref_a", "ud_v", "uq_v", "target_position_counts",
             "target_velocity_counts_s", "velocity_offset_counts_s")
INTS = ("sp_new", "sp_seq", "sp_controlword", "sp_mode", "fb_statusword", "fb_fault",
        "drive_state", "drive_enable")
STAMPS = ("tick_start_ns", "sp_t_ns", "sp_rx_ns", "fb_t_ns", "fb_rx_ns")
_PLANT_UNITS = {"status": "1", "time_s": "s", "motor_pos": "rad (m on linear motors)",
                "motor_vel": "rad/s (m/s)", "table_pos": "m (rad on rotary tables)",
                "table_vel": "m/s (rad/s)", "encoder_counts": "counts",
                "scale_counts": "counts", "id_a": "A", "iq_a": "A", "id_meas_a": "A",
                "iq_meas_a": "A", "torque": "N*m (N on linear motors)", "ud_v": "V",
                "uq_v": "V", "nut_force_n": "N", "friction": "N (N*m on rotary tables)",
                "limit_neg": "1", "limit_pos": "1", "end_stop_force_n": "N"}
#: column -> unit
UNITS = {"lateness_ns": "ns", "compute_ns": "ns", **{s: "ns" for s in STAMPS},
         "sp_new": "1", "sp_seq": "1", "sp_controlword": "6040h", "sp_mode": "6060h",
         "sp_iq_ref_a": "A", "sp_id_ref_a": "A", "sp_ud_v": "V", "sp_uq_v": "V",
         "sp_target_position_counts": "counts", "sp_target_velocity_counts_s": "counts/s",
         "sp_velocity_offset_counts_s": "counts/s", "fb_statusword": "6041h",
         "fb_fault": "plant STATUS_* or 8130h", "drive_state": "hil.cia402.State",
         "drive_enable": "1", **{f"plant_{n}": _PLANT_UNITS[n] for n in OUTPUTS}}
RUN_NPZ = "run.npz"
#: columns a multi-axis recording has once, not per axis
COMMON = ("lateness_ns", "compute_ns", *STAMPS, "sp_new", "sp_seq")


def units(axis_names: tuple[str, ...] | None = None) -> dict:
    """Column -> unit: :data:`UNITS` for one axis (``axis_names`` None), else the common
    columns and each per-axis column per axis letter."""
    if axis_names is None:
        return dict(UNITS)
    out = {c: UNITS[c] for c in COMMON}
    for a in axis_names:
        out.update({f"{a}_{c}": u for c, u in UNITS.items() if c not in COMMON})
    return out


class Recorder:
    """Preallocated per-tick buffers for ``capacity`` deadlines, of one axis
    (``axis_names`` None: the single-axis column names) or of each axis named."""

    def __init__(self, capacity: int, axis_names: tuple[str, ...] | None = None):
        n_sp = len(SP_FLOATS)
        n_axes = 1 if axis_names is None else len(axis_names)
        self.capacity = capacity
        self.axis_names = axis_names
        self.floats = np.full((capacity, n_axes, n_sp + L.O_COUNT), np.nan)
        self.ints = np.zeros((capacity, n_axes, len(INTS)), dtype=np.int64)
        self.stamps = np.zeros((capacity, len(STAMPS)), dtype=np.int64)
        self._sp_floats = attrgetter(*SP_FLOATS)
        self._sp = slice(0, n_sp)
        self._out = slice(n_sp, n_sp + L.O_COUNT)

    def record(self, k: int, heard: bool, tick_start_ns: int, sp, fb,
               drives: EmulatedDrive | DriveSet) -> None:
        """Slot ``k``: the setpoint applied, the drives' answer and the plants' outputs
        (``sp``/``fb`` plain records or groups, ``drives`` one drive or a DriveSet)."""
        rows, ints = self.floats[k], self.ints[k]
        each = drives.drives if isinstance(drives, DriveSet) else (drives,)
        for i, (s, f, drive) in enumerate(zip(axis_records(sp), axis_records(fb), each)):
            row = rows[i]
            row[self._sp] = self._sp_floats(s)
            row[self._out] = drive.plant.out
            ints[i] = (heard, sp.seq, s.controlword, s.mode, f.statusword, f.fault,
                       drive.sm.state, drive.plant.inp[L.I_ENABLE])
        if heard:
            self.stamps[k] = (tick_start_ns, sp.t_ns, sp.rx_ns, fb.t_ns, 0)

    def columns(self, lateness_ns: np.ndarray, compute_ns: np.ndarray) -> dict:
        """Named 1-D columns over the slots the loop covered (``len(lateness_ns)``)."""
        n = len(lateness_ns)
        cols = {"lateness_ns": np.array(lateness_ns), "compute_ns": np.array(compute_ns)}
        for i, name in enumerate(STAMPS):
            cols[name] = self.stamps[:n, i].copy()
        for a, prefix in enumerate(("",) if self.axis_names is None
                                   else tuple(f"{x}_" for x in self.axis_names)):
            for i, name in enumerate(INTS):
                key = name if name in COMMON else prefix + name
                if key not in cols:
                    cols[key] = self.ints[:n, a, i].copy()
            for i, name in enumerate(SP_FLOATS):
                cols[f"{prefix}sp_{name}"] = self.floats[:n, a, i].copy()
            for name, index in OUTPUTS.items():
                cols[f"{prefix}plant_{name}"] = self.floats[:n, a, len(SP_FLOATS) + index].copy()
        return cols


def write_npz(path: Path, columns: dict) -> Path:
    """Write the columns atomically: ``path`` is complete or absent."""
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **columns)
    os.replace(tmp, path)
    return path
