"""The screw a rigid or two-mass machine file lumps, declared for ``hil identify``: the
``[identify.screw]`` section (issue 30, item 3).

A rigid or two-mass file on a screw axis has no ``[screw]`` (the plant refuses one
there): its screw is part of ``[mechanics] load_inertia_kgm2`` and, in the two-mass
model, of the coupling's spring.  Compliance in the screw model -- the coupling's
torsion, the screw's torsion and the nut's axial spring apart, the screw's inertia
between them -- needs the screw's geometry, which nothing else in such a file gives: its
length and root diameter (its inertia and its torsional and axial stiffness), the nut's
place on it and the thrust bearing.  ``[identify.screw]`` takes them with the plant's own
``[screw]`` keys, units and ranges (``hil config-keys``; :data:`KEYS`); the plant ignores
it, and where identification writes the screw model, its keys go into ``[screw]``.  The
nut's stiffness is fitted, so it is not one of them; ``segments`` defaults to 1 (a lumped
screw, whose compliance at the nut is the continuous screw's, interpolated along it).

The screw model that results keeps the file's moved inertia: the screw's own inertia
(rho J_p l) comes out of ``load_inertia_kgm2``, which held it, the rest stays there, on
the screw's motor end behind the coupling.  A screw heavier than that inertia is not the
file's, and the screw model is not offered (:func:`why_not`).
"""

import math
from dataclasses import fields

from plant.assemble import build_chains, transmission_ratio
from plant.config import MachineConfig, build_section, load_machine, shown_name
from plant.errors import ConfigError
from plant.schema import describe
from plant.sections import ScrewSection

#: the machine-file section (a table of the ``[identify]`` section the plant passes on)
SECTION = "identify.screw"
#: what the screw model needs that no default can stand for
REQUIRED = ("length_m", "diameter_m", "nut_offset_m", "thrust_bearing_stiffness_n_per_m")
#: the [screw] keys the section takes: the screw's geometry, material, elasticity and
#: dampers.  Not the nut's stiffness, which is fitted, nor the screw's friction and the
#: nut's gap: the rigid or two-mass file has its friction in [friction] and [motor], and a
#: gap is the backlash effect's to find; a screw model that added them would not be the
#: declared file's
KEYS = ("length_m", "diameter_m", "nominal_diameter_m", "inertia_diameter",
        "stiffness_diameter", "segments", "density_kg_m3", "youngs_modulus_pa",
        "shear_modulus_pa", "torsional_damping_nms_per_rad", "axial_damping_ns_per_m",
        "thrust_bearing_stiffness_n_per_m", "thrust_bearing_damping_ns_per_m", "support",
        "nut_damping_ns_per_m", "nut_offset_m")
#: [screw] segments where the section gives none: a lumped screw
DEFAULT_SEGMENTS = 1
#: share of the declared load inertia a screw may exceed it by: the round-off of a value
#: printed to 7 digits (the identified file's, hil.identify.config_out)
INERTIA_SLACK = 1e-6


def declared(cfg: MachineConfig) -> dict:
    """The keys of ``[identify.screw]`` (empty when absent); a key not among
    :data:`KEYS`, or the section on an axis without a screw, is refused
    (:class:`ConfigError`, naming the file and the key)."""
    raw = cfg.section("identify")
    unknown = sorted(set(raw) - {"screw"})
    if unknown:
        raise ConfigError(f"{cfg.path}: unknown key [identify] {shown_name(unknown[0])} "
                          f"(the section holds [{SECTION}])")
    sec = raw.get("screw", {})
    if not isinstance(sec, dict):
        raise ConfigError(f"{cfg.path}: [{SECTION}] must be a table of keys")
    if sec and cfg.machine.kind != "screw":
        raise ConfigError(f"{cfg.path}: [{SECTION}] does not apply to kind = "
                          f"'{cfg.machine.kind}' (a ball-screw axis only)")
    for name in sec:
        if name not in KEYS:
            why = ("fitted by hil identify" if name == "nut_stiffness_n_per_m" else
                   "the screw model's, but the file's friction and gap are declared "
                   "elsewhere" if name in {f.name for f in fields(ScrewSection)} else
                   "not a [screw] key")
            raise ConfigError(f"{cfg.path}: [{SECTION}] {shown_name(name)}: {why} (it takes "
                              f"{', '.join(KEYS)})")
    return dict(sec)


def missing(cfg: MachineConfig) -> list[str]:
    """The keys of :data:`REQUIRED` that ``[identify.screw]`` lacks."""
    sec = declared(cfg)
    return [k for k in REQUIRED if k not in sec]


def screw_section(cfg: MachineConfig, nut_stiffness: float) -> dict:
    """``[screw]`` of the screw model: the declared keys, ``segments`` by default, the nut
    at ``nut_stiffness`` (N/m); checked against the plant's ranges, a value outside
    refused naming ``[identify.screw]``."""
    sec = {"segments": DEFAULT_SEGMENTS, **declared(cfg), "nut_stiffness_n_per_m": nut_stiffness}
    build_section(ScrewSection, sec, cfg.path, SECTION)
    return sec


def screw_inertia(cfg: MachineConfig) -> float:
    """kg·m²: the rotating inertia of the declared screw, rho J_p l as the plant's chain
    has it (the torsional nodes behind the coupling, without the coupling's half there)."""
    try:
        probe = load_machine(cfg.path, conversion(cfg, 1.0, 1e8, 0.0))
    except ConfigError as exc:
        raise ConfigError(f"[{SECTION}] makes no screw model: {exc}") from exc
    rot, _ = build_chains(probe)
    return float(rot.m[1:].sum()) - 0.5 * probe.coupling.inertia_kgm2


def conversion(cfg: MachineConfig, coupling_stiffness: float, nut_stiffness: float,
               load_inertia: float) -> dict:
    """Overrides that make ``cfg`` (rigid or two-mass) the screw model of its declared
    screw: coupling at ``coupling_stiffness`` (N·m/rad; a two-mass file's inertia,
    damping kept, a rigid file's none), nut at ``nut_stiffness`` (N/m),
    ``load_inertia`` (kg·m²) on the screw's motor end."""
    cp = cfg.coupling
    coupling = {"stiffness_nm_per_rad": coupling_stiffness}
    if cp is not None:
        coupling.update(inertia_kgm2=cp.inertia_kgm2, damping_nms_per_rad=cp.damping_nms_per_rad)
    return {"mechanics": {"model": "screw", "load_inertia_kgm2": load_inertia},
            "coupling": coupling, "screw": screw_section(cfg, nut_stiffness)}


def kept_load_inertia(cfg: MachineConfig) -> float:
    """kg·m²: what stays of ``load_inertia_kgm2`` once the declared screw takes its own
    inertia out (negative: the screw is heavier than the file's load inertia)."""
    return cfg.mechanics.load_inertia_kgm2 - screw_inertia(cfg)


def why_not(cfg: MachineConfig) -> str | None:
    """Why the screw model cannot stand for ``cfg``'s mechanics, or None.  A screw-model
    file has it; a rigid or two-mass one on a screw axis needs ``[identify.screw]``
    (the missing keys named), a screw no heavier than its load inertia, and no coupling
    backlash (the screw model's gap is the nut's)."""
    model = cfg.mechanics.model
    if model == "screw":
        return None
    if cfg.machine.kind != "screw":
        return f"kind = '{cfg.machine.kind}' has no ball screw"
    lack = missing(cfg)
    if lack:
        return (f"mechanics.model = '{model}' declares no screw to place coupling, screw and "
                f"nut compliance in: [{SECTION}] {', '.join(lack)} missing (hil config-keys)")
    if cfg.coupling is not None and cfg.coupling.backlash_rad > 0.0:
        return ("the two-mass file's coupling backlash has no place in the screw model "
                "(its gap is the nut's, [screw] backlash_m)")
    kept = kept_load_inertia(cfg)
    if kept < -INERTIA_SLACK * max(cfg.mechanics.load_inertia_kgm2, 1e-300):
        return (f"the screw of [{SECTION}] has {screw_inertia(cfg):.4g} kg*m^2 of inertia, "
                f"more than [mechanics] load_inertia_kgm2 = "
                f"{cfg.mechanics.load_inertia_kgm2:.4g} kg*m^2 that holds it in the "
                f"'{model}' model")
    return None


def check(cfg: MachineConfig) -> None:
    """Refuse a wrong ``[identify.screw]`` before anything runs (:class:`ConfigError`):
    keys it cannot hold, and a complete one whose screw model the plant refuses."""
    if not missing(cfg) and cfg.mechanics.model != "screw":
        why_not(cfg)


def screw_config(cfg: MachineConfig) -> MachineConfig:
    """``cfg`` itself on the screw model; else its screw model (:func:`conversion`) with
    the coupling and the nut as compliant as the thrust bearing, at the table (any
    stiffness the fit replaces; the plant's ranges hold it), a two-mass file's coupling as
    declared.  Call only where :func:`why_not` is None."""
    if cfg.mechanics.model == "screw":
        return cfg
    k_tb = float(declared(cfg)["thrust_bearing_stiffness_n_per_m"])
    r2 = transmission_ratio(cfg) ** 2
    k_c = (cfg.coupling.stiffness_nm_per_rad if cfg.coupling is not None
           else min(max(r2 * k_tb, 1.0), 1e9))
    return load_machine(cfg.path, conversion(cfg, k_c, k_tb, max(0.0, kept_load_inertia(cfg))))


def torsional_stiffness(cfg: MachineConfig, shear_modulus: float) -> float:
    """N·m/rad: the whole screw's torsional stiffness G J_p / l of a screw-model ``cfg``
    at shear modulus ``shear_modulus`` (Pa)."""
    sc = cfg.screw
    d = sc.diameter(sc.stiffness_diameter)
    return shear_modulus * math.pi * d ** 4 / 32.0 / sc.length_m


def schema_rows() -> list[dict]:
    """``hil config-keys`` rows of ``[identify.screw]``: the plant's ``[screw]`` keys of
    :data:`KEYS`, ``segments`` defaulting to 1."""
    rows = []
    for row in describe(ScrewSection):
        if row["key"] not in KEYS:
            continue
        if row["key"] == "segments":
            row = {**row, "default": repr(DEFAULT_SEGMENTS)}
        rows.append({**row, "only": "kind=screw",
                     "doc": "(hil identify: the screw the file lumps) " + row["doc"]})
    return rows
