"""What an experiment is, what one compared figure (a row) says, the registry of
experiments, and running them all.

An experiment is a function ``(out_dir: Path | None) -> list[Result]`` registered with
:func:`experiment`.  It runs the plant and compares each figure with a reference; when
``out_dir`` is given it writes its plot there.  Tests call the same functions.

Every row has a *kind*, which says what its agreement is worth:

- ``verification``: the reference is the model's own analytic formula, a second solver,
  or the model's own configuration.  A "paper" value that the machine file copied is a
  configuration value: the row then verifies the configuration and reproduces nothing.
  A verification that fails is a bug (``hil validate --strict`` exits 1).
- ``reproduction``: the reference is a number or curve a seed reports (``source`` names
  the seed, section, figure or table, page and the words), and a machine-file value the
  row depends on was, or may have been, chosen with that number in view.
- ``prediction``: the reference is a number a seed reports that no machine-file value the
  row depends on was chosen from; ``note`` says how we know.

A row either agrees with its reference within its tolerance (``ok``) or disagrees; a
disagreement is a finding, reported with its reason in ``note``, never passed off as ok.
Tolerances of seed numbers come from their printed precision: half a unit of the last
printed digit, one unit where the seed says "approximately", "around" or "~".
"""

import enum
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

from plant.errors import PlantError

#: the repository's machine files and part programs, which the experiments run
REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"
PROGRAMS = REPO / "programs"


class Kind(str, enum.Enum):
    """What a row's reference is (see the module docstring)."""
    VERIFICATION = "verification"
    REPRODUCTION = "reproduction"
    PREDICTION = "prediction"


VERIFICATION, REPRODUCTION, PREDICTION = Kind.VERIFICATION, Kind.REPRODUCTION, Kind.PREDICTION


@dataclass(frozen=True)
class SeedRef:
    """Where in a seed paper a number comes from.

    Attributes:
        seed: the seed paper, "000".."004" (the files in ``../shared/seeds/``).
        where: section, figure, table or equation, e.g. "§4, Fig. 5".
        page: the page as the seed's text marks it (seed 002's PDF pages), None where the
            seed's text carries no page marks.
        quote: the seed's words that state the number, verbatim from its text.
    """
    seed: str
    where: str
    page: int | None
    quote: str

    def __str__(self) -> str:
        page = f", p. {self.page}" if self.page is not None else ""
        return f'seed {self.seed} {self.where}{page}: "{self.quote}"'


@dataclass(frozen=True)
class Result:
    """One compared figure.

    Attributes:
        experiment: short name, e.g. "current step 0.84 A: rise time".
        paper: the reference value (the seed's, or the formula's, solver's or
            configuration's: ``reference`` says which).
        model: the model's value.
        unit: unit of both values.
        ok: the model agrees with the reference within ``tolerance``.
        reference: where ``paper`` comes from, in words.
        tolerance: the acceptance rule in words, with where it comes from.
        kind: verification, reproduction or prediction.
        source: the seed passage of a reproduction or prediction (or of a configuration
            value a verification checks).
        note: why a disagreement disagrees; for a prediction, how we know the machine
            file was not tuned to the number.
        uncertainty: ± of ``paper`` in ``unit`` (the seed's printed precision), None where
            the reference is exact or not a number.
    """
    experiment: str
    paper: float | str
    model: float | str
    unit: str
    ok: bool
    reference: str
    tolerance: str
    kind: Kind
    source: SeedRef | None = None
    note: str = ""
    uncertainty: float | None = None

    def __post_init__(self):
        # plain Python values (NumPy scalars do not serialise); notes are joined sentences
        for name in ("paper", "model", "uncertainty"):
            value = getattr(self, name)
            if hasattr(value, "item"):
                object.__setattr__(self, name, value.item())
        object.__setattr__(self, "ok", bool(self.ok))
        object.__setattr__(self, "note", self.note.strip())

    @property
    def verdict(self) -> str:
        """"agrees" or "disagrees"."""
        return "agrees" if self.ok else "disagrees"

    def as_dict(self) -> dict:
        """Plain-Python fields with the verdict, ready for JSON."""
        out = asdict(self)
        out["kind"] = self.kind.value
        out["verdict"] = self.verdict
        return out


@dataclass(frozen=True)
class Experiment:
    """A registered experiment: its name, the seed it comes from and its function."""
    name: str
    seed: str
    func: Callable[[Path | None], list[Result]]


REGISTRY: dict[str, Experiment] = {}


def experiment(name: str, seed: str):
    """Register ``func`` as experiment ``name`` from seed paper ``seed`` ("000".."004")."""
    def register(func):
        if name in REGISTRY:
            raise ValueError(f"experiment {name!r} registered twice")
        REGISTRY[name] = Experiment(name, seed, func)
        return func
    return register


def within(model: float, ref: float, rel: float = 0.0, abs_: float = 0.0) -> bool:
    """True when |model - ref| <= max(rel * |ref|, abs_)."""
    return bool(abs(model - ref) <= max(rel * abs(ref), abs_))


def failing_verifications(rows: list[Result]) -> list[Result]:
    """The verification rows that disagree: bugs, where reproductions and predictions
    that disagree are findings."""
    return [r for r in rows if r.kind is VERIFICATION and not r.ok]


def run_all(out_dir: Path | None, only: list[str] | None = None,
            progress: Callable[[str, int, int], AbstractContextManager] | None = None
            ) -> list[Result]:
    """Run every registered experiment (or those named in ``only``), in registry order;
    each inside ``progress(name, its place from 1, how many)`` when given (the command's
    progress line).

    A plant error inside an experiment becomes one failed verification row (a model that
    cannot run its own experiment is a bug) rather than stopping the others.
    """
    import hil.validate.experiments  # noqa: F401  (registers the experiments)

    names = only or list(REGISTRY)
    unknown = [n for n in names if n not in REGISTRY]
    if unknown:
        raise KeyError(f"unknown experiment(s): {', '.join(unknown)}; "
                       f"known: {', '.join(REGISTRY)}")
    rows: list[Result] = []
    for i, name in enumerate(names, 1):
        exp = REGISTRY[name]
        with nullcontext() if progress is None else progress(name, i, len(names)):
            try:
                rows.extend(exp.func(out_dir))
            except PlantError as exc:
                rows.append(Result(name, "-", f"error: {exc}", "-", False, f"seed {exp.seed}",
                                   "-", VERIFICATION,
                                   note=f"the experiment did not run: {exc}"))
    return rows
