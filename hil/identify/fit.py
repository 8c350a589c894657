"""Greedy identification: find what the model lacks, one effect at a time.

Each round computes the residuals the current model leaves (the inverse model's force
residual from the measured motion, and the table-minus-motor position where both
encoders were recorded) and lets *every* effect of the library not yet in the model --
a delay too, which only the replay shows -- fit itself to its residual on half of the
record; each candidate's machine file is replayed in closed loop and ranked by its gain
on the other half (:mod:`hil.identify.candidates`, in parallel processes).  The best
is proposed again on the whole record, its parameters fitted jointly with every term of
its domain -- the base parameters (mass, viscous friction, ...) freed again, but held by
a prior at their declared values -- and the replay decides: a step is kept only when the
replay's errors, each over its channel's measurement noise floor, gain more than its
added parameters cost (:func:`hil.identify.floor.judge`, an information criterion);
otherwise the next of the ranking is tried.  The inverse model can mistake one effect for
another; the closed loop settles it.  At the end the single-coefficient terms and the
scalar shapes are refined on the replay itself (:mod:`hil.identify.refine`), and the
declared parameters' changes are listed with their uncertainties
(:mod:`hil.identify.changes`).

It stops when no candidate gains on the held-out half, when every replay channel is
within ``floor_factor`` of its noise floor (:func:`hil.identify.floor.replay_floor`), or
after ``max_steps``.
"""

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.identify import screw_geometry
from hil.identify.candidates import Candidate, CandidatePool, Setting, n_coef
from hil.identify.changes import declared_changes, finding_text
from hil.identify.conventions import read_conventions
from hil.identify.effects import BY_NAME, FORCE, LIBRARY, POSITION, REPLAY, Context
from hil.identify.effects.base import correlation
from hil.identify.effects.joint import companions, domain_of, propose
from hil.identify.floor import floor_origins, judge, normalised_cost, replay_floor
from hil.identify.model import Model
from hil.identify.motion import Drive, motion
from hil.identify.record import Record
from hil.identify.refine import refine
from hil.identify.replay import ERROR_START, Replay, errors
from hil.identify.spectrum import position_spectrum
from hil.progress import Progress
from plant.config import load_machine


@dataclass
class Step:
    """One added effect: name, fitted parameters (SI), evidence and the replay's errors."""
    effect: str
    params: dict
    evidence: dict
    error: dict


def record_errors(rec: Record, rep: Replay | None) -> dict:
    """The replay's errors against the record (:func:`hil.identify.replay.errors`), with
    the motor encoder's when both have one; {"status": ...} when the replay failed."""
    if rep is None:
        return {"status": "invalid machine file"}
    if rep.status != 0:
        return {"status": f"plant fault {rep.status}"}
    out = errors(rec, rep)
    if (rec.motor_pos is not None and rep.motor_pos is not None
            and not np.array_equal(rec.motor_pos, rec.pos)):
        d = rec.motor_pos[ERROR_START:] - rep.motor_pos[ERROR_START:]
        out["motor_pos_rms_um"] = float(np.sqrt(np.mean(d * d)) * 1e6)
    return out


@dataclass
class Identification:
    """Identify the effects a machine file lacks from one record.

    Args:
        config: the machine file to start from.
        rec: the record (see :func:`hil.identify.record.load_record`).
        min_explained: smallest share of its residual's energy a ranked candidate must
            explain to be tried on the whole record (in that round; a delay, which has no
            residual, is judged by the replay alone).
        floor_factor: a replay whose every channel is within this factor of its noise
            floor is done.
        max_steps: most effects added.
        refine_nfev: closed-loop refinement's budget of least-squares iterations (0: off).
        cutoff_hz: low-pass corner of the inverse model (None: a tenth of the sample rate).
        exclude: names of library effects not to look for (known absent, or to compare
            models: on EMPS, without ``viscous_asymmetry`` the search takes the constant
            offset of the paper's symmetric model instead).
        workers: processes evaluating a round's candidates (1: this one).
        tolerance: effect name -> relative tolerance of its declared values (the
            prior's deviation; :data:`hil.identify.model.DEFAULT_TOLERANCE` otherwise).
        log: optional callable(str) for progress lines (and a progress bar per round).

    After :meth:`fit`: ``steps`` (the effects added, in order), ``rejected`` and
    ``skipped`` (effect -> why), ``proposals`` (every step tried, kept or not, with its
    parameters, errors before and after and the reason), ``floor`` (the replay channels'
    noise floors) and ``floor_origins`` (how each was found), ``refinement``,
    ``error_before``/``error_after`` (replay errors), ``residual_before``/
    ``residual_after`` (domain -> residual, shape (n,)),
    ``replay_before``/``replay_after``, ``friction_before``/``friction_after`` (v -> force),
    ``unexplained`` (the signature of what is left), ``rounds`` (every round's candidates
    ranked by their held-out gain), ``declared_changes`` (:func:`hil.identify.changes.
    declared_changes`), and ``model`` (the terms; its ``overrides()`` are the fitted
    machine-file keys).
    """
    config: str | Path
    rec: Record
    min_explained: float = 0.05
    floor_factor: float = 1.5
    max_steps: int = 6
    refine_nfev: int = 10
    cutoff_hz: float | None = None
    exclude: tuple = ()
    workers: int = 1
    tolerance: dict = field(default_factory=dict)
    log: object = None
    steps: list[Step] = field(default_factory=list)
    skipped: dict = field(default_factory=dict)
    rejected: dict = field(default_factory=dict)
    proposals: list = field(default_factory=list)
    refinement: dict = field(default_factory=dict)
    rounds: list = field(default_factory=list)

    def _say(self, text: str) -> None:
        if self.log is not None:
            self.log(f"[{time.monotonic() - self._t0:6.1f} s] {text}")

    def fit(self) -> "Identification":
        """Run the greedy search; returns self."""
        self._t0 = time.monotonic()
        cfg = load_machine(self.config)
        read_conventions(self.rec, cfg)  # a header the replay cannot honour: refused first
        screw_geometry.check(cfg)
        self.drive = Drive.of(cfg)
        self.motion = motion(self.rec, self.drive, self.cutoff_hz)
        self.ctx = Context.of(cfg, self.drive, self.rec, self.motion)
        self.model = Model(self.ctx, self.config, tolerance=self.tolerance)
        self._say(f"replaying {self.rec.n} samples through {Path(self.config).name}")
        self.replay_before = self.model.replay()
        self.error_before = record_errors(self.rec, self.replay_before)
        self.residual_before = {d: self.model.residual(d) for d in self.domains()}
        self.friction_before = friction_curve(self.model)
        self.model_before_inertia = float(self.model.term("inertia").coef[0])
        self.floor = replay_floor(self.rec, cfg)
        self.floor_origins = floor_origins(self.rec, cfg)
        # independent samples: the inverse model's band, 2 f_c per second
        self.n_eff = self.rec.n * 2.0 * self.motion.cutoff_hz * self.rec.dt
        self._say(f"error before: {_fmt(self.error_before)}; noise floor "
                  + ", ".join(f"{k} {v:.4g} ({self.floor_origins[k]})"
                              for k, v in self.floor.items()))
        err = self.error_before
        setting = Setting(str(self.config), self.rec, self.cutoff_hz, self.floor, self.n_eff,
                          self.tolerance)
        with CandidatePool(setting, self.workers) as pool:
            while len(self.steps) < self.max_steps:
                if self._replay_at_floor(err):
                    self._say(f"every channel within {self.floor_factor}x its noise floor")
                    break
                names = self._candidate_names()
                if not names or not self._round(pool, names, err):
                    break
                err = self.steps[-1].error
        if self.refine_nfev > 0 and self.steps:
            self.refinement = refine(self.model, self.rec, self.floor, self.n_eff,
                                     self.refine_nfev, self._say)
        self.replay_after = self.model.replay()
        self.error_after = record_errors(self.rec, self.replay_after)
        self.residual_after = {d: self.model.residual(d) for d in self.domains()}
        self.friction_after = friction_curve(self.model)
        self.unexplained = self._describe_rest()
        self.declared_changes = declared_changes(self.model)
        for row in self.declared_changes:
            if row["beyond_tolerance"]:
                self._say(f"declared {finding_text(row)}")
        self._say("done")
        return self

    def domains(self) -> list[str]:
        """The residual domains this record has: force, and position with two sensors."""
        return [FORCE] + ([POSITION] if self.motion.dx is not None else [])

    def _replay_at_floor(self, err: dict) -> bool:
        """Every replay channel within ``floor_factor`` of its noise floor."""
        return all(isinstance(err.get(k), float) and err[k] <= self.floor_factor * f
                   for k, f in self.floor.items())

    def noise_floor(self, domain: str) -> float:
        return self.motion.noise_force if domain == FORCE else self.motion.noise_dx

    def _candidate_names(self) -> list[str]:
        """The candidates this round may try: the library's effects available in the record,
        not excluded, not rejected before, not in the model yet (or declared and
        correctable, and not replaced by a term of the model); then the joint candidates
        they call for (Coulomb with the Stribeck
        dip wherever Coulomb is a candidate, :mod:`hil.identify.effects.joint`), unless
        rejected before."""
        out = []
        domains = self.domains() + [REPLAY]
        for effect in LIBRARY:
            if effect.domain not in domains:
                continue
            why = ("excluded by the caller" if effect.name in self.exclude
                   else effect.unavailable(self.ctx))
            if why is not None:
                self.skipped[effect.name] = why
                continue
            if effect.name in self.rejected:
                continue
            instead = next((t.effect.name for t in self.model.terms
                            if effect.name in t.effect.replaces), None)
            if instead is not None:
                self.skipped[effect.name] = f"{instead} takes its place in the model"
                continue
            have = self.model.term(effect.name)
            if have is not None and (have.added or not effect.correctable):
                continue
            out.append(effect.name)

        def joins(name: str) -> bool:
            # a member already rejected alone may still belong beside the other
            effect = BY_NAME[name]
            return (name not in self.exclude and effect.unavailable(self.ctx) is None
                    and self.model.term(name) is None)

        return out + [j for j in companions(out, joins) if j not in self.rejected]

    def _round(self, pool: CandidatePool, names: list[str], err: dict) -> bool:
        """Rank every candidate by its held-out gain (:mod:`hil.identify.candidates`) and
        add the best that the whole record confirms; False when none is added."""
        n_round = len(self.rounds) + 1
        self._say(f"round {n_round}: {len(names)} candidates ({', '.join(names)})")
        finished = []

        def done(c: Candidate) -> None:
            finished.append(c)
            if bar is not None:
                bar.update(len(finished))

        bar = (Progress(f"round {n_round}: candidates", total=len(names), ticking=True)
               if self.log is not None else None)
        try:
            cost0, ranked = pool.rank(self.model.snapshot(), names, done)
        finally:
            if bar is not None:
                bar.close()
        best = ranked[0]
        self._say(f"held-out J {cost0:.4g}; best {best.effect} (J {best.cost:.4g}, "
                  f"BIC {best.delta_bic:+.1f})")
        self.rounds.append({"heldout_cost_before": cost0, "ranking": [
            {"effect": c.effect, "heldout_cost": c.cost, "heldout_delta_bic": c.delta_bic,
             "explained": (c.terms[-1].evidence.get("explained") if c.terms else None),
             "params": c.params, "note": c.note} for c in ranked]})
        for c in ranked:
            if not c.delta_bic < 0.0:
                break
            # a delay's "explained" is the effort error's share alone: the ranking's
            # replay over every channel is its measure
            explains = c.terms[-1].evidence.get("explained", 1.0)
            if c.terms[-1].effect.domain != REPLAY and explains < self.min_explained:
                self._say(f"  {c.effect} not tried on the whole record: explains "
                          f"{explains:.3g} of its residual, under {self.min_explained:g}")
                continue
            if self._try(c, err):
                return True
        return False

    def _try(self, candidate: Candidate, err: dict) -> bool:
        """Propose the candidate again on the whole record (its shape, fitted on half of it
        for the ranking, is sharper on all of it: a pitch period, a Stribeck velocity),
        with its domain refitted jointly or not, whichever replays better, and keep it
        when the replay's information criterion says so (:func:`hil.identify.floor.judge`)."""
        name = candidate.effect
        where = domain_of(name, BY_NAME)
        residual = self.model.residual(where) if where != REPLAY else None
        terms = propose(name, self.ctx, residual, self.model, BY_NAME) or candidate.terms
        saved = self.model.snapshot()
        for term in terms:
            self.model.add(dataclasses.replace(term, coef=term.coef.copy()))
        new = record_errors(self.rec, self.model.replay())
        if where != REPLAY:
            # the domain refitted jointly too; the replay keeps the better of the two, so
            # a declared parameter moves only where the closed loop gains by it (the
            # inverse model's joint fit can move one to absorb what its statics miss)
            alone = self.model.snapshot()
            self.model.refit(where)
            joint = record_errors(self.rec, self.model.replay())
            if normalised_cost(joint, self.floor) <= normalised_cost(new, self.floor):
                new = joint
            else:
                self.model.restore(alone)
                self._say(f"  {name}: the joint refit of its domain replays "
                          "worse; the declared terms kept")
        verdict = judge(err, new, self.floor, n_coef(terms), self.n_eff)
        added = [self.model.term(t.effect.name) for t in terms]
        params = {k: v for t in added for k, v in t.params(self.ctx).items()}
        evidence = terms[-1].evidence
        self.proposals.append({"effect": name, "params": params,
                               "evidence": evidence, "error_before": err,
                               "error_after": new, "accepted": verdict.keep,
                               "reason": verdict.reason})
        if not verdict.keep:
            self.model.restore(saved)
            self.rejected[name] = verdict.reason
            self._say(f"rejected {name}: {verdict.reason}")
            return False
        # a joint candidate names the effects new to the model first; a member the file
        # declared (Coulomb's level beside a Stribeck dip) is a correction of it
        had = {t.effect.name for t in saved}
        for t in sorted(added, key=lambda t: t.effect.name in had):
            self.steps.append(Step(t.effect.name, t.params(self.ctx), t.evidence, new))
        self._say(f"added {name} ({evidence.get('text', '')}); {verdict.reason}")
        return True

    def _describe_rest(self) -> dict:
        """The signature of what is left, whatever the library says about it."""
        out = {}
        m, ctx = self.motion, self.ctx
        for domain in self.domains():
            r = self.model.residual(domain)
            mask = ctx.moving
            rms = float(np.sqrt(np.mean(r[mask] ** 2))) if mask.any() else 0.0
            info = {"rms": rms, "noise_floor": self.noise_floor(domain),
                    "corr_sign_v": correlation(r[mask], np.sign(m.v[mask])),
                    "corr_v": correlation(r[mask], m.v[mask]),
                    "corr_a": correlation(r[mask], m.a[mask])}
            travel = float(np.ptp(m.x[mask])) if mask.any() else 0.0
            if travel > 0:
                spec = position_spectrum(r, m.x, mask, travel / 4000)
                peaks = spec.peaks(3, min_cycles=2.0 / travel)
                info["periodic_in_table_position"] = [
                    {"period_m": 1.0 / f, "amplitude": a,
                     "per_motor_rev": self.drive.ratio * 2 * math.pi * f
                     if self.drive.kind == "screw" else None} for f, a in peaks]
            out[domain] = info
        return out


def friction_curve(model: Model):
    """The model's sliding friction against velocity: a function of v (array, m/s or
    rad/s) returning the force (N or N·m) the motor must overcome."""
    def coef(name):
        t = model.term(name)
        return (float(t.coef[0]), t.shape) if t is not None else (0.0, {})

    fv, _ = coef("viscous_friction")
    dfv, _ = coef("viscous_asymmetry")
    fc, _ = coef("coulomb_friction")
    fs, shape = coef("stribeck")
    vs = shape.get("vs", 1.0)
    return lambda v: fv * v + dfv * np.abs(v) + np.sign(v) * (fc + fs * np.exp(-(v / vs) ** 2))


def _fmt(err: dict) -> str:
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                     for k, v in err.items())
