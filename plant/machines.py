"""Machines of several axes: a manifest naming one machine file per axis.

A machine file (:mod:`plant.config`) describes one axis.  A *manifest* groups several
into one machine, each under its program letter::

    [machine]
    name = "Arrow 500 XY"                 # required, text
    source = "seed 000; Y assumed a copy"  # required, text: where the axes come from

    [[axis]]
    name = "X"                            # required: program letter, X Y Z U V W A B C
    file = "../arrow500_x.toml"           # required: machine file, relative to the manifest

    [[axis]]
    name = "Y"
    file = "../arrow500_x.toml"
    [axis.overrides.controller]           # optional: {section: {key: value}} on top of the
    kv_m_min_per_mm = 1.5                 # file, checked like the file's own keys

Rules, checked before anything runs (:class:`~plant.errors.ConfigError` naming the
manifest, the axis, the key and the unit):

* a manifest is a TOML file with an ``[[axis]]`` array; only the keys above are allowed;
* axis names are unique; A, B and C need a rotary machine file (``kind = "rotary"``), the
  linear letters a screw or linear one;
* every axis runs at the same PWM frequency (``[motor] pwm_frequency_hz``, Hz): one
  real-time loop steps them all, one PWM period per tick, and the controller's cycles are
  whole multiples of it.

A plain machine file is a machine of one axis (:func:`load_machine_set` reads either), named
X (C on a rotary table) unless the caller names it; everything single-axis keeps working
on it unchanged.  Manifests live in ``configs/machines/`` so that the tools that take every
``configs/*.toml`` as a machine file never see them.
"""

from dataclasses import dataclass
from pathlib import Path

from plant.config import MachineConfig, load_machine, read_toml, shown_name
from plant.errors import ConfigError
from plant.files import checked_name

LINEAR_LETTERS = "XYZUVW"
ROTARY_LETTERS = "ABC"
#: manifest keys: section -> key -> meaning (unit)
MANIFEST_KEYS = {
    "machine": {"name": "the machine's name (text)",
                "source": "where its axes come from, and which are assumed copies (text)"},
    "axis": {"name": "program letter (one of XYZUVW for screw/linear, ABC for rotary)",
             "file": "machine file of the axis, relative to the manifest (path)",
             "overrides": "optional {section: {key: value}} on top of that file"},
}

#: key -> meaning, for the error messages
MANIFEST_KEYS_DOC = {**MANIFEST_KEYS["machine"], **MANIFEST_KEYS["axis"]}


@dataclass(frozen=True)
class Axis:
    """One axis of a machine: its program letter and its checked machine file."""
    name: str
    config: MachineConfig

    @property
    def rotary(self) -> bool:
        """True on a rotary table (positions in rad, program words in degrees)."""
        return self.config.machine.kind == "rotary"


@dataclass(frozen=True)
class MachineSet:
    """A machine of one or more axes sharing one PWM period.

    Attributes:
        path: the manifest (or the single machine file).
        name: the machine's name.
        source: where it comes from.
        axes: the axes in manifest order (at least one).
        manifest: True when read from a manifest, False for a plain machine file.
    """
    path: str
    name: str
    source: str
    axes: tuple[Axis, ...]
    manifest: bool

    @property
    def names(self) -> tuple[str, ...]:
        """The axis letters in order."""
        return tuple(a.name for a in self.axes)

    @property
    def configs(self) -> tuple[MachineConfig, ...]:
        """The axes' machine files in order."""
        return tuple(a.config for a in self.axes)

    @property
    def pwm_frequency_hz(self) -> float:
        """The common PWM frequency, Hz."""
        return self.axes[0].config.motor.pwm_frequency_hz

    @property
    def multi_axis(self) -> bool:
        """More than one axis."""
        return len(self.axes) > 1


def default_axis_name(cfg: MachineConfig) -> str:
    """The letter of a single machine file's axis: C on a rotary table, else X."""
    return "C" if cfg.machine.kind == "rotary" else "X"


def single_axis(cfg: MachineConfig, axis_name: str | None = None) -> MachineSet:
    """A machine file as a machine of one axis (named :func:`default_axis_name` unless
    ``axis_name`` is given)."""
    axis = Axis(axis_name or default_axis_name(cfg), cfg)
    return MachineSet(cfg.path, cfg.machine.name, cfg.machine.source, (axis,), False)


def is_manifest(raw: dict) -> bool:
    """True when a parsed TOML file is a manifest (it has an ``[[axis]]`` array)."""
    return "axis" in raw


def _text(where: str, table: dict, key: str) -> str:
    if key not in table:
        raise ConfigError(f"{where}: key '{key}' is missing ({MANIFEST_KEYS_DOC[key]})")
    value = table[key]
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where}: key '{key}' must be a non-empty string, got {value!r}")
    return value


def _unknown(where: str, table: dict, allowed) -> None:
    for key in table:
        if key not in allowed:
            raise ConfigError(f"{where}: unknown key '{shown_name(key)}' (allowed: "
                              f"{', '.join(allowed)})")


def _axis(manifest: Path, index: int, entry, seen: set[str]) -> Axis:
    where = f"{manifest}: [[axis]] #{index + 1}"
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: must be a table")
    _unknown(where, entry, MANIFEST_KEYS["axis"])
    name = _text(where, entry, "name")
    if len(name) != 1 or name not in LINEAR_LETTERS + ROTARY_LETTERS:
        raise ConfigError(f"{where}: name = {name!r} must be one letter of "
                          f"{LINEAR_LETTERS + ROTARY_LETTERS}")
    if name in seen:
        raise ConfigError(f"{where}: axis name {name!r} given twice")
    seen.add(name)
    where = f"{manifest}: axis {name}"
    overrides = entry.get("overrides", {})
    if not isinstance(overrides, dict) or not all(isinstance(v, dict)
                                                  for v in overrides.values()):
        raise ConfigError(f"{where}: overrides must be tables of keys, "
                          "[axis.overrides.SECTION] key = value")
    given = manifest.parent / _text(where, entry, "file")
    try:
        file = checked_name(given, "machine file").resolve()
        cfg = load_machine(file, {sec: dict(v) for sec, v in overrides.items()})
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from e
    rotary = cfg.machine.kind == "rotary"
    if rotary != (name in ROTARY_LETTERS):
        raise ConfigError(f"{where}: {file.name} has [machine] kind = "
                          f"'{cfg.machine.kind}', which axis {name} cannot be (A, B and C "
                          "are rotary tables, X Y Z U V W screw or linear axes)")
    return Axis(name, cfg)


def load_machine_set(path: str | Path, axis_name: str | None = None) -> MachineSet:
    """Read a manifest, or a plain machine file as a machine of one axis named
    ``axis_name`` (default :func:`default_axis_name`).  Raises :class:`ConfigError`."""
    path = Path(path)
    raw = read_toml(path)
    if not is_manifest(raw):
        return single_axis(load_machine(path), axis_name)
    _unknown(str(path), raw, ("machine", "axis"))
    machine = raw.get("machine")
    if not isinstance(machine, dict):
        raise ConfigError(f"{path}: section [machine] (name, source) is missing")
    _unknown(f"{path}: [machine]", machine, MANIFEST_KEYS["machine"])
    name = _text(f"{path}: [machine]", machine, "name")
    source = _text(f"{path}: [machine]", machine, "source")
    entries = raw["axis"]
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}: [[axis]] must be an array of at least one axis table")
    seen: set[str] = set()
    axes = tuple(_axis(path, i, e, seen) for i, e in enumerate(entries))
    f0 = axes[0].config.motor.pwm_frequency_hz
    for a in axes[1:]:
        f = a.config.motor.pwm_frequency_hz
        if f != f0:
            raise ConfigError(
                f"{path}: axis {a.name} has [motor] pwm_frequency_hz = {f:g} Hz, axis "
                f"{axes[0].name} {f0:g} Hz: all axes must share one PWM period (one loop "
                "steps them all); override pwm_frequency_hz (Hz) to make them equal")
    return MachineSet(str(path), name, source, axes, True)
