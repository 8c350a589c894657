"""Analytic test functions run through the study pipeline in place of a simulation.

They are pipeline checks, not physics: the same spec parsing, sampling, Dask tasks,
Parquet store, SALib analysis and Optuna tuning run on a function whose answer is known,
so the tests can compare with it exactly.

* ``ishigami``: y = sin x1 + a sin^2 x2 + b x3^4 sin x1, x_i uniform on [-pi, pi]
  (Ishigami and Homma 1990), a = 7, b = 0.1: first-order Sobol indices 0.3139, 0.4424, 0,
  total indices 0.5576, 0.4424, 0.2437 (:func:`ishigami_indices`, from the closed-form
  variances).
* ``constrained_quadratic``: y = (x1 - 1 - x3)^2 + (x2 - 2)^2 and g = x1 + x2 on
  [-5, 5]^3 (x3 = 0 unless given): with x3 = 0 and g <= 2 the optimum is (0.5, 1.5),
  y = 0.5 (the projection of (1, 2) onto the line); with x3 a tolerance and the worst
  case minimised, x1 = 1 + the middle of x3's values, y = (half their span)^2.

* ``linear``: y = x1 + 2 x2 + 0 x3 on [-5, 5]^3: every elementary effect of x_i is its
  coefficient, so Morris' mu* over a parameter's whole range is the coefficient times
  that range's width, and sigma is 0.

Their parameters are named ``analytic.x1`` ... in the study file's ``[vary.analytic]`` or
``[tune.analytic]``, checked against the function's domain.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.study.experiments import Experiment, Measurement
from hil.study.keys import KeyRef, Range, StudySpecError
from hil.study.machine import MachineSource
from plant.machines import MachineSet
from plant.schema import key

ISHIGAMI_A = 7.0
ISHIGAMI_B = 0.1
#: function -> (its inputs, their domain, its outputs); an input not in the study is 0
FUNCTIONS = {
    "ishigami": (("x1", "x2", "x3"), Range(-math.pi, False, math.pi), ("y",)),
    "constrained_quadratic": (("x1", "x2", "x3"), Range(-5.0, False, 5.0), ("y", "g")),
    "linear": (("x1", "x2", "x3"), Range(-5.0, False, 5.0), ("y",)),
}
LINEAR_COEFFICIENTS = (1.0, 2.0, 0.0)


@dataclass(frozen=True, kw_only=True)
class AnalyticOptions:
    """``[experiment] kind = "analytic"``."""
    kind: str = key("-", "The experiment.", choices=("analytic",))
    function: str = key("-", "The test function.", choices=tuple(FUNCTIONS))


def ishigami(x1: float, x2: float, x3: float) -> float:
    """The Ishigami function with a = 7, b = 0.1."""
    return math.sin(x1) + ISHIGAMI_A * math.sin(x2) ** 2 + ISHIGAMI_B * x3 ** 4 * math.sin(x1)


def ishigami_indices() -> tuple[np.ndarray, np.ndarray]:
    """(first-order, total) Sobol indices of :func:`ishigami` for x uniform on [-pi, pi]^3,
    from its closed-form partial variances."""
    a, b, pi4 = ISHIGAMI_A, ISHIGAMI_B, math.pi ** 4
    v1 = 0.5 * (1.0 + b * pi4 / 5.0) ** 2
    v2 = a * a / 8.0
    v13 = b * b * pi4 * pi4 * (1.0 / 18.0 - 1.0 / 50.0)
    total = v1 + v2 + v13
    first = np.array([v1, v2, 0.0]) / total
    return first, np.array([v1 + v13, v2, v13]) / total


class AnalyticExperiment(Experiment):
    """One of :data:`FUNCTIONS` on the sample's parameters."""
    kind = "analytic"
    options = AnalyticOptions
    outputs = ("y", "g")
    needs_machine = False

    @classmethod
    def default_outputs(cls, opts) -> tuple[str, ...]:
        return FUNCTIONS[opts.function][2]

    def check(self, study_dir: Path, machine: MachineSource | None) -> None:
        inputs, _, given = FUNCTIONS[self.opts.function]
        self.inputs = inputs
        for name in self.selected:
            if name not in given:
                raise StudySpecError(f"{self.where}: [experiment] function = "
                                     f"'{self.opts.function}' gives {', '.join(given)}, not "
                                     f"'{name}'")

    def parameter(self, name: str, where: str) -> KeyRef:
        """The KeyRef of ``analytic.<input>``; StudySpecError for other names."""
        inputs, domain, _ = FUNCTIONS[self.opts.function]
        section, _, arg = name.partition(".")
        if section != "analytic" or arg not in inputs:
            raise StudySpecError(f"{where}: parameter '{name}': function "
                                 f"'{self.opts.function}' takes analytic."
                                 + ", analytic.".join(inputs))
        return KeyRef(name, "", "analytic", arg, "1", domain, False, None)

    def run(self, machine: MachineSet | None, values: dict) -> Measurement:
        x = [values.get(f"analytic.{name}", 0.0) for name in self.inputs]
        if self.opts.function == "ishigami":
            out = {"y": ishigami(*x)}
        elif self.opts.function == "linear":
            out = {"y": sum(c * v for c, v in zip(LINEAR_COEFFICIENTS, x))}
        else:
            out = {"y": (x[0] - 1.0 - x[2]) ** 2 + (x[1] - 2.0) ** 2, "g": x[0] + x[1]}
        return Measurement({name: out[name] for name in self.selected}, None)
