"""``hil identify TRACE --config CONFIG --out DIR [--validate TRACE2]``."""

import math
import sys
import time
from pathlib import Path

from hil.identify.candidates import default_workers
from hil.identify.diagnosis import summary_lines
from hil.identify.effects import NAMES
from hil.identify.fit import Identification, record_errors
from hil.identify.model import DEFAULT_TOLERANCE, Model
from hil.identify.record import load_record, timing_warning
from hil.identify.report import EMPS_PUBLISHED, EMPS_REFERENCE_KEYS, write
from hil.trace_file import TraceFormatError


def add_arguments(p) -> None:
    p.add_argument("trace", type=Path,
                   help="servo-trace CSV, an EMPS .mat record, or a hil run folder")
    p.add_argument("--config", type=Path, required=True, help="machine file to start from")
    p.add_argument("--out", type=Path, required=True, help="folder for the report")
    p.add_argument("--validate", type=Path, metavar="TRACE2",
                   help="a second record to replay with the parameters fitted on TRACE")
    p.add_argument("--min-explained", type=float, default=0.05,
                   help="share of a residual's energy an effect must explain (default 0.05)")
    p.add_argument("--floor-factor", type=float, default=1.5,
                   help="done when every replay channel is within this factor of its "
                        "noise floor (default %(default)s)")
    p.add_argument("--max-steps", type=int, default=6, help="most effects added (default %(default)s)")
    p.add_argument("--refine-nfev", type=int, default=10,
                   help="iterations of the closed-loop refinement (0: off; default 10)")
    p.add_argument("--cutoff-hz", type=float, default=None,
                   help="inverse model's low-pass corner (default: a tenth of the sample rate)")
    p.add_argument("--exclude", nargs="+", default=(), choices=NAMES, metavar="EFFECT",
                   help="library effects not to look for (default: none): " + ", ".join(NAMES))
    p.add_argument("--workers", type=int, default=None,
                   help="processes evaluating a round's candidates (default: the CPUs "
                        "available, at most 2; 1: none)")
    p.add_argument("--tolerance", nargs="+", default=(), metavar="EFFECT=FRACTION",
                   help="relative tolerance of a declared effect's coefficients and shapes "
                        "(a Stribeck velocity, a presliding spring's k1, x1, exponent): the "
                        "prior's deviation in the refits and the change the report flags (default "
                        f"{DEFAULT_TOLERANCE:g} for every effect), e.g. inertia=0.05")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--json", action="store_true", help="print report.json to stdout")


def validation(ident: Identification, path: Path) -> dict:
    """Errors on a second record, before and after, with the parameters fitted on the
    first (nothing is fitted on this one)."""
    rec = load_record(path)
    before = Model(ident.ctx, ident.config)
    before.restore([])  # the config as given: no overrides
    return {"trace": str(path), "error_before": record_errors(rec, before.replay(rec=rec)),
            "error_after": record_errors(rec, ident.model.replay(rec=rec))}


def identify(trace: Path, config: Path, out: Path, validate: Path | None = None,
             log=None, warn=None, **options) -> dict:
    """Run the whole identification and write the report; returns report.json's content.
    ``warn`` receives why the trace's timing may spoil it (:func:`timing_warning`)."""
    t0 = time.monotonic()
    rec = load_record(trace)
    if warn is not None and (why := timing_warning(rec)) is not None:
        warn(why)
    ident = Identification(config, rec, log=log, **options).fit()
    val = None
    if validate is not None:
        if log:
            log(f"[{time.monotonic() - t0:6.1f} s] validating on {validate.name}")
        val = validation(ident, validate)
    reference = None
    if Path(trace).stem in EMPS_PUBLISHED:
        reference = {Path(p).stem: emps_reference(ident, load_record(p))
                     for p in [trace] + ([validate] if validate is not None else [])}
    return write(ident, out, val, time.monotonic() - t0, reference)


def emps_reference(ident: Identification, rec) -> dict:
    """Errors of the EMPS reference model's parameters replayed through our loop."""
    model = Model(ident.ctx, ident.config)
    model.restore([])
    return record_errors(rec, model.replay(extra=EMPS_REFERENCE_KEYS, rec=rec))


def tolerances(items) -> dict:
    """``EFFECT=FRACTION`` items as {effect: fraction}; ValueError naming a bad one."""
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        try:
            frac = float(value)
        except ValueError:
            frac = math.nan
        if name not in NAMES or not 0.0 < frac < math.inf:
            raise ValueError(f"--tolerance {item!r}: want EFFECT=FRACTION with EFFECT one of "
                             f"{', '.join(NAMES)} and FRACTION > 0")
        out[name] = frac
    return out


def run_from_args(args) -> int:
    log = None if args.quiet else (lambda text: print(text, file=sys.stderr, flush=True))
    try:
        tolerance = tolerances(args.tolerance)
        if args.workers is not None and args.workers < 1:
            raise ValueError(f"--workers {args.workers}: want 1 or more")
    except ValueError as exc:
        print(f"hil identify: {exc}", file=sys.stderr)
        return 2
    try:
        rep = identify(args.trace, args.config, args.out, args.validate, log=log,
                       warn=lambda why: print(f"hil identify: warning: {why}",
                                              file=sys.stderr, flush=True),
                       min_explained=args.min_explained, floor_factor=args.floor_factor,
                       max_steps=args.max_steps, refine_nfev=args.refine_nfev,
                       cutoff_hz=args.cutoff_hz, exclude=tuple(args.exclude),
                       workers=args.workers or default_workers(), tolerance=tolerance)
    except (TraceFormatError, FileNotFoundError) as exc:
        print(f"hil identify: {exc}", file=sys.stderr)
        return 2
    if args.json:
        import json
        print(json.dumps(rep, indent=2))
    else:
        print(f"effects added: {', '.join(rep['effects_added']) or 'none'}; report in "
              f"{args.out / 'report.md'}")
        for line in summary_lines(rep["faults"], rep["effects_added"]):
            print(line)
    return 0
