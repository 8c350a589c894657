"""Machine files: TOML → frozen dataclasses, refused before anything runs when wrong.

A machine file has the sections declared in :mod:`plant.sections`; every key carries
its SI unit in its name (``mass_kg``, ``stiffness_n_per_m``), except dimensionless counts and text.
Unknown keys, missing required keys, keys that do not belong to the chosen
model, wrong types and impossible values raise :class:`ConfigError` naming the
file, the section, the key and the expected unit or range.  ``hil config-keys``
prints the whole schema from these declarations.
"""

import difflib
import math
import re
from dataclasses import dataclass, fields
from pathlib import Path

import tomllib

from plant.cogging_orders import slot_orders
from plant.errors import ConfigError
from plant.files import read_text
from plant.layout import N_DELAY_MAX, N_PITCH
from plant.schema import describe, in_range, is_required, range_text
from plant.sections import (
    BrakeSection,
    FOREIGN_SECTIONS,
    OPTIONAL_SECTIONS,
    SECTIONS,
    CoggingSection,
    CouplingSection,
    CurrentLoopSection,
    FieldWeakeningSection,
    FrictionSection,
    MachineSection,
    MechanicsSection,
    MotorSection,
    PitchErrorSection,
    PreslidingSection,
    ScrewSection,
    SensorsSection,
    SimulationSection,
    TableSection,
)


@dataclass(frozen=True, kw_only=True)
class MachineConfig:
    """A whole machine file, checked. ``coupling``, ``screw`` and ``table`` are
    None where the mechanical model has no such part."""
    path: str
    machine: MachineSection
    motor: MotorSection
    current_loop: CurrentLoopSection
    field_weakening: FieldWeakeningSection
    cogging: CoggingSection
    mechanics: MechanicsSection
    coupling: CouplingSection | None
    screw: ScrewSection | None
    table: TableSection | None
    pitch_error: PitchErrorSection
    friction: FrictionSection
    presliding: PreslidingSection
    sensors: SensorsSection
    simulation: SimulationSection
    brake: BrakeSection
    foreign: dict

    def section(self, name: str) -> dict:
        """A section another package owns (see FOREIGN_SECTIONS), as a raw table; {} if absent."""
        return dict(self.foreign.get(name, {}))


def load_machine(path: str | Path, overrides: dict | None = None) -> MachineConfig:
    """Read and check a machine file.

    Args:
        path: the TOML file.
        overrides: ``{"section": {"key": value}}`` applied on top of the file
            (used by tests and the CLI); checked like the file's own keys.
    Raises:
        ConfigError: naming the file, key and expected unit or range.
    """
    path = Path(path)
    raw = read_toml(path)
    for sec, values in (overrides or {}).items():
        raw.setdefault(sec, {}).update(values)
    return parse_machine(raw, str(path))


#: a machine file, manifest or study file larger than this is refused unread, bytes
MAX_FILE_BYTES = 1_000_000
#: tables and arrays nested deeper than this are refused (a table of a table is 2, each
#: ``[`` or ``{`` and each part of a dotted key one more): tomllib recurses once per
#: bracket level and Python's stack ends a few hundred levels down; the deepest shipped
#: files nest 4 (a manifest's ``[axis.overrides.SECTION]``, a study's ``[vary.X.table]
#: key = { uniform = [a, b] }``)
MAX_NESTING = 16

#: what the bracket count skips, strings and comments, and the brackets themselves
_TOML_TOKENS = re.compile(
    r'"""(?:[^\\]|\\.)*?"""(?!")'  # multi-line basic string (may end in 2 more quotes)
    r"|'''.*?'''(?!')"  # multi-line literal string
    r'|"(?:[^"\\\n]|\\.)*"?'  # basic string
    r"|'[^'\n]*'?"  # literal string
    r"|#[^\n]*"  # comment
    r"|[\[\]{}]", re.DOTALL)


def read_toml(path: Path, what: str = "machine file") -> dict:
    """The TOML table of ``path``, or a :class:`ConfigError` of one line naming the file
    and why: what :func:`plant.files.read_text` refuses (missing, not a regular file --
    a directory, a FIFO or a device is never read, so nothing can block here --,
    larger than :data:`MAX_FILE_BYTES`, not UTF-8, each with the line), tables and arrays
    nested deeper than :data:`MAX_NESTING` (checked before parsing, so the parser's
    recursion stays bounded), or not TOML (with tomllib's line and column).  ``what``
    names the file's role in the messages."""
    text = read_text(path, what, MAX_FILE_BYTES)
    _check_brackets(path, text, what)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    _check_nesting(path, raw, what)
    return raw


def _too_deep(path: Path, what: str, where: str) -> ConfigError:
    return ConfigError(f"{path}: tables and arrays nested more than {MAX_NESTING} deep"
                       f"{where}; a {what} needs a few levels (a table of tables is 2)")


def _check_brackets(path: Path, text: str, what: str) -> None:
    """Refuse ``[`` and ``{`` nested deeper than MAX_NESTING outside strings and comments,
    naming the line; a loop over tokens, so any depth is counted without recursion.
    The tokens follow TOML's string rules as tomllib does, so up to the first syntax
    error (where tomllib stops) the count is tomllib's own nesting."""
    depth = 0
    for token in _TOML_TOKENS.finditer(text):
        c = token.group()
        if c in "[{":
            depth += 1
            if depth > MAX_NESTING:
                line = text.count("\n", 0, token.start()) + 1
                raise _too_deep(path, what, f" (line {line})")
        elif c in "]}":
            depth = max(depth - 1, 0)


def _check_nesting(path: Path, raw: dict, what: str) -> None:
    """Refuse a parsed document nested deeper than MAX_NESTING (dotted keys nest
    without brackets); walked with a stack, not recursion."""
    stack = [(raw, 0)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_NESTING:
            raise _too_deep(path, what, " (dotted keys count, one level a part)")
        children = node.values() if isinstance(node, dict) else node
        stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))


def parse_machine(raw: dict, where: str) -> MachineConfig:
    """Check a machine description already parsed from TOML (see :func:`load_machine`)."""
    foreign = {sec: raw[sec] for sec in FOREIGN_SECTIONS if sec in raw}
    raw = {sec: v for sec, v in raw.items() if sec not in FOREIGN_SECTIONS}
    for sec in raw:
        if sec not in SECTIONS:
            known = list(SECTIONS) + list(FOREIGN_SECTIONS)
            raise ConfigError(f"{where}: unknown section [{shown_name(sec)}]"
                              f"{_suggest(sec, known)}")
    sections = {}
    for sec, cls in SECTIONS.items():
        # the model's parts are built once the model says they belong: a [table] on a
        # rotary axis is refused as such, not for a key it lacks
        if sec in raw and sec not in _MODEL_PARTS:
            sections[sec] = _build(cls, raw[sec], where, sec)
        else:
            sections[sec] = None
    kind = _need(sections, "machine", where).kind
    motor = _need(sections, "motor", where)
    mech = _need(sections, "mechanics", where)
    context = {"kind": kind, "model": motor.model}
    for sec in ("machine", "motor", "cogging", "friction", "sensors", "mechanics",
                "pitch_error", "brake"):
        if sections[sec] is not None:
            check_applies(sections[sec], raw.get(sec, {}), context, where, sec)
    if sections["current_loop"] is not None:
        check_applies(sections["current_loop"], raw["current_loop"], context, where,
                    "current_loop")
    wanted = {"coupling": mech.model in ("two_mass", "screw"), "screw": mech.model == "screw",
              "table": kind in ("screw", "linear")}
    for sec, needed in wanted.items():
        if needed and sec not in raw:
            raise ConfigError(f"{where}: section [{sec}] is required for kind = '{kind}', "
                              f"mechanics.model = '{mech.model}'")
        if not needed and sec in raw:
            raise ConfigError(f"{where}: section [{sec}] is not used by kind = '{kind}', "
                              f"mechanics.model = '{mech.model}'; remove it")
        if needed:
            sections[sec] = _build(SECTIONS[sec], raw[sec], where, sec)
    for sec in OPTIONAL_SECTIONS:
        if sections[sec] is None:
            sections[sec] = SECTIONS[sec]()
    sections["cogging"] = slot_orders(sections["cogging"], motor, where)
    cfg = MachineConfig(path=where, foreign=foreign, **sections)
    _check_physics(cfg)
    return cfg


_MODEL_PARTS = ("coupling", "screw", "table")


def _build(cls, values, where, sec):
    if not isinstance(values, dict):
        raise ConfigError(f"{where}: [{sec}] must be a table of keys")
    return build_section(cls, values, where, sec)


def _need(sections, sec, where):
    if sections[sec] is None:
        raise ConfigError(f"{where}: section [{sec}] is missing")
    return sections[sec]


#: a name from a file longer than this is shown cut short in a message
_NAME_SHOWN = 40


def shown_name(name: str) -> str:
    """A section or key name from a file as a message shows it: as written when it is
    printable (a quoted TOML key may hold a newline, which would break the message's one
    line), else as a Python string literal; cut short when longer than a name can be."""
    cut = name if len(name) <= _NAME_SHOWN else name[:_NAME_SHOWN] + "…"
    return cut if cut.isprintable() else repr(cut)


def _suggest(name, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.5)
    return f"; did you mean '{close[0]}'?" if close else ""


def build_section(cls, values: dict, where: str, sec: str):
    """Check one table of keys against a section class declared with plant.schema.key."""
    known = {f.name: f for f in fields(cls)}
    for name in values:
        if name not in known:
            hint = _suggest(name, known)
            if hint:
                f = known[hint.split("'")[1]]
                hint += f" (unit {f.metadata['unit']})"
            raise ConfigError(f"{where}: unknown key [{sec}] {shown_name(name)}{hint}")
    kwargs = {}
    for name, f in known.items():
        if name not in values:
            if is_required(f):
                raise ConfigError(f"{where}: missing key [{sec}] {name} "
                                  f"(unit {f.metadata['unit']}): {f.metadata['doc']}")
            continue
        kwargs[name] = _check_value(f, values[name], where, sec)
    return cls(**kwargs)


def _check_value(f, value, where, sec):
    m = f.metadata
    label = f"{where}: [{sec}] {f.name} = {value!r}"
    if f.type in (float, "float"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{label}: expected a number in {m['unit']}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{label}: must be finite (unit {m['unit']})")
    elif f.type in (int, "int"):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{label}: expected a whole number")
    elif f.type in (bool, "bool"):
        if not isinstance(value, bool):
            raise ConfigError(f"{label}: expected true or false")
        return value
    elif f.type in (str, "str"):
        if not isinstance(value, str):
            raise ConfigError(f"{label}: expected text")
        if m["choices"] and value not in m["choices"]:
            raise ConfigError(f"{label}: expected one of {', '.join(m['choices'])}")
        return value
    elif f.type in (tuple, "tuple"):
        if not isinstance(value, list) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise ConfigError(f"{label}: expected a list of numbers in {m['unit']}")
        value = tuple(float(v) for v in value)
        for v in value:
            if not math.isfinite(v):
                raise ConfigError(f"{label}: every element must be finite (unit {m['unit']})")
            if not in_range(m, v):
                raise ConfigError(f"{label}: every element must be {range_text(m)} "
                                  f"{m['unit']} (got {v:g})")
        return value
    if not in_range(m, value):
        raise ConfigError(f"{label}: must be {range_text(m)} {m['unit']}")
    return value


def _applies(only: str, context: dict) -> bool:
    name, allowed = only.split("=")
    return context[name] in allowed.split("|")


def check_applies(section, given: dict, context, where, sec):
    """Refuse keys that the chosen kind / motor model does not use."""
    for f in fields(section):
        only = f.metadata.get("only")
        if only and f.name in given and not _applies(only, context):
            raise ConfigError(f"{where}: [{sec}] {f.name} does not apply here ({only} only; "
                              f"this machine has kind = '{context['kind']}', motor.model = "
                              f"'{context['model']}')")


def _require(cfg, sec, name, why):
    section = getattr(cfg, sec)
    value = getattr(section, name)
    if not value:
        f = {g.name: g for g in fields(section)}[name]
        raise ConfigError(f"{cfg.path}: [{sec}] {name} must be given and > 0 for {why} "
                          f"(unit {f.metadata['unit']}): {f.metadata['doc']}")


def _check_physics(cfg: MachineConfig) -> None:
    """Cross-key rules: what each kind and model needs, and what cannot be."""
    kind, mo, mech = cfg.machine.kind, cfg.motor.model, cfg.mechanics.model
    if kind == "linear":
        for name in ("pole_pitch_m", "force_constant_n_per_a", "mass_kg"):
            _require(cfg, "motor", name, "a linear motor")
        _require(cfg, "sensors", "encoder_resolution_m", "a linear motor")
        if mech != "rigid":
            raise ConfigError(f"{cfg.path}: [mechanics] model = '{mech}': a linear motor "
                              "drives the table directly; use 'rigid'")
    else:
        for name in ("pole_pairs", "torque_constant_nm_per_a", "inertia_kgm2"):
            _require(cfg, "motor", name, "a rotary motor")
        _require(cfg, "sensors", "encoder_counts_per_rev", "a rotary motor")
    if kind == "screw":
        _require(cfg, "mechanics", "lead_m", "a ball-screw axis")
    if kind == "rotary" and mech == "screw":
        raise ConfigError(f"{cfg.path}: [mechanics] model = 'screw' needs kind = 'screw'")
    if mo in ("dq", "commutation"):
        for name in ("resistance_ohm", "inductance_d_h", "dc_link_v"):
            _require(cfg, "motor", name, f"motor model '{mo}'")
        for name in ("kp_v_per_a", "ti_s"):
            _require(cfg, "current_loop", name, f"motor model '{mo}'")
    if mo == "dq":
        _require(cfg, "motor", "inductance_q_h", "motor model 'dq'")
    if mo == "first_order":
        _require(cfg, "current_loop", "time_constant_s", "motor model 'first_order'")
    fw = cfg.field_weakening
    if fw.enabled:
        if mo != "commutation":
            raise ConfigError(f"{cfg.path}: [field_weakening] enabled needs motor.model = "
                              "'commutation'")
        _require(cfg, "field_weakening", "max_torque_nm", "field weakening")
    cog = cfg.cogging
    amps = cog.amplitudes_n if kind == "linear" else cog.amplitudes_nm
    if len(amps) != len(cog.orders) or (cog.phases_deg and len(cog.phases_deg) != len(amps)):
        raise ConfigError(f"{cfg.path}: [cogging] orders, amplitudes and phases_deg must have "
                          f"the same length (got {len(cog.orders)}, {len(amps)}, "
                          f"{len(cog.phases_deg)})")
    if len(amps) > 6:
        raise ConfigError(f"{cfg.path}: [cogging] at most 6 harmonics (got {len(amps)})")
    _check_pitch_error(cfg)
    _check_delay(cfg)
    fr = cfg.friction
    f_c, f_h = (fr.coulomb_nm, fr.breakaway_nm) if kind == "rotary" else (fr.coulomb_n,
                                                                           fr.breakaway_n)
    if f_h and f_h < f_c:
        sfx, unit = ("_nm", "N*m") if kind == "rotary" else ("_n", "N")
        raise ConfigError(f"{cfg.path}: [friction] breakaway{sfx} = {f_h:g} {unit} must be >= "
                          f"coulomb{sfx} = {f_c:g} {unit}")
    if kind == "rotary":
        b, db, sfx, unit = (fr.viscous_nms_per_rad, fr.viscous_asymmetry_nms_per_rad,
                            "_nms_per_rad", "N*m*s/rad")
    else:
        b, db, sfx, unit = (fr.viscous_ns_per_m, fr.viscous_asymmetry_ns_per_m, "_ns_per_m",
                            "N*s/m")
    if abs(db) > b:
        raise ConfigError(f"{cfg.path}: [friction] |viscous_asymmetry{sfx}| = {abs(db):g} "
                          f"{unit} must be <= viscous{sfx} = {b:g} {unit} (friction would push)")
    pre = cfg.presliding
    if fr.karnopp_reversal == "stop" and (pre.enabled or not max(f_h, f_c)):
        why = "[presliding] replaces it" if pre.enabled else "no Coulomb or breakaway level"
        raise ConfigError(f"{cfg.path}: [friction] karnopp_reversal = 'stop' needs Karnopp "
                          f"stick-slip friction, and this machine has none ({why})")
    if pre.enabled:
        _require(cfg, "presliding", "stiffness_n_per_m", "presliding friction")
        _require(cfg, "presliding", "x1_m", "presliding friction")
        if kind == "rotary":
            raise ConfigError(f"{cfg.path}: [presliding] is for screw and linear axes")
    if cfg.coupling is not None and cfg.coupling.backlash_rad and mech != "two_mass":
        raise ConfigError(f"{cfg.path}: [coupling] backlash_rad applies to the two_mass model; "
                          "the screw model takes [screw] backlash_m")
    if mech != "screw" and cfg.mechanics.solver == "tlm":
        raise ConfigError(f"{cfg.path}: [mechanics] solver = 'tlm' needs model = 'screw'")
    tb = cfg.table
    if tb is not None and not tb.limit_switch_overtravel_m < tb.end_stop_overtravel_m:
        raise ConfigError(f"{cfg.path}: [table] limit_switch_overtravel_m = "
                          f"{tb.limit_switch_overtravel_m:g} m must be < end_stop_overtravel_m "
                          f"= {tb.end_stop_overtravel_m:g} m: the limit switches trip before "
                          "the table reaches the end stops")
    if cfg.screw is not None:
        sc, tb = cfg.screw, cfg.table
        if sc.nut_offset_m + tb.travel_m > sc.length_m:
            raise ConfigError(f"{cfg.path}: [screw] nut_offset_m + [table] travel_m = "
                              f"{sc.nut_offset_m + tb.travel_m:g} m exceeds [screw] length_m "
                              f"= {sc.length_m:g} m")
        if tb.mass_kg <= 0:
            raise ConfigError(f"{cfg.path}: [table] mass_kg must be > 0 kg for the screw model")
        _check_screw_diameters(cfg)
        _check_screw_friction(cfg)
    _check_brake(cfg)


#: [screw] friction keys the velocity projection of plant.effects.screw_friction carries,
#: which needs the lumped solver's forces
SCREW_FRICTION_KEYS = ("bearing_coulomb_nm", "nut_coulomb_nm", "nut_viscous_nms_per_rad",
                       "nut_load_friction")


def _check_brake(cfg: MachineConfig) -> None:
    """The brake's Coulomb projection (plant.effects.brake) needs the lumped solver's
    forces, as the screw's friction does."""
    level = cfg.brake.holding_torque_nm or cfg.brake.holding_force_n
    if level and cfg.mechanics.solver == "tlm":
        raise ConfigError(f"{cfg.path}: [brake] holding {level:g} needs [mechanics] solver = "
                          "'lumped' (the TLM solver does not carry the brake)")


def _check_screw_friction(cfg: MachineConfig) -> None:
    if cfg.mechanics.solver != "tlm":
        return
    for name in SCREW_FRICTION_KEYS:
        if getattr(cfg.screw, name):
            raise ConfigError(f"{cfg.path}: [screw] {name} = {getattr(cfg.screw, name):g} "
                              "needs [mechanics] solver = 'lumped' (the TLM solver does not "
                              "carry the screw's bearing and nut friction)")


def _check_screw_diameters(cfg: MachineConfig) -> None:
    sc = cfg.screw
    d0 = sc.nominal_diameter_m
    if d0 and d0 < sc.diameter_m:
        raise ConfigError(f"{cfg.path}: [screw] nominal_diameter_m = {d0:g} m must be >= "
                          f"diameter_m = {sc.diameter_m:g} m (the root diameter)")
    for name in ("inertia_diameter", "stiffness_diameter"):
        if getattr(sc, name) == "nominal" and not d0:
            raise ConfigError(f"{cfg.path}: [screw] {name} = 'nominal' needs "
                              "nominal_diameter_m (m), the screw's outer diameter")


#: bound on the pitch error's slope |e'| (sum of 2 pi A/P, plus the linear part); real
#: screws are near 1e-3.  Below 1 the nut position is monotone in the screw angle; the
#: rigid and two-mass models keep the table's reflected inertia at m (lead/2pi)^2, a
#: relative error of 2 |e'| in the table's share (see plant.kernel.lumped_mechanics).
PITCH_SLOPE_MAX = 0.05


def _check_pitch_error(cfg: MachineConfig) -> None:
    pe = cfg.pitch_error
    n = len(pe.periods_m)
    if len(pe.amplitudes_m) != n or (pe.phases_deg and len(pe.phases_deg) != n):
        raise ConfigError(f"{cfg.path}: [pitch_error] periods_m (m), amplitudes_m (m) and "
                          f"phases_deg (deg) must have the same length (got {n}, "
                          f"{len(pe.amplitudes_m)}, {len(pe.phases_deg)})")
    if n > N_PITCH:
        raise ConfigError(f"{cfg.path}: [pitch_error] at most {N_PITCH} harmonics (got {n})")
    for period in pe.periods_m:
        if not period > 0.0:
            raise ConfigError(f"{cfg.path}: [pitch_error] periods_m = {list(pe.periods_m)}: "
                              "every period must be > 0 m")
    slope = abs(pe.linear_ppm) * 1e-6 + sum(
        2.0 * math.pi * abs(a) / period for a, period in zip(pe.amplitudes_m, pe.periods_m))
    if slope > PITCH_SLOPE_MAX:
        raise ConfigError(f"{cfg.path}: [pitch_error] the error's largest slope, sum of 2 pi "
                          f"amplitudes_m / periods_m + linear_ppm 1e-6 = {slope:.3g} m/m, "
                          f"must be <= {PITCH_SLOPE_MAX:g} m/m")


def delay_periods(cfg: MachineConfig) -> int:
    """[sensors] delay_s in whole PWM periods (checked by the loader)."""
    return round(cfg.sensors.delay_s * cfg.motor.pwm_frequency_hz)


def _check_delay(cfg: MachineConfig) -> None:
    delay, f_pwm = cfg.sensors.delay_s, cfg.motor.pwm_frequency_hz
    n = delay_periods(cfg)
    label = f"{cfg.path}: [sensors] delay_s = {delay:g} s"
    if abs(delay * f_pwm - n) > 1e-6:
        raise ConfigError(f"{label} must be a whole number of PWM periods "
                          f"(1 / [motor] pwm_frequency_hz = {1.0 / f_pwm:g} s)")
    if n > N_DELAY_MAX:
        raise ConfigError(f"{label} is {n} PWM periods; at most {N_DELAY_MAX} "
                          f"({N_DELAY_MAX / f_pwm:g} s) are supported")


def schema_rows() -> list[dict]:
    """Every key of every section, for documentation (``hil config-keys``)."""
    rows = []
    for sec, cls in SECTIONS.items():
        for row in describe(cls):
            rows.append({"section": sec, **row})
    return rows
