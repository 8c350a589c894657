"""Every candidate of a search round, fitted on part of the record and ranked by the
closed-loop replay's gain on the rest.

The record's samples are split into blocks of :data:`BLOCK_S` seconds, alternately *fit*
and *held out*.  A candidate effect is proposed -- fitted to its domain's residual, the
rest of the model as it is -- on the fit blocks alone (the inverse model's masks are
narrowed to them), and the machine file it makes is replayed in closed loop over the
whole record; its score is the replay's normalised cost J = sum over channels of
(rms error / noise floor)² on the held-out blocks, and its rank the information criterion
of that gain, n ln(J1/J0) + k ln n with n the held-out blocks' independent samples (the
same criterion :func:`hil.identify.floor.judge` applies to the whole record).  An effect
that only fits the noise of the fit blocks gains nothing on the others.

Candidates are independent of one another, so they are evaluated in parallel processes
(:class:`CandidatePool`, a ``concurrent.futures`` process pool; each worker builds the
record's filtered motion once), or in the calling process with one worker.
"""

import dataclasses
import math
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from hil.identify.effects import BY_NAME, LIBRARY, REPLAY, Context, Term
from hil.identify.effects.joint import domain_of, members, propose
from hil.identify.floor import channel_residuals
from hil.identify.model import Model
from hil.identify.motion import Drive, motion
from hil.identify.record import Record
from hil.identify.replay import ERROR_START, Replay
from plant.config import load_machine

#: length of the alternating fit / held-out blocks, s: shorter than the program's moves so
#: that every kind of motion (reversals, slow and fast moves) lands in both
BLOCK_S = 0.5


def holdout_rows(rec: Record) -> np.ndarray:
    """True on the held-out samples (odd blocks of BLOCK_S), shape (n,)."""
    block = max(1, round(BLOCK_S / rec.dt))
    return (np.arange(rec.n) // block) % 2 == 1


def fit_context(ctx: Context, held_out: np.ndarray) -> Context:
    """``ctx`` with the fits' masks narrowed to the fit blocks."""
    m = dataclasses.replace(ctx.m, use=ctx.m.use & ~held_out)
    return dataclasses.replace(ctx, m=m, moving=ctx.moving & ~held_out)


def heldout_cost(rec: Record, rep: Replay | None, rows: np.ndarray, floor: dict) -> float:
    """J on ``rows`` (from ERROR_START on): sum over the floor's channels of
    (rms error / floor)²; inf for a failed replay."""
    if rep is None or rep.status != 0:
        return math.inf
    use = rows.copy()
    use[:ERROR_START] = False
    total = 0.0
    for r in channel_residuals(rec, rep, floor):
        total += float(np.mean(r[use] ** 2))
    return total if math.isfinite(total) else math.inf


@dataclass
class Candidate:
    """One candidate's try in a round: a library effect, or a joint candidate of two
    (:mod:`hil.identify.effects.joint`).

    Attributes:
        effect: its name.
        terms: the proposed terms (fit blocks only); empty when it proposed nothing.
        cost: J on the held-out blocks with it (inf: nothing proposed or a failed replay).
        delta_bic: the criterion's change against the round's start (negative: better).
        params: its parameters as proposed, for the report.
        note: why it has no score, or the evidence's sentence.
    """
    effect: str
    terms: list[Term]
    cost: float
    delta_bic: float
    params: dict
    note: str


@dataclass
class Setting:
    """What a candidate's evaluation needs besides the model's terms: the record and
    config, the inverse model's corner, the replay floor, the effective number of
    independent samples and the declared coefficients' tolerances."""
    config: str
    rec: Record
    cutoff_hz: float | None
    floor: dict
    n_eff: float
    tolerance: dict


class Evaluator:
    """Builds the record's context once; evaluates candidates against term snapshots."""

    def __init__(self, setting: Setting):
        self.setting = s = setting
        cfg = load_machine(s.config)
        drive = Drive.of(cfg)
        self.ctx = Context.of(cfg, drive, s.rec, motion(s.rec, drive, s.cutoff_hz))
        self.held_out = holdout_rows(s.rec)
        self.fit_ctx = fit_context(self.ctx, self.held_out)
        self.n_ho = max(2.0, 0.5 * s.n_eff)

    def model(self, terms: list[Term]) -> Model:
        model = Model(self.fit_ctx, self.setting.config,
                      tolerance=self.setting.tolerance)
        model.restore([dataclasses.replace(t, coef=t.coef.copy()) for t in terms])
        return model

    def cost(self, terms: list[Term]) -> float:
        """Held-out J of the model made of ``terms`` as they are."""
        model = self.model(terms)
        return heldout_cost(self.setting.rec, model.replay(), self.held_out,
                            self.setting.floor)

    def evaluate(self, terms: list[Term], name: str, cost0: float) -> Candidate:
        """Propose candidate ``name`` on the fit blocks from the model of ``terms`` (fitted
        to its domain's residual alone), replay, score on the held-out blocks."""
        where = domain_of(name, BY_NAME)
        model = self.model(terms)
        residual = model.residual(where) if where != REPLAY else None
        proposed = propose(name, self.fit_ctx, residual, model, BY_NAME)
        if proposed is None:
            return Candidate(name, [], math.inf, math.inf, {}, "nothing to propose")
        params = {}
        # the candidate alone, the rest as it is: a joint refit would give every candidate
        # of a domain the same gain of its base terms' refit
        for term in proposed:
            params.update(term.params(self.ctx))
            model.add(term)
        cost = heldout_cost(self.setting.rec, model.replay(), self.held_out,
                            self.setting.floor)
        k = n_coef(proposed)
        delta = (self.n_ho * math.log(cost / cost0) + k * math.log(self.n_ho)
                 if 0.0 < cost0 and math.isfinite(cost) else math.inf)
        return Candidate(name, proposed, cost, delta, params,
                         proposed[-1].evidence.get("text", ""))


def n_coef(terms: list[Term]) -> int:
    """The parameters a candidate's terms add, as the criterion counts them: each term's
    coefficients, at least one."""
    return sum(max(1, t.effect.n_coef(t.shape)) for t in terms)


_WORKER: Evaluator | None = None


def _init_worker(setting: Setting) -> None:
    global _WORKER
    _WORKER = Evaluator(setting)


def _evaluate_in_worker(terms: list[Term], name: str, cost0: float) -> Candidate:
    return _WORKER.evaluate(terms, name, cost0)


def default_workers() -> int:
    """Processes for the candidates: the CPUs this process may use, at most 2 (the
    machines this runs on are shared)."""
    return max(1, min(2, len(os.sched_getaffinity(0))))


class CandidatePool:
    """Evaluates a round's candidates, in ``workers`` processes (1: in this process).

    Use as a context manager; :meth:`rank` returns the candidates best first."""

    def __init__(self, setting: Setting, workers: int = 1):
        self.local = Evaluator(setting)
        self.workers = workers
        self._pool = None
        if workers > 1:
            self._pool = ProcessPoolExecutor(workers, initializer=_init_worker,
                                              initargs=(setting,))

    def __enter__(self) -> "CandidatePool":
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def rank(self, terms: list[Term], names: list[str], done=None) -> tuple[float, list]:
        """(held-out J of ``terms``, the candidates of ``names`` best first by their
        criterion); ``done(candidate)`` is called as each finishes."""
        cost0 = self.local.cost(terms)
        if self._pool is None:
            out = []
            for n in names:
                out.append(self.local.evaluate(terms, n, cost0))
                if done is not None:
                    done(out[-1])
        else:
            futures = [self._pool.submit(_evaluate_in_worker, terms, n, cost0) for n in names]
            out = []
            for f in futures:
                out.append(f.result())
                if done is not None:
                    done(out[-1])
        order = {e.name: i for i, e in enumerate(LIBRARY)}
        # among equal scores the simpler first: a single effect before a joint one
        out.sort(key=lambda c: (c.delta_bic, len(members(c.effect)),
                                order[members(c.effect)[0]]))
        return cost0, out
