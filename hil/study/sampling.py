"""Sample designs on the unit cube, and the parameter values they stand for.

Every design is a matrix u of shape (rows, D) in [0, 1); each parameter's distribution
maps its column to values (:meth:`~hil.study.distributions.Distribution.ppf`).  The
design is computed by the client before any task is sent, from the study's seed alone,
so the numbers do not depend on how many workers run it or in which order:

* ``monte_carlo``: row i is ``numpy.random.default_rng([seed, i]).random(D)``: it depends
  on the seed and i only, so a study with more samples keeps the first ones;
* ``sobol`` (tolerance): row i of the scrambled Sobol' sequence of ``scipy.stats.qmc``
  seeded with the seed (a power-of-2 count keeps its balance properties);
* ``saltelli`` (sensitivity, method sobol): SALib's Saltelli design for first-order and
  total indices, N (D + 2) rows, for each base row j the rows A_j, AB_j^1 .. AB_j^D,
  B_j;
* ``morris``: SALib's Morris trajectories, N (D + 1) rows on a grid of ``levels`` levels.
"""

import numpy as np
from SALib.sample import morris as morris_sample
from SALib.sample import sobol as saltelli_sample
from scipy.stats import qmc

from hil.study.distributions import Distribution


def unit_problem(names: tuple[str, ...]) -> dict:
    """The SALib problem of ``names`` on the unit cube."""
    return {"num_vars": len(names), "names": list(names), "bounds": [[0.0, 1.0]] * len(names)}


def monte_carlo(dim: int, n: int, seed: int) -> np.ndarray:
    """(n, dim): row i from its own generator seeded with (seed, i)."""
    return np.array([np.random.default_rng([seed, i]).random(dim) for i in range(n)]
                    ).reshape(n, dim)


def sobol_sequence(dim: int, n: int, seed: int) -> np.ndarray:
    """(n, dim): the first n points of the scrambled Sobol' sequence (seeded)."""
    return qmc.Sobol(dim, scramble=True, seed=seed).random(n)


def saltelli(names: tuple[str, ...], n: int, seed: int) -> np.ndarray:
    """(n (D + 2), D): Saltelli's design for first-order and total Sobol indices."""
    return saltelli_sample.sample(unit_problem(names), n, calc_second_order=False,
                                  scramble=True, seed=seed)


def morris(names: tuple[str, ...], n: int, levels: int, seed: int) -> np.ndarray:
    """(n (D + 1), D): Morris trajectories on a grid of ``levels`` levels."""
    return morris_sample.sample(unit_problem(names), n, num_levels=levels, seed=seed)


def design(kind: str, names: tuple[str, ...], n: int, seed: int, levels: int = 4) -> np.ndarray:
    """The unit-cube design ``kind`` (module docstring) for the parameters ``names``:
    "monte_carlo", "sobol" (a quasi-random sample), "saltelli" or "morris"."""
    dim = len(names)
    if kind == "monte_carlo":
        return monte_carlo(dim, n, seed)
    if kind == "sobol":
        return sobol_sequence(dim, n, seed)
    if kind == "saltelli":
        return saltelli(names, n, seed)
    if kind == "morris":
        return morris(names, n, levels, seed)
    raise ValueError(f"unknown design {kind!r}")


def to_values(u: np.ndarray, dists: tuple[Distribution, ...]) -> np.ndarray:
    """Parameter values (rows, D) in each key's unit for the unit-cube design ``u``."""
    return np.column_stack([d.ppf(u[:, j]) for j, d in enumerate(dists)]) if dists else (
        np.empty((u.shape[0], 0)))
