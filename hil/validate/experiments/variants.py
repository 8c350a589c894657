"""Shared tools of the validation experiments: machine-file variants built in memory
(rigid, two-mass, undamped, torque-free, frictionless), views of the screw state as the
coordinate vector of :func:`plant.assemble.mechanics_matrices`, and small measurements
(zero-crossing frequency, energy, acceleration)."""

import copy
import math
from pathlib import Path

import numpy as np
import tomllib

from hil.validate.core import CONFIGS
from plant import Plant
from plant import layout as L
from plant.config import load_machine, parse_machine
from plant.effects.chain import chain_energy
from plant.effects.tlm import tlm_init

ARROW = CONFIGS / "arrow500_x.toml"
HELD_MOTOR_KGM2 = 1.0e4  # motor inertia that stands for a clamped rotor (10^7 x the real one)


# --- machine-file variants ------------------------------------------------------------------

def machine_raw(path: Path = ARROW) -> dict:
    """A machine file as a nested dict of TOML tables (a fresh copy)."""
    return tomllib.loads(path.read_text())


def with_keys(raw: dict, changes: dict) -> dict:
    """Copy of ``raw`` with ``{"section": {"key": value}}`` set; a section value of None
    removes the section."""
    out = copy.deepcopy(raw)
    for sec, values in changes.items():
        if values is None:
            out.pop(sec, None)
        else:
            out.setdefault(sec, {}).update(values)
    return out


def plant_of(raw: dict, label: str, table_pos: float = 0.0) -> Plant:
    """Check ``raw`` like a machine file (named ``label`` in errors) and build the axis."""
    return Plant(parse_machine(raw, label), table_pos)


def torque_free(raw: dict, t_cl: float = 1.0e-4) -> dict:
    """The motor as a first-order current loop without cogging: zero current gives exactly
    zero torque (a d-q motor with blocked pulses would brake through its shorted winding).
    ``t_cl`` in s."""
    out = with_keys(raw, {"cogging": None, "field_weakening": None,
                          "current_loop": None})
    out["motor"]["model"] = "first_order"
    out["motor"].pop("inductance_q_h", None)
    out["current_loop"] = {"time_constant_s": t_cl}
    return out


def frictionless(raw: dict) -> dict:
    """No table friction, no presliding, no motor bearing drag."""
    out = with_keys(raw, {"friction": None, "presliding": None})
    out["motor"]["viscous_nms_per_rad"] = 0.0
    return out


def undamped(raw: dict) -> dict:
    """Every damper of the coupling, screw, bearings and nut set to zero."""
    out = frictionless(raw)
    if "coupling" in out:
        out["coupling"]["damping_nms_per_rad"] = 0.0
    if "screw" in out:
        out["screw"].update(torsional_damping_nms_per_rad=0.0, axial_damping_ns_per_m=0.0,
                            bearing_viscous_nms_per_rad=0.0, nut_damping_ns_per_m=0.0,
                            thrust_bearing_damping_ns_per_m=0.0)
    return out


def screw_inertia(path: Path = ARROW) -> float:
    """Polar mass moment of the screw of a screw machine file, rho*pi*d^4/32*L (kg·m²), d
    the diameter its [screw] inertia_diameter names."""
    sc = load_machine(path).screw
    return sc.density_kg_m3 * math.pi * sc.diameter(sc.inertia_diameter) ** 4 / 32.0 * sc.length_m


def lumped_variant(raw: dict, model: str, path: Path = ARROW) -> dict:
    """The screw axis as a 'rigid' or 'two_mass' model: the screw becomes load inertia
    (and, for 'rigid', the coupling hubs too)."""
    j_load = screw_inertia(path)
    if model == "rigid":
        j_load += raw["coupling"].get("inertia_kgm2", 0.0)
        out = with_keys(raw, {"coupling": None, "screw": None})
    else:
        out = with_keys(raw, {"screw": None})
    out["mechanics"] = {"model": model, "lead_m": raw["mechanics"]["lead_m"],
                        "load_inertia_kgm2": j_load}
    return out


# --- measurements -----------------------------------------------------------------------------

def crossing_frequency(t: np.ndarray, y: np.ndarray) -> float:
    """Frequency (Hz) of a zero-mean oscillation ``y(t)`` from a straight-line fit through
    its linearly interpolated zero crossings (needs at least three crossings)."""
    i = np.nonzero(np.signbit(y[:-1]) != np.signbit(y[1:]))[0]
    tc = t[i] - y[i] * (t[i + 1] - t[i]) / (y[i + 1] - y[i])
    half_period = np.polyfit(np.arange(tc.size), tc, 1)[0]
    return 0.5 / half_period


class ScrewState:
    """Views of a screw-model plant's state as the coordinate vector q of
    :func:`plant.assemble.mechanics_matrices` (torsional nodes, axial nodes, table)."""

    def __init__(self, plant: Plant):
        p = plant.params
        self.plant = plant
        self.ro, self.nr = int(p[L.P_SOFF_ROT]), int(p[L.P_N_ROT])
        self.ao, self.na = int(p[L.P_SOFF_AX]), int(p[L.P_N_AX])
        self.q0 = self.positions()

    def positions(self) -> np.ndarray:
        """q (rad, m), shape (nr + na + 1,)."""
        s = self.plant.state
        return np.concatenate([s[self.ro:self.ro + self.nr], s[self.ao:self.ao + self.na],
                               [s[L.S_TABLE_X]]])

    def displace(self, dq: np.ndarray) -> None:
        """Add ``dq`` to the positions; re-derive the TLM waves; refresh the outputs."""
        s, p, plant = self.plant.state, self.plant.params, self.plant
        nr, na = self.nr, self.na
        s[self.ro:self.ro + nr] += dq[:nr]
        s[self.ao:self.ao + na] += dq[nr:nr + na]
        s[L.S_TABLE_X] += dq[-1]
        if p[L.P_SOLVER] == L.SOLVER_TLM:
            tlm_init(p, int(p[L.P_OFF_ROT]), s, self.ro, nr, plant.dt)
            tlm_init(p, int(p[L.P_OFF_AX]), s, self.ao, na, plant.dt)
        plant.step(0)

    def record(self, n_calls: int, n_sub: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Step ``n_calls`` times by ``n_sub``; returns (t in s of shape (n_calls,),
        q - q_rest of shape (n_calls, nq), worst kernel status)."""
        t = np.empty(n_calls)
        q = np.empty((n_calls, self.q0.size))
        status = 0
        for k in range(n_calls):
            status = max(status, self.plant.step(n_sub))
            t[k] = self.plant.output("time_s")
            q[k] = self.positions() - self.q0
        return t, q, status


def nut_deflection(plant: Plant) -> float:
    """Nut spring deflection (m) at the nut's present place, as the kernel computes it
    (backlash dead zone not applied)."""
    cfg, s = plant.config, plant.state
    st = ScrewState(plant)
    seg = cfg.screw.length_m / cfg.screw.segments
    pos = (cfg.screw.nut_offset_m + s[L.S_TABLE_X]) / seg
    j = min(max(int(pos), 0), st.na - 2)
    w = min(max(pos - j, 0.0), 1.0)
    theta = (1 - w) * s[st.ro + 1 + j] + w * s[st.ro + 2 + j]
    u = (1 - w) * s[st.ao + j] + w * s[st.ao + j + 1]
    return u + plant.built.ratio * theta - s[L.S_TABLE_X]


def screw_energy(plant: Plant) -> float:
    """Kinetic plus elastic energy (J) of both chains, the table and the nut spring."""
    p, s = plant.params, plant.state
    st = ScrewState(plant)
    e = chain_energy(p, int(p[L.P_OFF_ROT]), s, st.ro, st.nr)
    e += chain_energy(p, int(p[L.P_OFF_AX]), s, st.ao, st.na)
    e += 0.5 * p[L.P_TABLE_M] * s[L.S_TABLE_V] ** 2
    return e + 0.5 * p[L.P_NUT_K] * nut_deflection(plant) ** 2


# --- 1. rigid body ----------------------------------------------------------------------------

def rigid_inertia(plant: Plant) -> float:
    """Analytic J_total = J_m + J_load + m (lead/2pi)^2 (kg·m²) of a rigid screw axis."""
    cfg = plant.config
    r = cfg.mechanics.lead_m / (2.0 * math.pi)
    return cfg.motor.inertia_kgm2 + cfg.mechanics.load_inertia_kgm2 + cfg.table.mass_kg * r * r


def mean_acceleration(plant: Plant, inputs: dict, t_settle: float, t_end: float):
    """Apply ``inputs`` from rest, return (motor acceleration in rad/s² between t_settle and
    t_end (s), mean torque there in N·m, worst status, the trace)."""
    plant.set_input(**inputs)
    n = round(t_end / plant.pwm_period)
    tr = plant.run(n, plant.sub_per_pwm)
    k0 = round(t_settle / plant.pwm_period)
    acc = (tr["motor_vel"][-1] - tr["motor_vel"][k0]) / (tr["time_s"][-1] - tr["time_s"][k0])
    return acc, float(tr["torque"][k0 + 1:].mean()), int(tr["status"].max()), tr
