"""One axis of a recording as a servo trace (``../shared/docs/trace-format.md``): which
recording columns make which trace column, in the trace's units (mm or deg, mm/min or
deg/min, A).

What the emulated drive sees is what it can trace: its setpoint as the controller sent it
and its plant's sensors.  So, per row:

===================  ==========================================================================
trace column         from the recording
===================  ==========================================================================
``t_s``              ``tick`` times the period (exact decimals: :meth:`AxisTrace.t_s`)
``pos_set_mm``       the CSP target 607Ah in table units; empty (NaN) in rows not in CSP
``pos_mm``           the linear scale (``plant_scale_counts``); without one the motor encoder
``vel_set_mm_min``   CSP: the speed feed-forward 60B1h; CSV: the target 60FFh; else NaN
``vel_mm_min``       the table's velocity (the plant's, there is no velocity sensor)
``iq_set_a``         CST: the q-current setpoint; else NaN (the drive's own speed loop's
                     output is not recorded)
``iq_a``             the measured q current
``motor_pos_mm``     the motor encoder in table units
===================  ==========================================================================

A CST or CSV run's position setpoint (and a CST run's velocity setpoint) stays in the
controller; :class:`ControllerSetpoints` takes them from ``hil controller``'s
``controller.npz``, for the setpoint each tick applied (``hil export --controller DIR``).

Rotary tables have ``_deg`` columns.  Counts become table units through the axis's
``table_per_count`` in the recording's metadata (the lead over the counts per
revolution on a screw axis).
"""

import json
import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from hil.decimal_grid import decimal_step, on_grid
from hil.runtime.record_reader import Recording, RecordingError
from hil.runtime.run_folder import REPORT
from hil.runtime.timing_quality import TimingQuality
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_CSV

#: the trace columns, in file order, without their unit suffix (see the module docstring)
_COLUMNS = ("t_s", "pos_set", "pos", "vel_set", "vel", "iq_set_a", "iq_a", "motor_pos")


@dataclass(frozen=True)
class AxisTrace:
    """How one axis of a recording becomes a servo trace.

    Attributes:
        name: the axis letter.
        prefix: its column prefix in the recording ("" on a single-axis run).
        rotary: positions are angles (deg in the trace).
        table_per_count: table units (m or rad) per motor-encoder count.
        scale_resolution_m: the linear scale's count, m (0: none).
        period_s: the recording's sample time, s.
    """
    name: str
    prefix: str
    rotary: bool
    table_per_count: float
    scale_resolution_m: float
    period_s: float

    @property
    def unit(self) -> str:
        """The trace's position unit: "deg" or "mm"."""
        return "deg" if self.rotary else "mm"

    @property
    def k(self) -> float:
        """Trace position units per SI unit (deg/rad or mm/m)."""
        return 180.0 / math.pi if self.rotary else 1e3

    def names(self) -> list[str]:
        """The trace's column names, in file order."""
        u = self.unit
        return [f"{c}_{u}" if c in ("pos_set", "pos", "motor_pos") else
                f"{c}_{u}_min" if c in ("vel_set", "vel") else c for c in _COLUMNS]

    def sources(self) -> list[str]:
        """The recording columns :meth:`convert` needs."""
        return ["tick", *(self.prefix + c for c in (
            "sp_mode", "sp_target_position_counts", "sp_target_velocity_counts_s",
            "sp_velocity_offset_counts_s", "sp_iq_ref_a", "plant_encoder_counts",
            "plant_scale_counts", "plant_table_vel", "plant_iq_meas_a"))]

    def t_s(self, tick: np.ndarray) -> np.ndarray:
        """The times of ``tick`` (deadline indices), s: on the period's grid, so that each
        prints as its exact decimal (:mod:`hil.decimal_grid`)."""
        return on_grid(tick, decimal_step(self.period_s))

    def per_count(self) -> Fraction:
        """Trace position units (mm or deg) per motor-encoder count: the decimal the
        metadata's ``table_per_count`` stands for, in mm exactly; in deg through the one
        rounding of 180/pi."""
        if self.rotary:
            return decimal_step(self.table_per_count * self.k)
        return decimal_step(self.table_per_count) * 1000

    def convert(self, rows: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Trace columns (name -> float array) of recording ``rows`` (:meth:`sources`);
        times and counts on their grids (:meth:`t_s`, :meth:`per_count`), so that a
        position of the 0.1 µm scale prints with at most 4 decimals in mm."""
        p, step = self.prefix, self.per_count()
        mode = rows[p + "sp_mode"]
        encoder = on_grid(rows[p + "plant_encoder_counts"], step)
        pos = (on_grid(rows[p + "plant_scale_counts"],
                       decimal_step(self.scale_resolution_m) * 1000)
               if self.scale_resolution_m else encoder)
        per_min = step * 60
        vel_set = np.where(mode == MODE_CSP,
                           on_grid(rows[p + "sp_velocity_offset_counts_s"], per_min),
                           np.where(mode == MODE_CSV,
                                    on_grid(rows[p + "sp_target_velocity_counts_s"], per_min),
                                    np.nan))
        values = (self.t_s(rows["tick"]),
                  np.where(mode == MODE_CSP,
                           on_grid(rows[p + "sp_target_position_counts"], step), np.nan),
                  pos, vel_set, rows[p + "plant_table_vel"] * (self.k * 60.0),
                  np.where(mode == MODE_CST, rows[p + "sp_iq_ref_a"], np.nan),
                  rows[p + "plant_iq_meas_a"], encoder)
        return {name: np.asarray(v, dtype=np.float64) for name, v in zip(self.names(), values)}

    def metadata(self, rec: Recording, stop_at_corrupt: bool = False) -> dict[str, str]:
        """The trace header's ``# key: value`` lines; each fault injected into this axis
        (the recording's ``inject`` events) as ``injected_N: T s: what``
        (``stop_at_corrupt``: see :meth:`Recording.batches
        <hil.runtime.record_reader.Recording.batches>`)."""
        ev = rec.events(stop_at_corrupt)
        injected = [f"{t:.6g} s: {why}" for t, src, kind, axis, why in zip(
            ev["t_s"], ev["source"], ev["kind"], ev["axis"], ev["reason"])
            if src == "inject" and kind == "injected" and axis == self.name]
        return {"sample_time_s": repr(self.period_s), "axis": self.name,
                "machine": rec.meta.get("machine", ""),
                "machine_file": rec.meta.get("machine_file", ""),
                "source": f"hil run recording {rec.folder} (adapter {rec.meta.get('adapter')})",
                **{f"injected_{i + 1}": text for i, text in enumerate(injected)},
                **run_timing(rec.folder)}


@dataclass(frozen=True)
class ControllerSetpoints:
    """One axis's position and velocity setpoints as ``hil controller`` computed them
    (its ``controller.npz``), found for each drive tick by the sequence number of the
    setpoint the tick applied (``sp_seq``): tick k of the controller sent sequence number
    ``k + seq_minus_k`` (mod 2**32).

    Attributes:
        source: the file, for the trace's header.
        k: the controller ticks recorded, ascending.
        x_set: the position setpoint of each, m (rad on a rotary table).
        v_set: the velocity setpoint (the NC's feed-forward) of each, m/s (rad/s).
        seq_minus_k: the sequence number of tick k's setpoint less k.
    """
    source: Path
    k: np.ndarray
    x_set: np.ndarray
    v_set: np.ndarray
    seq_minus_k: int

    @classmethod
    def load(cls, folder: Path, axis: str) -> "ControllerSetpoints":
        """``axis``'s setpoints from ``folder/controller.npz``.

        Raises:
            RecordingError: no such file, no such axis in it, or a file of a version
                before the sequence numbers were kept.
        """
        path = folder / "controller.npz"
        try:
            npz = np.load(path)
        except (OSError, ValueError) as e:
            raise RecordingError(f"{path}: cannot read it: {e}") from e
        with npz:  # only the four columns used are read from the file
            prefix = "" if "x_set" in npz.files else f"{axis}_"
            if f"{prefix}x_set" not in npz.files:
                raise RecordingError(f"{path}: no setpoints of axis {axis}")
            if "seq_minus_k" not in npz.files:
                raise RecordingError(f"{path}: written by a hil controller that did not "
                                     "keep its setpoints' sequence numbers; run it again")
            return cls(path, npz["k"].astype(np.int64), npz[f"{prefix}x_set"],
                       npz[f"{prefix}v_set"], int(npz["seq_minus_k"]))

    def at(self, sp_seq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) setpoints of the setpoints numbered ``sp_seq`` (SI); NaN
        where the controller recorded no such tick (before its program, after it)."""
        if self.k.size == 0:
            return np.full(sp_seq.shape, np.nan), np.full(sp_seq.shape, np.nan)
        k = (sp_seq.astype(np.int64) - self.seq_minus_k) % (1 << 32)
        i = np.clip(np.searchsorted(self.k, k), 0, self.k.size - 1)
        found = self.k[i] == k
        return np.where(found, self.x_set[i], np.nan), np.where(found, self.v_set[i], np.nan)


def run_timing(folder: Path) -> dict[str, str]:
    """The run's timing for a trace header (:meth:`TimingQuality.header
    <hil.runtime.timing_quality.TimingQuality.header>`), from its ``report.json``; says
    so when there is none (a run cut short)."""
    try:
        report = json.loads((folder / REPORT).read_text())
        return TimingQuality.of_emulator(report).header()
    except (OSError, ValueError, KeyError):
        return {"timing_within_limits": f"unknown (no readable {REPORT}: the run was cut "
                                        "short?)"}


def axis_trace(rec: Recording, axis: str | None = None) -> AxisTrace:
    """The servo-trace view of ``axis`` (a letter; None: the only axis) of ``rec``.

    Raises:
        RecordingError: no such axis, or None on a recording of several axes.
    """
    axes = {a["name"]: a for a in rec.meta.get("axes", [])}
    if axis is None:
        if len(axes) != 1:
            raise RecordingError(f"{rec.path}: the recording has axes {', '.join(axes)}: "
                                 "name one")
        axis = next(iter(axes))
    if axis not in axes:
        raise RecordingError(f"{rec.path}: no axis {axis!r} (has {', '.join(axes)})")
    a = axes[axis]
    return AxisTrace(name=axis, prefix=a["prefix"], rotary=a["kind"] == "rotary",
                     table_per_count=float(a["table_per_count"]),
                     scale_resolution_m=float(a["scale_resolution_m"]),
                     period_s=rec.period_ns / 1e9)
