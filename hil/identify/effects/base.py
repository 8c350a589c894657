"""What every effect of the identification library provides, and the data they share.

An effect lives in one *domain*, the residual it explains:

``force``
    the inverse model's force residual: measured force at the table minus
    ``M a + friction + ...`` computed from the measured motion (N, or N·m on rotary tables);
``position``
    the difference between the table's measured position and the motor encoder's, in
    table units (m), which the config's mechanics predicts (pitch error, backlash,
    compliance); only when the record has both sensors;
``replay``
    the closed-loop replay's error, for what neither residual can show (a delay that
    shifts position and current alike).

Each effect is linear in its coefficients once its shape parameters are fixed (the
Stribeck velocity, the cogging orders, the pitch periods, the presliding shape): it
returns regressor columns, and :mod:`hil.identify.fit` solves every active effect of a
domain jointly by bounded linear least squares.
"""

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from hil.identify.motion import Drive, Motion
from hil.identify.record import Record
from plant.config import MachineConfig

FORCE, POSITION, REPLAY = "force", "position", "replay"


@dataclass(frozen=True)
class Context:
    """Everything an effect may look at.

    Attributes:
        cfg: the config as it was read (before any effect was added).
        drive: its drive train in table units.
        rec: the record.
        m: the filtered motion.
        moving: samples in use where |v| exceeds 1 % of the largest speed: the inverse
            model's friction terms are sign(v) functions, undefined at rest.
        direction: +1/-1, the direction of the last motion (held through standstill).
    """
    cfg: MachineConfig
    drive: Drive
    rec: Record
    m: Motion
    moving: np.ndarray
    direction: np.ndarray

    @classmethod
    def of(cls, cfg: MachineConfig, drive: Drive, rec: Record, m: Motion) -> "Context":
        v_eps = 0.01 * float(np.max(np.abs(m.v[m.use]))) if m.use.any() else 0.0
        moving = m.use & (np.abs(m.v) > v_eps)
        direction = np.empty(rec.n)
        last = 1.0
        for k, vk in enumerate(m.v):
            if vk > v_eps:
                last = 1.0
            elif vk < -v_eps:
                last = -1.0
            direction[k] = last
        return cls(cfg, drive, rec, m, moving, direction)


@dataclass
class Term:
    """One effect in the model: its fixed shape and its fitted coefficients.

    Attributes:
        effect: the library entry.
        shape: shape parameters, fixed during the linear fits (SI, names with units).
        coef: coefficients of ``effect.columns``, shape (k,).
        added: True when identification added it, False when the config declared it.
        evidence: what pointed to it (numbers and a sentence), for the report.
        sigma: standard uncertainty of each coefficient from the last fit, shape (k,), and
            of the scalar shapes after the closed-loop refinement, shape (k + s,) as
            :meth:`values` (NaN where unknown), or None before a fit.
        wanted: for a declared effect, the coefficients and scalar shapes the data asked
            for (laid out as :meth:`values`) where that lies beyond the declared values'
            tolerance, which held them; None when what they ask for is within it.  A
            finding, not taken.
        wanted_by: what asked for ``wanted`` (its proposal, the joint refit, the
            closed-loop refinement).
    """
    effect: "Effect"
    shape: dict
    coef: np.ndarray
    added: bool = False
    evidence: dict = field(default_factory=dict)
    sigma: np.ndarray | None = None
    wanted: np.ndarray | None = None
    wanted_by: str = ""

    def values(self) -> np.ndarray:
        """The term's parameters as one vector, shape (k + s,): its coefficients, then its
        scalar shapes (:meth:`Effect.shape_keys_of` its shape, in their order).  What a
        declared term holds to its tolerance (:meth:`hil.identify.model.Model.box`) and
        ``wanted``."""
        shapes = [float(self.shape[key]) for key in self.effect.shape_keys_of(self.shape)]
        return np.concatenate([self.coef, np.array(shapes)])

    def set_values(self, values: np.ndarray) -> None:
        """Set the coefficients and scalar shapes from a vector laid out as :meth:`values`."""
        k = self.coef.size
        self.coef = np.array(values[:k], dtype=float)
        keys = self.effect.shape_keys_of(self.shape)
        self.shape = {**self.shape, **{key: float(v) for key, v in zip(keys, values[k:])}}

    def contribution(self, ctx: Context) -> np.ndarray:
        """The term's part of its domain's prediction, shape (n,)."""
        out = self.effect.columns(ctx, self.shape) @ self.coef
        fixed = self.effect.fixed(ctx, self.shape)
        return out if fixed is None else out + fixed

    def params(self, ctx: Context) -> dict:
        return self.effect.params(ctx, self.shape, self.coef)


class Effect(ABC):
    """A physical effect the identification can name, fit and write into a machine file.

    Subclasses set ``name``, ``domain``, ``n_params`` (what parsimony counts when two
    effects explain about as much) and implement the methods below.
    """
    name = ""
    domain = FORCE
    n_params = 1
    #: whether a declared term may still be proposed, as a correction of its coefficients
    correctable = False
    #: whether :meth:`params` gives one machine-file key per coefficient, in their order
    #: (a single coefficient always does)
    keys_per_coefficient = False
    #: whether the closed-loop refinement adjusts each coefficient of a term of several
    #: (:func:`hil.identify.refine.parameters`; one key per coefficient always is)
    refined_per_coefficient = False
    #: the scalar shape parameters (positive, SI) that the linear fits hold fixed and the
    #: closed-loop refinement adjusts (in log space); a declared term's are declared values
    #: like its coefficients, held to the same tolerance (:meth:`Term.values`).  A term's
    #: own are :meth:`shape_keys_of` its shape
    shape_keys: tuple[str, ...] = ()
    #: whether the one coefficient is a fixed scale of the shape (never fitted: the shape
    #: carries the machine-file keys)
    fixed_scale = False
    #: effects whose terms this one's takes the place of (the model holds one or the other:
    #: the screw model's compliance and the two-mass form write the same keys)
    replaces: tuple = ()

    def unavailable(self, ctx: Context) -> str | None:
        """Why the effect cannot be looked for in this record or config, or None."""
        return None

    def declared(self, ctx: Context) -> Term | None:
        """The term the config already holds, or None."""
        return None

    def declared_coefficients(self, ctx: Context) -> np.ndarray | None:
        """Where the config holds no term of the effect but declares some of its
        coefficients elsewhere (the screw's torsion, from the geometry a rigid file gives
        its screw): those coefficients, NaN for the ones it does not declare, laid out as
        :meth:`Term.values` of a term of no shape; else None.  They are held within their
        tolerance like a declared term's values (a NaN one is not held)."""
        return None

    @abstractmethod
    def propose(self, ctx: Context, residual: np.ndarray, model) -> Term | None:
        """Fit the effect alone to ``residual`` (its domain's, shape (n,)); the rest of
        ``model`` stays fixed.  Returns the term with its evidence, or None."""

    @abstractmethod
    def columns(self, ctx: Context, shape: dict) -> np.ndarray:
        """Regressors, shape (n, k)."""

    def bounds(self, shape: dict) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the coefficients for the joint fit, each shape (k,)."""
        k = self.n_coef(shape)
        return np.full(k, -np.inf), np.full(k, np.inf)

    def n_coef(self, shape: dict) -> int:
        return 1

    def value_bounds(self, shape: dict) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of :meth:`Term.values`, each shape (k + s,): the coefficients'
        (:meth:`bounds`), then (0, inf) for each scalar shape."""
        lo, hi = self.bounds(shape)
        n = len(self.shape_keys_of(shape))
        return np.concatenate([lo, np.zeros(n)]), np.concatenate([hi, np.full(n, np.inf)])

    def shape_keys_of(self, shape: dict) -> tuple[str, ...]:
        """The scalar shapes a term of ``shape`` has (:attr:`shape_keys`; an effect whose
        shape holds one only where a proposal chose it says which: the screw model's
        compliance, its damping ratio)."""
        return self.shape_keys

    def shape_label(self, ctx: Context, key: str) -> str:
        """The name :meth:`params` gives the scalar shape ``key``."""
        return key

    def fixed(self, ctx: Context, shape: dict) -> np.ndarray | None:
        """The part of the effect's prediction that no coefficient scales, shape (n,) (the
        screw model's compliance the fit leaves as declared), or None."""
        return None

    def declared_for(self, c0: np.ndarray, shape: dict) -> np.ndarray:
        """The declared values ``c0`` (laid out as the declared term's :meth:`Term.values`)
        as a term of ``shape`` lays them out: a shape that holds a coefficient at its
        declared value leaves it out, a scalar shape the declaration has no value for is
        NaN (not declared: neither prior nor box)."""
        return c0

    def declared_box(self, c0: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """Where a declared term's values ``c0`` (coefficients and scalar shapes, laid out as
        :meth:`Term.values`) may move within the relative ``tolerance``, each shape as
        ``c0``: +- tolerance x |c0|.  An effect whose coefficients
        are the inverse of the machine file's keys (a compliance, the file's stiffness)
        narrows it so that the keys move by at most that share."""
        dev = tolerance * np.abs(c0)
        return c0 - dev, c0 + dev

    def mask(self, ctx: Context) -> np.ndarray:
        """Samples the fits of this effect use."""
        return ctx.moving if self.domain == FORCE else ctx.m.use

    @abstractmethod
    def params(self, ctx: Context, shape: dict, coef: np.ndarray) -> dict:
        """The physical parameters (SI, names with units) for the report."""

    @abstractmethod
    def overrides(self, ctx: Context, shape: dict, coef: np.ndarray, model) -> dict:
        """What to write into the machine file: ``{"section": {"key": value}}``; ``model``
        gives the other terms where a key depends on them."""


#: a signal is on a grid of step q when more than this share of its changes are whole
#: multiples of q ...
ON_GRID_SHARE = 0.9
#: ... each to within this fraction of q
ON_GRID_TOLERANCE = 0.01
#: multiples of the smallest change the step's first refinement uses: the smallest change
#: is off by the round-off of two printed values, and a change of n steps by n times that
FIRST_FIT_MULTIPLES = 100
#: most steps the smallest change of a quantised signal may span
MAX_STEPS_IN_SMALLEST = 4


def _changes(x: np.ndarray) -> np.ndarray:
    steps = np.abs(np.diff(x))
    return steps[steps > 0]


def on_grid(x: np.ndarray, q: float) -> bool:
    """Whether nearly every change of ``x`` (n,) is a whole multiple of ``q`` (same unit)."""
    steps = _changes(x)
    if steps.size == 0 or not q > 0.0:
        return False
    ratio = steps / q
    return bool(np.mean(np.abs(ratio - np.round(ratio)) < ON_GRID_TOLERANCE) > ON_GRID_SHARE)


def quantum(x: np.ndarray) -> float:
    """The step of a quantized signal (shape (n,)), fitted to its changes, else 0 (not on
    a grid).

    The smallest change is the first guess; a file that prints the values rounded (a
    76.29 nm encoder step in mm to 8 decimals) makes it off by up to twice the print's
    resolution, which a change of a thousand steps multiplies by a thousand.  The step
    is therefore refitted by least squares, q = sum(n s) / sum(n^2) over the changes s of
    n = round(s / q) steps, first on the changes of up to :data:`FIRST_FIT_MULTIPLES`
    steps, then on all; the signal is on the grid when :func:`on_grid` says so (else the
    smallest change is tried as two, three, ... :data:`MAX_STEPS_IN_SMALLEST` steps)."""
    steps = _changes(x)
    if steps.size == 0:
        return 0.0
    smallest = float(steps.min())
    # a signal that never changed by one step has its smallest change a few steps wide
    for divisor in range(1, MAX_STEPS_IN_SMALLEST + 1):
        q = smallest / divisor
        for limit in (FIRST_FIT_MULTIPLES, math.inf):
            n = np.round(steps / q)
            use = n <= limit
            q = float(steps[use] @ n[use] / (n[use] @ n[use]))
        if on_grid(x, q):
            return q
    return 0.0


def explained(residual: np.ndarray, fitted: np.ndarray, mask: np.ndarray) -> float:
    """Fraction of the residual's energy on ``mask`` that ``fitted`` removes."""
    r = residual[mask]
    e0 = float(r @ r)
    if e0 <= 0.0:
        return 0.0
    d = r - fitted[mask]
    return max(0.0, 1.0 - float(d @ d) / e0)


def lstsq(cols: np.ndarray, y: np.ndarray, mask: np.ndarray,
          lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """Least squares of ``cols`` (n, k) on ``y`` (n,) over ``mask``, within bounds."""
    from scipy.optimize import lsq_linear
    a = cols[mask]
    b = y[mask]
    # scale columns so that bounds and conditioning do not depend on their units
    scale = np.sqrt(np.mean(a * a, axis=0))
    scale[scale == 0.0] = 1.0
    k = a.shape[1]
    lo = np.full(k, -np.inf) if lo is None else lo
    hi = np.full(k, np.inf) if hi is None else hi
    res = lsq_linear(a / scale, b, bounds=(lo * scale, hi * scale), method="bvls")
    return res.x / scale


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two signals (0 when either is constant)."""
    sa, sb = float(np.std(a)), float(np.std(b))
    if sa == 0.0 or sb == 0.0:
        return 0.0
    return float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))


def uncertainty(a_w: np.ndarray, misfit: float) -> np.ndarray:
    """Standard uncertainties of a fit's parameters from its Jacobian (or a linear fit's
    weighted columns) ``a_w``, rows in noise units: sqrt of the diagonal of (AᵀA)⁻¹,
    times the data's rms residual over the noise floor (``misfit``) where it exceeds 1:
    a model that does not reach the floor knows its parameters less well.  NaN where the
    columns are degenerate."""
    try:
        cov = np.linalg.inv(a_w.T @ a_w)
    except np.linalg.LinAlgError:
        return np.full(a_w.shape[1], math.nan)
    return np.sqrt(np.clip(np.diag(cov), 0.0, None)) * max(1.0, misfit)
