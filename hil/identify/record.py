"""A measured servo trace in SI on a uniform time grid, whatever file it came from.

Three sources:

* the servo-trace CSV of ``docs/trace-format.md`` (shared docs), read with
  :func:`hil.trace_file.read_trace`: ``t_s``, ``pos_set_mm``, ``pos_mm`` and ``iq_a`` (or
  ``force_n``) are required, ``_deg`` columns stand in for ``_mm`` on rotary tables;
* the recording of ``hil run`` (its run folder, or its ``recording.arrows``), read with
  :mod:`hil.runtime.record_reader` and mapped onto the same columns by
  :mod:`hil.runtime.record_trace`: the longest stretch of consecutive ticks in which the
  drive ran in OPERATION ENABLED in one mode, CSP or CST, one axis (a run of several axes:
  export the axis with ``hil export RUN --to csv``).  In CSP the record holds the
  position setpoints the drive applied, which the replay feeds through the machine file's
  position and speed loops; in CST (``hil controller`` on a current-input plant: the
  controller closes those loops itself and sends a q-current setpoint each tick) the
  position setpoint stays in the controller, and the record holds the q-current setpoint
  the drive applied each tick, which the replay feeds straight to the plant
  (``Record.applied``).  CSV (the drive's speed loop on 60FFh) and voltage mode (the
  controller's current loop) are refused;
* the EMPS benchmark's ``.mat`` files (``/work/shared/data/EMPS/SOURCE.md``): ``qg`` is the
  position setpoint, ``qm`` the motor encoder expressed at the load, and the force on the
  load is ``gtau * vir``; the dSPACE PD loop that produced them is kept as
  :class:`EmpsLoop` so that the replay can close the same loop.

Every error is a :class:`~hil.trace_file.TraceFormatError` naming the file and what is
wrong with it.
"""

import dataclasses
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.cia402 import State, mode_name
from hil.runtime.record_reader import Recording, RecordingError
from hil.runtime.record_trace import axis_trace
from hil.runtime.run_folder import RECORDING
from hil.trace_file import (
    IDENTIFICATION,
    MAX_TRACE_BYTES,
    MAX_VALUE,
    TIME_TOLERANCE,
    TraceFormatError,
    read_trace,
    si_factor,
)
from io_adapters.messages import MODE_CSP, MODE_CST
from plant.files import read_bytes

#: variables an EMPS ``.mat`` file must hold (``pulses_N`` is optional)
EMPS_VARIABLES = ("t", "qm", "qg", "vir", "gtau", "kp", "kv")
#: the EMPS loop's saturation of the controller output nu, V (SOURCE.md)
EMPS_V_MAX = 10.0
#: what a record's replay feeds the drive (``Record.applied``)
APPLIED = ("position", "current")


@dataclass(frozen=True)
class EmpsLoop:
    """The EMPS dSPACE PD loop (SOURCE.md): nu = kp kv (qr - q) - kv dq/dt, |nu| <= v_max,
    then the pulse added and the force gtau * (nu + pulse) applied.

    Attributes:
        kp: outer position gain, 1/s.
        kv: inner velocity gain, V/(m/s).
        gtau: drive gain, N/V.
        v_max: saturation of nu, V.
        pulses_v: shape (n,), V added after the saturation (the PULSES record), or None.
    """
    kp: float
    kv: float
    gtau: float
    v_max: float = EMPS_V_MAX
    pulses_v: np.ndarray | None = None


@dataclass(frozen=True)
class Record:
    """A measured servo trace in SI on a uniform time grid (all arrays shape (n,)).

    Attributes:
        source: the file it was read from.
        t: s, k * dt from 0.
        pos_set: position setpoint, m (rad on rotary tables); None on a CST run's record
            (the controller kept it).
        pos: measured table position (linear scale, else the motor encoder in table
            units), m or rad.
        effort: measured q-current in A (``effort_kind == "iq"``) or force in N
            (``"force"``).
        effort_kind: "iq" or "force".
        motor_pos: motor encoder in table units (m or rad), when recorded.
        vel_set: speed command sent to the speed loop (feed-forward and excitation
            included), m/s or rad/s, when recorded.
        vel: measured table velocity, m/s or rad/s, when recorded.
        iq_set: q-current setpoint, A, when recorded.
        applied: what the replay feeds the drive (:mod:`hil.identify.replay`):
            "position", the position setpoints through the machine file's loops (a servo
            trace, an EMPS record, a CSP run), or "current", ``iq_set`` as the q-current
            setpoint the drive applied each sample (a CST run).
        emps: for EMPS records, the loop that produced them.
        meta: text metadata of the file (trace metadata, or the EMPS variable names), and
            ``position_unit``: "m", or "rad" when the trace had ``_deg`` columns.
    """
    source: str
    t: np.ndarray
    pos_set: np.ndarray | None
    pos: np.ndarray
    effort: np.ndarray
    effort_kind: str
    motor_pos: np.ndarray | None = None
    vel_set: np.ndarray | None = None
    vel: np.ndarray | None = None
    iq_set: np.ndarray | None = None
    applied: str = "position"
    emps: EmpsLoop | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.effort_kind not in ("iq", "force"):
            raise ValueError(f"{self.source}: effort_kind {self.effort_kind!r} is not "
                             "'iq' or 'force'")
        if self.applied not in APPLIED:
            raise ValueError(f"{self.source}: applied {self.applied!r} is not one of "
                             f"{', '.join(APPLIED)}")
        if (self.pos_set if self.applied == "position" else self.iq_set) is None:
            raise ValueError(f"{self.source}: a record whose replay applies its "
                             f"{self.applied} setpoints needs "
                             f"{'pos_set' if self.applied == 'position' else 'iq_set'}")
        n = self.t.shape
        if len(n) != 1 or n[0] < 2:
            raise ValueError(f"{self.source}: t has shape {n}, needs (n,) with n >= 2")
        for name, value in self._arrays().items():
            if value.shape != n:
                raise ValueError(f"{self.source}: {name} has shape {value.shape}, t has {n}")

    def _arrays(self) -> dict[str, np.ndarray]:
        """Every array of shape (n,), by field name ('pulses_v' for the EMPS pulses)."""
        names = ("pos_set", "pos", "effort", "motor_pos", "vel_set", "vel", "iq_set")
        arrays = {k: getattr(self, k) for k in names if getattr(self, k) is not None}
        if self.emps is not None and self.emps.pulses_v is not None:
            arrays["pulses_v"] = self.emps.pulses_v
        return arrays

    @property
    def dt(self) -> float:
        """Sample time, s."""
        return float(self.t[1] - self.t[0])

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.size)

    @property
    def rotary(self) -> bool:
        """True when the positions are angles (the trace had ``_deg`` columns)."""
        return self.meta.get("position_unit") == "rad"

    def slice(self, start: int, stop: int) -> "Record":
        """Samples start..stop-1, time again from 0 (pulses sliced with them)."""
        if not 0 <= start < stop - 1 < self.n:
            raise ValueError(f"{self.source}: slice {start}:{stop} of {self.n} samples "
                             "must keep at least 2")
        cut = {k: v[start:stop] for k, v in self._arrays().items()}
        pulses = cut.pop("pulses_v", None)
        emps = None if self.emps is None else dataclasses.replace(self.emps, pulses_v=pulses)
        return dataclasses.replace(self, t=self.t[start:stop] - self.t[start], emps=emps,
                                   **cut)


#: what ``hil identify RUN`` replays of a run in each mode it takes
_RUN_REPLAYS = {"CSP": "the position targets the drive held, through the machine file's loops",
                "CST": "the q-current setpoint the drive applied in each tick, straight into "
                       "the plant"}


def timing_warning(rec: Record) -> str | None:
    """Why ``rec``'s run may show its timing rather than the machine (its header's
    ``timing_*`` lines, :meth:`hil.runtime.timing_quality.TimingQuality.header`), and what
    to identify instead for the run's mode of operation; None when its timing was within
    the limits or is not stated, or when the record is a CST run's (the setpoint each tick
    applied is the replay's input, so the timing is in it and not in the model error)."""
    if rec.meta.get("timing_within_limits") != "no" or rec.applied == "current":
        return None
    counts = ", ".join(f"{k.removeprefix('timing_').replace('_', ' ')} {v}"
                       for k, v in rec.meta.items()
                       if k.startswith("timing_") and k not in ("timing_within_limits",
                                                                "timing_side"))
    why = (f"{rec.source}: its run's timing was beyond the limits "
           f"({rec.meta.get('timing_side')}: {counts})")
    if rec.meta.get("mode") == "CSP":  # a CSP run's folder (_load_run)
        return (f"{why}; the replay takes {_RUN_REPLAYS['CSP']} at each position cycle, so a "
                "target that came late or not at all between two cycles shows as model error: "
                "identify a run within the limits")
    modes = [m.strip() for m in rec.meta["modes"].split(",")] if "modes" in rec.meta else None
    replayed = [m for m in (modes or _RUN_REPLAYS) if m in _RUN_REPLAYS]
    advice = ("; ".join(f"in {m}, {_RUN_REPLAYS[m]}" for m in replayed)
              if replayed else f"none of {', '.join(modes)}")
    return (f"{why}; the replay takes every setpoint as on time, so late and missed ones show "
            f"as model error.  The run's folder (hil identify RUN, of hil run --record DIR) "
            f"replays what the drive applied: {advice} (CSV and voltage-mode runs it does not "
            "replay); or identify a run within the limits")


def load_record(path: str | Path) -> Record:
    """Read a servo-trace ``.csv``, an EMPS ``.mat`` file or a ``hil run`` recording (its
    run folder or ``recording.arrows``) as a :class:`Record`.

    Raises:
        TraceFormatError: naming the file and the missing column or variable, a
            non-uniform time axis, or a suffix that is neither.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return _load_csv(path)
    if suffix == ".mat":
        return _load_mat(path)
    if path.is_dir() or path.name == RECORDING:
        return _load_run(path if path.is_dir() else path.parent)
    raise TraceFormatError(f"{path}: unknown record type {path.suffix!r}; give a servo-trace "
                           ".csv (trace-format.md), an EMPS benchmark .mat file or a hil run "
                           "folder")


def _longest_span(ok: np.ndarray, tick: np.ndarray, mode: np.ndarray) -> slice:
    """The longest run of rows where ``ok`` holds on consecutive ticks in one ``mode``
    (empty: none)."""
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return slice(0, 0)
    new = np.r_[True, (np.diff(rows) != 1) | (np.diff(tick[rows]) != 1)
                | (np.diff(mode[rows]) != 0)]
    starts = np.flatnonzero(new)
    lengths = np.diff(np.r_[starts, rows.size])
    first = rows[starts[np.argmax(lengths)]]
    return slice(first, first + int(lengths.max()))


def _load_run(folder: Path) -> Record:
    """The CSP or CST stretch of a ``hil run`` recording (module docstring) in SI."""
    try:
        rec = Recording(folder)
        trace = axis_trace(rec)
        rows = rec.read([*trace.sources(), trace.prefix + "drive_state"])
        meta = trace.metadata(rec)
    except RecordingError as e:
        raise TraceFormatError(str(e)) from e
    mode = rows[trace.prefix + "sp_mode"]
    enabled = rows[trace.prefix + "drive_state"] == State.OPERATION_ENABLED
    span = _longest_span(enabled & np.isin(mode, (MODE_CSP, MODE_CST)), rows["tick"], mode)
    if span.stop - span.start < 2:
        seen = ", ".join(mode_name(m) for m in np.unique(mode[enabled])) or "none"
        raise TraceFormatError(
            f"{rec.path}: no two consecutive ticks with the drive in OPERATION ENABLED in CSP "
            f"(6060h = 8) or CST (10) (modes while enabled: {seen}): the replay feeds the "
            "drive's position setpoints (CSP) or q-current setpoints (CST); it does not "
            "replay the drive's speed loop on a CSV target nor the controller's current "
            "loop behind voltage setpoints; identify the controller's trace.csv instead")
    columns = trace.convert({k: v[span] for k, v in rows.items()})
    u = trace.unit
    cst = mode[span.start] == MODE_CST

    def si(name: str) -> np.ndarray:
        return columns[name] * si_factor(name)[0]

    return Record(source=str(rec.path), t=np.arange(span.stop - span.start) * trace.period_s,
                  pos_set=None if cst else si(f"pos_set_{u}"), pos=si(f"pos_{u}"),
                  effort=columns["iq_a"], effort_kind="iq", motor_pos=si(f"motor_pos_{u}"),
                  vel_set=None if cst else si(f"vel_set_{u}_min"), vel=si(f"vel_{u}_min"),
                  iq_set=columns["iq_set_a"] if cst else None,
                  applied="current" if cst else "position",
                  meta={**meta, "position_unit": "rad" if trace.rotary else "m",
                        "mode": mode_name(int(mode[span.start])),
                        "ticks": f"{rows['tick'][span.start]}..{rows['tick'][span.stop - 1]}"})


def _load_csv(path: Path) -> Record:
    """A servo-trace CSV; columns resolved to their rotary or force alternatives; every
    value finite and bounded (:data:`~hil.trace_file.MAX_VALUE`), two rows at least."""
    trace = read_trace(path, require=IDENTIFICATION, bounded=True)
    if trace.n_samples < 2:
        raise TraceFormatError(f"{path}: {trace.n_samples} data row; a record needs two "
                               "samples at least")
    pos_set, pos = trace.resolve("pos_set_mm"), trace.resolve("pos_mm")
    rotary = pos.endswith("_deg")
    if pos_set.endswith("_deg") != rotary:
        raise TraceFormatError(f"{path}: {pos_set!r} and {pos!r} mix degrees and mm")
    effort = trace.resolve("iq_a")

    def optional(name: str) -> np.ndarray | None:
        try:
            column = trace.resolve(name)
        except KeyError:
            return None
        if ("_deg" in column) != rotary:
            raise TraceFormatError(f"{path}: column {column!r} does not match the "
                                   f"{'degrees' if rotary else 'mm'} of {pos!r}")
        return trace.si(column)

    meta = {**trace.metadata, "position_unit": "rad" if rotary else "m"}
    return Record(source=str(path), t=np.arange(trace.n_samples) * trace.sample_time_s,
                  pos_set=trace.si(pos_set), pos=trace.si(pos), effort=trace.si(effort),
                  effort_kind="force" if effort == "force_n" else "iq",
                  motor_pos=optional("motor_pos_mm"), vel_set=optional("vel_set_mm_min"),
                  vel=optional("vel_mm_min"),
                  iq_set=trace.si("iq_set_a") if "iq_set_a" in trace.data else None,
                  meta=meta)


def _load_mat(path: Path) -> Record:
    """An EMPS benchmark file: qm -> pos and motor_pos, qg -> pos_set, gtau vir -> force."""
    from scipy.io import loadmat  # only .mat records need scipy.io

    raw = read_bytes(path, "MATLAB .mat record", MAX_TRACE_BYTES, TraceFormatError)
    try:
        data = loadmat(io.BytesIO(raw))
    # a corrupt file makes scipy's reader raise errors of many kinds (MatReadError,
    # zlib.error, IndexError, OSError and more): each means the same to the user
    except Exception as exc:  # noqa: BLE001
        why = " ".join(str(exc).split())  # one line, whatever the reader said
        raise TraceFormatError(f"{path}: not a readable MATLAB .mat file ({why})") from None
    names = sorted(k for k in data if not k.startswith("__"))
    missing = [v for v in EMPS_VARIABLES if v not in data]
    if missing:
        raise TraceFormatError(f"{path}: an EMPS .mat record needs the variables "
                               f"{', '.join(EMPS_VARIABLES)}; missing {', '.join(missing)} "
                               f"(has {', '.join(names) or 'none'})")
    t_raw = _column(path, data, "t")
    n = t_raw.size
    columns = {v: _column(path, data, v, n) for v in ("qm", "qg", "vir")}
    scalars = {v: _scalar(path, data, v) for v in ("gtau", "kp", "kv")}
    pulses = _column(path, data, "pulses_N", n) if "pulses_N" in data else None
    t = _uniform_time(path, t_raw)
    # SOURCE.md: vir already holds the pulse, and the pulse is added in volts before gtau
    loop = EmpsLoop(kp=scalars["kp"], kv=scalars["kv"], gtau=scalars["gtau"], pulses_v=pulses)
    qm = columns["qm"]
    return Record(source=str(path), t=t, pos_set=columns["qg"], pos=qm,
                  effort=scalars["gtau"] * columns["vir"], effort_kind="force",
                  motor_pos=qm.copy(), emps=loop,
                  meta={"format": "EMPS .mat", "variables": ", ".join(names),
                        "position_unit": "m"})


def _numbers(path: Path, data: dict, name: str) -> np.ndarray:
    """Variable ``name`` as a float array; refused when it holds no real numbers (text, a
    struct, a cell array, complex values)."""
    value = data[name]
    try:
        if np.iscomplexobj(value):
            raise TypeError("complex")
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TraceFormatError(f"{path}: variable {name!r} is not real numbers (MATLAB "
                               f"class {getattr(value, 'dtype', type(value).__name__)})") from None


def _column(path: Path, data: dict, name: str, n: int | None = None) -> np.ndarray:
    """Variable ``name`` as a float vector (of length ``n`` when given) of finite values
    below MAX_VALUE in magnitude."""
    value = _numbers(path, data, name)
    if value.ndim != 2 or min(value.shape) != 1 or (n is not None and value.size != n):
        want = "a vector" if n is None else f"a vector of {n} values like t"
        raise TraceFormatError(f"{path}: variable {name!r} has shape {value.shape}, "
                               f"needs {want}")
    value = np.ascontiguousarray(value.ravel())
    bad = np.flatnonzero(~(np.abs(value) < MAX_VALUE))
    if bad.size:
        raise TraceFormatError(f"{path}: variable {name!r} holds {float(value[bad[0]])!r} at "
                               f"index {int(bad[0])}; every value must be finite and below "
                               f"{MAX_VALUE:.0e} in magnitude")
    return value


def _scalar(path: Path, data: dict, name: str) -> float:
    """Variable ``name`` as one positive float below MAX_VALUE."""
    value = _numbers(path, data, name)
    if value.size != 1 or not 0.0 < float(value.ravel()[0]) < MAX_VALUE:
        raise TraceFormatError(f"{path}: variable {name!r} must be one positive number "
                               f"below {MAX_VALUE:.0e}, got shape {value.shape}")
    return float(value.ravel()[0])


def _uniform_time(path: Path, t: np.ndarray) -> np.ndarray:
    """k * dt from 0 with dt = (t[-1] - t[0]) / (n - 1), after checking that every t
    lies within TIME_TOLERANCE * dt of its grid instant (the EMPS times carry +-2e-8 s
    of rounding)."""
    if t.size < 2:
        raise TraceFormatError(f"{path}: variable 't' has {t.size} sample(s), needs >= 2")
    dt = (t[-1] - t[0]) / (t.size - 1)
    grid = np.arange(t.size) * dt
    off = np.abs(t - t[0] - grid)
    if not dt > 0.0 or off.max() > TIME_TOLERANCE * dt:
        k = int(np.argmax(off))
        raise TraceFormatError(f"{path}: variable 't' is not uniform: t[{k}] = {t[k]!r} is "
                               f"{off[k]:.3g} s off the grid of dt = {dt!r} s")
    return grid
