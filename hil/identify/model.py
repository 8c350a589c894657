"""The model being identified: the config's terms plus the added ones, their joint fits,
and the closed-loop replay of the config they make.
"""

import dataclasses
import json
import math
from collections import OrderedDict
from pathlib import Path

import numpy as np

from hil.identify.effects import FORCE, LIBRARY, POSITION, Context, Term
from hil.identify.effects.base import lstsq, uncertainty
from hil.identify.record import Record
from hil.identify.replay import ERROR_START, Replay, replay
from plant.config import ConfigError, MachineConfig, load_machine


def merge(into: dict, more: dict) -> dict:
    """Merge ``{"section": {"key": value}}`` tables (``more`` wins)."""
    for sec, values in more.items():
        into.setdefault(sec, {}).update(values)
    return into


#: a declared parameter's default tolerance, relative: the prior's deviation, and how far
#: a refit may move it; what the data ask for beyond it is reported as a finding
#: (``hil identify --tolerance EFFECT=FRACTION``)
DEFAULT_TOLERANCE = 0.1
#: replays of the identification record a model keeps, by the machine-file changes that
#: made them (the most recent): a replay is a deterministic function of the record and
#: the machine file, and the closed-loop refinement asks for the same point again and
#: again (each pass, the polish and the Jacobian start where the last one ended)
REMEMBERED_REPLAYS = 8


def _key(changes: dict) -> str:
    """Machine-file changes as a string, equal for equal changes: json writes a float as
    repr does, with every digit (numpy scalars and arrays as their Python values)."""
    return json.dumps(changes, sort_keys=True,
                      default=lambda v: v.tolist() if hasattr(v, "tolist") else repr(v))


class Model:
    """Terms of the inverse model by domain, and the machine file they amount to.

    The terms the machine file declares keep their declared values -- coefficients and
    scalar shapes alike (:meth:`~hil.identify.effects.base.Term.values`: the Stribeck
    velocity, the presliding spring's k1, x1 and exponent) -- as a prior: a joint refit
    (:meth:`refit`) moves the coefficients only as far as the data outweigh a Gaussian
    prior of deviation ``tolerance`` x |declared value| (:data:`DEFAULT_TOLERANCE`), the
    closed-loop refinement every value the same way, and nothing moves beyond
    ``tolerance`` x |declared value| (:meth:`box`): what the data ask for beyond it stays
    in ``Term.wanted``, a finding the report lists, not a change taken (issue 30, item 3:
    a declared mass or viscous friction moved to absorb what the model lacked; a declared
    Stribeck velocity or presliding shape moved by up to a factor 3 unchecked).  Each
    refit leaves every coefficient's standard uncertainty in ``Term.sigma``.

    Args:
        ctx: the record, its motion and the config as read.
        path: the machine file (the overrides are applied on top of it).
        progress: optional callable(fraction) for the replays.
        tolerance: effect name -> relative tolerance of its declared values
            (coefficients and scalar shapes).
    """

    def __init__(self, ctx: Context, path: str | Path, progress=None,
                 tolerance: dict | None = None):
        self.ctx = ctx
        self.path = Path(path)
        self.progress = progress
        self.terms: list[Term] = [t for t in (e.declared(ctx) for e in LIBRARY) if t is not None]
        self.declared = {t.effect.name: t.values() for t in self.terms}
        for e in LIBRARY:
            c0 = None if e.name in self.declared else e.declared_coefficients(ctx)
            if c0 is not None:
                self.declared[e.name] = c0
        self.tolerance = dict(tolerance or {})
        self._replay: Replay | None = None
        self._replays: OrderedDict[str, Replay] = OrderedDict()
        #: replays of the record run so far (not those given back from memory)
        self.replays_run = 0
        self.pwm_period = 1.0 / ctx.cfg.motor.pwm_frequency_hz

    def tolerance_of(self, name: str) -> float:
        """Relative tolerance of effect ``name``'s declared values."""
        return self.tolerance.get(name, DEFAULT_TOLERANCE)

    def term(self, name: str) -> Term | None:
        return next((t for t in self.terms if t.effect.name == name), None)

    def declared_of(self, term: Term) -> np.ndarray | None:
        """The declared values of ``term``'s effect laid out as ``term.values()`` (as its
        shape has them, :meth:`~hil.identify.effects.base.Effect.declared_for`: NaN where
        one is not declared), or None where the file does not declare the effect (or
        declared another number of them: cogging orders of its own)."""
        c0 = self.declared.get(term.effect.name)
        if c0 is None:
            return None
        c0 = term.effect.declared_for(c0, term.shape)
        return c0 if c0.size == term.values().size else None

    def box(self, term: Term) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of ``term``'s values (coefficients, then scalar shapes: ``term.values()``),
        each that shape: its effect's, narrowed for a declared effect to the declared
        values +- tolerance x |declared| (or the effect's own
        :meth:`~hil.identify.effects.base.Effect.declared_box`: a declared stiffness moves
        by the tolerance's share); a declared 0 has no relative tolerance and keeps its
        effect's bounds, as does a value the file does not declare (NaN,
        :meth:`~hil.identify.effects.base.Effect.declared_coefficients`, or a shape the
        declaration lacks)."""
        lo, hi = term.effect.value_bounds(term.shape)
        c0 = self.declared_of(term)
        if c0 is None:
            return lo, hi
        free = (c0 == 0.0) | np.isnan(c0)
        d_lo, d_hi = term.effect.declared_box(np.where(free, 1.0, c0),
                                              self.tolerance_of(term.effect.name))
        return (np.where(free, lo, np.maximum(lo, d_lo)),
                np.where(free, hi, np.minimum(hi, d_hi)))

    def add(self, term: Term) -> None:
        """Add a term (replacing the same effect's) and forget the cached replay.  A
        declared effect's values are held within their tolerance (:meth:`hold`); what the
        term asked for beyond it is kept as its ``wanted`` -- or what the proposal itself
        kept there, where it held its declared values and fitted the rest beside them (the
        screw model's compliance).  The terms its effect replaces (``Effect.replaces``)
        leave the model."""
        term = dataclasses.replace(term, coef=term.coef.copy(), shape=dict(term.shape))
        asked, by = term.wanted, term.wanted_by
        if not self.hold(term, "its proposal") and asked is not None:
            term.wanted, term.wanted_by = asked, by
        gone = (term.effect.name, *term.effect.replaces)
        self.terms = [t for t in self.terms if t.effect.name not in gone] + [term]
        self._replay = None

    def hold(self, term: Term, by: str) -> bool:
        """Hold ``term``'s values within :meth:`box`; where they lay beyond it, what they
        were becomes its ``wanted`` (asked for by ``by``), else ``wanted`` is cleared.
        True where something was held."""
        values = term.values()
        held = np.clip(values, *self.box(term))
        beyond = not np.array_equal(held, values)
        term.wanted = values if beyond else None
        term.wanted_by = by if beyond else ""
        if beyond:
            term.set_values(held)
            self._replay = None
        return beyond

    def snapshot(self) -> list[Term]:
        """A copy of the terms (coefficients and shapes copied) for :meth:`restore`."""
        return [dataclasses.replace(t, coef=t.coef.copy(), shape=dict(t.shape))
                for t in self.terms]

    def restore(self, terms: list[Term]) -> None:
        self.terms = terms
        self._replay = None

    def coefficients_changed(self) -> None:
        """Forget the cached replay after a term's coefficients were set from outside."""
        self._replay = None

    def _domain(self, domain: str) -> list[Term]:
        return [t for t in self.terms if t.effect.domain == domain]

    def _mask(self, domain: str) -> np.ndarray:
        if domain == FORCE:
            pre = self.term("presliding_hysteresis")
            return self.ctx.moving if pre is None else pre.effect.mask(self.ctx)
        # position: the samples every term can use (backlash leaves its flank changes out)
        mask = self.ctx.m.use.copy()
        for t in self._domain(domain):
            mask &= t.effect.mask(self.ctx)
        return mask

    def prediction(self, domain: str) -> np.ndarray:
        """The domain's terms' prediction, shape (n,): force (N) or table-minus-motor
        position (m, without the encoders' zero offset)."""
        return sum((t.contribution(self.ctx) for t in self._domain(domain)),
                   np.zeros(self.ctx.rec.n))

    def residual(self, domain: str) -> np.ndarray:
        """The domain's measured signal less the model's prediction, shape (n,): force (N)
        or table-minus-motor position (m, its mean removed: the encoders' zeros differ)."""
        m = self.ctx.m
        pred = self.prediction(domain)
        if domain == FORCE:
            return m.force - pred
        if domain == POSITION and m.dx is not None:
            r = m.dx - pred
            return r - float(np.mean(r[m.use]))
        raise ValueError(f"no residual in domain {domain!r}")

    def residual_rms(self, domain: str, mask: np.ndarray | None = None) -> float:
        """rms of the domain's residual on ``mask`` (default: the samples its fits use)."""
        r = self.residual(domain)[self._mask(domain) if mask is None else mask]
        return float(np.sqrt(np.mean(r * r))) if r.size else 0.0

    def refit(self, domain: str) -> None:
        """Fit every term of the domain jointly, shapes fixed: the samples in noise units
        (each over the domain's noise floor, weighted by the share of independent samples,
        2 f_c dt, of the low-passed signals), the declared coefficients with their priors;
        sets each term's ``coef`` (the declared ones within :meth:`box`), ``wanted`` (the
        fit without the box with the term's shapes, where that goes beyond it) and
        ``sigma`` (standard uncertainty from the weighted Jacobian, inflated by the
        residual's ratio to the floor where it exceeds 1)."""
        terms = [t for t in self._domain(domain) if t.effect.n_coef(t.shape) > 0]
        if not terms:
            return
        cols = [t.effect.columns(self.ctx, t.shape) for t in terms]
        lo = [t.effect.bounds(t.shape)[0] for t in terms]
        hi = [t.effect.bounds(t.shape)[1] for t in terms]
        k_of = [t.effect.n_coef(t.shape) for t in terms]
        box = []
        for t, k in zip(terms, k_of):
            b_lo, b_hi = self.box(t)
            box.append((b_lo[:k], b_hi[:k]))
        y = self.ctx.m.force if domain == FORCE else self.ctx.m.dx
        for t in terms:
            fixed = t.effect.fixed(self.ctx, t.shape)
            if fixed is not None:
                y = y - fixed
        if domain == POSITION:
            # the encoders' zero offset is fitted too, and thrown away
            cols.append(np.ones((self.ctx.rec.n, 1)))
            lo.append(np.full(1, -np.inf))
            hi.append(np.full(1, np.inf))
        mask = self._mask(domain)
        a, b = np.hstack(cols)[mask], y[mask]
        noise = self.ctx.m.noise_force if domain == FORCE else self.ctx.m.noise_dx
        w = math.sqrt(min(1.0, 2.0 * self.ctx.m.cutoff_hz * self.ctx.rec.dt)) / noise \
            if noise > 0.0 else 1.0
        prior_a, prior_b = self._priors(terms, a.shape[1]) if noise > 0.0 else ([], [])
        a_w = np.vstack([w * a] + prior_a)
        b_w = np.concatenate([w * b] + prior_b)
        rows = np.ones(b_w.size, dtype=bool)
        free = lstsq(a_w, b_w, rows, np.concatenate(lo), np.concatenate(hi))
        lo_box = np.concatenate([b_lo for b_lo, _ in box] + lo[len(terms):])
        hi_box = np.concatenate([b_hi for _, b_hi in box] + hi[len(terms):])
        coef = (free if np.all((free >= lo_box) & (free <= hi_box))
                else lstsq(a_w, b_w, rows, lo_box, hi_box))
        r = b - a @ coef
        misfit = float(np.sqrt(np.mean(r * r))) / noise if noise > 0.0 and r.size else 1.0
        sigma = uncertainty(a_w, misfit)
        i = 0
        for t, k in zip(terms, k_of):
            # what the fit without the box asked for, held like any proposal: the shapes,
            # which it does not fit, as they are
            t.set_values(np.concatenate([free[i:i + k], t.values()[k:]]))
            self.hold(t, "the joint refit of its domain")
            t.coef = coef[i:i + k]
            t.sigma = sigma[i:i + k]
            i += k
        self._replay = None

    def _priors(self, terms: list[Term], width: int) -> tuple[list, list]:
        """Rows (c - c_declared) / (tolerance |c_declared|) for the declared coefficients
        of ``terms`` (in the order of the joint fit's columns, ``width`` of them)."""
        rows, rhs = [], []
        i = 0
        for t in terms:
            k = t.effect.n_coef(t.shape)
            c0 = self.declared_of(t)
            if c0 is not None:
                for j in range(k):
                    if c0[j] != 0.0 and not math.isnan(c0[j]):
                        s = self.tolerance_of(t.effect.name) * abs(float(c0[j]))
                        row = np.zeros((1, width))
                        row[0, i + j] = 1.0 / s
                        rows.append(row)
                        rhs.append(np.array([float(c0[j]) / s]))
            i += k
        return rows, rhs

    def overrides(self, extra: dict | None = None) -> dict:
        """The machine-file changes the terms amount to: ``{"section": {"key": value}}``."""
        out: dict = {}
        for t in self.terms:
            merge(out, t.effect.overrides(self.ctx, t.shape, t.coef, self))
        return merge(out, extra or {})

    def config(self, extra: dict | None = None) -> MachineConfig:
        return load_machine(self.path, self.overrides(extra))

    def replay(self, extra: dict | None = None, rec: Record | None = None) -> Replay | None:
        """Closed-loop replay of ``rec`` (default: the identification record) through the
        config with the terms (and ``extra``); None when the overrides make no valid
        machine file (a fit outside the schema's ranges, or a spring too stiff for the
        plant's sub-steps: a refinement that drives a compliance toward 0).  The machine
        file as declared, refused, is the caller's to hear of: its error is raised."""
        cached = extra is None and rec is None
        if cached and self._replay is not None:
            return self._replay
        try:
            changes = self.overrides(extra)
        except ConfigError:
            return None
        key = _key(changes) if rec is None else None
        rep = self._replays.get(key)
        if rep is None:
            try:
                cfg = load_machine(self.path, changes)
            except ConfigError:
                return None
            try:
                rep = replay(cfg, rec if rec is not None else self.ctx.rec,
                             progress=self.progress)
            except ConfigError:
                if extra is None and not any(t.added for t in self.terms):
                    raise
                return None
            self.replays_run += 1
            if key is not None:
                self._replays[key] = rep
                if len(self._replays) > REMEMBERED_REPLAYS:
                    self._replays.popitem(last=False)
        else:
            self._replays.move_to_end(key)
        if cached:
            self._replay = rep
        return rep

    def effort_error(self, rep: Replay, start: int = ERROR_START) -> float:
        """rms of the effort's replay error from sample ``start`` on."""
        d = self.ctx.rec.effort[start:] - rep.effort[start:]
        return float(np.sqrt(np.mean(d * d)))
