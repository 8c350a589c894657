"""What an experiment is, the registry of them, and running them all.

An experiment is a function ``(out_dir: Path | None) -> list[Result]``
registered with :func:`experiment`.  It runs the plant, compares each
figure with the paper's (or with an independent reference where the paper
gives none: an analytic result, a linearisation, a second solver; the
``reference`` field says which) and, when ``out_dir`` is given, writes its
plot there.  Tests call the same functions and assert ``ok``.
"""

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from plant.errors import PlantError

#: the repository's machine files and part programs, which the experiments run
REPO = Path(__file__).resolve().parents[2]
CONFIGS = REPO / "configs"
PROGRAMS = REPO / "programs"


@dataclass(frozen=True)
class Result:
    """One compared figure.

    Attributes:
        experiment: short name, e.g. "current step 0.84 A: rise time".
        paper: the paper's (or reference's) value.
        model: the model's value.
        unit: unit of both values.
        ok: whether the model meets the stated tolerance.
        reference: where ``paper`` comes from (e.g. "seed 002 Fig. 9",
            "analytic: continuous rod", "solve_ivp").
        tolerance: the acceptance rule in words (e.g. "±5 %").
    """
    experiment: str
    paper: float | str
    model: float | str
    unit: str
    ok: bool
    reference: str
    tolerance: str

    def as_dict(self) -> dict:
        """Plain-Python fields (NumPy scalars converted), ready for JSON."""
        return {k: (v.item() if hasattr(v, "item") else v) for k, v in asdict(self).items()}


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


def run_all(out_dir: Path | None, only: list[str] | None = None,
            progress: Callable[[str, float], None] | None = None) -> list[Result]:
    """Run every registered experiment (or those named in ``only``), in registry order.

    A plant error inside an experiment becomes one failed row rather than
    stopping the others.
    """
    import hil.validate.experiments  # noqa: F401  (registers the experiments)

    names = only or list(REGISTRY)
    unknown = [n for n in names if n not in REGISTRY]
    if unknown:
        raise KeyError(f"unknown experiment(s): {', '.join(unknown)}; "
                       f"known: {', '.join(REGISTRY)}")
    rows: list[Result] = []
    for name in names:
        exp = REGISTRY[name]
        t0 = time.perf_counter()
        try:
            rows.extend(exp.func(out_dir))
        except PlantError as exc:
            rows.append(Result(name, "-", f"error: {exc}", "-", False, f"seed {exp.seed}", "-"))
        if progress is not None:
            progress(name, time.perf_counter() - t0)
    return rows
