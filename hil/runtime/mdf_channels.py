"""What ``hil export --to mdf4`` makes of each recording column: its MDF4 channel's data
type, unit, comment and conversion (:func:`channels`).

* **Value to text**: ``drive_state`` shows the CiA 402 state's name
  (:class:`hil.cia402.State`), ``sp_mode`` the mode of operation's
  (:class:`hil.cia402.ModeOfOperation`), ``fb_fault`` and the events' ``code`` the fault
  cause(s) of the 603Fh code (:data:`hil.drive.faults.ERROR_CODE`), all through MDF4
  value-to-text conversions (the raw value stays in the file: ``MDF.get(name, raw=True)``);
  ``fb_statusword`` lists its set bits by their CiA 402 names
  (:data:`hil.cia402.STATUSWORD_BITS`) through a bitfield text table.
* **Counts**: a column in counts or counts/s is stored as int64 when every value the
  recording holds is a whole number (a CAN run's 607Ah, the plant's encoder and scale,
  always); else as recorded, float64, because a controller on ``udp://`` or ``serial://``
  sends fractional counts and rounding them would change what was sent.  Each has a twin in
  table units beside it -- ``sp_target_position`` in the unit of the axis's
  ``plant_table_pos`` (m, or rad on a rotary table), ``sp_target_velocity`` and
  ``sp_velocity_offset`` in that of ``plant_table_vel``, ``plant_encoder_pos``,
  and ``plant_scale_pos`` in m where the axis has a linear scale -- the same raw counts with
  a linear conversion from the recording's metadata (the axis's ``table_per_count``,
  ``scale_resolution_m``).  SI rather than mm: the twin then shares its unit, and a plot
  axis, with the plant's channels it is compared with (the servo trace of ``hil export --to
  csv`` is the place for mm).
* **Units**: one convention, :data:`NO_UNIT`.
"""

from dataclasses import dataclass

import numpy as np

from hil.cia402 import STATUSWORD_BITS, ModeOfOperation, State
from hil.drive.faults import ERROR_CODE
from hil.runtime.record_reader import Recording
from hil.runtime.record_trace import AxisTrace, axis_trace

#: the unit string of every channel without a unit (a count of things, a flag, a CiA 402
#: word, a text): none.  Not "1": the SI brochure (9th edition) says the unit one is
#: generally not written, and MDF tools (asammdf's GUI, CANape) print the unit beside every
#: value and plot axis, where "1" reads as a unit.  The recording marks such columns "1"
#: (dimensionless) or "-" (a CiA 402 word) so that an empty unit there means "forgotten"
#: (hil.runtime.recording); the export maps both to this.
NO_UNIT = ""
_RECORDING_NO_UNIT = frozenset({"1", "-"})
#: units of the columns stored as integers when their values are whole numbers
_COUNT_UNITS = frozenset({"counts", "counts/s"})
#: a value-to-text table's text for a value outside it
_UNKNOWN = "unknown"

#: counts column -> (its twin in table units, the column whose unit the twin takes)
_TWINS = {"sp_target_position_counts": ("sp_target_position", "plant_table_pos"),
          "sp_target_velocity_counts_s": ("sp_target_velocity", "plant_table_vel"),
          "sp_velocity_offset_counts_s": ("sp_velocity_offset", "plant_table_vel"),
          "plant_encoder_counts": ("plant_encoder_pos", "plant_table_pos")}
_SCALE = "plant_scale_counts"
_SCALE_TWIN = "plant_scale_pos"


@dataclass(frozen=True)
class Channel:
    """One MDF4 channel of the recording's channel group.

    Attributes:
        name: the channel's name.
        source: the recording column its samples are.
        dtype: their data type in the file.
        unit: its unit (:data:`NO_UNIT`: none).
        comment: what it is.
        conversion: asammdf's conversion dict (None: the raw value is the value).
    """
    name: str
    source: str
    dtype: np.dtype
    unit: str
    comment: str
    conversion: dict | None = None


def unit(recorded: str) -> str:
    """The MDF4 unit of a recording column of unit ``recorded``."""
    return NO_UNIT if recorded in _RECORDING_NO_UNIT else recorded


def value_to_text(names: dict[int, str]) -> dict:
    """asammdf's value-to-text conversion dict for ``names`` (value -> text); other values
    read :data:`_UNKNOWN`."""
    out: dict = {}
    for i, (value, text) in enumerate(sorted(names.items())):
        out[f"val_{i}"], out[f"text_{i}"] = value, text
    return {**out, "default_addr": _UNKNOWN}


def statusword_bits() -> dict:
    """asammdf's bitfield text table for the statusword 6041h: each set bit by its CiA 402
    name (:data:`hil.cia402.STATUSWORD_BITS`), joined by ``|``; a clear bit adds nothing."""
    out: dict = {}
    for i, (mask, name) in enumerate(STATUSWORD_BITS.items()):
        out[f"mask_{i}"] = mask
        out[f"text_{i}"] = {"val_0": mask, "text_0": name, "default_addr": ""}
    return out


def fault_names() -> dict[int, str]:
    """603Fh code -> the drive's fault cause(s) with that code, by name (0: no error)."""
    names: dict[int, list[str]] = {}
    for cause, code in ERROR_CODE.items():
        names.setdefault(code, []).append(cause.name)
    return {0: "no error", **{code: " or ".join(n) for code, n in names.items()}}


def _text_tables() -> dict[str, dict]:
    """Per-axis column (no prefix) -> its value-to-text conversion."""
    return {"drive_state": value_to_text({s.value: s.name for s in State}),
            "sp_mode": value_to_text({m.value: m.name for m in ModeOfOperation}),
            "fb_fault": value_to_text(fault_names()),
            "fb_statusword": statusword_bits()}


def whole_columns(rec: Recording, names: list[str]) -> set[str]:
    """Those of ``names`` whose every value (up to a corrupt batch) is a finite whole number
    that float64 holds exactly (within 2**53): one pass over these columns."""
    whole = set(names)
    if not names:
        return whole
    for rows in rec.batches(names, stop_at_corrupt=True):
        for name in list(whole):
            v = rows[name]
            if not np.all(np.isfinite(v) & (v == np.round(v)) & (np.abs(v) <= 2.0 ** 53)):
                whole.discard(name)
    return whole


def channels(rec: Recording) -> list[Channel]:
    """The channels of ``rec``'s columns, in file order, each twin after its counts column
    (see the module docstring)."""
    per_axis = {}  # column -> (its name without the axis prefix, the axis's trace view)
    for a in rec.meta.get("axes", []):
        trace = axis_trace(rec, a["name"]) if "table_per_count" in a else None
        for name in rec.names:
            if name.startswith(a["prefix"]):
                per_axis[name] = (name[len(a["prefix"]):], trace)
    counts = [n for n in rec.names if rec.units[n] in _COUNT_UNITS]
    whole = whole_columns(rec, counts)
    tables = _text_tables()
    out = []
    for name in rec.names:
        base, trace = per_axis.get(name, (name, None))
        stored = np.dtype(np.int64 if name in whole
                          else rec.schema.field(name).type.to_pandas_dtype())
        comment = rec.docs[name]
        if name in counts and name not in whole:
            comment += " (float: not every value is a whole number of counts)"
        out.append(Channel(name, name, stored, unit(rec.units[name]), comment,
                           tables.get(base)))
        twin = _twin(rec, name, base, trace)
        if twin is not None:
            out.append(Channel(twin[0], name, stored, twin[1], twin[2],
                               {"a": twin[3], "b": 0.0}))
    return out


def _twin(rec: Recording, name: str, base: str,
          trace: AxisTrace | None) -> tuple[str, str, str, float] | None:
    """(name, unit, comment, factor) of the table-units twin of column ``name`` (``base``
    without its axis prefix; ``trace``: its axis's view), or None when it has none."""
    if trace is None:
        return None
    prefix = trace.prefix
    if base == _SCALE:
        if not trace.scale_resolution_m:
            return None
        twin, twin_unit, factor, key = _SCALE_TWIN, "m", trace.scale_resolution_m, \
            "scale_resolution_m"
    elif base in _TWINS and prefix + _TWINS[base][1] in rec.units:
        twin, like = _TWINS[base]
        twin_unit = rec.units[prefix + like]
        factor, key = trace.table_per_count, "table_per_count"
    else:
        return None
    comment = (f"{rec.docs[name]}, in {twin_unit}: the counts times {factor:.9g} ({key} of "
               "the run's metadata)")
    return prefix + twin, twin_unit, comment, factor
