"""The closed-loop refinement: scalar parameters fitted on the replay itself.

The inverse model weighs every sample's force balance equally; the closed loop weighs
them as the controller does, and its error is what the report measures.  So at the end of
the search the single-coefficient terms (mass, viscous and Coulomb friction, the
constant force, the Stribeck excess; backlash, compliance), each coefficient of a term
whose coefficients are one machine-file key each (the screw model's coupling, nut and
torsion compliance, in log space: they span decades), the cogging's sine and cosine
coefficients (a fast periodic force's amplitude matters far more in the closed loop than
in the inverse model) and the scalar shapes that the
linear fits hold fixed (``Effect.shape_keys_of``: the Stribeck velocity, the presliding
spring's k1, x1 and exponent, the damping ratio the replay chose for a rigid file's
coupling in the screw model) are adjusted together so that the replay matches the record
(``scipy.optimize.least_squares``), on the acceptance's measure: every replay channel's
error over its noise floor, with the record's n_eff independent samples -- the residual
vector is sqrt(n_eff / n) (y - y_hat) / (floor s_k) per channel and sample.  A channel
that stays far above its floor would outweigh the others, so each pass (a coarse and a
fine finite-difference step, then the polish) first sets s_k = max(1, its rms error /
floor): the likelihood with each channel's deviation its floor or its misfit, whichever
is larger.  The result is kept only where J = sum over channels of (rms error / floor)²,
the acceptance's measure, falls.

Stick-slip friction makes the replay's per-sample errors jump (a breakaway one sample
earlier or later), so the finite-difference Jacobian can stop the least-squares passes
well short of the minimum of the sum of squares, which is smooth on the scale of a
percent: on screw_stribeck of ``hil bench identify`` they ended at 1.6x the table scale's
floor with the mass 2 % high, where the truth's own parameters give 1.3x.  A
derivative-free pass (Powell's conjugate directions, at most :data:`POLISH_REPLAYS`
replays per parameter) polishes their point on the same sum of squares, kept where J
falls by it.

The declared values -- coefficients and scalar shapes alike (``Term.values``) -- keep their
prior (:class:`hil.identify.model.Model`): one more residual (c - c_declared) /
(tolerance |c_declared|) each, and stay within their tolerance
(:meth:`hil.identify.model.Model.box`): the refinement runs first without the box (a
shape within :data:`SHAPE_RANGE` of its start), and where that takes a declared value
beyond its tolerance, what it asked for is kept as the term's ``wanted`` (a finding, not
taken) and the refinement runs again from there with the values held within it.
Before issue 30 a declared shape had neither prior nor box: a Stribeck velocity or a
presliding spring moved by up to the factor 3 unreported.  (Bounds change the least squares'
steps, so a box that would not bind is left out: on EMPS, boxed from the start, the
refinement stopped elsewhere and the validation's force error moved by 0.02 points.)

The Jacobian at the solution, its rows in those deviations, gives each parameter's
standard uncertainty: sqrt of the diagonal of (JᵀJ)⁻¹.
"""

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize

from hil.identify.effects import FORCE, POSITION
from hil.identify.effects.base import uncertainty
from hil.identify.floor import channel_residuals
from hil.identify.model import Model
from hil.identify.record import Record
from hil.identify.replay import ERROR_START

#: how far the refinement may take a scalar shape (``Effect.shape_keys_of``, fitted in
#: log space): within this factor of where it starts, the linear fit's value (a declared
#: shape no further than its tolerance besides, like a declared coefficient)
SHAPE_RANGE = 3.0
#: relative finite-difference steps of the two passes: stick-slip friction makes the
#: replay's error rough in the friction levels at small scales, so a coarse pass first
DIFF_STEPS = (3e-2, 3e-3)
#: penalty residual of a replay that failed, per sample and channel
FAILED = 1e3
#: the polish's budget, replays per refined parameter, and its tolerance on the
#: parameters (relative to their scale: 0.1 % of a coefficient, 1e-4 of a log shape)
POLISH_REPLAYS = 20
POLISH_XTOL = 1e-3


@dataclass(frozen=True)
class Parameter:
    """One refined parameter: entry ``index`` of a term's values (``Term.values``: its
    coefficients, then its scalar shapes), the shape ``key`` where it is one (None: a
    coefficient, ``several`` where the term has more than one refined); its log where
    ``log``."""
    effect: str
    key: str | None
    log: bool
    index: int = 0
    several: bool = False

    @property
    def label(self) -> str:
        if self.key is not None:
            return f"{self.effect}.{self.key}"
        return f"{self.effect}[{self.index}]" if self.several else self.effect


def parameters(model: Model) -> list[Parameter]:
    """What the refinement adjusts in ``model``."""
    out = []
    for t in model.terms:
        n = t.effect.n_coef(t.shape)
        if t.effect.domain in (FORCE, POSITION) and not t.effect.fixed_scale:
            if n == 1:
                out.append(Parameter(t.effect.name, None, False))
            elif n > 1 and (t.effect.keys_per_coefficient or t.effect.refined_per_coefficient):
                lo = t.effect.bounds(t.shape)[0]
                # a positive coefficient in log space: a compliance spans decades
                out += [Parameter(t.effect.name, None, bool(lo[j] >= 0.0 and t.coef[j] > 0.0),
                                  j, True) for j in range(n)]
        # the term's scalar shapes follow its coefficients in its values (the screw model's
        # damping ratio only where the replay chose one, and not 0: its log is refined).
        # A screw-model torsion held as declared is no coefficient of its term (n_coef 2,
        # Effect.declared_for): the refinement takes coupling and nut alone, the torsion
        # stays in the term's fixed part, and the shapes' indices follow the two
        out += [Parameter(t.effect.name, key, True, n + j)
                for j, key in enumerate(t.effect.shape_keys_of(t.shape))]
    return out


def refine(model: Model, rec: Record, floor: dict, n_eff: float, max_nfev: int,
           say=None) -> dict:
    """Adjust :func:`parameters` on the closed-loop replay (module docstring); the model's
    terms are left at the best point found (or as they were when nothing is better), the
    declared values (coefficients and scalar shapes) within their tolerance, their terms'
    ``wanted`` set to what the replay asked for beyond it (cleared where it asked for no
    more).

    Returns the report's ``refinement``: ``before``/``after`` (label -> value),
    ``sigma`` (label -> standard uncertainty), ``wanted`` (label -> what the replay asks
    for beyond the tolerance), ``cost_before``/``cost_after`` (J) and ``replays``."""
    out = _refine(model, rec, floor, n_eff, max_nfev, say, boxed=False,
                  rerun=lambda: _beyond_tolerance(model))
    if not out:
        return out
    declared = _declared(model)
    wanted = {}
    for name in dict.fromkeys(p.effect for p in declared):
        t = model.term(name)
        if model.hold(t, "the closed-loop refinement"):
            taken = t.values()
            wanted.update({p.label: float(t.wanted[p.index]) for p in declared
                           if p.effect == name and taken[p.index] != t.wanted[p.index]})
    if not wanted:
        return {**out, "wanted": wanted}
    model.coefficients_changed()
    if say is not None:
        say(f"{', '.join(wanted)} beyond tolerance: a finding; refined again within it")
    held = _refine(model, rec, floor, n_eff, max_nfev, say, boxed=True)
    return {**held, "before": out["before"], "cost_before": out["cost_before"],
            "wanted": wanted, "replays": out["replays"] + held["replays"]}


def _declared(model: Model) -> list[Parameter]:
    """The refined parameters that are declared values."""
    return [p for p in parameters(model) if model.declared_of(model.term(p.effect)) is not None]


def _beyond_tolerance(model: Model) -> bool:
    """Whether a refined declared value lies beyond its tolerance (:meth:`Model.box`):
    :func:`refine` then holds it and refines again within the box."""
    for p in _declared(model):
        t = model.term(p.effect)
        lo, hi = model.box(t)
        if not lo[p.index] <= t.values()[p.index] <= hi[p.index]:
            return True
    return False


def _refine(model: Model, rec: Record, floor: dict, n_eff: float, max_nfev: int, say,
            boxed: bool, rerun=None) -> dict:
    """One refinement from the model's point (:func:`refine`), the declared values
    held within their tolerance where ``boxed``; the report's ``refinement`` but
    ``wanted``.  Where ``rerun()`` is true at the point found, another refinement
    follows whose uncertainties replace these: they are not computed (no ``sigma``, and
    the terms' ``sigma`` as they were)."""
    params = parameters(model)
    if not params:
        return {}
    terms = {t.effect.name: t for t in model.terms}

    def get(p: Parameter) -> float:
        v = float(terms[p.effect].values()[p.index])
        return math.log(v) if p.log else v

    def put(p: Parameter, z: float) -> None:
        t = terms[p.effect]
        values = t.values()
        values[p.index] = math.exp(z) if p.log else z
        t.set_values(values)

    z0 = np.array([get(p) for p in params])
    lo, hi = np.empty(z0.size), np.empty(z0.size)
    for i, p in enumerate(params):
        t = terms[p.effect]
        box = model.box(t) if boxed else t.effect.value_bounds(t.shape)
        lo[i], hi[i] = box[0][p.index], box[1][p.index]
        if p.log:
            # the value is positive and within its bounds: hi > 0
            lo[i] = math.log(lo[i]) if lo[i] > 0.0 else -np.inf
            hi[i] = math.log(hi[i])
        if p.key is not None:
            lo[i] = max(lo[i], z0[i] - math.log(SHAPE_RANGE))
            hi[i] = min(hi[i], z0[i] + math.log(SHAPE_RANGE))
    z0 = np.clip(z0, lo + 1e-12 * np.abs(z0), hi)
    prior = []  # (index, declared value, deviation, whether z is its log)
    for i, p in enumerate(params):
        c0 = model.declared_of(terms[p.effect])
        # a value the file does not declare (NaN: a rigid file's coupling and nut beside
        # the torsion its [identify.screw] declares, a damping ratio the replay chose) has
        # no prior
        if c0 is not None and c0[p.index] != 0.0 and not math.isnan(c0[p.index]):
            c0j = float(c0[p.index])
            prior.append((i, c0j, model.tolerance_of(p.effect) * abs(c0j), p.log))
    n = rec.n - ERROR_START
    weight = math.sqrt(max(n_eff, 1.0) / n)
    replays_before = model.replays_run
    costs = []
    last = np.ones(len(floor))  # the last replay's rms error / floor per channel
    scale_k = np.ones(len(floor))  # each channel's deviation over its floor (>= 1)

    def residual(z):
        for p, value in zip(params, z):
            put(p, float(value))
        model.coefficients_changed()
        run = model.replays_run
        rep = model.replay()
        count = model.replays_run - replays_before
        if rep is None or rep.status != 0:
            chans = [np.full(n, FAILED)] * len(floor)
        else:
            chans = [np.where(np.isfinite(c), c, FAILED)
                     for c in (r[ERROR_START:] for r in channel_residuals(rec, rep, floor))]
        ratios = np.array([math.sqrt(float(np.mean(c * c))) for c in chans])
        costs.append(float(np.sum(ratios ** 2)))
        last[:] = ratios
        if say is not None and model.replays_run > run and count % 10 == 0:
            say(f"  refinement: {count} replays, J {costs[-1]:.4g}")
        pri = [((math.exp(z[i]) if log else z[i]) - c0) / s for i, c0, s, log in prior]
        data = np.concatenate([c / s for c, s in zip(chans, scale_k)])
        return np.concatenate([weight * data, np.array(pri)])

    before = {p.label: (math.exp(v) if p.log else float(v)) for p, v in zip(params, z0)}
    if say is not None:
        say(f"refining {', '.join(before)} on the closed-loop replay")
    residual(z0)
    j0 = costs[-1]
    scale = np.where([p.log for p in params], 0.1,
                     np.maximum(np.abs(z0), 1e-3 * max(float(np.max(np.abs(z0))), 1e-9)))
    best = z0
    for step in DIFF_STEPS:
        residual(best)
        scale_k[:] = np.maximum(last, 1.0)
        start = residual(best)
        best_cost = 0.5 * float(start @ start)
        sol = least_squares(residual, best, bounds=(lo, hi), x_scale=scale, diff_step=step,
                            max_nfev=max_nfev)
        if sol.cost < best_cost:
            best = sol.x
    residual(best)
    j_passes = costs[-1]
    scale_k[:] = np.maximum(last, 1.0)
    polished = _polish(residual, best, (lo, hi), scale, POLISH_REPLAYS * len(params))
    residual(polished)
    if costs[-1] < j_passes:
        best = polished
    residual(best)
    j1 = costs[-1]
    found = best
    if j1 > j0:
        # the passes' channel weights balance the channels; the acceptance's J decides
        best = z0
        residual(best)
        j1 = costs[-1]
    after = {p.label: (math.exp(v) if p.log else float(v)) for p, v in zip(params, best)}
    out = {"before": before, "after": after, "cost_before": j0, "cost_after": j1}
    if rerun is not None and rerun():
        if say is not None:
            say(f"refined in {model.replays_run - replays_before} replays: "
                f"J {j0:.4g} -> {j1:.4g}")
        return {**out, "replays": model.replays_run - replays_before}
    # the uncertainties at the point the passes and the polish found
    jac = _jacobian(residual, found, (lo, hi), DIFF_STEPS[-1])
    residual(best)
    # the rows are in units of each channel's deviation already (its floor, or its misfit)
    sigma = uncertainty(jac, 1.0)
    sig = {p.label: (after[p.label] * s if p.log else s) for p, s in zip(params, sigma)}
    for p in params:
        t = terms[p.effect]
        size = t.values().size
        if t.sigma is None or t.sigma.size != size:
            known = t.sigma if t.sigma is not None and t.sigma.size == t.coef.size else None
            t.sigma = np.full(size, math.nan)
            if known is not None:
                t.sigma[:known.size] = known
        t.sigma = t.sigma.copy()
        t.sigma[p.index] = sig[p.label]
    if say is not None:
        say(f"refined in {model.replays_run - replays_before} replays: J {j0:.4g} -> {j1:.4g}")
    return {**out, "sigma": sig, "replays": model.replays_run - replays_before}


def _polish(residual, z: np.ndarray, bounds: tuple, scale: np.ndarray,
            max_replays: int) -> np.ndarray:
    """Powell's method from ``z`` on 0.5 |residual|², in the coordinates (z' - z) / scale
    within ``bounds`` (lo, hi); the best point seen (``z`` when nothing is better)."""
    seen = {"cost": math.inf, "z": z}

    def cost(y):
        zz = np.clip(z + y * scale, *bounds)
        r = residual(zz)
        c = 0.5 * float(r @ r)
        if c < seen["cost"]:
            seen["cost"], seen["z"] = c, zz
        return c

    y_bounds = list(zip((bounds[0] - z) / scale, (bounds[1] - z) / scale))
    minimize(cost, np.zeros(z.size), method="Powell", bounds=y_bounds,
             options={"maxfev": max_replays, "xtol": POLISH_XTOL, "ftol": 1e-6})
    return seen["z"]


def _jacobian(residual, z: np.ndarray, bounds: tuple, step: float) -> np.ndarray:
    """Forward-difference Jacobian of ``residual`` at ``z``, shape (rows, z.size), with
    least_squares' relative step (step max(1, |z_i|)), taken backward at an upper bound."""
    r0 = residual(z)
    cols = []
    for i in range(z.size):
        h = step * max(1.0, abs(float(z[i])))
        if z[i] + h > bounds[1][i]:
            h = -h
        zz = z.copy()
        zz[i] += h
        cols.append((residual(zz) - r0) / h)
    return np.stack(cols, axis=1)
