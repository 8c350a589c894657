"""Which parameters explain the spread: Sobol and Morris indices (SALib), rank correlations.

* **Sobol** (method sensitivity, design sobol): first-order S1 (the share of the output's
  variance that one parameter explains alone) and total ST (with its interactions) by
  SALib's estimators on Saltelli's design, with bootstrap confidence intervals (95 %).
  Indices do not change under a monotone map of an input, so they are computed on the
  unit-cube design and hold for the parameters' own distributions.
* **Morris** (design morris): mu* (the mean absolute elementary effect, in the output's
  unit per whole range of the parameter's distribution) and sigma (its spread:
  nonlinearity or interaction).
* **Rank correlation** (any study, tolerance included): Spearman's rho of every parameter
  with every output over the samples, a cheap first look.

Every sample of the design must have the output for Sobol and Morris; an output with
failed or NaN samples is reported as such instead of getting indices.
"""

from dataclasses import dataclass

import numpy as np
from SALib.analyze import morris as morris_analyze
from SALib.analyze import sobol as sobol_analyze
from scipy.stats import spearmanr

from hil.study.run import study_design
from hil.study.sampling import design, unit_problem
from hil.study.spec import Study
from hil.study.store import Results

BOOTSTRAP = 200


@dataclass(frozen=True)
class Indices:
    """One output's indices, one value per parameter (names in order).

    ``kind`` is "sobol" (first = S1, total = ST), "morris" (first = mu*, total = sigma)
    or "spearman" (first = rho, total unused, NaN); ``*_conf`` are 95 % half-widths
    (NaN where the method gives none).  ``missing`` counts samples without a value;
    ``constant``: the output has one value over the whole design.  Either way the
    indices are NaN: there is no spread to explain.
    """
    kind: str
    names: tuple[str, ...]
    first: np.ndarray
    first_conf: np.ndarray
    total: np.ndarray
    total_conf: np.ndarray
    missing: int = 0
    constant: bool = False

    @property
    def defined(self) -> bool:
        """The indices exist (every sample has a value, and they differ)."""
        return not self.missing and not self.constant

    def as_dict(self) -> dict:
        """JSON-ready."""
        keys = {"sobol": ("S1", "ST"), "morris": ("mu_star", "sigma"),
                "spearman": ("rho", "-")}[self.kind]
        return {"kind": self.kind, "missing": self.missing, "constant": self.constant,
                "parameters": {
            n: {keys[0]: _f(self.first[i]), f"{keys[0]}_conf": _f(self.first_conf[i]),
                keys[1]: _f(self.total[i]), f"{keys[1]}_conf": _f(self.total_conf[i])}
            for i, n in enumerate(self.names)}}


def _f(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def _undefined(kind: str, names: tuple[str, ...], missing: int) -> Indices:
    n = np.full(len(names), np.nan)
    return Indices(kind, names, n, n, n, n, missing, constant=not missing)


def _complete(study: Study, results: Results, output: str) -> tuple[np.ndarray | None, int]:
    """The output over the whole design in sample order; None (and how many samples
    miss) when some sample has no value or all have the same."""
    n = study_design(study).ids.size
    y = np.full(n, np.nan)
    y[results.ids[results.ids < n]] = results.outputs[output][results.ids < n]
    missing = int(np.sum(~np.isfinite(y)))
    return (None, missing) if missing or np.ptp(y) == 0.0 else (y, 0)


def sobol_indices(study: Study, results: Results, output: str) -> Indices:
    """First-order and total Sobol indices of ``output``."""
    names = tuple(r.name for r in study.varied)
    y, missing = _complete(study, results, output)
    if y is None:
        return _undefined("sobol", names, missing)
    si = sobol_analyze.analyze(unit_problem(names), y, calc_second_order=False,
                               num_resamples=BOOTSTRAP, seed=study.study.seed)
    return Indices("sobol", names, np.asarray(si["S1"]), np.asarray(si["S1_conf"]),
                   np.asarray(si["ST"]), np.asarray(si["ST_conf"]))


def morris_indices(study: Study, results: Results, output: str) -> Indices:
    """Morris mu* and sigma of ``output``."""
    names = tuple(r.name for r in study.varied)
    y, missing = _complete(study, results, output)
    if y is None:
        return _undefined("morris", names, missing)
    s = study.study
    x = design("morris", names, s.samples, s.seed, s.morris_levels)
    mi = morris_analyze.analyze(unit_problem(names), x, y, num_resamples=BOOTSTRAP,
                                num_levels=s.morris_levels, seed=s.seed)
    none = np.full(len(names), np.nan)
    return Indices("morris", names, np.asarray(mi["mu_star"]),
                   np.asarray(mi["mu_star_conf"]), np.asarray(mi["sigma"]), none)


def rank_correlations(study: Study, results: Results, output: str) -> Indices:
    """Spearman's rho of each varied parameter with ``output`` over the good samples."""
    names = tuple(r.name for r in study.varied)
    y = results.outputs[output]
    good = np.isfinite(y)
    none = np.full(len(names), np.nan)
    if good.sum() < 3 or np.ptp(y[good]) == 0.0:
        return Indices("spearman", names, none, none, none, none, int((~good).sum()),
                       constant=bool(good.sum() >= 3))
    rho = []
    for n in names:
        x = results.params[n][good]
        rho.append(spearmanr(x, y[good]).statistic if np.ptp(x) > 0.0 else np.nan)
    return Indices("spearman", names, np.asarray(rho, dtype=float), none, none, none,
                   int((~good).sum()))


def indices(study: Study, results: Results) -> dict[str, Indices]:
    """Output name -> its indices by the study's method (Sobol or Morris for a
    sensitivity study, rank correlations otherwise)."""
    s = study.study
    if s.method == "sensitivity":
        method = sobol_indices if s.design == "sobol" else morris_indices
    else:
        method = rank_correlations
    return {name: method(study, results, name) for name in study.outputs}
