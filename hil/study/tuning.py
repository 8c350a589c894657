"""Tuning: Optuna over the ``[tune]`` keys, under constraints, robust over tolerances.

Trials are asked in batches (``[tuning] batch``, default two per worker; TPE with the
constant liar so a batch spreads out), each trial run on ``robust_samples`` machines
drawn from ``[vary]`` (the same machines for every trial; none: the machine file as
written) as Dask tasks, and told:

* objectives (``minimize``, ``maximize``): per trial the worst over its machines
  (``robust = "worst"``) or their mean;
* constraints (``[tuning.constraints] output = { min, max }``): met on every machine;
  an output that is NaN on a machine violates them (counted as 1e9), except where NaN
  means there is nothing to limit (no resonance peak, no phase crossover:
  :attr:`~hil.study.outputs.Output.nan_is_absent`);
* a trial with a failed machine or a NaN objective fails (Optuna's FAIL state).

Every machine of every trial is a row of the Parquet store, its id trial x M + j (M the
machines per trial), so a killed tuning study resumes: finished trials are given back to
Optuna as they were, a trial cut short runs only its missing machines.  The best
feasible trial (single objective), or the feasible Pareto front's best in the first
objective, is written as a machine file: the study's file with the tuned keys changed in
place, every comment kept (``best.toml``; on a manifest ``best_<AXIS>.toml`` per tuned
axis, the manifest's overrides of that axis included).
"""

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import optuna
from distributed import Future

from hil.identify.config_out import patch_config
from hil.study.outputs import OUTPUTS
from hil.study.run import Design, dispatch_sized, job_of, send_job
from hil.study.sampling import design, to_values
from hil.study.spec import Study
from hil.study.store import Results, ResultStore

VIOLATED = 1e9  # the constraint value of an output that is NaN where it must not be


@dataclass
class Trial:
    """One trial: its index (sample ids index x M ... index x M + M - 1), tuned values,
    its machines' outputs (name -> values, one per machine), and once told its aggregated
    values, constraint values (<= 0: met) and state."""
    index: int
    params: dict
    rows: dict = field(default_factory=dict)
    values: dict = field(default_factory=dict)
    constraints: dict = field(default_factory=dict)
    failed: str = ""

    @property
    def feasible(self) -> bool:
        """Told, not failed, every constraint met."""
        return not self.failed and all(v <= 0.0 for v in self.constraints.values())


@dataclass(frozen=True)
class TuningResult:
    """The trials (in index order), the best trial (None: no feasible one) and the
    machine files written for it."""
    trials: tuple[Trial, ...]
    best: Trial | None
    files: tuple[Path, ...]


def robust_values(study: Study) -> np.ndarray:
    """(M, varied) the machines every trial runs on (M >= 1; no columns when nominal)."""
    t = study.tuning.settings
    if t.robust_samples == 0:
        return np.empty((1, 0))
    names = tuple(r.name for r in study.varied)
    return to_values(design(study.study.design, names, t.robust_samples, study.study.seed),
                     study.distributions)


def _distributions(study: Study) -> dict:
    out = {}
    for ref, space in zip(study.tuned, study.spaces):
        if space.kind == "values":
            out[ref.name] = optuna.distributions.CategoricalDistribution(list(space.values))
        else:
            out[ref.name] = optuna.distributions.FloatDistribution(space.low, space.high,
                                                                   log=space.log)
    return out


def _sampler(study: Study) -> optuna.samplers.BaseSampler:
    t, seed = study.tuning.settings, study.study.seed
    if t.sampler == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    if t.sampler == "nsga2":
        return optuna.samplers.NSGAIISampler(seed=seed)
    return optuna.samplers.TPESampler(seed=seed, n_startup_trials=t.startup_trials,
                                      multivariate=True, constant_liar=True)


def aggregate(study: Study, trial: Trial, machines: int) -> None:
    """Fill ``trial``'s values, constraints and failure from its machines' rows."""
    tuning = study.tuning
    if trial.failed:
        return
    mean = tuning.settings.robust == "mean"
    for name, direction in tuning.objectives:
        y = np.asarray(trial.rows[name])
        if y.size != machines or not np.all(np.isfinite(y)):
            trial.failed = f"{name} is NaN on a machine"
            return
        worst = np.max(y) if direction == "minimize" else np.min(y)
        trial.values[name] = float(np.mean(y) if mean else worst)
    for c in tuning.constraints:
        y = np.asarray(trial.rows[c.output], dtype=float)
        absent = OUTPUTS[c.output].nan_is_absent
        v = [c.violation(x) if np.isfinite(x) else 0.0 if absent else VIOLATED for x in y]
        trial.constraints[c.output] = float(max(v))
        worst = np.nanmin if c.high is None else np.nanmax  # the machine nearest the bound
        trial.values.setdefault(c.output, float(worst(y)) if np.any(np.isfinite(y))
                                else math.nan)


def _restore(study: Study, results: Results, machines: int) -> dict[int, Trial]:
    """Trials found in the store, by index, with the rows they have."""
    trials: dict[int, Trial] = {}
    for k, sample_id in enumerate(results.ids):
        index = int(sample_id) // machines
        trial = trials.get(index)
        if trial is None:
            trial = trials[index] = Trial(index, {r.name: float(results.params[r.name][k])
                                                  for r in study.tuned})
        if results.status[k] != "ok":
            trial.failed = results.status[k]
        for name in study.outputs:
            trial.rows.setdefault(name, []).append(float(results.outputs[name][k]))
    return trials


def _rows_design(study: Study, trials: list[Trial], robust: np.ndarray,
                 skip: set[int]) -> Design:
    """The sample ids and values of ``trials``' machines, leaving out ids in ``skip``."""
    machines = robust.shape[0]
    ids, values = [], []
    for t in trials:
        tuned = [t.params[r.name] for r in study.tuned]
        for j in range(machines):
            sid = t.index * machines + j
            if sid not in skip:
                ids.append(sid)
                values.append(tuned + list(robust[j]))
    width = len(study.parameters)
    return Design(np.asarray(ids, dtype=np.int64),
                  np.asarray(values, dtype=float).reshape(-1, width))


def _take(study: Study, trial: Trial, row: dict) -> None:
    """File one machine's result row under its trial."""
    if row["status"] != "ok":
        trial.failed = row["status"]
    for name in study.outputs:
        trial.rows.setdefault(name, []).append(row[name])


def _machines_done(study: Study, trial: Trial) -> int:
    return len(trial.rows.get(study.outputs[0], []))


def _tell(study: Study, opt: optuna.Study, trial: Trial, asked) -> None:
    if trial.failed:
        opt.tell(asked, state=optuna.trial.TrialState.FAIL)
        return
    for name, value in trial.constraints.items():
        asked.set_constraint(name, value)
    opt.tell(asked, [trial.values[name] for name, _ in study.tuning.objectives])


def _add_told(study: Study, opt: optuna.Study, trial: Trial, dists: dict) -> None:
    """Give a finished trial of an earlier run back to Optuna as it was."""
    failed = bool(trial.failed)
    opt.add_trial(optuna.trial.create_trial(
        state=optuna.trial.TrialState.FAIL if failed else optuna.trial.TrialState.COMPLETE,
        values=None if failed else [trial.values[n] for n, _ in study.tuning.objectives],
        params=trial.params, distributions=dists,
        constraints=None if failed else trial.constraints))


@dataclass(frozen=True)
class Runner:
    """What a batch of trials runs with: the client, the job sent to the workers
    (:func:`~hil.study.run.send_job`), the store, the tolerance machines (M, varied),
    the samples per task asked for (0: :func:`~hil.study.run.dispatch_sized` chooses
    per batch), and the progress line."""
    client: object
    payload: Future
    store: ResultStore
    robust: np.ndarray
    requested_task_size: int
    progress: Callable[[int, int], None]

    def run(self, study: Study, trials: list[Trial], skip: set[int], done_before: int) -> int:
        """Run the machines of ``trials`` (ids in ``skip`` excepted), file their rows;
        how many ran."""
        rows = _rows_design(study, trials, self.robust, skip)
        by_index = {t.index: t for t in trials}
        machines = self.robust.shape[0]
        result, _ = dispatch_sized(self.client, self.payload, rows, self.store,
                                   self.requested_task_size,
                                   lambda done, failed: self.progress(done_before + done, failed))
        for table in result.tables:
            for row in table.to_pylist():
                _take(study, by_index[row["sample_id"] // machines], row)
        return result.done


def run_tuning(client, study: Study, store: ResultStore, requested_task_size: int,
               progress, note: Callable[[str], None]) -> TuningResult:
    """Run (or resume) the tuning study on ``client`` (module docstring);
    ``requested_task_size``: samples per task (0: chosen per batch of trials, as for the
    other methods)."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    settings = study.tuning.settings
    robust = robust_values(study)
    machines = robust.shape[0]
    runner = Runner(client, send_job(client, job_of(study, store)), store, robust,
                    requested_task_size, progress)
    dists = _distributions(study)
    opt = optuna.create_study(directions=[d for _, d in study.tuning.objectives],
                              sampler=_sampler(study))
    trials = _restore(study, store.read(), machines)
    unfinished = [t for t in trials.values() if _machines_done(study, t) < machines]
    if unfinished:
        note(f"resuming {len(unfinished)} trial(s) cut short: only their missing machines run")
        progress.start(len(unfinished) * machines - sum(_machines_done(study, t)
                                                        for t in unfinished), "resuming")
        runner.run(study, unfinished, store.done_ids(), 0)
    for t in sorted(trials.values(), key=lambda t: t.index):
        aggregate(study, t, machines)
        _add_told(study, opt, t, dists)
    if trials:
        note(f"{len(trials)} trial(s) restored from {store.dir}")
    batch = settings.batch or 2 * max(1, len(client.scheduler_info()["workers"]))
    next_index = max(trials, default=-1) + 1
    progress.start((settings.trials - len(trials)) * machines, "tuning")
    done = 0
    while len(trials) < settings.trials:
        asked = [opt.ask(dists) for _ in range(min(batch, settings.trials - len(trials)))]
        new = [Trial(next_index + k, dict(a.params)) for k, a in enumerate(asked)]
        next_index += len(new)
        done += runner.run(study, new, set(), done)
        for t, a in zip(new, asked):
            aggregate(study, t, machines)
            _tell(study, opt, t, a)
            trials[t.index] = t
    ordered = tuple(sorted(trials.values(), key=lambda t: t.index))
    best = best_trial(study, ordered)
    files = write_best(study, best, Path(store.out)) if best is not None else ()
    return TuningResult(ordered, best, files)


def best_trial(study: Study, trials: tuple[Trial, ...]) -> Trial | None:
    """The feasible trial best in the first objective among the feasible non-dominated
    ones (with one objective: simply the best feasible)."""
    goals = study.tuning.objectives
    feasible = [t for t in trials if t.feasible]
    if not feasible:
        return None
    signed = np.array([[t.values[n] * (1.0 if d == "minimize" else -1.0) for n, d in goals]
                       for t in feasible])
    front = [i for i, p in enumerate(signed)
             if not np.any(np.all(signed <= p, axis=1) & np.any(signed < p, axis=1))]
    return feasible[min(front, key=lambda i: signed[i, 0])]


def write_best(study: Study, best: Trial, out: Path) -> tuple[Path, ...]:
    """The best trial's machine file(s) in ``out`` (module docstring); none for analytic
    experiments."""
    if study.machine is None:
        return ()
    note = f"tuned by hil study {Path(study.path).name}, trial {best.index}"
    files = []
    for axis in study.machine.axes:
        changes = copy.deepcopy(axis.overrides)
        tuned = [r for r in study.tuned if r.axis in ("", axis.name)]
        if not tuned:
            continue
        for ref in tuned:
            value = best.params[ref.name]
            changes.setdefault(ref.section, {})[ref.key] = int(value) if ref.integer else value
        name = "best.toml" if not study.machine.manifest else f"best_{axis.name}.toml"
        path = out / name
        path.write_text(patch_config(axis.text, changes, note))
        files.append(path)
    return tuple(files)


def tuning_from_store(study: Study, store: ResultStore) -> TuningResult:
    """The trials already in ``store`` (complete ones), their best, its machine file."""
    machines = robust_values(study).shape[0]
    trials = _restore(study, store.read(), machines)
    complete = tuple(t for _, t in sorted(trials.items())
                     if _machines_done(study, t) == machines)
    for t in complete:
        aggregate(study, t, machines)
    best = best_trial(study, complete)
    return TuningResult(complete, best,
                        write_best(study, best, Path(store.out)) if best is not None else ())
