"""The figures of a study, PNG files a person looks at (matplotlib, no screen needed).

* ``histograms.png``: every output over the distribution sample, its percentiles marked;
* ``curve_<i>.png``: experiment i's curve over the sample as percentile bands (the
  outermost pair of the study's percentiles, the next pair, the median): the step
  response, the Bode magnitude, the following error, or the circle's radial deviation
  (polar, as a ballbar plot);
* ``sensitivity.png``: the indices per output as bars (S1 and ST with their 95 %
  intervals, Morris mu* and sigma, or Spearman's rho);
* ``pareto.png``: a tuning study's trials in the plane of its first two objectives (or
  the objective against the first constrained output): feasible and not, the feasible
  non-dominated ones joined, the chosen best marked.

Values are drawn in the units a person reads them in (:func:`shown`: seconds as ms, um as
µm), with plain tick labels: no offset ("+1.22e-1") that would hide them.
"""

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from hil.study.outputs import OUTPUTS
from hil.study.sensitivity import Indices
from hil.study.spec import Study
from hil.study.store import Results

DPI = 110


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    return path


#: a unit -> (factor from it, the unit drawn) where another reads better: a study's times
#: are tens of ms, and "0.12202 s" is read digit by digit
_DRAWN = {"s": (1e3, "ms"), "um": (1.0, "µm")}


def shown(unit: str) -> tuple[float, str]:
    """(factor, unit) that turn values in ``unit`` into the unit they are drawn in."""
    return _DRAWN.get(unit, (1.0, unit))


def _output(name: str) -> tuple[float, str]:
    """(factor, axis label) of an output: its name (as the report's tables give it) with
    the unit drawn."""
    if name not in OUTPUTS:
        return 1.0, name
    factor, unit = shown(OUTPUTS[name].unit)
    return factor, f"{name} ({unit})" if factor == 1.0 else f"{name}, shown in {unit}"


def _plain(ax: Axes, axis: str = "both") -> None:
    """Tick labels without an offset or a shared power of ten."""
    ax.ticklabel_format(axis=axis, useOffset=False, style="plain")


def histograms(study: Study, results: Results, rows: np.ndarray, path: Path) -> Path:
    """Histograms of every output over the samples ``rows`` (mask)."""
    names = study.outputs
    cols = min(3, len(names))
    nrows = -(-len(names) // cols)
    fig = Figure(figsize=(4.6 * cols, 3.3 * nrows + 0.3))
    fig.suptitle(f"{study.study.name}\n{int(rows.sum())} machines; dotted: p"
                 + ", p".join(f"{p:g}" for p in study.report.percentiles))
    for k, name in enumerate(names):
        ax = fig.add_subplot(nrows, cols, k + 1)
        factor, label = _output(name)
        y = results.outputs[name][rows] * factor
        y = y[np.isfinite(y)]
        if y.size:
            ax.hist(y, bins=min(40, max(8, y.size // 8)), color="tab:blue", alpha=0.8)
            for p in study.report.percentiles:
                ax.axvline(np.percentile(y, p), color="k", ls=":", lw=0.9)
        ax.set(xlabel=label, ylabel="machines")
        ax.xaxis.set_major_locator(MaxNLocator(nbins=4))  # room for long plain labels
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        _plain(ax)
        ax.grid(alpha=0.3)
    return _save(fig, path)


def _band_pairs(percentiles) -> list[tuple[float, float]]:
    p = sorted(percentiles)
    return [(p[i], p[-1 - i]) for i in range(len(p) // 2)]


def _bands(ax, x, values, percentiles, label: str) -> None:
    """Percentile bands of ``values`` (n, grid) over ``x`` and the median."""
    for (lo, hi), alpha in zip(_band_pairs(percentiles), (0.2, 0.4)):
        ax.fill_between(x, np.nanpercentile(values, lo, axis=0),
                        np.nanpercentile(values, hi, axis=0), color="tab:blue", alpha=alpha,
                        lw=0, label=f"p{lo:g} .. p{hi:g}")
    ax.plot(x, np.nanmedian(values, axis=0), color="tab:blue", lw=1.2, label=label)


def curve_bands(study: Study, curve_info: dict, values: np.ndarray, path: Path) -> Path:
    """Percentile bands of one experiment's curves ``values`` (n, grid): over the grid
    and, below, as the difference from the median curve, where a spread too small to see
    on the curve shows; a polar plot for a curve over the angle (the circle)."""
    grid_factor, grid_unit = shown(curve_info["grid_unit"])
    grid = np.asarray(curve_info["grid"]) * grid_factor
    factor, unit = shown(curve_info["unit"])
    good = values[np.any(np.isfinite(values), axis=1)] * factor
    title = f"{study.study.name}\n{curve_info['name']}, {good.shape[0]} machines"
    if curve_info["grid_unit"] == "deg":
        fig = Figure(figsize=(7.0, 6.4))
        ax = fig.add_subplot(1, 1, 1, projection="polar")
        _bands(ax, np.radians(grid), good, study.report.percentiles, "median")
        ax.set_title(f"{title}\nradial deviation ({unit}) against the angle", fontsize=9)
        ax.legend(fontsize=8, loc="lower left", bbox_to_anchor=(-0.1, -0.1))
        return _save(fig, path)
    fig = Figure(figsize=(7.0, 6.4))
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=(3, 2))
    _bands(top, grid, good, study.report.percentiles, "median")
    _bands(bottom, grid, good - np.nanmedian(good, axis=0), study.report.percentiles,
           "median")
    top.set(ylabel=f"{curve_info['name']} ({unit})", title=title)
    bottom.set(xlabel=f"{curve_info['grid_name']} ({grid_unit})",
               ylabel=f"minus the median ({unit})")
    for ax in (top, bottom):
        if curve_info["log_grid"]:
            ax.set_xscale("log")
        _plain(ax, "y" if curve_info["log_grid"] else "both")
        ax.grid(alpha=0.3, which="both")
    top.legend(fontsize=8, loc="best")
    return _save(fig, path)


def sensitivity_bars(study: Study, found: dict[str, Indices], spread: dict[str, str],
                     path: Path) -> Path:
    """Bar charts of the indices, one panel per output with a defined spread (its
    percentile range, ``spread``, in the title)."""
    outputs = [o for o, ind in found.items() if ind.defined]
    cols = min(2, max(1, len(outputs)))
    nrows = max(1, -(-len(outputs) // cols))
    fig = Figure(figsize=(6.4 * cols, 0.9 + 0.42 * len(study.varied) * nrows + 0.8 * nrows))
    fig.suptitle(study.study.name)
    for k, output in enumerate(outputs):
        ind = found[output]
        ax = fig.add_subplot(nrows, cols, k + 1)
        pos = np.arange(len(ind.names))
        # Morris's mu* and sigma are in the output's unit, the others have none
        factor, unit = shown(OUTPUTS[output].unit) if ind.kind == "morris" else (1.0, "")
        conf = [np.nan_to_num(c) * factor for c in (ind.first_conf, ind.total_conf)]
        if ind.kind == "spearman":
            ax.barh(pos, ind.first, color="tab:blue", label="Spearman rho")
        else:
            first, second = ("S1", "ST") if ind.kind == "sobol" else ("mu*", "sigma")
            ax.barh(pos - 0.2, ind.first * factor, 0.4, xerr=conf[0], label=first,
                    color="tab:blue")
            ax.barh(pos + 0.2, ind.total * factor, 0.4, xerr=conf[1], label=second,
                    color="tab:orange")
        ax.set_yticks(pos, ind.names, fontsize=8)
        ax.invert_yaxis()
        _plain(ax, "x")
        xlabel = {"sobol": "share of the variance",
                  "morris": f"effect ({unit} over the parameter's range)",
                  "spearman": "rank correlation"}[ind.kind]
        ax.set(title=f"{output}\n{spread.get(output, '')}", xlabel=xlabel)
        ax.grid(alpha=0.3, axis="x")
        ax.legend(fontsize=8)
    return _save(fig, path)


def pareto(trials: list[dict], axes: tuple[str, str], signs: tuple[float, float],
           best: dict | None, path: Path) -> Path:
    """Trials (dicts with ``values``: output -> aggregated value, and ``feasible``) in the
    plane of ``axes``; the feasible non-dominated ones joined (``signs``: +1 where smaller
    is better on that axis, -1 where larger is), the best marked."""
    fig = Figure(figsize=(6.4, 4.8))
    ax = fig.add_subplot(1, 1, 1)
    (fx, xlabel), (fy, ylabel) = _output(axes[0]), _output(axes[1])
    scale = np.array([fx, fy])
    pts = np.array([[t["values"].get(a, np.nan) for a in axes] for t in trials],
                   dtype=float) * scale
    feasible = np.array([t["feasible"] for t in trials], dtype=bool)
    ax.scatter(pts[~feasible, 0], pts[~feasible, 1], s=14, c="tab:red", marker="x",
               label="constraint violated")
    ax.scatter(pts[feasible, 0], pts[feasible, 1], s=16, c="tab:blue", label="feasible")
    sign = np.asarray(signs)
    front = _front(pts[feasible] * sign) * sign if feasible.any() else np.empty((0, 2))
    if front.size:
        order = np.argsort(front[:, 0])
        ax.plot(front[order, 0], front[order, 1], "k-", lw=1.0, label="Pareto front")
    if best is not None:
        ax.plot(best["values"][axes[0]] * fx, best["values"][axes[1]] * fy, "o", ms=11,
                mfc="none", mec="tab:green", mew=2, label="best")
    ax.set(xlabel=xlabel, ylabel=ylabel, title=f"{len(trials)} trials")
    _plain(ax)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def _front(pts: np.ndarray) -> np.ndarray:
    """The non-dominated rows of ``pts`` (both columns minimised)."""
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    keep = [i for i, p in enumerate(pts)
            if not np.any(np.all(pts <= p, axis=1) & np.any(pts < p, axis=1))]
    return pts[keep]
