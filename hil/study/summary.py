"""The numbers of a finished study: percentiles of every output, the indices, the run.

Percentiles are taken over the samples that are a draw of the parameters'
distributions: every sample of a tolerance study; the A and B rows of Saltelli's design
in a Sobol sensitivity study (its mixed rows are not an independent sample); none of a
Morris design (a grid).  ``summary.json`` holds everything; ``report.md`` the tables a
person reads, beside the figures of :mod:`hil.study.report`.
"""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.study import report
from hil.study.outputs import OUTPUTS
from hil.study.sensitivity import Indices, indices
from hil.study.spec import Study
from hil.study.store import Results


@dataclass(frozen=True)
class OutputStats:
    """One output over the distribution sample: count of values, NaN count, mean, sd,
    min, max and the study's percentiles (percent -> value), in the output's unit."""
    name: str
    unit: str
    n: int
    missing: int
    mean: float
    sd: float
    low: float
    high: float
    percentiles: dict

    def as_dict(self) -> dict:
        """JSON-ready."""
        return {"unit": self.unit, "n": self.n, "missing": self.missing, "mean": self.mean,
                "sd": self.sd, "min": self.low, "max": self.high,
                "percentiles": {f"p{p:g}": v for p, v in self.percentiles.items()}}


def distribution_rows(study: Study, results: Results) -> np.ndarray | None:
    """Mask (n,) of the stored samples that draw the distributions; None for Morris."""
    s = study.study
    if s.method == "sensitivity":
        if s.design == "morris":
            return None
        width = len(study.varied) + 2
        return (results.ids % width == 0) | (results.ids % width == width - 1)
    return np.ones(results.ids.size, dtype=bool)


def output_stats(study: Study, results: Results) -> list[OutputStats]:
    """Every output's statistics over the distribution sample (empty for Morris)."""
    rows = distribution_rows(study, results)
    if rows is None:
        return []
    stats = []
    for name in study.outputs:
        y = results.outputs[name][rows]
        good = y[np.isfinite(y)]
        nan = float("nan")
        pct = {p: (float(np.percentile(good, p)) if good.size else nan)
               for p in study.report.percentiles}
        stats.append(OutputStats(
            name, OUTPUTS[name].unit, int(good.size), int(y.size - good.size),
            float(good.mean()) if good.size else nan, float(good.std(ddof=1))
            if good.size > 1 else nan, float(good.min()) if good.size else nan,
            float(good.max()) if good.size else nan, pct))
    return stats


def failures(results: Results, limit: int = 5) -> list[dict]:
    """The first ``limit`` failed samples with their reasons."""
    return [{"sample_id": int(i), "status": s} for i, s in zip(results.ids, results.status)
            if s != "ok"][:limit]


def _fmt(x) -> str:
    return "–" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.4g}"


def stats_table(stats: list[OutputStats], percentiles) -> list[str]:
    """Markdown table of the output statistics."""
    head = ["output", "unit", "n"] + [f"p{p:g}" for p in percentiles] + ["mean", "sd",
                                                                           "min", "max"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in stats:
        cells = [s.name, s.unit, f"{s.n}" + (f" ({s.missing} NaN)" if s.missing else "")]
        cells += [_fmt(s.percentiles[p]) for p in percentiles]
        cells += [_fmt(v) for v in (s.mean, s.sd, s.low, s.high)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def indices_table(found: dict[str, Indices]) -> list[str]:
    """Markdown table: one row per output and parameter."""
    if not found:
        return []
    kind = next(iter(found.values())).kind
    cols = {"sobol": ("S1 ± 95 %", "ST ± 95 %"), "morris": ("mu* ± 95 %", "sigma"),
            "spearman": ("Spearman rho",)}[kind]
    lines = ["| output | parameter | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]

    def cell(value, conf):
        return _fmt(value) + (f" ± {_fmt(conf)}" if np.isfinite(conf) else "")

    for output, ind in found.items():
        if not ind.defined:
            why = "the same value on every sample" if ind.constant else (
                f"{ind.missing} samples without a value")
            lines.append(f"| {output} | – | {why} |" + " |" * (len(cols) - 1))
            continue
        for i, name in enumerate(ind.names):
            cells = [cell(ind.first[i], ind.first_conf[i]),
                     cell(ind.total[i], ind.total_conf[i])][:len(cols)]
            lines.append(f"| {output} | {name} | " + " | ".join(cells) + " |")
    return lines


def write_summary(out: Path, study: Study, summary: dict, markdown: list[str]) -> None:
    """``summary.json`` and ``report.md`` in ``out``."""
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    (out / "report.md").write_text("\n".join(markdown) + "\n")


def _tuning_part(study: Study, tuning) -> tuple[dict, list[str]]:
    """summary.json's and report.md's tuning part."""
    goals = study.tuning.objectives
    best = tuning.best
    rows = [{"trial": t.index, "params": t.params, "values": t.values,
             "constraints": t.constraints, "feasible": t.feasible, "failed": t.failed}
            for t in tuning.trials]
    part = {"trials": len(tuning.trials),
            "feasible": sum(t.feasible for t in tuning.trials),
            "objectives": [{"output": n, "direction": d} for n, d in goals],
            "constraints": [{"output": c.output, "min": c.low, "max": c.high}
                            for c in study.tuning.constraints],
            "robust_samples": study.tuning.settings.robust_samples,
            "robust": study.tuning.settings.robust,
            "best": None if best is None else {"trial": best.index, "params": best.params,
                                               "values": best.values},
            "machine_files": [str(f) for f in tuning.files], "trial_rows": rows}
    md = [f"## Tuning: {part['trials']} trials, {part['feasible']} feasible", ""]
    if best is None:
        md.append("No trial met every constraint.")
        return part, md
    md += ["| parameter | best | search space |", "|---|---|---|"]
    for ref, space in zip(study.tuned, study.spaces):
        md.append(f"| {ref.name} | {best.params[ref.name]:.5g} {ref.unit} | "
                  f"{space.describe(ref.unit)} |")
    md += ["", "| output | best trial | goal |", "|---|---|---|"]
    for name, value in best.values.items():
        md.append(f"| {name} | {value:.5g} {OUTPUTS[name].unit} | {_goal(study, name)} |")
    written = ", ".join(f"`{f.name}`" for f in tuning.files)
    md += ["", f"Trial {best.index}" + (f"; written as {written} beside this report."
                                        if written else ".")]
    return part, md


def _goal(study: Study, output: str) -> str:
    """What a tuning study asks of ``output``: its direction, or its bounds."""
    bounds = [f"{op} {v:g}" for c in study.tuning.constraints if c.output == output
              for op, v in ((">=", c.low), ("<=", c.high)) if v is not None]
    return " and ".join(bounds) or dict(study.tuning.objectives).get(output, "")


def build(out: Path, study: Study, results: Results, tuning, run: dict) -> dict:
    """Figures, summary.json and report.md of ``study`` in ``out``; the summary."""
    figures = []
    md = [f"# {study.study.name}", "",
          (f"Study file `{study.path}`, method {study.study.method}, design "
           f"{study.study.design}, seed {study.study.seed}: {results.ids.size} samples "
           f"({int((~results.ok).sum())} failed)."), ""]
    if study.varied:
        md += ["| parameter | distribution |", "|---|---|"]
        md += [f"| {r.name} | {d.describe(r.unit)} |"
               for r, d in zip(study.varied, study.distributions)]
        md.append("")
    summary = {"study": study.path, "name": study.study.name, "method": study.study.method,
               "design": study.study.design, "seed": study.study.seed,
               "samples": int(results.ids.size), "failed": int((~results.ok).sum()),
               "failures": failures(results), "run": run}
    manifest = json.loads((out / "study.json").read_text())
    if study.tuning is not None:
        part, lines = _tuning_part(study, tuning)
        summary["tuning"] = part
        md += lines
        trials = [{"values": t.values, "feasible": t.feasible}
                  for t in tuning.trials if not t.failed]
        axes, signs = pareto_axes(study)
        if trials and len(axes) == 2:
            best = None if tuning.best is None else {"values": tuning.best.values}
            figures.append(report.pareto(trials, axes, signs, best, out / "pareto.png"))
    else:
        stats = output_stats(study, results)
        rows = distribution_rows(study, results)
        found = indices(study, results)
        summary["outputs"] = {s.name: s.as_dict() for s in stats}
        summary["indices"] = {n: ind.as_dict() for n, ind in found.items()}
        if stats:
            md += ["## Outputs", ""] + stats_table(stats, study.report.percentiles) + [""]
            figures.append(report.histograms(study, results, rows & results.ok,
                                             out / "histograms.png"))
            for i, values in results.curves.items():
                if not np.isfinite(values[rows]).any():  # every sample failed: no band
                    continue
                info = manifest["curves"][f"curve_{i}"]
                figures.append(report.curve_bands(study, info, values[rows], out /
                                                  f"curve_{i}.png"))
        title = {"sobol": "Sobol indices", "morris": "Morris indices"}.get(
            study.study.design if study.study.method == "sensitivity" else "",
            "Rank correlations")
        md += [f"## {title}", ""] + indices_table(found) + [""]
        lo, hi = min(study.report.percentiles), max(study.report.percentiles)
        spread = {s.name: f"p{lo:g} .. p{hi:g}: {s.percentiles[lo]:.4g} .. "
                  f"{s.percentiles[hi]:.4g} {s.unit}" for s in stats}
        figures.append(report.sensitivity_bars(study, found, spread, out / "sensitivity.png"))
    summary["figures"] = [str(f) for f in figures]
    md += ["Figures: " + ", ".join(f"`{Path(f).name}`" for f in figures)]
    write_summary(out, study, summary, md)
    return summary


def pareto_axes(study: Study) -> tuple[tuple[str, ...], tuple[float, ...]]:
    """The Pareto plot's two axes (the objectives first, then the constrained outputs,
    then the others) and the sign that makes each one "smaller is better"."""
    goals = dict(study.tuning.objectives)
    lower_only = {c.output for c in study.tuning.constraints if c.high is None}
    names = list(goals)
    names += [c.output for c in study.tuning.constraints if c.output not in names]
    names += [n for n in study.outputs if n not in names]
    axes = tuple(names[:2])
    signs = tuple(-1.0 if goals.get(a) == "maximize" or (a not in goals and a in lower_only)
                  else 1.0 for a in axes)
    return axes, signs
