"""``hil study SPEC.toml``: run a study file on Dask and write its results and report.

::

    hil study configs/studies/seed000_position_step.toml [--out DIR] [--workers N]
        [--scheduler tcp://HOST:8786] [--task-size N] [--fresh] [--report-only] [--json]

The study file (:mod:`hil.study.spec`) is checked before anything starts; a bad one is
refused with exit status 2, naming the file, the key, the value and its unit or range.
The samples run on a LocalCluster of ``--workers`` processes (default: the machine's
cores) or on the cluster of ``--scheduler``; results stream to ``DIR/results/`` (Parquet,
:mod:`hil.study.store`) and a study started again on the same folder resumes.  At the
end ``DIR`` holds ``summary.json``, ``report.md`` and the figures; the report's tables
are printed (``--json``: the summary).  Exit status 0; 1 when a sample failed (its
reason is in the results and the report) or the cluster did (what finished is kept);
2 for a bad study file, and when every sample failed (one line on stderr with the first
reason: the study as written gives nothing to report; the report is written all the
same); 130 when stopped by SIGINT or SIGTERM (the cluster is shut down,
what finished is kept).  Progress goes to stderr.
"""

import argparse
import json
import os
import signal
import sys
from pathlib import Path

DEFAULT_OUT = "study-out"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil study``."""
    p.add_argument("spec", help="study file (TOML)")
    p.add_argument("--out", help=f"results folder (default: {DEFAULT_OUT}/<study file's stem>)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                   help="an existing Dask scheduler (default: a LocalCluster here)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="LocalCluster worker processes (default: the cores, %(default)s; "
                   "not used with --scheduler)")
    p.add_argument("--task-size", type=int, default=0, metavar="N",
                   help="samples per task (default 0: about four tasks per worker, "
                        "<= 32)")
    p.add_argument("--fresh", action="store_true", help="discard earlier results in --out")
    p.add_argument("--report-only", action="store_true",
                   help="run nothing: report on the results already in --out")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil study``: 0; 1 when a sample failed or the cluster did; 2 on a bad study
    file."""
    if args.fresh and args.report_only:
        print("hil study: --fresh deletes the results --report-only reports on: give one",
              file=sys.stderr)
        return 2
    from distributed.client import FutureCancelledError
    from distributed.scheduler import KilledWorker

    from hil.study.driver import run_study
    from hil.study.keys import StudySpecError
    from hil.study.progress import Progress
    from hil.study.spec import load_study

    try:
        study = load_study(args.spec)
    except StudySpecError as exc:
        print(f"hil study: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out or Path(DEFAULT_OUT) / Path(args.spec).stem)
    # SIGTERM stops the study as Ctrl-C does: the LocalCluster and its worker processes
    # are shut down on the way out, not left behind
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        result = run_study(study, out, args, Progress())
    except KeyboardInterrupt:
        print(f"hil study: stopped; the results so far are in {out}: run the same command "
              "again to resume", file=sys.stderr)
        return 130
    except StudySpecError as exc:
        print(f"hil study: {exc}", file=sys.stderr)
        return 2
    except (OSError, KilledWorker, FutureCancelledError) as exc:
        print(f"hil study: the Dask cluster failed ({type(exc).__name__}: {exc}); the "
              f"results so far are in {out}: run the same command again to resume",
              file=sys.stderr)
        return 1
    if result["samples"] and result["failed"] == result["samples"]:
        first = result["failures"][0]
        why = " ".join(first["status"].split())  # one line, whatever the exception said
        print(f"hil study: every one of the {result['samples']} samples failed, sample "
              f"{first['sample_id']}: {why}; report in {out / 'report.md'}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print((out / "report.md").read_text())
        print(f"results in {out}/")
    return 1 if result["failed"] else 0


def main(argv: list[str] | None = None) -> int:
    """``python3 -m hil.study ...``: the same as ``hil study ...``."""
    parser = argparse.ArgumentParser(prog="hil study", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))
