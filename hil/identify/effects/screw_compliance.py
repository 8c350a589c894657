"""Compliance in the screw model: the coupling's torsion, the screw's torsion and the nut's
axial spring fitted apart, the screw's axial stretch and the thrust bearing kept as
declared (issue 30, item 3, cause 6).

The two-mass form puts the whole train into one spring between the motor and everything
else, so it cannot hold a soft coupling and a soft nut together: on an outside trace it
took the table mass 12 % down instead.  In the screw model the springs carry different
forces -- the coupling the motor's force less what accelerates the rotor, the screw's
torsion that less what accelerates the screw up to each of its sections, the nut only
what moves the table -- and, quasi-statically (the train's own modes far above the
motion), the table's deflection behind the motor is the rotor-held mechanics' response
to those loads:

    table - motor = -(h_n(x) F_n + h_a(x) a + h_v(x) v),

F_n the force through the nut (the motor's force less what accelerates and drags every
rotating part), h_n(x) the train's compliance at the table, h_a(x) and h_v(x) the
table's deflection per unit acceleration and velocity of the screw's rotating inertia
and drag, all with the rotor held, from the plant's own linearised mechanics
(:func:`plant.assemble.mechanics_matrices`) at the nut's place x.  Each of the three
compliances -- coupling r²/k_c, screw torsion r² l/(G J_p), nut 1/k_n -- enters them
linearly (the train is a statically determinate chain from the held rotor to the table),
so each is a coefficient whose column is its share of the declared deflection; the rest
(the screw's stretch and the thrust bearing) is the fixed part.  The screw's stretch
grows with the nut's distance from the thrust bearing as its torsion does, and the thrust
bearing carries the nut's force as the nut does: the position residual cannot tell them
apart, so they stay as declared and the fitted torsion and nut stand for them where they
differ.  Near the thrust bearing the torsion is a few per cent of the train's compliance;
where the record does not determine it within its declared tolerance (its standard
uncertainty from the position fit beyond it) it stays as declared too, and the
candidate fits coupling and nut alone (a torsion fitted there wanders with whatever the
model lacks: on a rigid file's trace the refinement asked for +47 to +82 % of a
correct shear modulus).

Rigid and two-mass files on a screw axis get the same candidate where they declare the
screw they lump (``[identify.screw]``, :mod:`hil.identify.screw_geometry`): the screw
model is built from it (the moved inertia kept), the torsion held by the geometry's
prior, the coupling and nut fitted freely; it replaces the two-mass compliance, which is
ranked beside it by the same held-out criterion.
"""

import math
from dataclasses import replace

import numpy as np

from hil.identify import screw_geometry as geometry
from hil.identify.effects.base import (
    POSITION,
    Effect,
    Term,
    explained,
    lstsq,
    uncertainty,
)
from hil.identify.effects.drivetrain import NO_SECOND_SENSOR, stiffness_box
from plant.assemble import build_chains, mechanics_matrices, transmission_ratio
from plant.config import MachineConfig

#: nut places at which the train's influence is computed across the travel the record
#: covers (interpolated between them)
GRID_POINTS = 33
#: the compliances fitted, in coefficient order
GROUPS = ("coupling", "nut", "torsion")
#: stiffest coupling (N·m/rad) and nut (N/m), and the shear moduli (Pa) the machine
#: file's schema takes
COUPLING_MAX = 1e9
NUT_MAX = 1e11
SHEAR_MIN, SHEAR_MAX = 1e9, 5e11
#: the shape's flag of a torsion held at its declared value: the record does not determine
#: it within its tolerance (its standard uncertainty from the position fit beyond it)
HELD = "torsion_held"
#: damping ratios tried on the replay for the coupling's and the nut's modes where a rigid
#: file, or [identify.screw], declares no damper for them (as the two-mass compliance does)
ZETAS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.4)


def stiffer(cfg: MachineConfig, group: str, factor: float) -> MachineConfig:
    """A screw-model ``cfg`` with ``group``'s stiffness (one of :data:`GROUPS`) times
    ``factor`` (for the linearised mechanics only: not checked against the schema)."""
    if group == "coupling":
        k = cfg.coupling.stiffness_nm_per_rad * factor
        return replace(cfg, coupling=replace(cfg.coupling, stiffness_nm_per_rad=k))
    if group == "nut":
        screw = replace(cfg.screw, nut_stiffness_n_per_m=cfg.screw.nut_stiffness_n_per_m * factor)
    else:
        screw = replace(cfg.screw, shear_modulus_pa=cfg.screw.shear_modulus_pa * factor)
    return replace(cfg, screw=screw)


def influence(cfg: MachineConfig, places: np.ndarray) -> np.ndarray:
    """(h_n, h_a, h_v) at each table position of ``places`` (m, shape (g,)), shape (3, g):
    the table's deflection with the rotor held per N through the nut (m/N), per m/s² and
    per m/s of the rigid motion's loads on the screw's rotating inertia and drag (m per
    m/s², m per m/s), from the linearised mechanics of a screw-model ``cfg``."""
    out = np.empty((3, places.size))
    for k, p in enumerate(places):
        m, c, stiff = mechanics_matrices(cfg, float(p))
        phi = _rigid_mode(cfg, m.shape[0])
        # coordinate 0 is the rotor: held, it removes the train's rigid-body motion
        h = np.linalg.solve(stiff[1:, 1:], np.eye(stiff.shape[0] - 1)[-1])
        out[0, k] = h[-1]
        out[1, k] = h[:-1] @ (m @ phi)[1:-1]
        out[2, k] = h[:-1] @ (c @ phi)[1:-1]
    return out


def _rigid_mode(cfg: MachineConfig, n: int) -> np.ndarray:
    """The rigid-body motion per m of table travel, shape (n,): every torsional node 1/r
    rad, the axial screw nodes still, the table 1 m."""
    rot, _ = build_chains(cfg)
    phi = np.zeros(n)
    phi[:rot.n] = 1.0 / transmission_ratio(cfg)
    phi[-1] = 1.0
    return phi


def nut_force(cfg: MachineConfig, force: np.ndarray, a: np.ndarray,
              v: np.ndarray) -> np.ndarray:
    """N, shape (n,): the force through the nut of a screw-model ``cfg``, the motor's
    ``force`` at the table (N) less what accelerates (``a``, m/s²) and drags (``v``, m/s)
    every rotating part."""
    m, c, _ = mechanics_matrices(cfg, 0.0)
    phi = _rigid_mode(cfg, m.shape[0])
    table = cfg.table.mass_kg
    return force - (phi @ m @ phi - table) * a - (phi @ c @ phi) * v


def compliances(cfg: MachineConfig) -> np.ndarray:
    """m/N at the table, shape (3,): the coupling's r²/k_c, the nut's 1/k_n and the whole
    screw's torsion r² l/(G J_p) of a screw-model ``cfg``."""
    r2 = transmission_ratio(cfg) ** 2
    return np.array([r2 / cfg.coupling.stiffness_nm_per_rad, 1.0 / cfg.screw.nut_stiffness_n_per_m,
                     r2 / geometry.torsional_stiffness(cfg, cfg.screw.shear_modulus_pa)])


def held_motor_compliance(cfg: MachineConfig, table_pos: float) -> float:
    """m/N: the table's deflection per N pushed on it with the motor's rotor held, at table
    position ``table_pos`` (m), from the lumped mechanics the plant runs (coupling, screw
    torsion and stretch, thrust bearings, nut)."""
    return float(influence(cfg, np.array([table_pos]))[0, 0])


def deflection(cfg: MachineConfig, ctx, places: np.ndarray) -> np.ndarray:
    """m, shape (n,): table minus motor position the screw-model ``cfg`` predicts for the
    record's motion (the influence at ``places``, interpolated along the table)."""
    m = ctx.m
    h = influence(cfg, places)
    f_n = nut_force(cfg, m.force, m.a, m.v)
    return -(np.interp(m.x, places, h[0]) * f_n + np.interp(m.x, places, h[1]) * m.a
             + np.interp(m.x, places, h[2]) * m.v)


class ScrewModelCompliance(Effect):
    """The screw model's coupling, nut and screw-torsion stiffness, from the motor-minus-
    table position.

    Coefficients: the coupling's, the nut's and the whole screw's torsional compliance at
    the table (m/N, :func:`compliances`), the torsion left out where the shape holds it
    as declared (:data:`HELD`); the shape holds too the damping ratio chosen by the
    replay where the file declares no damper for coupling or nut (``zeta``).  Declared
    wherever the machine file is a screw model, and correctable: a proposal fits what the
    position residual asks of all three.  The tolerance applies to the stiffnesses the file
    declares (:func:`stiffness_box`); on a rigid or two-mass file with
    ``[identify.screw]`` only the torsion is declared (by the geometry)."""
    name = "screw_model_compliance"
    domain = POSITION
    n_params = 3
    correctable = True
    keys_per_coefficient = True
    replaces = ("compliance",)

    def __init__(self):
        self._cache: dict = {}

    def __getstate__(self) -> dict:
        # a term sent to a candidate's worker process carries its effect: not the cache
        return {**self.__dict__, "_cache": {}}

    def unavailable(self, ctx):
        if ctx.m.dx is None:
            return NO_SECOND_SENSOR
        return geometry.why_not(ctx.cfg)

    def declared(self, ctx):
        if ctx.cfg.mechanics.model != "screw":
            return None
        return Term(self, {}, compliances(ctx.cfg))

    def declared_coefficients(self, ctx):
        if ctx.cfg.mechanics.model == "screw" or self.unavailable(ctx) is not None:
            return None
        # the geometry declares the screw's torsion; coupling and nut are the fit's
        return np.array([math.nan, math.nan, compliances(self._screw(ctx))[2]])

    def n_coef(self, shape):
        return 2 if shape.get(HELD) else 3

    def bounds(self, shape):
        k = self.n_coef(shape)
        return np.zeros(k), np.full(k, np.inf)

    def shape_keys_of(self, shape):
        # the damping ratio is a scalar shape (refined in log space, Term.values) only
        # where the replay chose one, and not 0
        return ("zeta",) if shape.get("zeta", 0.0) > 0.0 else ()

    def shape_label(self, ctx, key):
        return "damping_ratio"

    def declared_for(self, c0, shape):
        # the declared values are the three compliances (a term of no shape): a held
        # torsion is no coefficient of the term, and no file declares the damping ratio
        # the replay chose (NaN: neither prior nor box)
        coef = c0[:2] if shape.get(HELD) else c0[:3]
        return np.concatenate([coef, np.full(len(self.shape_keys_of(shape)), math.nan)])

    def declared_box(self, c0, tolerance):
        return stiffness_box(c0, tolerance)

    def _screw(self, ctx) -> MachineConfig:
        return self._train(ctx)[0]

    def _train(self, ctx) -> tuple:
        """(the screw-model config, columns (n, 3), fixed part (n,)) for ``ctx``, cached per
        config and record span."""
        x = ctx.m.x
        use = x[ctx.m.use] if ctx.m.use.any() else x
        key = (id(ctx.cfg), id(ctx.m.x), float(np.min(use)), float(np.max(use)))
        hit = self._cache.get(key)
        if hit is not None and hit[0] is ctx.cfg and hit[1] is ctx.m.x:
            return hit[2]
        cfg = geometry.screw_config(ctx.cfg)
        places = np.linspace(key[2], key[3], GRID_POINTS)
        whole = deflection(cfg, ctx, places)
        # each compliance's share: the deflection is linear in it, so twice the change
        # when its spring is made twice as stiff
        shares = [2.0 * (whole - deflection(stiffer(cfg, g, 2.0), ctx, places)) for g in GROUPS]
        cols = np.stack(shares, axis=1) / compliances(cfg)
        out = (cfg, cols, whole - sum(shares))
        if len(self._cache) > 8:
            self._cache.clear()
        self._cache[key] = (ctx.cfg, ctx.m.x, out)
        return out

    def columns(self, ctx, shape):
        cols = self._train(ctx)[1]
        return cols[:, :2] if shape.get(HELD) else cols

    def fixed(self, ctx, shape):
        _, cols, fixed = self._train(ctx)
        return fixed + cols[:, 2] * self._torsion(ctx) if shape.get(HELD) else fixed

    def _torsion(self, ctx) -> float:
        """m/N: the screw's torsional compliance at the table the file (or its
        [identify.screw]) declares."""
        return float(compliances(self._screw(ctx))[2])

    def propose(self, ctx, residual, model):
        mask = ctx.m.use
        # what the term and those it replaces explain is fitted anew
        old = sum((t.contribution(ctx) for t in model.terms
                   if t.effect.name == self.name or t.effect.name in self.replaces),
                  np.zeros(residual.size))
        shape = {}
        spread = self._spread(ctx, residual + old - self.fixed(ctx, shape), model)
        c0 = model.declared.get(self.name)
        if c0 is not None and np.isfinite(c0[2]) and spread > model.tolerance_of(self.name) * c0[2]:
            shape[HELD] = True
        coef, wanted = self._fit(ctx, residual + old - self.fixed(ctx, shape), model, shape)
        change = self.columns(ctx, shape) @ coef + self.fixed(ctx, shape) - old
        change -= float(np.mean(change[mask]))
        ev = {"explained": explained(residual, change, mask)}
        if self._undamped(ctx):
            shape["zeta"] = self._damping_by_replay(ctx, coef, model, shape)
        k = self.params(ctx, shape, coef)
        where = ("" if ctx.cfg.mechanics.model == "screw"
                 else f" in the screw model of [{geometry.SECTION}]")
        damped = (f", damping ratio {shape['zeta']:g} by the replay" if "zeta" in shape else "")
        torsion = (f"as declared (the record gives it to +-{100.0 * spread / c0[2]:.3g} %, "
                   "beyond its tolerance)" if shape.get(HELD) else
                   f"(shear modulus {k['shear_modulus_pa'] / 1e9:.3g} GPa)")
        ev["text"] = (f"motor minus table position follows the forces through coupling, screw "
                      f"and nut apart{where}: coupling "
                      f"{k['coupling_stiffness_nm_per_rad']:.4g} N*m/rad, screw torsion "
                      f"{k['screw_torsional_stiffness_nm_per_rad']:.4g} N*m/rad {torsion}, nut "
                      f"{k['nut_stiffness_n_per_m']:.4g} N/m (screw stretch and thrust bearing "
                      f"as declared){damped}")
        if wanted is not None:
            # laid out as Term.values: the coefficients asked for, the shapes as chosen
            wanted = np.concatenate([wanted, [shape[key] for key in self.shape_keys_of(shape)]])
        return Term(self, shape, coef, True, ev, wanted=wanted,
                    wanted_by="its proposal" if wanted is not None else "")

    def _fit(self, ctx, target, model, shape) -> tuple[np.ndarray, np.ndarray | None]:
        """(coefficients, what was asked beyond the declared ones' tolerance or None) of
        the columns of ``shape`` on ``target`` (m, shape (n,)), the encoders' zero offset
        fitted too (the position residual's mean is removed) and thrown away; a declared
        stiffness asked beyond its tolerance is held at it and the others fitted beside
        it, what was asked a finding."""
        cols = self.columns(ctx, shape)
        k = cols.shape[1]
        a = np.hstack([cols, np.ones((cols.shape[0], 1))])
        lo, hi = self.bounds(shape)
        free = lstsq(a, target, ctx.m.use, np.append(lo, -np.inf), np.append(hi, np.inf))
        b_lo, b_hi = model.box(Term(self, shape, free[:k]))
        if not np.any((free[:k] < b_lo) | (free[:k] > b_hi)):
            return free[:k], None
        held = lstsq(a, target, ctx.m.use, np.append(b_lo, -np.inf), np.append(b_hi, np.inf))
        return held[:k], free[:k].copy()

    def _spread(self, ctx, target, model) -> float:
        """m/N: the standard uncertainty of the torsion's compliance fitted beside the
        coupling's and the nut's to ``target``, from the position noise after the
        low-pass (its samples weighted by their independent share, as the joint refit
        weighs them), times the fit's misfit over that noise where it exceeds 1."""
        m = ctx.m
        if not m.noise_dx > 0.0:
            return math.inf
        cols = self.columns(ctx, {})
        a = np.hstack([cols, np.ones((cols.shape[0], 1))])[m.use]
        coef, *_ = np.linalg.lstsq(a, target[m.use], rcond=None)
        misfit = float(np.sqrt(np.mean((target[m.use] - a @ coef) ** 2))) / m.noise_dx
        w = math.sqrt(min(1.0, 2.0 * m.cutoff_hz * ctx.rec.dt)) / m.noise_dx
        return float(uncertainty(w * a, misfit)[2])

    def _undamped(self, ctx) -> bool:
        """Whether a rigid file's coupling, or the nut of [identify.screw], has no damper."""
        if ctx.cfg.mechanics.model == "screw":
            return False
        return ctx.cfg.coupling is None or "nut_damping_ns_per_m" not in geometry.declared(ctx.cfg)

    def _damping_by_replay(self, ctx, coef, model, shape) -> float:
        """The damping ratio of ZETAS whose replay has the smallest floor-normalised cost."""
        from hil.identify.fit import record_errors
        from hil.identify.floor import normalised_cost, replay_floor
        floor = replay_floor(ctx.rec, ctx.cfg)
        best, best_cost = ZETAS[0], math.inf
        for zeta in ZETAS:
            rep = model.replay(extra=self.overrides(ctx, {**shape, "zeta": zeta}, coef, model))
            cost = normalised_cost(record_errors(ctx.rec, rep), floor)
            if cost < best_cost:
                best, best_cost = zeta, cost
        return best

    def params(self, ctx, shape, coef):
        r2 = transmission_ratio(ctx.cfg) ** 2
        unit_g = geometry.torsional_stiffness(self._screw(ctx), 1.0)
        c_t = self._torsion(ctx) if shape.get(HELD) else float(coef[2])
        out = {"coupling_stiffness_nm_per_rad": float(r2 / coef[0]) if coef[0] > 0 else math.inf,
               "nut_stiffness_n_per_m": float(1.0 / coef[1]) if coef[1] > 0 else math.inf,
               "shear_modulus_pa": float(r2 / c_t / unit_g) if c_t > 0 else math.inf,
               "screw_torsional_stiffness_nm_per_rad": float(r2 / c_t) if c_t > 0 else math.inf}
        if "zeta" in shape:
            out["damping_ratio"] = shape["zeta"]
        return out

    def overrides(self, ctx, shape, coef, model):
        k = self.params(ctx, shape, coef)
        k_c = float(min(k["coupling_stiffness_nm_per_rad"], COUPLING_MAX))
        k_n = float(min(k["nut_stiffness_n_per_m"], NUT_MAX))
        shear = float(min(max(k["shear_modulus_pa"], SHEAR_MIN), SHEAR_MAX))
        cfg = ctx.cfg
        if cfg.mechanics.model == "screw":
            out = {"coupling": {"stiffness_nm_per_rad": k_c},
                   "screw": {"nut_stiffness_n_per_m": k_n}}
        else:
            out = geometry.conversion(cfg, k_c, k_n, max(0.0, geometry.kept_load_inertia(cfg)))
        if not shape.get(HELD):
            out["screw"]["shear_modulus_pa"] = shear
        if "zeta" in shape:
            self._damp(ctx, shape["zeta"], k_c, k_n, out)
        return out

    def _damp(self, ctx, zeta: float, k_c: float, k_n: float, out: dict) -> None:
        """Dampers of damping ratio ``zeta`` on the modes of the coupling (rotor against
        the rest, N·m·s/rad) where a rigid file has none, and of the nut (the rotating
        parts at the table against the table, N·s/m) where [identify.screw] has none, into
        ``out``: c = 2 zeta sqrt(k m_eq)."""
        cfg = self._screw(ctx)
        rot, _ = build_chains(cfg)
        r2 = transmission_ratio(cfg) ** 2
        table = cfg.table.mass_kg
        if ctx.cfg.coupling is None:
            j0, j1 = float(rot.m[0]), float(rot.m[1:].sum()) + table * r2
            out["coupling"]["damping_nms_per_rad"] = 2.0 * zeta * math.sqrt(
                k_c * j0 * j1 / (j0 + j1))
        if "nut_damping_ns_per_m" not in geometry.declared(ctx.cfg):
            m_rot = float(rot.m.sum()) / r2
            out["screw"]["nut_damping_ns_per_m"] = 2.0 * zeta * math.sqrt(
                k_n * m_rot * table / (m_rot + table))
