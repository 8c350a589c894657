"""Machine-file keys as study parameters: their unit, physical range and nominal value.

A study varies (or tunes) keys of the machine file by name, ``section.key`` on a machine
file and ``AXIS.section.key`` on a manifest (``X.table.mass_kg``).  The unit and the range
of every key come from its own declaration (:func:`plant.schema.key`: the plant's sections,
the controller's ``[controller]`` and the drive's ``[drive]``), so a distribution that
reaches outside what the machine file would accept is refused before any work starts,
with the same words the machine-file loader uses.
"""

import math
from dataclasses import dataclass, fields

from hil.controller.config import ControllerSection, load_controller
from hil.drive.config import DriveSection
from plant.config import MachineConfig, build_section, shown_name
from plant.errors import ConfigError
from plant.sections import SECTIONS

#: every section a study may vary: name -> the dataclass declaring its keys
KEY_SECTIONS = {**SECTIONS, "controller": ControllerSection, "drive": DriveSection}


class StudySpecError(ConfigError):
    """A study file is unreadable or asks for something impossible; the message names the
    study file, the section or parameter, the value and the unit or range."""


@dataclass(frozen=True)
class Range:
    """A key's physical range: ``low`` < or <= value <= ``high`` (infinite: unbounded),
    and 0 besides where ``zero`` says what 0 means (:func:`plant.schema.key`)."""
    low: float = -math.inf
    low_open: bool = False
    high: float = math.inf
    zero: str | None = None

    def contains(self, value: float) -> bool:
        """True when ``value`` is inside."""
        if value == 0.0 and self.zero:
            return True
        above = value > self.low if self.low_open else value >= self.low
        return above and value <= self.high

    def describe(self, unit: str) -> str:
        """The range in words, e.g. '> 0 N/m', '>= 0 and <= 2 1', '0 (off) or > 1 s',
        'any value (kg)'."""
        parts = []
        if self.low > -math.inf:
            parts.append(f"{'>' if self.low_open else '>='} {self.low:g} {unit}")
        if self.high < math.inf:
            parts.append(f"<= {self.high:g} {unit}")
        if not parts:
            return f"any value ({unit})"
        text = " and ".join(parts)
        return f"0 ({self.zero}) or {text}" if self.zero else text


@dataclass(frozen=True)
class KeyRef:
    """One parameter of a study.

    Attributes:
        name: its name in the study and in the results (``section.key`` or
            ``AXIS.section.key``).
        axis: the axis letter on a manifest, "" on a machine file.
        section, key: where it is in the machine file.
        unit: the key's unit as declared.
        range: the key's physical range as declared.
        integer: a whole-number key (only a list of whole numbers may vary it).
        nominal: its value in the machine file (None when absent and derived).
    """
    name: str
    axis: str
    section: str
    key: str
    unit: str
    range: Range
    integer: bool
    nominal: float | None


def declared_field(section: str, key: str, where: str):
    """The dataclass field declaring ``[section] key``; StudySpecError when there is none."""
    cls = KEY_SECTIONS.get(section)
    if cls is None:
        raise StudySpecError(f"{where}: no machine-file section [{shown_name(section)}] "
                             f"(sections: {', '.join(KEY_SECTIONS)})")
    declared = {f.name: f for f in fields(cls)}
    if key not in declared:
        raise StudySpecError(f"{where}: unknown key [{section}] {shown_name(key)} (keys of "
                             f"[{section}]: {', '.join(declared)})")
    return declared[key]


def _range(meta: dict) -> Range:
    high = math.inf if meta["le"] is None else meta["le"]
    zero = meta.get("zero")
    if meta["gt"] is not None:
        return Range(meta["gt"], True, high, zero)
    return Range(-math.inf if meta["ge"] is None else meta["ge"], False, high, zero)


def nominal_value(cfg: MachineConfig, section: str, key: str) -> float | None:
    """The value ``[section] key`` has in ``cfg`` (defaults included); None when the file
    leaves it to be derived, or the machine's model has no such part."""
    if section == "controller":
        return getattr(load_controller(cfg), key)
    if section == "drive":
        return getattr(build_section(DriveSection, cfg.section("drive"), cfg.path, "drive"),
                       key)
    part = getattr(cfg, section)
    return None if part is None else getattr(part, key)


def key_ref(name: str, configs: dict[str, MachineConfig], where: str) -> KeyRef:
    """Resolve a parameter name against the machine's axes (``configs``: axis letter ->
    its machine file; a single machine file has the one letter ""), naming ``where`` (the
    study file) in any refusal."""
    parts = name.split(".")
    if "" in configs:
        if len(parts) != 2:
            raise StudySpecError(f"{where}: parameter '{shown_name(name)}': a machine file's "
                                 "keys are named section.key (e.g. table.mass_kg)")
        axis, (section, key) = "", parts
    else:
        if len(parts) != 3 or parts[0] not in configs:
            raise StudySpecError(f"{where}: parameter '{shown_name(name)}': a manifest's keys "
                                 f"are named AXIS.section.key with AXIS one of "
                                 f"{', '.join(configs)}")
        axis, section, key = parts
    label = f"{where}: parameter '{shown_name(name)}'"
    f = declared_field(section, key, label)
    kind = f.type if isinstance(f.type, str) else f.type.__name__
    if kind not in ("float", "int"):
        raise StudySpecError(f"{label}: [{section}] {key} is a {kind} key; a study varies "
                             "numbers only")
    try:
        nominal = nominal_value(configs[axis], section, key)
    except ConfigError as exc:
        raise StudySpecError(f"{label}: {exc}") from exc
    meta = f.metadata
    return KeyRef(name, axis, section, key, meta["unit"], _range(meta), kind == "int",
                  None if nominal is None else float(nominal))


def overrides_of(refs: tuple[KeyRef, ...], values) -> dict[str, dict[str, dict]]:
    """``{axis: {section: {key: value}}}`` for one sample's ``values`` (one per ref, in
    order); whole-number keys get ints."""
    out: dict[str, dict[str, dict]] = {}
    for ref, value in zip(refs, values, strict=True):
        v = round(value) if ref.integer else float(value)
        out.setdefault(ref.axis, {}).setdefault(ref.section, {})[ref.key] = v
    return out


def checked_section(cls: type, values: dict, where: str, section: str):
    """A study-file table checked like a machine-file section
    (:func:`plant.config.build_section`: unknown key, type, range, each with its unit),
    refusals as StudySpecError."""
    try:
        return build_section(cls, values, where, section)
    except ConfigError as exc:
        raise StudySpecError(str(exc)) from exc
