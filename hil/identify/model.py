"""The model being identified: the config's terms plus the added ones, their joint fits,
and the closed-loop replay of the config they make.
"""

import dataclasses
from pathlib import Path

import numpy as np

from hil.identify.effects import FORCE, LIBRARY, POSITION, Context, Term
from hil.identify.effects.base import lstsq
from hil.identify.record import Record
from hil.identify.replay import ERROR_START, Replay, replay
from plant.config import ConfigError, MachineConfig, load_machine


def merge(into: dict, more: dict) -> dict:
    """Merge ``{"section": {"key": value}}`` tables (``more`` wins)."""
    for sec, values in more.items():
        into.setdefault(sec, {}).update(values)
    return into


class Model:
    """Terms of the inverse model by domain, and the machine file they amount to.

    Args:
        ctx: the record, its motion and the config as read.
        path: the machine file (the overrides are applied on top of it).
        progress: optional callable(fraction) for the replays.
    """

    def __init__(self, ctx: Context, path: str | Path, progress=None):
        self.ctx = ctx
        self.path = Path(path)
        self.progress = progress
        self.terms: list[Term] = [t for t in (e.declared(ctx) for e in LIBRARY) if t is not None]
        self._replay: Replay | None = None
        self.pwm_period = 1.0 / ctx.cfg.motor.pwm_frequency_hz

    def term(self, name: str) -> Term | None:
        return next((t for t in self.terms if t.effect.name == name), None)

    def add(self, term: Term) -> None:
        """Add a term (replacing the same effect's) and forget the cached replay."""
        self.terms = [t for t in self.terms if t.effect.name != term.effect.name] + [term]
        self._replay = None

    def snapshot(self) -> list[Term]:
        """A copy of the terms (coefficients copied) for :meth:`restore`."""
        return [dataclasses.replace(t, coef=t.coef.copy()) for t in self.terms]

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

    def residual(self, domain: str) -> np.ndarray:
        """The domain's measured signal less the model's prediction, shape (n,): force (N)
        or table-minus-motor position (m, its mean removed: the encoders' zeros differ)."""
        m = self.ctx.m
        pred = sum((t.contribution(self.ctx) for t in self._domain(domain)),
                   np.zeros(self.ctx.rec.n))
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
        """Fit every term of the domain jointly (base parameters freed), shapes fixed."""
        terms = [t for t in self._domain(domain) if t.effect.n_coef(t.shape) > 0]
        if not terms:
            return
        cols = [t.effect.columns(self.ctx, t.shape) for t in terms]
        lo = [t.effect.bounds(t.shape)[0] for t in terms]
        hi = [t.effect.bounds(t.shape)[1] for t in terms]
        y = self.ctx.m.force if domain == FORCE else self.ctx.m.dx
        if domain == POSITION:
            # the encoders' zero offset is fitted too, and thrown away
            cols.append(np.ones((self.ctx.rec.n, 1)))
            lo.append(np.full(1, -np.inf))
            hi.append(np.full(1, np.inf))
        coef = lstsq(np.hstack(cols), y, self._mask(domain), np.concatenate(lo),
                     np.concatenate(hi))
        i = 0
        for t in terms:
            k = t.effect.n_coef(t.shape)
            t.coef = coef[i:i + k]
            i += k
        self._replay = None

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
        machine file (a fit outside the schema's ranges)."""
        cached = extra is None and rec is None
        if cached and self._replay is not None:
            return self._replay
        try:
            cfg = self.config(extra)
        except ConfigError:
            return None
        rep = replay(cfg, rec if rec is not None else self.ctx.rec, progress=self.progress)
        if cached:
            self._replay = rep
        return rep

    def effort_error(self, rep: Replay, start: int = ERROR_START) -> float:
        """rms of the effort's replay error from sample ``start`` on."""
        d = self.ctx.rec.effort[start:] - rep.effort[start:]
        return float(np.sqrt(np.mean(d * d)))
