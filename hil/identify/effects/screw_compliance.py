"""Compliance in the screw model: the coupling's torsion and the nut's axial spring fitted
apart, the screw's own torsion and axial stretch and the thrust bearing kept as declared
(issue 30, item 3, cause 6).

The two-mass form puts the whole train into one spring between the motor and everything
else, so it cannot hold a soft coupling and a soft nut together: on an outside trace it
took the table mass 12 % down instead.  In the screw model the two springs carry
different forces -- the coupling the motor's force less what accelerates the motor
itself, the nut only what moves the table, the screw's inertia lying between them -- and
the motor-to-table deflection is, quasi-statically,

    motor - table = c_c F_c + c_n F_n + c_rest(x) F_n,

c_c = r²/k_c the coupling's compliance at the table (r = lead/2pi), c_n = 1/k_n the
nut's, and c_rest(x) the rest of the train's (screw torsion and stretch up to the nut,
thrust bearing), which changes with the nut's place x along the screw.  c_c and c_n are
the coefficients; c_rest is the declared file's, from the plant's own linearised
mechanics (:func:`plant.assemble.mechanics_matrices`, the motor held), so that the
prediction is the lumped model's.
"""

import math

import numpy as np

from hil.identify.effects.base import POSITION, Effect, Term, explained, lstsq
from hil.identify.effects.drivetrain import NO_SECOND_SENSOR, stiffness_box
from plant.assemble import build_chains, mechanics_matrices
from plant.config import MachineConfig

#: nut places at which the declared train's compliance is computed across the travel
#: the record covers (interpolated between them)
GRID_POINTS = 33
#: stiffest coupling (N·m/rad) and nut (N/m) the machine file's schema takes
COUPLING_MAX = 1e9
NUT_MAX = 1e11


def held_motor_compliance(cfg: MachineConfig, table_pos: float) -> float:
    """m/N: the table's deflection per N pushed on it with the motor's rotor held, at table
    position ``table_pos`` (m), from the lumped mechanics the plant runs (coupling, screw
    torsion and stretch, thrust bearings, nut)."""
    _, _, k = mechanics_matrices(cfg, table_pos)
    unit = np.zeros(k.shape[0] - 1)
    unit[-1] = 1.0
    # coordinate 0 is the rotor: held, it removes the train's rigid-body motion
    return float(np.linalg.solve(k[1:, 1:], unit)[-1])


def train_forces(ctx) -> tuple[np.ndarray, np.ndarray]:
    """(through the coupling, through the nut), each N at the table, shape (n,): the
    motor's force less what accelerates and drags the rotor (node 0 of the torsional
    chain, with half the coupling), and less what accelerates and drags every rotating
    part (rotor, coupling, screw)."""
    rot, _ = build_chains(ctx.cfg)
    r2 = ctx.drive.ratio ** 2
    m = ctx.m
    coupling = m.force - rot.m[0] / r2 * m.a - rot.c_gnd[0] / r2 * m.v
    nut = m.force - float(rot.m.sum()) / r2 * m.a - float(rot.c_gnd.sum()) / r2 * m.v
    return coupling, nut


class ScrewModelCompliance(Effect):
    """The screw model's coupling and nut stiffness, from the motor-minus-table position.

    Coefficients: the coupling's and the nut's compliance at the table (m/N); the shape
    is empty.  Declared wherever the machine file is a screw model, and correctable: a
    proposal fits what the position residual asks of both on top of the declared ones.
    The tolerance applies to the stiffnesses the file declares (:func:`stiffness_box`)."""
    name = "screw_model_compliance"
    domain = POSITION
    n_params = 2
    correctable = True
    keys_per_coefficient = True

    def unavailable(self, ctx):
        if ctx.m.dx is None:
            return NO_SECOND_SENSOR
        if ctx.cfg.mechanics.model != "screw":
            return (f"mechanics.model = '{ctx.cfg.mechanics.model}' has no screw geometry "
                    "(length, diameter, nut place) to place coupling and nut compliance "
                    "in; the two-mass compliance stands for them there")
        return None

    def declared(self, ctx):
        if ctx.cfg.mechanics.model != "screw":
            return None
        return Term(self, {}, self._declared_coef(ctx))

    def _declared_coef(self, ctx) -> np.ndarray:
        cfg = ctx.cfg
        return np.array([ctx.drive.ratio ** 2 / cfg.coupling.stiffness_nm_per_rad,
                         1.0 / cfg.screw.nut_stiffness_n_per_m])

    def n_coef(self, shape):
        return 2

    def bounds(self, shape):
        return np.zeros(2), np.full(2, np.inf)

    def declared_box(self, c0, tolerance):
        return stiffness_box(c0, tolerance)

    def columns(self, ctx, shape):
        coupling, nut = train_forces(ctx)
        # pushing toward +, the motor leads the table
        return -np.stack([coupling, nut], axis=1)

    def fixed(self, ctx, shape):
        x = ctx.m.x
        use = x[ctx.m.use] if ctx.m.use.any() else x
        grid = np.linspace(float(np.min(use)), float(np.max(use)), GRID_POINTS)
        own = float(np.sum(self._declared_coef(ctx)))
        rest = np.array([held_motor_compliance(ctx.cfg, p) - own for p in grid])
        _, nut = train_forces(ctx)
        return -np.interp(x, grid, rest) * nut

    def propose(self, ctx, residual, model):
        cols = self.columns(ctx, {})
        mask = ctx.m.use
        base = model.term(self.name)
        start = base.coef if base is not None else np.zeros(2)
        # the change asked for, on top of the model's; the sum stays a compliance (>= 0)
        step = lstsq(cols, residual, mask, -start, np.full(2, np.inf))
        coef = start + step
        ev = {"explained": explained(residual, cols @ step, mask)}
        k = self.params(ctx, {}, coef)
        ev["text"] = (f"motor minus table position follows the forces through coupling and "
                      f"nut apart: coupling {k['coupling_stiffness_nm_per_rad']:.4g} N*m/rad, "
                      f"nut {k['nut_stiffness_n_per_m']:.4g} N/m (screw and thrust bearing "
                      "as declared)")
        return Term(self, {}, coef, True, ev)

    def params(self, ctx, shape, coef):
        r2 = ctx.drive.ratio ** 2
        return {"coupling_stiffness_nm_per_rad":
                float(r2 / coef[0]) if coef[0] > 0 else math.inf,
                "nut_stiffness_n_per_m": float(1.0 / coef[1]) if coef[1] > 0 else math.inf}

    def overrides(self, ctx, shape, coef, model):
        k = self.params(ctx, shape, coef)
        return {"coupling": {"stiffness_nm_per_rad":
                             float(min(k["coupling_stiffness_nm_per_rad"], COUPLING_MAX))},
                "screw": {"nut_stiffness_n_per_m":
                          float(min(k["nut_stiffness_n_per_m"], NUT_MAX))}}
