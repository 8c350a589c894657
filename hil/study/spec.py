"""The study file: a strict TOML description of one study, checked before any work starts.

::

    [study]
    name = "Arrow 500 X: position step over the manufacturer tolerances"
    machine = "../arrow500_x.toml"   # machine file or manifest, relative to this file
    method = "sensitivity"           # tolerance | sensitivity | tuning
    seed = 1
    samples = 256                    # machines (tolerance); base samples N (sensitivity)
    design = "sobol"                 # tolerance: monte_carlo | sobol; sensitivity: sobol | morris

    [experiment]                     # or several [[experiment]] (hil.study.experiments)
    kind = "step"
    at_mm = 250.0
    outputs = ["rise_time_s", "overshoot_pct"]

    [vary.table]                     # [vary.AXIS.section] on a manifest
    mass_kg = { tolerance_pct = 10 } # hil.study.distributions

    [tune.controller]                # tuning: the search space, bounded forms
    kv_m_min_per_mm = { uniform = [1.0, 6.0] }

    [tuning]
    trials = 60
    minimize = ["settling_time_s"]   # and/or maximize = [...]
    robust_samples = 8               # each trial on 8 machines drawn from [vary]
    [tuning.constraints]
    overshoot_pct = { max = 2.0 }

    [report]
    percentiles = [5, 50, 95]

Everything is refused before the first simulation, naming the study file, the section
or parameter, the value and the unit or range: an unknown section or key, a key the
machine file has not, a distribution reaching outside the key's physical range (the
range the machine-file loader enforces), a machine file that does not load with a
parameter at either end of its range, an output an experiment does not give.
"""

import hashlib
from dataclasses import dataclass, replace
from pathlib import Path

from hil.controller.config import load_controller
from hil.study.analytic import AnalyticExperiment
from hil.study.circularity import CircularityExperiment
from hil.study.distributions import Distribution, parse_distribution
from hil.study.experiments import (
    Experiment,
    FrequencyResponseExperiment,
    ProgramExperiment,
    StepExperiment,
    parse_experiment,
)
from hil.study.keys import (
    KeyRef,
    StudySpecError,
    checked_section,
    key_ref,
    overrides_of,
)
from hil.study.machine import MachineSource, read_machine
from plant.assemble import build
from plant.config import read_toml, shown_name
from plant.errors import ConfigError
from plant.files import checked_name, shown_path
from plant.schema import key

EXPERIMENTS = {cls.kind: cls for cls in (StepExperiment, FrequencyResponseExperiment,
                                         ProgramExperiment, CircularityExperiment,
                                         AnalyticExperiment)}
SECTIONS = ("study", "experiment", "vary", "tune", "tuning", "report")
DESIGNS = {"tolerance": ("monte_carlo", "sobol"), "sensitivity": ("sobol", "morris"),
           "tuning": ("monte_carlo", "sobol")}


@dataclass(frozen=True, kw_only=True)
class StudySection:
    """``[study]``."""
    name: str = key("-", "What the study is, for the report.")
    machine: str = key("-", "Machine file or manifest, relative to the study file (not "
                       "needed by analytic experiments).", "")
    method: str = key("-", "tolerance: distributions and percentiles of every output; "
                      "sensitivity: Sobol or Morris indices (SALib); tuning: Optuna over "
                      "[tune] keys.", choices=tuple(DESIGNS))
    seed: int = key("1", "Seed of the sample design and of the tuning sampler.", 0, ge=0)
    samples: int = key("1", "tolerance: machines simulated; sensitivity: base samples N "
                       "(Sobol: N (D + 2) runs, a power of 2; Morris: N (D + 1) runs).", 64,
                       ge=1)
    design: str = key("-", "tolerance and tuning's robust sample: monte_carlo or sobol "
                      "(scrambled Sobol' quasi-random); sensitivity: sobol (Saltelli) or "
                      "morris.  Default: monte_carlo, or sobol for sensitivity.", "",
                      choices=("", "monte_carlo", "sobol", "morris"))
    morris_levels: int = key("1", "Morris grid levels.", 4, ge=2, le=16)


@dataclass(frozen=True, kw_only=True)
class TuningSection:
    """``[tuning]`` (besides minimize, maximize and constraints)."""
    trials: int = key("1", "Optuna trials.", 50, ge=1)
    batch: int = key("1", "Trials evaluated at once (0: two per worker).", 0, ge=0)
    robust_samples: int = key("1", "Machines from [vary] every trial runs on (0: the "
                              "nominal machine only).", 0, ge=0)
    robust: str = key("-", "How a trial's machines combine into its objectives: worst "
                      "(the worst machine's value) or mean; constraints hold on every "
                      "machine either way.", "worst", choices=("worst", "mean"))
    sampler: str = key("-", "Optuna sampler.", "tpe", choices=("tpe", "random", "nsga2"))
    startup_trials: int = key("1", "TPE: random trials before the model.", 10, ge=1)


@dataclass(frozen=True, kw_only=True)
class ReportSection:
    """``[report]``."""
    percentiles: tuple = key("%", "Percentiles reported and drawn as bands.", (5.0, 50.0, 95.0))


@dataclass(frozen=True)
class Constraint:
    """An output bound of a tuning study: ``low`` <= output <= ``high`` (None: open)."""
    output: str
    low: float | None
    high: float | None

    def violation(self, value: float) -> float:
        """<= 0 when met (Optuna's convention), in the output's unit."""
        over = value - self.high if self.high is not None else -float("inf")
        under = self.low - value if self.low is not None else -float("inf")
        return max(over, under)


@dataclass(frozen=True)
class Tuning:
    """What a tuning study optimises.

    Attributes:
        settings: the ``[tuning]`` keys.
        objectives: (output, "minimize" or "maximize") in order.
        constraints: output bounds.
    """
    settings: TuningSection
    objectives: tuple[tuple[str, str], ...]
    constraints: tuple[Constraint, ...]


@dataclass(frozen=True)
class Study:
    """A checked study file.

    Attributes:
        path: the study file.
        study: its ``[study]`` keys (``design`` resolved).
        machine: the machine as text (None for analytic experiments).
        experiments: what runs on every sample.
        varied, distributions: the ``[vary]`` parameters and how each varies.
        tuned, spaces: the ``[tune]`` parameters and their search spaces.
        tuning: the ``[tuning]`` goal (None unless method = "tuning").
        report: the ``[report]`` keys.
        fingerprint: hash of the study file, machine files and programs (resuming
            refuses results of another study).
    """
    path: str
    study: StudySection
    machine: MachineSource | None
    experiments: tuple[Experiment, ...]
    varied: tuple[KeyRef, ...]
    distributions: tuple[Distribution, ...]
    tuned: tuple[KeyRef, ...]
    spaces: tuple[Distribution, ...]
    tuning: Tuning | None
    report: ReportSection
    fingerprint: str

    @property
    def outputs(self) -> tuple[str, ...]:
        """Every output column, in experiment order."""
        return tuple(name for exp in self.experiments for name in exp.selected)

    @property
    def parameters(self) -> tuple[KeyRef, ...]:
        """Every parameter column: tuned first, then varied."""
        return self.tuned + self.varied


def _table(raw: dict, name: str, where: str) -> dict:
    value = raw.get(name, {})
    if not isinstance(value, dict):
        raise StudySpecError(f"{where}: [{name}] must be a table")
    return value


def _flatten(table: dict, depth: int, where: str, section: str) -> list[tuple[str, object]]:
    """``{a: {b: {key: dist}}}`` -> [("a.b.key", dist)], ``depth`` names deep."""
    if depth == 1:
        return list(table.items())
    rows = []
    for name, sub in table.items():
        if not isinstance(sub, dict):
            shown = shown_name(name)
            raise StudySpecError(f"{where}: [{section}] {shown} = {sub!r}: expected a table "
                                 f"[{section}.{shown}.…] (parameters are named "
                                 f"{'AXIS.section.key' if depth == 3 else 'section.key'})")
        rows += [(f"{name}.{k}", v) for k, v in _flatten(sub, depth - 1, where,
                                                        f"{section}.{name}")]
    return rows


def _parameters(raw: dict, section: str, resolve, where: str, depth: int, bounded: bool):
    refs, dists = [], []
    for name, table in _flatten(_table(raw, section, where), depth, where, section):
        ref = resolve(name)
        refs.append(ref)
        dists.append(parse_distribution(table, ref, where, bounded))
    return tuple(refs), tuple(dists)


def _experiments(raw: dict, where: str, study_dir: Path, machine) -> tuple[Experiment, ...]:
    tables = raw.get("experiment")
    if isinstance(tables, dict):
        tables = [tables]
    if not isinstance(tables, list) or not tables:
        raise StudySpecError(f"{where}: [experiment] (or [[experiment]]) is missing: kind = "
                             f"one of {', '.join(EXPERIMENTS)}")
    out = []
    for table in tables:
        kind = table.get("kind") if isinstance(table, dict) else None
        if not isinstance(kind, str) or kind not in EXPERIMENTS:
            raise StudySpecError(f"{where}: [experiment] kind = {kind!r}: one of "
                                 f"{', '.join(EXPERIMENTS)}")
        out.append(parse_experiment(EXPERIMENTS[kind], table, where, study_dir, machine))
    names = [n for exp in out for n in exp.selected]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise StudySpecError(f"{where}: output {', '.join(twice)} selected by two "
                             "experiments: give each experiment its own outputs = [...]")
    return tuple(out)


def _tuning(raw: dict, where: str, outputs: tuple[str, ...]) -> Tuning:
    table = dict(_table(raw, "tuning", where))
    goals = []
    for direction in ("minimize", "maximize"):
        names = table.pop(direction, [])
        if not isinstance(names, list) or any(n not in outputs for n in names):
            raise StudySpecError(f"{where}: [tuning] {direction} = {names!r}: a list of this "
                                 f"study's outputs ({', '.join(outputs)})")
        goals += [(n, direction) for n in names]
    if not goals:
        raise StudySpecError(f"{where}: [tuning] needs minimize = [...] or maximize = [...]")
    bounds = table.pop("constraints", {})
    if not isinstance(bounds, dict):
        raise StudySpecError(f"{where}: [tuning.constraints] must be a table")
    constraints = []
    for name, limits in bounds.items():
        if (name not in outputs or not isinstance(limits, dict) or not limits
                or set(limits) - {"min", "max"} or any(
                    isinstance(v, bool) or not isinstance(v, (int, float))
                    for v in limits.values())):
            raise StudySpecError(f"{where}: [tuning.constraints] {shown_name(name)} = "
                                 f"{limits!r}: an output of this study "
                                 f"({', '.join(outputs)}) = {{ min = ..., max = ... }}, "
                                 "numbers in the output's unit")
        constraints.append(Constraint(name, limits.get("min"), limits.get("max")))
    settings = checked_section(TuningSection, table, where, "tuning")
    return Tuning(settings, tuple(goals), tuple(constraints))


def _check_corners(spec: Study) -> None:
    """Build the machine with every parameter at each end of its range (the others as
    written), as a worker will: a value the machine-file rules refuse is refused now, and
    so is one that leaves an experiment nothing to run (a position beyond the travel)."""
    if spec.machine is None:
        return
    refs = spec.parameters
    dists = spec.spaces + spec.distributions
    for ref, dist in zip(refs, dists):
        for value in dist.support():
            try:
                machine = spec.machine.build(overrides_of((ref,), (value,)))
                for axis in machine.axes:
                    load_controller(axis.config)
                    build(axis.config)
                for exp in spec.experiments:
                    exp.check_machine(machine)
            except StudySpecError as exc:  # an experiment this machine cannot run
                raise StudySpecError(f"{exc} (with parameter '{ref.name}' = {value:g} "
                                     f"{ref.unit}, an end of its range)") from exc
            except ConfigError as exc:
                raise StudySpecError(f"{spec.path}: parameter '{ref.name}' = {value:g} "
                                     f"{ref.unit} (an end of its range) makes the machine "
                                     f"file invalid: {exc}") from exc


def _power_of_two(n: int) -> bool:
    return n > 0 and n & (n - 1) == 0


def _fingerprint(path: Path, machine: MachineSource | None, experiments) -> str:
    digest = hashlib.sha256(path.read_bytes())
    for axis in machine.axes if machine is not None else ():
        digest.update(axis.text.encode())
    for exp in experiments:
        digest.update(getattr(exp, "text", "").encode())
    return digest.hexdigest()[:16]


def load_study(path: str | Path) -> Study:
    """Read and check a study file (module docstring); StudySpecError names the file,
    the section or parameter, the value and the unit or range."""
    path = Path(path)
    where = str(path)
    try:
        raw = read_toml(path, "study file")
    except ConfigError as exc:
        raise StudySpecError(str(exc)) from exc
    for name in raw:
        if name not in SECTIONS:
            raise StudySpecError(f"{where}: unknown section [{shown_name(name)}] (sections: "
                                 f"{', '.join(SECTIONS)})")
    study = checked_section(StudySection, _table(raw, "study", where), where, "study")
    allowed = DESIGNS[study.method]
    design = study.design or allowed[0]
    if design not in allowed:
        raise StudySpecError(f"{where}: [study] design = '{design}' does not go with method "
                             f"= '{study.method}' (one of {', '.join(allowed)})")
    study = replace(study, design=design)
    if design == "sobol" and not _power_of_two(study.samples):
        raise StudySpecError(f"{where}: [study] samples = {study.samples}: the Sobol' design "
                             "needs a power of 2 (64, 128, 256, ...)")
    machine = None
    if study.machine:
        try:
            machine = read_machine(checked_name(path.parent / study.machine,
                                                "machine file").resolve())
        except ConfigError as exc:
            raise StudySpecError(f"{where}: [study] machine = '{shown_path(study.machine)}': "
                                 f"{exc}") from exc
    experiments = _experiments(raw, where, path.parent, machine)
    analytic = next((e for e in experiments if isinstance(e, AnalyticExperiment)), None)
    if analytic is not None and len(experiments) > 1:
        raise StudySpecError(f"{where}: an analytic experiment runs alone")
    if analytic is not None:
        resolve, depth = (lambda name: analytic.parameter(name, where)), 2
    else:
        configs = machine.configs()
        resolve, depth = (lambda name: key_ref(name, configs, where)), 2 if "" in configs else 3
    varied, dists = _parameters(raw, "vary", resolve, where, depth, bounded=False)
    tuned, spaces = _parameters(raw, "tune", resolve, where, depth, bounded=True)
    both = {r.name for r in varied} & {r.name for r in tuned}
    if both:
        raise StudySpecError(f"{where}: {', '.join(sorted(both))} both varied and tuned")
    outputs = tuple(n for e in experiments for n in e.selected)
    tuning = None
    if study.method == "tuning":
        tuning = _tuning(raw, where, outputs)
        if not tuned:
            raise StudySpecError(f"{where}: method = 'tuning' needs [tune.SECTION] keys")
        robust = tuning.settings.robust_samples
        if design == "sobol" and robust and not _power_of_two(robust):
            raise StudySpecError(f"{where}: [tuning] robust_samples = {robust}: the Sobol' "
                                 "design needs a power of 2 (4, 8, 16, ...)")
        if bool(varied) != (robust > 0):
            raise StudySpecError(f"{where}: [tuning] robust_samples > 0 goes with [vary] "
                                 "(the tolerances the trials must hold over), and only then")
    else:
        for name in ("tune", "tuning"):
            if name in raw:
                raise StudySpecError(f"{where}: [{name}] belongs to method = 'tuning'")
        if not varied:
            raise StudySpecError(f"{where}: method = '{study.method}' needs [vary] keys")
    report = checked_section(ReportSection, _table(raw, "report", where), where, "report")
    if any(not 0.0 <= p <= 100.0 for p in report.percentiles):
        raise StudySpecError(f"{where}: [report] percentiles = {list(report.percentiles)} "
                             "must lie within 0 .. 100 %")
    spec = Study(where, study, machine, experiments, varied, dists, tuned, spaces, tuning,
                 report, _fingerprint(path, machine, experiments))
    _check_corners(spec)
    return spec
