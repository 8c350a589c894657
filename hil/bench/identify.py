"""``hil bench identify``: undeclared effects in traces of independent simulators.

Two generators, neither using the plant's kernel nor the replay, write the traces of the
truth, and ``hil identify``'s search runs on each from the declared machine file:

* ``solve_ivp`` (:mod:`hil.bench.identify_gen`): scipy's solve_ivp on the documented
  equations, a Sinumerik-style cascade, noise and quantisation;
* ``fixed_step`` (:mod:`hil.bench.identify_gen2`, cases named ``g2_...``): written without
  the first one's or the replay's code, a fixed-step Runge-Kutta integrator and a cascade
  from the trace format's text, its cases covering every header convention (a position
  cycle slower than the record, rounding and zeroed encoders, a clipping ADC, the rigid
  screw); its repeat is the same run at four times the integration steps.

Scores per trace:

* **named first**: the first effect added is one of the case's undeclared effects (and
  ``found``: which of them were added at all);
* **error after / floor**: the closed-loop replay's rms error after identification over the
  measurement noise floor (the rms of measured minus true in the generator: current noise
  and ADC step, the sensors' quantisation), per main channel: current, position, and the
  motor encoder where a scale closes the loop;
* **truth / floor**: the same ratio for the truth's own machine file replayed with the
  header's conventions: how far the emulator's replay can follow this simulator at all;
* **repeat / floor**: the generator against itself, the same truth integrated at ten times
  the relative tolerance (same noise): where the closed loop amplifies a difference that
  small, no model follows the trace closer than this, and the floor goal is out of reach;
* the time identification took.

The traces are generated once into ``OUT/traces`` and reused (delete them to regenerate).
"""

import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from hil.bench.identify_gen.axis import RTOL
from hil.bench.identify_gen.cases import (
    ADC_BITS,
    CASES,
    CI_CASES,
    PREROLL_S,
    RECORD_EVERY,
    SINUMERIK_STYLE,
    Case,
    case,
    merged,
)
from hil.bench.identify_gen.generate import deviation, simulate, write
from hil.bench.identify_gen.trajectory import bench_moves
from hil.bench.identify_gen2 import cases as second
from hil.bench.identify_gen2.trace import write as write_second
from hil.identify.config_out import patch_config
from hil.identify.fit import Identification, record_errors
from hil.identify.record import load_record
from hil.identify.replay import replay
from plant.config import load_machine

#: a trace meets the issue's goal when every main channel's error after is within this
#: factor of its floor
FLOOR_GOAL = 1.5
#: the generator's version: a cached trace of another version is generated again
GENERATOR_VERSION = 8
#: the same for the second generator
SECOND_VERSION = 1
#: the generators by name, with their cases' names
GENERATORS = {"solve_ivp": tuple(c.name for c in CASES),
              "fixed_step": tuple(c.name for c in second.CASES)}


def _rms_keys(err: dict) -> list[str]:
    return [k for k in ("iq_rms_a", "force_rms_n", "pos_rms_um", "pos_rms_urad",
                        "motor_pos_rms_um") if k in err]


def ratios(err: dict, floor: dict) -> dict:
    """Error over floor per main channel (those the floor has)."""
    return {k: err[k] / floor[k] for k in _rms_keys(err)
            if k in floor and floor[k] > 0 and isinstance(err.get(k), float)}


def _machine_file(path: Path, text: str, keys: dict, note: str) -> Path:
    """The machine file ``text`` with ``keys`` (``{"section": {"key": value}}``) patched in
    (as it is without keys), written to ``path``."""
    path.write_text(patch_config(text, keys, note) if keys else text)
    return path


def _cached(folder: Path, version: int, duration_s: float | None) -> tuple[Path, Path, dict]:
    """(trace, floor file, what the floor file holds); the dict is empty where the trace
    must be generated again (missing, or of another generator version or duration)."""
    trace, info = folder / "trace.csv", folder / "floor.json"
    cached = json.loads(info.read_text()) if info.is_file() and trace.is_file() else {}
    if cached.get("version") != version or cached.get("duration_s") != duration_s:
        cached = {}
    return trace, info, cached


def prepare(c: Case, folder: Path, log=None, duration_s: float | None = None,
            repeat: bool = True) -> dict:
    """Write the case's truth and start machine files and its trace into ``folder`` (the
    trace only when absent or of another generator version or duration); returns the floor,
    the generator's repeat deviation (:func:`~.generate.deviation`) and paths.
    ``duration_s``: the program repeated to at least this long (None: one pass, 13-32 s).
    ``repeat``: False where the caller needs no repeat deviation: the second simulation
    (at ten times the tolerance, half of the generation's time) is not run and
    ``repeat`` is None; the trace is the same."""
    folder.mkdir(parents=True, exist_ok=True)
    text = c.axis.read_text()
    truth = _machine_file(folder / "truth.toml", text, merged(SINUMERIK_STYLE, c.truth),
                          "bench truth")
    # the truth's physics with the declared controller: its conventions come from the header
    truth_plain = _machine_file(folder / "truth_declared_controller.toml", text, c.truth,
                                "bench truth")
    start = _machine_file(folder / "start.toml", text, c.start, "bench start")
    trace, info, cached = _cached(folder, GENERATOR_VERSION, duration_s)
    if repeat and cached.get("repeat") is None:
        cached = {}
    if not cached:
        t0 = time.monotonic()
        traj = bench_moves(c.travel, c.speed, 0.3 * c.travel, duration_s)
        rec, *again = (simulate(truth, traj, record_every=RECORD_EVERY, preroll_s=PREROLL_S,
                                adc_bits=ADC_BITS, seed=c.seed, rtol=rtol)
                       for rtol in ((RTOL, 10.0 * RTOL) if repeat else (RTOL,)))
        write(rec, trace, f"hil bench identify ({c.name})")
        cached = {"version": GENERATOR_VERSION, "duration_s": duration_s, "floor": rec.floor,
                  "repeat": deviation(rec, again[0]) if again else None,
                  "generated_s": time.monotonic() - t0}
        info.write_text(json.dumps(cached, indent=1))
        if log:
            log(f"{c.name}: generated {traj.duration_s:.1f} s in {cached['generated_s']:.0f} s")
    return {"floor": cached["floor"], "repeat": cached["repeat"], "trace": trace,
            "start": start, "truth": truth_plain}


def prepare_second(c: second.Case, folder: Path, log=None,
                   duration_s: float | None = None) -> dict:
    """:func:`prepare` for a case of the second generator: truth and start machine files
    (the truth without controller keys: the header carries its conventions), the trace
    (None: :data:`~hil.bench.identify_gen2.cases.DURATION_S` long) and its floor and
    repeat."""
    folder.mkdir(parents=True, exist_ok=True)
    text = c.axis.read_text()
    truth = _machine_file(folder / "truth.toml", text, c.truth, "bench truth")
    # what the truth/floor column replays: the truth where the trace's encoders count from
    truth_trace = _machine_file(folder / "truth_trace_frame.toml", text,
                                second.truth_in_trace_frame(c), "bench truth")
    start = _machine_file(folder / "start.toml", text, c.start, "bench start")
    trace, info, cached = _cached(folder, SECOND_VERSION, duration_s)
    if not cached:
        t0 = time.monotonic()
        rec, repeat = second.generate(c, load_machine(truth), duration_s)
        write_second(rec, trace, f"hil bench identify, second generator ({c.name})")
        cached = {"version": SECOND_VERSION, "duration_s": duration_s, "floor": rec.floor,
                  "repeat": repeat, "generated_s": time.monotonic() - t0}
        info.write_text(json.dumps(cached, indent=1))
        if log:
            log(f"{c.name}: generated in {cached['generated_s']:.0f} s")
    return {"floor": cached["floor"], "repeat": cached["repeat"], "trace": trace,
            "start": start, "truth": truth_trace}


def lookup(name: str) -> tuple[str, Case | second.Case]:
    """(generator, case) of the case called ``name``; KeyError lists every case."""
    for generator, names in GENERATORS.items():
        if name in names:
            return generator, (case(name) if generator == "solve_ivp" else second.case(name))
    raise KeyError(f"no bench case {name!r}; cases: "
                   + ", ".join(n for names in GENERATORS.values() for n in names))


def traces_folder(out: Path, duration_s: float | None) -> Path:
    """Where the traces of one duration are cached under ``out``."""
    return out / ("traces" if duration_s is None else f"traces_{duration_s:g}s")


def run_case(name: str, out: Path, refine_nfev: int = 10, log=None,
             duration_s: float | None = None) -> dict:
    """Generate (or reuse) the case's trace, identify it, score it."""
    generator, c = lookup(name)
    make = prepare if generator == "solve_ivp" else prepare_second
    files = make(c, traces_folder(out, duration_s) / c.name, log, duration_s)
    rec = load_record(files["trace"])
    floor = files["floor"]
    truth_err = record_errors(rec, replay(load_machine(files["truth"]), rec))
    t0 = time.monotonic()
    ident = Identification(files["start"], rec, refine_nfev=refine_nfev,
                           tolerance=c.tolerance).fit()
    elapsed = time.monotonic() - t0
    added = [s.effect for s in ident.steps]
    after = ratios(ident.error_after, floor)
    row = {
        "case": c.name, "generator": generator, "axis": c.axis.stem.removeprefix("bench_"),
        "undeclared": list(c.effects), "added": added,
        "named_first": bool(added) and added[0] in c.effects,
        "found": [e for e in c.effects if e in added],
        "floor": floor, "error_before": ident.error_before, "error_after": ident.error_after,
        "before_over_floor": ratios(ident.error_before, floor), "after_over_floor": after,
        "truth_over_floor": ratios(truth_err, floor),
        "repeat_over_floor": ratios(files["repeat"], floor),
        "at_floor": bool(after) and max(after.values()) <= FLOOR_GOAL,
        "identify_s": elapsed, "samples": rec.n, "duration_s": rec.n * rec.dt,
    }
    if log:
        log(f"{c.name}: added {', '.join(added) or 'nothing'}; after/floor "
            + ", ".join(f"{k} {v:.2f}" for k, v in after.items()) + f"; {elapsed:.0f} s")
    return row


def run(names: list[str], out: Path, workers: int = 2, refine_nfev: int = 10,
        log=None, duration_s: float | None = None) -> dict:
    """Every named case, ``workers`` processes at a time; the bench's JSON
    (``bench_identify.json``, or ``bench_identify_60s.json`` for 60 s traces)."""
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            futures = [pool.submit(run_case, n, out, refine_nfev, None, duration_s)
                       for n in names]
            rows = []
            for f in futures:
                rows.append(f.result())
                if log:
                    log(_line(rows[-1]))
    else:
        rows = [run_case(n, out, refine_nfev, log, duration_s) for n in names]
    summary = {
        "cases": len(rows), "named_first": sum(r["named_first"] for r in rows),
        "at_floor": sum(r["at_floor"] for r in rows),
        "repeatable": sum(_repeatable(r) for r in rows),
        "at_floor_of_repeatable": sum(r["at_floor"] and _repeatable(r) for r in rows),
        "max_identify_s": max(r["identify_s"] for r in rows), "floor_goal": FLOOR_GOAL,
        "elapsed_s": time.monotonic() - t0, "duration_s": duration_s,
    }
    result = {"summary": summary, "rows": rows}
    suffix = "" if duration_s is None else f"_{duration_s:g}s"
    (out / f"bench_identify{suffix}.json").write_text(json.dumps(result, indent=1))
    return result


def _repeatable(row: dict) -> bool:
    """The generator repeats the trace within the floor goal on every main channel."""
    return max(row["repeat_over_floor"].values(), default=0.0) <= FLOOR_GOAL


def _fmt(ratio: dict) -> str:
    return " / ".join(f"{ratio[k]:.2f}" for k in _rms_keys(ratio))


def _line(r: dict) -> str:
    return (f"{r['case']}: first {'yes' if r['named_first'] else 'NO'}, after/floor "
            f"{_fmt(r['after_over_floor'])}, {r['identify_s']:.0f} s")


def table(result: dict) -> str:
    """The bench as a Markdown table (ratios: current / position / motor encoder)."""
    lines = ["| trace | generator | axis | undeclared | added (in order) | named first "
             "| before / floor | after / floor | truth / floor | repeat / floor | trace, s "
             "| identify, s |", "|---" * 12 + "|"]
    for r in result["rows"]:
        lines.append(
            f"| {r['case']} | {r['generator']} | {r['axis']} | {', '.join(r['undeclared'])} | "
            f"{', '.join(r['added']) or '-'} | {'yes' if r['named_first'] else 'no'} | "
            f"{_fmt(r['before_over_floor'])} | {_fmt(r['after_over_floor'])} | "
            f"{_fmt(r['truth_over_floor'])} | {_fmt(r['repeat_over_floor'])} | "
            f"{r['duration_s']:.0f} | {r['identify_s']:.0f} |")
    s = result["summary"]
    lines.append(f"\nnamed first {s['named_first']}/{s['cases']}, after within "
                 f"{s['floor_goal']}x the floor on every main channel {s['at_floor']}/"
                 f"{s['cases']} ({s['at_floor_of_repeatable']}/{s['repeatable']} of the traces "
                 f"the generator repeats within it), longest identification "
                 f"{s['max_identify_s']:.0f} s")
    return "\n".join(lines)


def add_arguments(p) -> None:
    p.add_argument("--cases", nargs="+", default=None, metavar="CASE",
                   help="cases to run (default: every case of the --generator): "
                        + ", ".join(n for names in GENERATORS.values() for n in names))
    p.add_argument("--generator", choices=("all", *GENERATORS), default="all",
                   help="the generator whose cases run when --cases is not given: "
                        "solve_ivp (scipy), fixed_step (the second, g2_ cases) or all")
    p.add_argument("--ci", action="store_true", help="the reduced set CI runs: "
                   + ", ".join(CI_CASES))
    p.add_argument("--out", type=Path, default=Path("bench-identify"),
                   help="folder for the traces (cached) and bench_identify.json "
                        "(default %(default)s)")
    p.add_argument("--workers", type=int, default=2, help="processes (default %(default)s)")
    p.add_argument("--refine-nfev", type=int, default=10,
                   help="closed-loop refinement iterations of hil identify (10)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="traces at least this long, s (the first generator repeats its "
                        "program at other speeds, the second its pass move by move; "
                        "default: one pass, 13-32 s; the second generator's 16 s)")
    p.add_argument("--json", action="store_true", help="print the JSON instead of the table")


def run_from_args(args) -> int:
    every = [n for g, names in GENERATORS.items() if args.generator in ("all", g)
             for n in names]
    names = list(CI_CASES) if args.ci else (args.cases or every)
    try:
        for n in names:
            lookup(n)
    except KeyError as exc:
        print(f"hil bench identify: {exc.args[0]}", file=sys.stderr)
        return 2

    def log(text):
        print(text, file=sys.stderr, flush=True)

    if args.duration is not None and not args.duration > 0.0:
        print(f"hil bench identify: --duration {args.duration:g} s must be > 0",
              file=sys.stderr)
        return 2
    result = run(names, args.out, args.workers, args.refine_nfev, log, args.duration)
    print(json.dumps(result, indent=1) if args.json else table(result))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.bench.identify``: the same as ``hil bench identify``."""
    import argparse
    p = argparse.ArgumentParser(prog="hil bench identify", description=__doc__.split("\n")[0])
    add_arguments(p)
    return run_from_args(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
