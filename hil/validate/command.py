"""``hil validate``: run the seed experiments and print every row with its kind and
verdict, then a summary.

    hil validate [--json] [--out DIR | --no-plots] [--only NAME ...] [--strict]

Exit status 0 when the experiments ran, whatever they found (a reproduction or prediction
that disagrees is a finding); with ``--strict`` 1 when a verification row disagrees (a
verification failing is a bug).  An unknown experiment raises KeyError, which the command
line reports with exit status 2.  An experiment that takes longer than two seconds (the
first one loading the compiled kernels, or compiling them on a cold cache) shows its
progress on stderr (:mod:`hil.progress`); stdout has the table or the JSON alone.
"""

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from hil.progress import COMPILING, Progress
from hil.validate.core import Kind, Result, failing_verifications, run_all


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``hil validate``."""
    parser.add_argument("--json", action="store_true",
                        help="print a JSON list of rows (kind and verdict included); the "
                        "summary goes to stderr")
    parser.add_argument("--out", default="validate-out", help="folder for the plots (default "
                        "%(default)s)")
    parser.add_argument("--no-plots", action="store_true", help="write no plots")
    import hil.validate.experiments  # noqa: F401  (registers the experiments: their names)
    from hil.validate.core import REGISTRY
    parser.add_argument("--only", nargs="*", metavar="NAME", choices=sorted(REGISTRY),
                        help="run only these experiments: " + ", ".join(sorted(REGISTRY)))
    parser.add_argument("--strict", action="store_true",
                        help="exit 1 when a verification row disagrees")


def run_from_args(args: argparse.Namespace) -> int:
    """Run the experiments ``args`` name and print their rows and summary; the exit status."""
    out_dir = None if args.no_plots else Path(args.out)
    rows = run_all(out_dir, args.only or None, progress=_experiment_progress)
    summary = summarize(rows)
    if args.json:
        print(json.dumps([r.as_dict() for r in rows], indent=1))
        _eprint(summary.text())
    else:
        print(table(rows))
        print()
        print(summary.text())
        if out_dir is not None:
            print(f"\nplots in {out_dir}/")
    return 1 if args.strict and summary.failing_verifications else 0


def _experiment_progress(name: str, i: int, n: int) -> Progress:
    """One experiment's progress line; the first's says that it may compile the kernels."""
    first = f", {COMPILING}" if i == 1 else ""
    return Progress(f"hil validate: {name} ({i} of {n}){first}", ticking=True)


@dataclass(frozen=True)
class Summary:
    """Rows counted by kind and verdict.

    Attributes:
        counts: kind -> (rows that agree, rows that disagree), every kind present.
        disagreements: the rows that disagree, in table order.
        failing_verifications: the verification rows among them (bugs).
    """
    counts: dict
    disagreements: tuple
    failing_verifications: tuple

    @property
    def total(self) -> int:
        """Number of rows."""
        return sum(a + d for a, d in self.counts.values())

    def text(self) -> str:
        """One line of counts, then one line per disagreement with its reason."""
        parts = [f"{a + d} {kind.value} ({a} agree, {d} disagree)"
                 for kind, (a, d) in self.counts.items()]
        lines = [f"{self.total} rows: " + ", ".join(parts) + "."]
        if self.disagreements:
            lines.append("disagreements:")
            lines += [f"- [{r.kind.value}] {r.experiment}: {r.note or 'no reason given'}"
                      for r in self.disagreements]
        return "\n".join(lines)


def summarize(rows: list[Result]) -> Summary:
    """Count ``rows`` by kind and verdict and collect the disagreements."""
    counts = {kind: (sum(1 for r in rows if r.kind is kind and r.ok),
                     sum(1 for r in rows if r.kind is kind and not r.ok)) for kind in Kind}
    return Summary(counts, tuple(r for r in rows if not r.ok),
                   tuple(failing_verifications(rows)))


def _cell(value) -> str:
    text = f"{value:.4g}" if isinstance(value, float) else str(value)
    return text.replace("|", "\\|")


def _reference(r: Result) -> str:
    return f"{r.reference}; {r.source}" if r.source is not None else r.reference


def table(rows: list[Result]) -> str:
    """Markdown table of the rows (what docs/validation.md shows): the reference value with its ± where
    it has one, kind, verdict and the note."""
    lines = [("| experiment | kind | reference value | model | unit | verdict | reference | "
              "tolerance | note |"),
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        paper = _cell(r.paper) + (f" ± {_cell(r.uncertainty)}" if r.uncertainty else "")
        verdict = "agrees" if r.ok else "**disagrees**"
        lines.append(f"| {_cell(r.experiment)} | {r.kind.value} | {paper} | {_cell(r.model)} | "
                     f"{_cell(r.unit)} | {verdict} | {_cell(_reference(r))} | "
                     f"{_cell(r.tolerance)} | {_cell(r.note)} |")
    return "\n".join(lines)


def _eprint(*args) -> None:
    print(*args, file=sys.stderr, flush=True)
