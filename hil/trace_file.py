"""The servo-trace CSV file (``docs/trace-format.md`` of the shared docs): reader and writer.

    # source: hil measure
    # sample_time_s: 0.001
    t_s,pos_set_mm,pos_mm,iq_a
    0.0,0.0,0.0,0.0
    0.001,0.002,0.0,0.31

``#`` lines before the header are comments, ``# key: value`` comments are metadata; one
header row; comma separated, ``.`` decimal point, no quoting.  Values stay in the file's
units (mm, mm/min, A, deg ...) in :class:`ServoTrace`; :meth:`ServoTrace.si` converts one
column to SI through :data:`UNITS`.  Every format error is a :class:`TraceFormatError`
naming the file, the line and the column or value at fault; the file itself is read
through :func:`plant.files.read_text` (a directory, a FIFO or a device refused unread, at
most :data:`MAX_TRACE_BYTES`, UTF-8 with an optional byte order mark).
"""

import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.measure.trace import Recording
from plant.files import read_text

TIME = "t_s"
#: The columns ``hil identify`` needs.
IDENTIFICATION = (TIME, "pos_set_mm", "pos_mm", "iq_a")
#: Columns that stand in for a named one: degrees on rotary axes, force on linear motors.
ALTERNATIVES: dict[str, tuple[str, ...]] = {
    "pos_set_mm": ("pos_set_deg",),
    "pos_mm": ("pos_deg",),
    "motor_pos_mm": ("motor_pos_deg",),
    "vel_set_mm_min": ("vel_set_deg_min",),
    "vel_mm_min": ("vel_deg_min",),
    "iq_a": ("force_n",),
}
#: Column-name suffix -> (factor from the file's unit to SI, SI unit); longest suffix first.
UNITS: tuple[tuple[str, float, str], ...] = (
    ("_mm_min", 1e-3 / 60.0, "m/s"),
    ("_deg_min", math.pi / 180.0 / 60.0, "rad/s"),
    ("_mm", 1e-3, "m"),
    ("_deg", math.pi / 180.0, "rad"),
    ("_s", 1.0, "s"),
    ("_a", 1.0, "A"),
    ("_n", 1.0, "N"),
)
METADATA = re.compile(r"#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*:\s*(.*?)\s*$")
#: Default tolerance on every time step, as a fraction of the sample time.
TIME_TOLERANCE = 1e-3
#: a trace file larger than this is refused unread, bytes: about two million rows of
#: eight columns, half an hour at 1 kHz (the rows become Python floats first)
MAX_TRACE_BYTES = 200_000_000
#: a value a fit accepts is below this in magnitude, in its column's unit (1000 km in mm,
#: 17 km/s in mm/min, 1e9 A or N: beyond anything measured, and far enough from the
#: float range that squares and sums in a fit stay finite)
MAX_VALUE = 1e9


class TraceFormatError(ValueError):
    """A trace file (or data to be written as one) breaks the format; the message names
    the file, the line and the column or value."""


def si_factor(name: str) -> tuple[float, str]:
    """(factor, SI unit) that turn column ``name``'s values into SI, from its suffix."""
    for suffix, factor, unit in UNITS:
        if name.endswith(suffix):
            return factor, unit
    raise TraceFormatError(f"column {name!r} has no unit suffix among "
                           f"{[s for s, _, _ in UNITS]}")


@dataclass(frozen=True)
class ServoTrace:
    """A trace read from a file: ``names`` in file order, ``data`` name -> array of shape
    (n_samples,) in the file's units, ``metadata`` and ``comments`` from the lines before
    the header, ``sample_time_s`` checked against ``t_s``."""

    path: Path
    names: tuple[str, ...]
    data: dict[str, np.ndarray]
    metadata: dict[str, str]
    comments: tuple[str, ...]
    sample_time_s: float

    @property
    def t_s(self) -> np.ndarray:
        """Sample times in seconds, shape (n_samples,)."""
        return self.data[TIME]

    @property
    def n_samples(self) -> int:
        return self.t_s.size

    def column(self, name: str) -> np.ndarray:
        """Column ``name`` in the file's unit."""
        if name not in self.data:
            raise self._no_column(name)
        return self.data[name]

    def si(self, name: str) -> np.ndarray:
        """Column ``name`` converted to SI (mm -> m, mm/min -> m/s, deg -> rad, ...)."""
        factor, _ = si_factor(name)
        return self.column(name) * factor

    def resolve(self, name: str) -> str:
        """``name`` if the trace has it, else the alternative it has (``pos_mm`` ->
        ``pos_deg`` on a rotary axis, ``iq_a`` -> ``force_n`` on a linear motor)."""
        for candidate in (name, *ALTERNATIVES.get(name, ())):
            if candidate in self.data:
                return candidate
        raise self._no_column(name)

    def _no_column(self, name: str) -> KeyError:
        return KeyError(f"{self.path}: no column {name!r}; columns are {', '.join(self.names)}")


def read_trace(path: str | Path, *, require: Iterable[str] = (),
               time_tolerance: float = TIME_TOLERANCE, bounded: bool = False) -> ServoTrace:
    """Read a servo-trace CSV file.

    ``t_s`` is always required, plus every column in ``require`` (an alternative from
    :data:`ALTERNATIVES` counts; pass :data:`IDENTIFICATION` for ``hil identify``).  The
    time axis must start at 0 and step by the sample time -- the ``sample_time_s``
    metadata when given, else the median step -- within ``time_tolerance`` of it.  With
    ``bounded``, a value in any column that is NaN, infinite or not below
    :data:`MAX_VALUE` in magnitude is refused, naming its line and column (a simulation
    that diverged may write them; a fit cannot use them).
    """
    path = Path(path)
    lines = read_text(path, "servo trace", MAX_TRACE_BYTES, TraceFormatError).splitlines()
    header_index, metadata, comments = _preamble(path, lines)
    names = _header(path, lines[header_index], header_index + 1)
    _check_required(path, header_index + 1, names, (TIME, *require))
    values, line_numbers = _rows(path, lines, header_index + 1, names)
    if bounded:
        _check_bounded(path, values, line_numbers, names)
    data = {name: np.ascontiguousarray(values[:, i]) for i, name in enumerate(names)}
    dt = _sample_time(path, data[TIME], line_numbers, metadata, time_tolerance)
    return ServoTrace(path=path, names=names, data=data, metadata=metadata,
                      comments=tuple(comments), sample_time_s=dt)


def _preamble(path: Path, lines: list[str]) -> tuple[int, dict[str, str], list[str]]:
    """Index of the header line, the metadata and the other comments before it."""
    metadata: dict[str, str] = {}
    comments: list[str] = []
    for index, line in enumerate(lines):
        if not line.strip():
            continue
        if not line.startswith("#"):
            return index, metadata, comments
        match = METADATA.match(line)
        if match is None:
            comments.append(line[1:].strip())
        elif match.group(1) in metadata:
            raise TraceFormatError(f"{path}:{index + 1}: metadata key {match.group(1)!r} "
                                   "given twice")
        else:
            metadata[match.group(1)] = match.group(2)
    raise TraceFormatError(f"{path}: no header row (only comments or nothing)")


def _header(path: Path, line: str, number: int) -> tuple[str, ...]:
    """Column names of the header row, checked for empty and repeated names."""
    names = tuple(name.strip() for name in line.split(","))
    for i, name in enumerate(names):
        if not name:
            raise TraceFormatError(f"{path}:{number}: column {i + 1} of the header has no name")
        if name in names[:i]:
            raise TraceFormatError(f"{path}:{number}: column {name!r} appears twice")
    return names


def _check_required(path: Path, number: int, names: Sequence[str],
                    require: Iterable[str]) -> None:
    """Every required column, or one of its alternatives, is in the header."""
    for name in require:
        accepted = (name, *ALTERNATIVES.get(name, ()))
        if not any(a in names for a in accepted):
            raise TraceFormatError(f"{path}:{number}: required column {name!r} missing "
                                   f"(accepted: {' or '.join(accepted)}); header has "
                                   f"{', '.join(names)}")


def _rows(path: Path, lines: list[str], first: int,
          names: tuple[str, ...]) -> tuple[np.ndarray, list[int]]:
    """Data rows after the header as an array (n_samples, n_columns), and their line
    numbers; blank lines are skipped."""
    rows: list[list[float]] = []
    numbers: list[int] = []
    for number, line in enumerate(lines[first:], start=first + 1):
        if not line.strip():
            continue
        fields = line.split(",")
        if len(fields) != len(names):
            raise TraceFormatError(f"{path}:{number}: {len(fields)} values, the header "
                                   f"has {len(names)} columns")
        rows.append(_floats(path, number, names, fields))
        numbers.append(number)
    if not rows:
        raise TraceFormatError(f"{path}: no data rows after the header")
    return np.array(rows, dtype=np.float64), numbers


def _floats(path: Path, number: int, names: Sequence[str], fields: list[str]) -> list[float]:
    """One row's values; a bad one is named with its column."""
    values = []
    for name, field in zip(names, fields):
        try:
            values.append(float(field))
        except ValueError:
            raise TraceFormatError(f"{path}:{number}: column {name!r}: bad value {field!r} "
                                   "(decimal point '.', no quotes)") from None
    return values


def _check_bounded(path: Path, values: np.ndarray, numbers: list[int],
                   names: tuple[str, ...]) -> None:
    """Refuse the first value of ``values`` (rows, columns) that is not finite and below
    MAX_VALUE in magnitude, naming its line and column."""
    bad = np.argwhere(~(np.abs(values) < MAX_VALUE))
    if bad.size:
        row, col = bad[0]
        raise TraceFormatError(f"{path}:{numbers[row]}: column {names[col]!r} is "
                               f"{float(values[row, col])!r} (data row {row + 1}); every "
                               f"value must be finite and below {MAX_VALUE:.0e} in magnitude "
                               "(in the column's unit)")


def _sample_time(path: Path, t: np.ndarray, numbers: list[int], metadata: dict[str, str],
                 tolerance: float) -> float:
    """The sample time (metadata or median step), checked against every step of ``t``."""
    not_finite = np.flatnonzero(~np.isfinite(t))
    if not_finite.size:
        k = int(not_finite[0])
        raise TraceFormatError(f"{path}:{numbers[k]}: t_s is {float(t[k])!r}")
    given = metadata.get("sample_time_s")
    if given is not None:
        dt = _positive(path, given)
    elif t.size >= 2:
        dt = float(np.median(np.diff(t)))
    else:
        raise TraceFormatError(f"{path}: one sample and no sample_time_s metadata")
    if not dt > 0.0:
        raise TraceFormatError(f"{path}: t_s does not increase (median step {dt} s)")
    if not abs(t[0]) <= tolerance * dt:
        raise TraceFormatError(f"{path}:{numbers[0]}: t_s starts at {float(t[0])!r}, not 0")
    bad = np.flatnonzero(~(np.abs(np.diff(t) - dt) <= tolerance * dt))
    if bad.size:
        k = int(bad[0]) + 1
        source = "sample_time_s" if given is not None else "median step"
        raise TraceFormatError(f"{path}:{numbers[k]}: t_s steps from {float(t[k - 1])!r} to "
                               f"{float(t[k])!r}, not by the sample time {dt!r} s ({source}, "
                               f"tolerance {tolerance:g} of it)")
    return dt


def _positive(path: Path, text: str) -> float:
    """The sample_time_s metadata value as a positive float."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0.0 or not math.isfinite(value):
        raise TraceFormatError(f"{path}: metadata sample_time_s {text!r} is not a "
                               "positive number of seconds")
    return value


def write_trace(path: str | Path, source: Recording | Mapping[str, Sequence[float]],
                metadata: Mapping[str, object] | None = None,
                comments: Sequence[str] = ()) -> Path:
    """Write a :class:`~hil.measure.trace.Recording`, or columns name -> 1-D values (with
    ``t_s``), as a servo-trace file; values are printed with ``repr`` so they read back
    exactly.  ``sample_time_s`` metadata is added from the recording (or the first time
    step) unless ``metadata`` gives it.  Returns the path."""
    path = Path(path)
    columns, dt = _columns(path, source)
    header: dict[str, object] = {} if dt is None else {"sample_time_s": repr(dt)}
    header.update(metadata or {})
    lines = [_metadata_line(path, k, v) for k, v in header.items()]
    lines += [_comment_line(path, c) for c in comments]
    lines.append(",".join(columns))
    lists = [column.tolist() for column in columns.values()]
    lines += [",".join(map(repr, row)) for row in zip(*lists)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _columns(path: Path, source: Recording | Mapping[str, Sequence[float]]
             ) -> tuple[dict[str, np.ndarray], float | None]:
    """The columns to write, t_s first, as float arrays of one length; the sample time."""
    if isinstance(source, Recording):
        raw: Mapping[str, Sequence[float]] = {TIME: source.t_s, **source.data}
        dt: float | None = source.dt_s
    else:
        raw = source
        dt = None
    if TIME not in raw:
        raise TraceFormatError(f"{path}: the columns to write have no {TIME!r}")
    columns = {TIME: np.asarray(raw[TIME], dtype=np.float64)}
    columns.update((k, np.asarray(v, dtype=np.float64)) for k, v in raw.items() if k != TIME)
    for name, column in columns.items():
        if not name or re.search(r"[,#\s]", name):
            raise TraceFormatError(f"{path}: column name {name!r} is empty or holds ',', "
                                   "'#' or white space")
        if column.shape != columns[TIME].shape or column.ndim != 1:
            raise TraceFormatError(f"{path}: column {name!r} has shape {column.shape}, "
                                   f"{TIME!r} has {columns[TIME].shape}")
    if dt is None and columns[TIME].size >= 2:
        dt = float(columns[TIME][1] - columns[TIME][0])
    return columns, dt


def _metadata_line(path: Path, key: str, value: object) -> str:
    """``# key: value``, refused when it would not read back as the same pair."""
    line = f"# {key}: {value}"
    match = METADATA.match(line)
    if match is None or match.groups() != (key, str(value)):
        raise TraceFormatError(f"{path}: metadata {key!r}: {value!r} would not read back "
                               "(key: letters, digits, '_', '.', '-'; value: one line "
                               "without surrounding space)")
    return line


def _comment_line(path: Path, comment: str) -> str:
    """``# comment``, refused when it would read back as metadata or not at all."""
    line = f"# {comment}"
    if "\n" in comment or "\r" in comment or METADATA.match(line) or comment != comment.strip():
        raise TraceFormatError(f"{path}: comment {comment!r} would not read back as "
                               "this comment (one line, no 'key: value' form)")
    return line
