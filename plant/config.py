"""Machine files: TOML → frozen dataclasses, refused before anything runs when wrong.

A machine file has the sections below; every key carries its SI unit in its
name (``mass_kg``, ``stiffness_n_per_m``), except dimensionless counts and text.
Unknown keys, missing required keys, keys that do not belong to the chosen
model, wrong types and impossible values raise :class:`ConfigError` naming the
file, the section, the key and the expected unit or range.  ``hil config-keys``
prints the whole schema from these declarations.
"""

import difflib
import math
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path

from plant.errors import ConfigError
from plant.schema import describe, is_required, key

KINDS = ("screw", "linear", "rotary")


@dataclass(frozen=True, kw_only=True)
class MachineSection:
    """What the machine is."""
    name: str = key("-", "Human-readable name of the axis.")
    source: str = key("-", "Where the values come from (paper, data sheet).")
    kind: str = key("-", "screw: rotary motor and ball screw, table in m; linear: linear "
                    "motor, table in m; rotary: direct-drive rotary axis, table in rad.",
                    choices=KINDS)


@dataclass(frozen=True, kw_only=True)
class MotorSection:
    """Motor and power stage."""
    model: str = key("-", "dq: PMSM in d-q with FOC current PI loops; first_order: current "
                     "loop as a first-order lag; commutation: torque motor with "
                     "commutation-angle field weakening (seed 001).",
                     choices=("dq", "first_order", "commutation"))
    pole_pairs: float = key("1", "Pole pairs of a rotary motor.", 0.0, ge=0.0,
                            only="kind=screw|rotary")
    pole_pitch_m: float = key("m", "Pole pitch of a linear motor (north to south).", 0.0,
                              ge=0.0, only="kind=linear")
    resistance_ohm: float = key("ohm", "Phase resistance.", 0.0, ge=0.0)
    inductance_d_h: float = key("H", "d-axis inductance (commutation model: coil inductance).",
                                0.0, ge=0.0)
    inductance_q_h: float = key("H", "q-axis inductance.", 0.0, ge=0.0, only="model=dq")
    torque_constant_nm_per_a: float = key("N*m/A", "Torque constant K_t = 1.5 p psi "
                                          "(commutation model: K_M at beta = 90 deg).", 0.0,
                                          ge=0.0, only="kind=screw|rotary")
    force_constant_n_per_a: float = key("N/A", "Force constant of a linear motor.", 0.0,
                                        ge=0.0, only="kind=linear")
    inertia_kgm2: float = key("kg*m^2", "Rotor inertia.", 0.0, ge=0.0,
                              only="kind=screw|rotary")
    mass_kg: float = key("kg", "Moving mass of a linear motor's thrust block.", 0.0, ge=0.0,
                         only="kind=linear")
    viscous_nms_per_rad: float = key("N*m*s/rad", "Viscous friction of the motor bearings.",
                                     0.0, ge=0.0, only="kind=screw|rotary")
    current_max_a: float = key("A", "Current limit I_max (peak).", gt=0.0)
    dc_link_v: float = key("V", "DC-link voltage; the d-q voltage vector is limited to "
                           "U_dc/2 (commutation model: |U| <= U_dc, seed 001 eq. 2).",
                           0.0, ge=0.0)
    pwm_frequency_hz: float = key("Hz", "PWM and current-controller frequency; the "
                                  "inverter applies each voltage one period late.",
                                  gt=0.0, le=1e6)


@dataclass(frozen=True, kw_only=True)
class CurrentLoopSection:
    """Current controller held by the drive (the plant)."""
    kp_v_per_a: float = key("V/A", "PI proportional gain.", 0.0, ge=0.0,
                            only="model=dq|commutation")
    ti_s: float = key("s", "PI integral time.", 0.0, ge=0.0, only="model=dq|commutation")
    time_constant_s: float = key("s", "First-order current-loop time constant T_cl.", 0.0,
                                 ge=0.0, only="model=first_order")
    decoupling: bool = key("-", "EMF and cross-coupling precontrol (u_d -= w_e L_q i_q, "
                           "u_q += w_e (psi + L_d i_d)), as drives have by default.", True,
                           only="model=dq")


@dataclass(frozen=True, kw_only=True)
class FieldWeakeningSection:
    """Commutation-angle field weakening (seed 001 eq. 6-10), commutation model only."""
    enabled: bool = key("-", "Reduce the commutation angle above omega_Mmax.", False)
    max_torque_nm: float = key("N*m", "M_max of seed 001 eq. 8.", 0.0, ge=0.0)


@dataclass(frozen=True, kw_only=True)
class CoggingSection:
    """Cogging / reluctance torque as harmonics of the electrical angle."""
    orders: tuple = key("1", "Harmonic orders in cycles per electrical revolution.", ())
    amplitudes_nm: tuple = key("N*m", "Amplitudes (rotary motors).", (),
                               only="kind=screw|rotary")
    amplitudes_n: tuple = key("N", "Amplitudes (linear motors).", (), only="kind=linear")
    phases_deg: tuple = key("deg", "Phases; empty means all zero.", ())


@dataclass(frozen=True, kw_only=True)
class MechanicsSection:
    """Which mechanical model and solver."""
    model: str = key("-", "rigid: one inertia; two_mass: motor-coupling-load; screw: "
                     "distributed ball screw with moving nut and table.",
                     choices=("rigid", "two_mass", "screw"))
    solver: str = key("-", "Solver of the screw chains.", "lumped", choices=("lumped", "tlm"))
    lead_m: float = key("m", "Ball-screw lead (table travel per screw revolution).", 0.0,
                        ge=0.0, only="kind=screw")
    load_inertia_kgm2: float = key("kg*m^2", "Load-side inertia besides the table (screw "
                                   "and coupling in rigid/two_mass models; the rotary "
                                   "table of a direct drive).", 0.0, ge=0.0)


@dataclass(frozen=True, kw_only=True)
class CouplingSection:
    """Elastic coupling between motor and screw (two_mass and screw models)."""
    stiffness_nm_per_rad: float = key("N*m/rad", "Torsional stiffness.", gt=0.0)
    damping_nms_per_rad: float = key("N*m*s/rad", "Torsional damping.", 0.0, ge=0.0)
    inertia_kgm2: float = key("kg*m^2", "Coupling inertia, split between its two sides.",
                              0.0, ge=0.0)
    backlash_rad: float = key("rad", "Backlash in the coupling (two_mass only).", 0.0, ge=0.0)


@dataclass(frozen=True, kw_only=True)
class ScrewSection:
    """Distributed ball screw (screw model)."""
    length_m: float = key("m", "Screw length between the bearings.", gt=0.0)
    diameter_m: float = key("m", "Root diameter used for stiffness and inertia.", gt=0.0)
    segments: int = key("1", "Number of screw segments N (N+1 nodes).", ge=1, le=64)
    density_kg_m3: float = key("kg/m^3", "Screw material density.", 7850.0, gt=0.0)
    youngs_modulus_pa: float = key("Pa", "Young's modulus E.", 2.1e11, gt=0.0)
    shear_modulus_pa: float = key("Pa", "Shear modulus G.", 8.1e10, gt=0.0)
    torsional_damping_nms_per_rad: float = key("N*m*s/rad", "Damper across each segment.",
                                               0.0, ge=0.0)
    axial_damping_ns_per_m: float = key("N*s/m", "Axial damper across each segment.", 0.0,
                                        ge=0.0)
    bearing_viscous_nms_per_rad: float = key("N*m*s/rad", "Rotational friction of each "
                                             "support bearing.", 0.0, ge=0.0)
    thrust_bearing_stiffness_n_per_m: float = key("N/m", "Axial stiffness of the fixed "
                                                  "(thrust) bearing.", gt=0.0)
    thrust_bearing_damping_ns_per_m: float = key("N*s/m", "Axial damping of the thrust "
                                                 "bearing.", 0.0, ge=0.0)
    support: str = key("-", "Axial support: the thrust bearing at the motor end only, or "
                       "at both ends.", "fixed-supported",
                       choices=("fixed-supported", "fixed-fixed"))
    nut_stiffness_n_per_m: float = key("N/m", "Axial stiffness of the nut.", gt=0.0)
    nut_damping_ns_per_m: float = key("N*s/m", "Axial damping of the nut.", 0.0, ge=0.0)
    nut_offset_m: float = key("m", "Nut distance from the motor-end bearing at table "
                              "position 0.", ge=0.0)
    backlash_m: float = key("m", "Backlash between screw and nut (total lost motion).", 0.0,
                            ge=0.0)


@dataclass(frozen=True, kw_only=True)
class TableSection:
    """The moving table (screw and linear axes)."""
    mass_kg: float = key("kg", "Table mass with workpiece (linear: payload besides the "
                         "thrust block).", ge=0.0)
    travel_m: float = key("m", "Usable travel from position 0.", gt=0.0)


@dataclass(frozen=True, kw_only=True)
class FrictionSection:
    """Table friction: viscous, Coulomb, Stribeck and Karnopp stick-slip."""
    viscous_ns_per_m: float = key("N*s/m", "Viscous coefficient.", 0.0, ge=0.0,
                                  only="kind=screw|linear")
    coulomb_n: float = key("N", "Coulomb (sliding) force F_C.", 0.0, ge=0.0,
                           only="kind=screw|linear")
    breakaway_n: float = key("N", "Breakaway force F_H >= F_C (0: equal to F_C).", 0.0,
                             ge=0.0, only="kind=screw|linear")
    stribeck_velocity_m_s: float = key("m/s", "Stribeck velocity (0: no Stribeck dip).",
                                       0.0, ge=0.0, only="kind=screw|linear")
    zero_velocity_band_m_s: float = key("m/s", "Karnopp zero-velocity band DV.", 0.0, ge=0.0,
                                        only="kind=screw|linear")
    viscous_nms_per_rad: float = key("N*m*s/rad", "Viscous coefficient.", 0.0, ge=0.0,
                                     only="kind=rotary")
    coulomb_nm: float = key("N*m", "Coulomb torque.", 0.0, ge=0.0, only="kind=rotary")
    breakaway_nm: float = key("N*m", "Breakaway torque (0: equal to Coulomb).", 0.0, ge=0.0,
                              only="kind=rotary")
    stribeck_velocity_rad_s: float = key("rad/s", "Stribeck velocity.", 0.0, ge=0.0,
                                         only="kind=rotary")
    zero_velocity_band_rad_s: float = key("rad/s", "Karnopp zero-velocity band.", 0.0,
                                          ge=0.0, only="kind=rotary")


@dataclass(frozen=True, kw_only=True)
class PreslidingSection:
    """Presliding nonlinear spring dF/dx = k1 / (|x/x1|^a + 1), reset at reversals (seed 004)."""
    enabled: bool = key("-", "Use the presliding spring instead of Karnopp stiction.", False)
    stiffness_n_per_m: float = key("N/m", "Initial stiffness k1 (T1 / (lead/2pi)^2 for a "
                                   "torque law).", 0.0, ge=0.0)
    x1_m: float = key("m", "Displacement scale x1.", 0.0, ge=0.0)
    exponent: float = key("1", "Shape exponent a.", 1.0, gt=0.0)


@dataclass(frozen=True, kw_only=True)
class SensorsSection:
    """Encoders and current measurement."""
    encoder_counts_per_rev: int = key("1", "Motor encoder counts per revolution "
                                      "(17 bit: 131072).", 0, ge=0, only="kind=screw|rotary")
    encoder_resolution_m: float = key("m", "Linear-motor encoder resolution.", 0.0, ge=0.0,
                                      only="kind=linear")
    scale_resolution_m: float = key("m", "Linear scale on the table (0: none).", 0.0, ge=0.0,
                                    only="kind=screw|linear")
    current_noise_a: float = key("A", "Standard deviation of current-measurement noise.",
                                 0.0, ge=0.0)
    current_lsb_a: float = key("A", "Current ADC quantization step (0: none).", 0.0, ge=0.0)
    seed: int = key("1", "Seed of the measurement-noise generator.", 1, ge=0)


@dataclass(frozen=True, kw_only=True)
class SimulationSection:
    """Integration settings."""
    substep_s: float = key("s", "Integration sub-step; 0 picks the largest divisor of the "
                           "PWM period with omega_max*dt <= max_omega_dt.", 0.0, ge=0.0)
    max_omega_dt: float = key("1", "Bound on omega_max*dt for the automatic sub-step "
                              "(relative frequency error (omega*dt)^2/24).", 0.5, gt=0.0,
                              le=1.9)


SECTIONS = {
    "machine": MachineSection, "motor": MotorSection, "current_loop": CurrentLoopSection,
    "field_weakening": FieldWeakeningSection, "cogging": CoggingSection,
    "mechanics": MechanicsSection, "coupling": CouplingSection, "screw": ScrewSection,
    "table": TableSection, "friction": FrictionSection, "presliding": PreslidingSection,
    "sensors": SensorsSection, "simulation": SimulationSection,
}
# sections read by other packages (hil's controller): the plant keeps them as raw tables
FOREIGN_SECTIONS = ("controller",)
# sections that may be absent: they then take every default
OPTIONAL_SECTIONS = {"field_weakening", "cogging", "friction", "presliding", "sensors",
                     "simulation", "current_loop"}


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
    friction: FrictionSection
    presliding: PreslidingSection
    sensors: SensorsSection
    simulation: SimulationSection
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
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: no such machine file") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    for sec, values in (overrides or {}).items():
        raw.setdefault(sec, {}).update(values)
    return parse_machine(raw, str(path))


def parse_machine(raw: dict, where: str) -> MachineConfig:
    """Check a machine description already parsed from TOML (see :func:`load_machine`)."""
    foreign = {sec: raw[sec] for sec in FOREIGN_SECTIONS if sec in raw}
    raw = {sec: v for sec, v in raw.items() if sec not in FOREIGN_SECTIONS}
    for sec in raw:
        if sec not in SECTIONS:
            known = list(SECTIONS) + list(FOREIGN_SECTIONS)
            raise ConfigError(f"{where}: unknown section [{sec}]{_suggest(sec, known)}")
    sections = {}
    for sec, cls in SECTIONS.items():
        if sec in raw:
            if not isinstance(raw[sec], dict):
                raise ConfigError(f"{where}: [{sec}] must be a table of keys")
            sections[sec] = build_section(cls, raw[sec], where, sec)
        else:
            sections[sec] = None
    kind = _need(sections, "machine", where).kind
    motor = _need(sections, "motor", where)
    mech = _need(sections, "mechanics", where)
    context = {"kind": kind, "model": motor.model}
    for sec in ("machine", "motor", "cogging", "friction", "sensors", "mechanics"):
        if sections[sec] is not None:
            check_applies(sections[sec], raw.get(sec, {}), context, where, sec)
    if sections["current_loop"] is not None:
        check_applies(sections["current_loop"], raw["current_loop"], context, where,
                    "current_loop")
    wanted = {"coupling": mech.model in ("two_mass", "screw"), "screw": mech.model == "screw",
              "table": kind in ("screw", "linear")}
    for sec, needed in wanted.items():
        if needed and sections[sec] is None:
            raise ConfigError(f"{where}: section [{sec}] is required for kind = '{kind}', "
                              f"mechanics.model = '{mech.model}'")
        if not needed and sections[sec] is not None:
            raise ConfigError(f"{where}: section [{sec}] is not used by kind = '{kind}', "
                              f"mechanics.model = '{mech.model}'; remove it")
    for sec in OPTIONAL_SECTIONS:
        if sections[sec] is None:
            sections[sec] = SECTIONS[sec]()
    cfg = MachineConfig(path=where, foreign=foreign, **sections)
    _check_physics(cfg)
    return cfg


def _need(sections, sec, where):
    if sections[sec] is None:
        raise ConfigError(f"{where}: section [{sec}] is missing")
    return sections[sec]


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
            raise ConfigError(f"{where}: unknown key [{sec}] {name}{hint}")
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
        return tuple(float(v) for v in value)
    unit = m["unit"]
    if m["gt"] is not None and not value > m["gt"]:
        raise ConfigError(f"{label}: must be > {m['gt']:g} {unit}")
    if m["ge"] is not None and not value >= m["ge"]:
        raise ConfigError(f"{label}: must be >= {m['ge']:g} {unit}")
    if m["le"] is not None and not value <= m["le"]:
        raise ConfigError(f"{label}: must be <= {m['le']:g} {unit}")
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
    fr = cfg.friction
    f_c, f_h = (fr.coulomb_nm, fr.breakaway_nm) if kind == "rotary" else (fr.coulomb_n,
                                                                           fr.breakaway_n)
    if f_h and f_h < f_c:
        sfx, unit = ("_nm", "N*m") if kind == "rotary" else ("_n", "N")
        raise ConfigError(f"{cfg.path}: [friction] breakaway{sfx} = {f_h:g} {unit} must be >= "
                          f"coulomb{sfx} = {f_c:g} {unit}")
    pre = cfg.presliding
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
    if cfg.screw is not None:
        sc, tb = cfg.screw, cfg.table
        if sc.nut_offset_m + tb.travel_m > sc.length_m:
            raise ConfigError(f"{cfg.path}: [screw] nut_offset_m + [table] travel_m = "
                              f"{sc.nut_offset_m + tb.travel_m:g} m exceeds [screw] length_m "
                              f"= {sc.length_m:g} m")
        if tb.mass_kg <= 0:
            raise ConfigError(f"{cfg.path}: [table] mass_kg must be > 0 kg for the screw model")


def schema_rows() -> list[dict]:
    """Every key of every section, for documentation (``hil config-keys``)."""
    rows = []
    for sec, cls in SECTIONS.items():
        for row in describe(cls):
            rows.append({"section": sec, **row})
    return rows
