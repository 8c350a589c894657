"""How a parameter varies: one small table per key in a study file.

Every form maps a number u in [0, 1) (one coordinate of a sample design,
:mod:`hil.study.sampling`) to a value in the key's unit through its inverse cumulative
distribution, so every design, Monte Carlo or quasi-random, and every sensitivity method
works on the same unit cube::

    mass_kg = { tolerance_pct = 10 }            # uniform on nominal * (1 +- 10 %)
    nut_stiffness_n_per_m = { range_pct = [-20, 0] }   # uniform on nominal * (0.8 .. 1.0)
    inertia_kgm2 = { uniform = [0.0014, 0.0016] }      # uniform, in the key's unit
    coulomb_n = { normal = [120.0, 12.0] }             # mean, standard deviation
    torque_constant_nm_per_a = { normal_pct = 3.3 }    # mean nominal, sd 3.3 % of it
    segments = { values = [5, 7, 9] }                  # equally likely values

A normal distribution is truncated at ``truncate_sd`` standard deviations (default 3, the
usual reading of a stated tolerance as three sigma) so that every value is finite and the
range check is exact.  Tuning takes the bounded forms only (``uniform``, ``range_pct``,
``tolerance_pct``, ``values``), with ``log = true`` for a log-uniform search.
"""

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

from hil.study.keys import KeyRef, StudySpecError

FORMS = ("tolerance_pct", "range_pct", "uniform", "normal", "normal_pct", "values")
BOUNDED_FORMS = ("tolerance_pct", "range_pct", "uniform", "values")
DEFAULT_TRUNCATE_SD = 3.0


@dataclass(frozen=True)
class Distribution:
    """One parameter's distribution.

    Attributes:
        kind: "uniform", "normal" or "values".
        low, high: uniform bounds (normal: mean and standard deviation), in the key's unit.
        values: the equally likely values of kind "values".
        truncate_sd: a normal's truncation, in standard deviations.
        log: uniform in log(value) (tuning search spaces).
    """
    kind: str
    low: float = 0.0
    high: float = 0.0
    values: tuple[float, ...] = ()
    truncate_sd: float = DEFAULT_TRUNCATE_SD
    log: bool = False

    def support(self) -> tuple[float, float]:
        """(smallest, largest) value it gives."""
        if self.kind == "values":
            return min(self.values), max(self.values)
        if self.kind == "normal":
            return (self.low - self.truncate_sd * self.high,
                    self.low + self.truncate_sd * self.high)
        return self.low, self.high

    def ppf(self, u: np.ndarray) -> np.ndarray:
        """Values for unit-cube coordinates ``u`` (any shape, in [0, 1])."""
        u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
        if self.kind == "values":
            index = np.minimum((u * len(self.values)).astype(int), len(self.values) - 1)
            return np.asarray(self.values)[index]
        if self.kind == "normal":
            tail = ndtr(-self.truncate_sd)
            return self.low + self.high * ndtri(tail + u * (1.0 - 2.0 * tail))
        if self.log:
            return np.exp(np.log(self.low) + u * (np.log(self.high) - np.log(self.low)))
        return self.low + u * (self.high - self.low)

    def describe(self, unit: str) -> str:
        """In words, for reports: 'uniform 315 .. 385 kg'."""
        if self.kind == "values":
            return "one of " + ", ".join(f"{v:g}" for v in self.values) + f" {unit}"
        if self.kind == "normal":
            return (f"normal {self.low:g} ± {self.high:g} {unit} (1 sd, truncated at "
                    f"{self.truncate_sd:g} sd)")
        return f"{'log-' if self.log else ''}uniform {self.low:g} .. {self.high:g} {unit}"


def _number(table: dict, form: str, label: str) -> float:
    value = table[form]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise StudySpecError(f"{label}: {form} = {value!r} must be a finite number")
    return float(value)


def _pair(table: dict, form: str, label: str) -> tuple[float, float]:
    value = table[form]
    if (not isinstance(value, list) or len(value) != 2 or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
            for v in value)):
        raise StudySpecError(f"{label}: {form} = {value!r} must be a list of two finite "
                             "numbers")
    return float(value[0]), float(value[1])


def _need_nominal(ref: KeyRef, form: str, label: str) -> float:
    if ref.nominal is None:
        raise StudySpecError(f"{label}: {form} needs the key's value in the machine file, "
                             f"and [{ref.section}] {ref.key} has none there (derived); give "
                             f"uniform = [low, high] in {ref.unit}")
    return ref.nominal


def _build(table: dict, form: str, ref: KeyRef, label: str) -> Distribution:
    if form == "values":
        values = table["values"]
        if (not isinstance(values, list) or not values or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) for v in values)):
            raise StudySpecError(f"{label}: values = {values!r} must be a non-empty list of "
                                 "numbers")
        if ref.integer and any(not isinstance(v, int) for v in values):
            raise StudySpecError(f"{label}: [{ref.section}] {ref.key} takes whole numbers")
        return Distribution("values", values=tuple(float(v) for v in values))
    if ref.integer:
        raise StudySpecError(f"{label}: [{ref.section}] {ref.key} takes whole numbers: vary "
                             "it with values = [...]")
    truncate = DEFAULT_TRUNCATE_SD
    if "truncate_sd" in table:
        truncate = _number(table, "truncate_sd", label)
        if not truncate > 0.0 or form not in ("normal", "normal_pct"):
            raise StudySpecError(f"{label}: truncate_sd = {truncate:g} belongs to a normal "
                                 "distribution and must be > 0")
    if form == "tolerance_pct":
        pct = _number(table, form, label)
        if not pct > 0.0:
            raise StudySpecError(f"{label}: tolerance_pct = {pct:g} must be > 0 %")
        nominal = _need_nominal(ref, form, label)
        low, high = sorted((nominal * (1.0 - pct / 100.0), nominal * (1.0 + pct / 100.0)))
    elif form == "range_pct":
        lo_pct, hi_pct = _pair(table, form, label)
        nominal = _need_nominal(ref, form, label)
        low, high = sorted((nominal * (1.0 + lo_pct / 100.0), nominal * (1.0 + hi_pct / 100.0)))
    elif form == "uniform":
        low, high = _pair(table, form, label)
    elif form == "normal":
        mean, sd = _pair(table, form, label)
        if not sd > 0.0:
            raise StudySpecError(f"{label}: normal = [{mean:g}, {sd:g}]: the standard "
                                 f"deviation must be > 0 {ref.unit}")
        return Distribution("normal", mean, sd, truncate_sd=truncate)
    else:  # normal_pct
        pct = _number(table, form, label)
        nominal = _need_nominal(ref, form, label)
        if not pct > 0.0 or nominal == 0.0:
            raise StudySpecError(f"{label}: normal_pct = {pct:g} needs pct > 0 and a "
                                 f"non-zero value in the machine file (it is {nominal:g})")
        return Distribution("normal", nominal, abs(nominal) * pct / 100.0, truncate_sd=truncate)
    if not high > low:
        raise StudySpecError(f"{label}: {form} gives the empty range {low:g} .. {high:g} "
                             f"{ref.unit}")
    return Distribution("uniform", low, high)


def parse_distribution(table, ref: KeyRef, where: str, bounded: bool = False) -> Distribution:
    """Read one key's table (module docstring), check it against the key's physical range
    and return it.  ``bounded``: a tuning search space (bounded forms and ``log``).

    Raises:
        StudySpecError: naming ``where`` (the study file), the parameter, the value and
            the key's unit and range.
    """
    label = f"{where}: parameter '{ref.name}'"
    if not isinstance(table, dict):
        raise StudySpecError(f"{label}: expected a table such as {{ tolerance_pct = 10 }}, "
                             f"got {table!r}")
    allowed = BOUNDED_FORMS if bounded else FORMS
    forms = [k for k in table if k in allowed]
    extra = [k for k in table if k not in allowed and k not in ("truncate_sd", "log")]
    if extra or len(forms) != 1:
        raise StudySpecError(f"{label}: give exactly one of {', '.join(allowed)}"
                             + (f" (unknown: {', '.join(extra)})" if extra else ""))
    log = table.get("log", False)
    if not isinstance(log, bool) or (log and not bounded):
        raise StudySpecError(f"{label}: log = {log!r}: true or false, for tuning only")
    dist = _build(table, forms[0], ref, label)
    if log:
        if dist.kind != "uniform" or not dist.low > 0.0:
            raise StudySpecError(f"{label}: log = true needs a uniform range above 0 "
                                 f"{ref.unit}")
        dist = Distribution("uniform", dist.low, dist.high, log=True)
    low, high = dist.support()
    for value in (low, high):
        if not ref.range.contains(value):
            raise StudySpecError(
                f"{label}: {dist.describe(ref.unit)} reaches {value:g} {ref.unit}, outside "
                f"the physical range of [{ref.section}] {ref.key}: "
                f"{ref.range.describe(ref.unit)}")
    return dist
