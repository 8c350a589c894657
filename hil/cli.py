"""The ``hil`` command line.

    hil demo [--config FILE] [--program FILE] [--out DIR] [--no-rt]
    hil linuxcnc INI [--program FILE.ngc] [--out DIR] [--inject [AXIS/]FAULT:KEY=VALUE,...]
    hil run CONFIG --adapter URL [--duration S] [--record DIR] [--watchdog-cycles N] ...
    hil controller CONFIG --adapter URL --program FILE [--out DIR] ...
    hil validate [--json] [--out DIR | --no-plots] [--only NAME ...] [--strict]
    hil bench plant [--json] [--config FILE ...] [--seconds S]
    hil bench loop [--rate 1000,4000,8000] [--seconds S] [--with-plant [--adapter udp]] [--json]
    hil bench adapters [--n N] [--adapter udp|serial] [--json]
    hil bench fuzz [--frames N] [--seed N] [--json]
    hil bench tick [--config FILE ...] [--seconds S] [--json]
    hil bench can [--config FILE] [--program FILE] [--sync-hz HZ] [--group G] [--json]
    hil bench study [--samples N] [--seconds S] [--json]
    hil bench controller [--config FILE --program FILE ...] [--no-rt] [--json]
    hil bench linuxcnc [--ini FILE] [--program FILE.ngc] [--out DIR] [--no-rt] [--json]
    hil bench scope [--config FILE] [--seconds S] [--segments N] [--no-rt] [--json]
    hil bench identify [--ci] [--generator all|solve_ivp|fixed_step] [--cases NAME ...]
                       [--out DIR] [--workers N] [--json]
    hil eds CONFIG --adapter can://... [--out DIR]
    hil study SPEC.toml [--out DIR] [--workers N | --scheduler tcp://HOST:8786] [--fresh]
    hil report RUN [--cyclictest] [--controller DIR]
    hil replay RUN [--tolerance REL] [--json]
    hil export RUN --to mdf4|csv [--axis X] [--out PATH] [--force]
    hil scope RUN [--port N]
    hil soak [--minutes N] [--rate HZ] [--no-rt] [--out DIR]
    hil config-keys [--markdown]
    hil identify TRACE --config CONFIG --out DIR [--validate TRACE2]
    hil sim CONFIG --program FILE --out DIR [--start MM] [--json]
    hil measure CONFIG step current|speed|position --amplitude X [--at MM] --out DIR
    hil measure CONFIG bode current|speed --amplitude X [--offset X] --out DIR

Exit status: 0 on success (``hil validate``: it ran, whatever rows disagree), 1 when
``hil validate --strict`` finds a failing verification row or the NC of ``hil sim`` raised
an alarm, ``hil report``'s verdict on the run is FAIL (:mod:`hil.report.run_verdict`), or
``hil report``/``hil export`` stopped at a corrupt batch of the recording (what precedes
it reported or exported), 2 on bad input (a machine file that does not
load, a part program that does not parse, an unknown experiment) and when the command
needs an optional extra that is not installed (:mod:`hil.extras`: the message names it).
"""

import argparse
import importlib
import json
import os
import select
import signal
import sys
from pathlib import Path

from hil.extras import missing_extra
from hil.inject import INJECT_HELP

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


def _eprint(*args) -> None:
    print(*args, file=sys.stderr, flush=True)


def cmd_bench_plant(args) -> int:
    from hil.bench.plant import run

    configs = [Path(c) for c in args.config] or sorted(CONFIG_DIR.glob("*.toml"))

    def progress(row):
        _eprint(f"  {row.config:<16} {row.ns_per_step:7.0f} ns/sub-step  "
                f"x{row.realtime_factor:5.1f}"
                f" real time  {row.speedup_vs_reference:6.0f}x reference")

    rows = run(configs, args.seconds, args.ref_seconds, progress)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for r in rows:
            print(f"{r['config']:<16} {r['ns_per_step']:8.0f} ns/sub-step  "
                  f"dt {r['substep_s'] * 1e6:6.2f} µs  "
                  f"real-time factor {r['realtime_factor']:6.1f}  reference "
                  f"{r['reference_ns_per_step']:9.0f} ns  "
                  f"speed-up {r['speedup_vs_reference']:6.0f}x  "
                  f"cold start {r['cold_start_s']:.1f} s  "
                  f"cold compile {r['cold_compile_s']:.1f} s"
                  + (f"  C {r['c_ns_per_step']:.0f} ns, ratio_to_c {r['ratio_to_c']:.2f}"
                     if r.get("ratio_to_c") is not None else ""))
    return 0


def cmd_bench_loop(args) -> int:
    from hil.bench.loop import main_rows

    if args.adapter and not args.with_plant:
        _eprint("hil bench loop: --adapter needs --with-plant")
        return 2
    if args.config is not None and not args.with_plant:
        _eprint("hil bench loop: --config needs --with-plant")
        return 2
    # with the emulator, the machine's own rate unless asked
    rates = ([int(r) for r in args.rate.split(",")] if args.rate is not None
             else [None] if args.adapter else [1000, 4000, 8000])
    rows = main_rows(rates, args.seconds, args.with_plant, adapter=args.adapter,
                     **({"config": Path(args.config)} if args.config else {}))
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for r in rows:
            lat, cyc = r["lateness_us"], r["cyclictest_us"]
            base = (f"cyclictest p99.9 {cyc['p999']:7.1f} µs" if cyc else "cyclictest: n/a")
            beyond = r.get("cyclictest_beyond")
            later = (f" ({r['overrun_episodes']} episodes); cyclictest later than "
                     f"{beyond['slack_us']:.1f} µs: {beyond['beyond']}" if beyond else "")
            wake = r.get("wake_latency_us")
            woke = f"  wake-up latency p99.9 {wake['p999']:7.1f} µs" if wake else ""
            print(f"{r['rate_hz']:6g} Hz  lateness p50 {lat['p50']:6.2f}  p99 {lat['p99']:7.2f}  "
                  f"p99.9 {lat['p999']:7.1f}  max {lat['max']:8.1f} µs{woke}  overruns "
                  f"{r['overruns']:4d}  {base}{later}")
    return 0


def cmd_report(args) -> int:
    from hil.report.latency import REPORT_MD, report_run
    from hil.report.run_verdict import judge_run

    run = Path(args.run)
    report = report_run(run, args.cyclictest_seconds if args.cyclictest else None,
                        note=_eprint, controller=args.controller)
    print((run / REPORT_MD).read_text())
    if report["corrupt"] is not None:  # the report stops at the batch: not the whole run
        _eprint(f"hil report: {report['corrupt']}")
        return 1
    verdict, lines = judge_run(run, None if args.controller is None else Path(args.controller))
    print("\n".join(["## Verdict", "", *(f"- {line}" for line in lines), "", verdict.line()]))
    return 0 if verdict.passed else 1


def cmd_bench_adapters(args) -> int:
    from hil.bench.adapters import TRANSPORTS, main_rows

    rows = main_rows(args.n, args.adapter or list(TRANSPORTS))
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for r in rows:
            rt, raw = r["round_trip_us"], r["raw_echo_us"]
            print(f"{r['adapter']:<7} {r['transport']:<20} round trip p50 {rt['p50']:7.1f}  "
                  f"p99.9 {rt['p999']:7.1f} µs   raw echo p50 {raw['p50']:7.1f}  "
                  f"p99.9 {raw['p999']:7.1f} µs   overhead p50 {r['overhead_p50_us']:+6.1f} µs")
    return 0


def cmd_config_keys(args) -> int:
    from hil.controller.config import ControllerSection
    from hil.drive.config import DriveSection
    from hil.identify import screw_geometry
    from hil.inject.catalog import FAULTS
    from plant.config import schema_rows
    from plant.schema import describe

    hil_sections = [("controller", ControllerSection), ("drive", DriveSection)] + [
        (f"inject.{name}", f.section) for name, f in FAULTS.items()]
    # a fault's level first, then when it acts (inherited keys come first in a dataclass)
    rows = schema_rows() + [{"section": name, **row} for name, cls in hil_sections
                            for row in sorted(describe(cls),
                                              key=lambda r: r["key"] in ("at_s", "ramp_s"))]
    rows += [{"section": screw_geometry.SECTION, **row} for row in screw_geometry.schema_rows()]
    if args.markdown:
        print("| section | key | unit | range | default | applies to | meaning |")
        print("|---|---|---|---|---|---|---|")
        for r in rows:
            cells = (r["section"], f"`{r['key']}`", r["unit"], r["range"], r["default"],
                     r["only"], r["doc"])
            # a | inside a cell would end it (GitHub's tables): escaped
            print("| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |")
    else:
        print(f"{'[section] key':<45} {'unit':<10} {'range':<18} {'default':<10} meaning")
        for r in rows:
            print(f"{'[' + r['section'] + '] ' + r['key']:<45} {r['unit']:<10} "
                  f"{r['range']:<18} {r['default']:<10} {r['doc']}")
    return 0


def cmd_sim(args) -> int:
    from hil.commands import print_summary, run_sim

    summary = run_sim(Path(args.config), Path(args.program), Path(args.out), args.start,
                      args.axis, args.every, args.trigger, args.depth, args.pre_trigger,
                      tuple(args.inject or ()))
    print_summary(summary, args.json)
    for alarm in summary["alarms"]:
        _eprint(f"hil sim: {alarm['message']}")
    return 1 if summary["alarms"] else 0


def cmd_measure(args) -> int:
    from hil.commands import print_summary, run_bode, run_step

    if args.kind == "step":
        summary = run_step(Path(args.config), args.loop, args.amplitude, args.at,
                           Path(args.out))
    else:
        if args.loop == "position":
            raise KeyError("bode measures the current or the speed loop, not 'position'")
        summary = run_bode(Path(args.config), args.loop, args.amplitude, args.offset,
                           args.order, args.periods, args.at, Path(args.out))
    print_summary(summary, args.json)
    return 0


def _chosen(argv: list[str]) -> tuple[str | None, str | None]:
    """The command and, for ``bench``, the benchmark ``argv`` names (None: not given)."""
    words = [a for a in argv if not a.startswith("-")]
    return (words[0] if words else None), (words[1] if len(words) > 1 else None)


def _version() -> str:
    """The installed package's version (pyproject.toml's), from its metadata."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("feeddrive-hil")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The command line's parser.  A command implemented in a module of its own gets its
    options only when ``argv`` (default: ``sys.argv[1:]``) names it: the module is
    imported then, so ``hil --help`` and every other command start without importing
    what they do not run (the CAN stack, asammdf, Dask, matplotlib: seconds)."""
    command, what = _chosen(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="hil", description="Feed-drive HIL plant emulator")
    parser.add_argument("--version", action="version", version=f"hil {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    def module(subparsers, name: str, help_: str, path: str, chosen: bool) -> None:
        """``name`` run by ``path``'s add_arguments and run_from_args (imported if
        ``chosen``)."""
        p = subparsers.add_parser(name, help=help_)
        if chosen:
            mod = importlib.import_module(path)
            mod.add_arguments(p)
            p.set_defaults(func=mod.run_from_args)

    def command_module(name: str, help_: str, path: str) -> None:
        module(sub, name, help_, path, command == name)

    command_module("validate", "run the seed experiments: each row's kind (verification, "
                   "reproduction, prediction) and verdict", "hil.validate.command")

    b = sub.add_parser("bench", help="benchmarks (JSON with --json)")
    bsub = b.add_subparsers(dest="what", required=True)
    bp = bsub.add_parser("plant", help="kernel ns per sub-step vs uncompiled reference")
    bp.add_argument("--json", action="store_true", help="print the rows as JSON instead of the table")
    bp.add_argument("--config", action="append", default=[], help="machine file (repeatable; "
                    "default: every file in configs/)")
    bp.add_argument("--seconds", type=float, default=0.3, help="timing per config, s (default "
                    "%(default)s)")
    bp.add_argument("--ref-seconds", type=float, default=0.5, help="reference timing, s (default "
                    "%(default)s)")
    bp.set_defaults(func=cmd_bench_plant)

    s = sub.add_parser("sim", help="controller and plant in lock-step on a part program",
                       description="The simulated NC and the emulated drive in lock-step on a "
                       "part program.  Exit status 0, 1 when the NC raised an alarm (contour, "
                       "standstill or clamping monitoring, encoder, drive fault: listed in the "
                       "summary and on stderr; the axis was stopped), 2 on bad input.")
    s.add_argument("config", help="machine file (TOML)")
    s.add_argument("--program", required=True, help="part program (G-code subset)")
    s.add_argument("--out", required=True, help="folder for trace.csv and sim.png")
    s.add_argument("--start", type=float, default=0.0, help="initial table position, mm (deg; "
                   "default %(default)s)")
    s.add_argument("--axis", help="axis letter in the program (default X, or C if rotary)")
    s.add_argument("--every", type=int, help="trace row every n ticks (default: the "
                   "position-control cycle)")
    s.add_argument("--trigger", help="servo trace with trigger: COLUMN:edge, "
                   "COLUMN:LEVEL[:rising|falling|either] or immediate (columns of trace.csv, "
                   "levels in their units) -> triggered.csv")
    s.add_argument("--depth", type=int, default=1000, help="triggered trace: rows in all "
                   "(default %(default)s)")
    s.add_argument("--pre-trigger", type=int, default=100,
                   help="triggered trace: rows kept before the trigger (default %(default)s)")
    s.add_argument("--inject", action="append", metavar="FAULT:KEY=VALUE,...",
                   help=INJECT_HELP)
    s.add_argument("--json", action="store_true",
                   help="print the summary as JSON instead of 'key: value' lines")
    s.set_defaults(func=cmd_sim)

    m = sub.add_parser("measure", help="the controller's step and frequency-response tests")
    m.add_argument("config", help="machine file (TOML)")
    m.add_argument("kind", choices=("step", "bode"),
                   help="step: a setpoint step, its rise time and overshoot; bode: a PRBS "
                        "around --offset, the closed loop's frequency response")
    m.add_argument("loop", choices=("current", "speed", "position"),
                   help="the loop whose setpoint is stepped or excited (bode: current or "
                        "speed)")
    m.add_argument("--amplitude", type=float, required=True,
                   help="step or PRBS amplitude: A, mm/min (deg/min) or mm (deg)")
    m.add_argument("--offset", type=float, default=0.0, help="bode: setpoint offset, same unit "
                   "(default %(default)s)")
    m.add_argument("--at", type=float, default=0.0,
                   help="table position, mm (deg; default %(default)s)")
    m.add_argument("--order", type=int, default=12, help="bode: PRBS register length "
                   "(default %(default)s)")
    m.add_argument("--periods", type=int, default=4,
                   help="bode: PRBS periods averaged (more: less noise, longer run; "
                        "default %(default)s)")
    m.add_argument("--out", required=True, help="folder for the plot and the CSV")
    m.add_argument("--json", action="store_true", help="print the figures as JSON")
    m.set_defaults(func=cmd_measure)

    bl = bsub.add_parser("loop", help="hard-timed loop lateness vs cyclictest, same interval")
    bl.add_argument("--rate", help="comma-separated rates, Hz (default: 1000,4000,8000; "
                    "with --adapter the machine's PWM frequency)")
    bl.add_argument("--seconds", type=float, default=5.0, help="run per rate and tool, s "
                    "(default %(default)s)")
    bl.add_argument("--with-plant", action="store_true",
                    help="step the Arrow 500 X plant every tick")
    bl.add_argument("--adapter", choices=("udp",), help="the emulator's whole tick (drive, "
                    "recording) behind this adapter, a controller process on the other end "
                    "(needs --with-plant)")
    bl.add_argument("--config", help="machine file or manifest of the plant or the emulator "
                    "(default: the Arrow 500 X)")
    bl.add_argument("--json", action="store_true", help="print the rows as JSON instead of the table")
    bl.set_defaults(func=cmd_bench_loop)

    ba = bsub.add_parser("adapters", help="setpoint-to-feedback round trip vs raw echo")
    ba.add_argument("--n", type=int, default=20000, help="round trips of each kind "
                    "(default %(default)s)")
    ba.add_argument("--adapter", action="append", choices=("udp", "serial"),
                    help="repeatable; default: all")
    ba.add_argument("--json", action="store_true", help="print the rows as JSON instead of the table")
    ba.set_defaults(func=cmd_bench_adapters)

    for name, help_ in (
            ("fuzz", "N frames through every decoder into running drives: counts, faults, "
                     "checks (exit 1 if a check fails)"),
            ("tick", "the emulator's whole tick vs the plant step alone"),
            ("can", "CSP over CAN at a 1 kHz SYNC against UDP and the lock-step simulation: "
                    "following error, overruns, bus load"),
            ("identify", "hil identify on traces of an independent simulator with undeclared "
                         "effects: named first, error / floor, time"),
            ("study", "hil study's samples/s on 1 and 2 local workers, per-task overhead "
                      "against a bare simulation"),
            ("controller", "hil controller's tick against hil run over UDP, one axis and "
                           "five: p50, p99.9, the NC's part"),
            ("linuxcnc", "LinuxCNC's servo-thread jitter beside cyclictest, and the fixed "
                         "wire's frames per second"),
            ("scope", "hil run's loop lateness with hil scope's page open and closed in turn, "
                      "in one run")):
        module(bsub, name, help_, f"hil.bench.{name}", command == "bench" and what == name)

    r = sub.add_parser("report", help="latency and jitter report of a run folder, and its "
                       "verdict (PASS or FAIL with the reasons)")
    r.add_argument("run", help="run folder of hil run (recording.arrows + report.json)")
    r.add_argument("--cyclictest", action="store_true",
                   help="cyclictest baseline at the run's period (needs rt-tests)")
    r.add_argument("--cyclictest-seconds", type=float, default=10.0, help="baseline length, s (default %(default)s)")
    r.add_argument("--controller", metavar="DIR",
                   help="hil controller's --out folder: pair its controller.npz with the "
                        "run for the round trip's total and transport")
    r.set_defaults(func=cmd_report)

    command_module("replay", "re-run a recorded run offline on the setpoints it applied and "
                   "compare it with its recording", "hil.replay.command")
    command_module("export", "a run's recording as MDF4 or servo-trace CSV",
                   "hil.runtime.export")
    command_module("scope", "a run's status, events and signals live in a browser, with a "
                   "trigger and fault injection (hil run --inject-port); a finished run's "
                   "whole length", "hil.scope.command")
    command_module("soak", "emulator and controller for minutes or hours: memory, lateness "
                   "and overruns per minute, a plot", "hil.runtime.soak")
    command_module("run", "the emulator daemon: the plant behind an adapter, in real time",
                   "hil.runtime.emulator")
    command_module("controller", "the simulated NC as a process over an adapter",
                   "hil.runtime.controller_proc")
    command_module("eds", "the CiA 306 EDS and DCF of the CANopen nodes hil run serves on a "
                   "can:// adapter", "hil.eds")
    command_module("demo", "emulator and controller over UDP loopback, compared with the "
                   "lock-step simulation", "hil.runtime.demo")
    command_module("linuxcnc", "LinuxCNC drives the emulated machine, headless: home, run a "
                   "G-code program, a verdict", "hil.linuxcnc.command")
    command_module("identify", "find, fit and add the effects a machine file lacks from a "
                   "measured trace", "hil.identify.command")
    command_module("study", "tolerance, sensitivity and tuning studies over many simulated "
                   "machines, on Dask", "hil.study.command")

    k = sub.add_parser("config-keys", help="every machine-file key with unit and meaning")
    k.add_argument("--markdown", action="store_true", help="a Markdown table (default: "
                   "plain columns)")
    k.set_defaults(func=cmd_config_keys)
    for parent, examples in ((sub, EXAMPLES), (bsub, BENCH_EXAMPLES)):
        for name, p in parent.choices.items():
            p.epilog = "example:\n  " + examples[name]
            p.formatter_class = _ExampleFormatter
    return parser


class _ExampleFormatter(argparse.HelpFormatter):
    """argparse's help, with the example at its end printed as written: a command line
    wrapped at the terminal's width would not paste."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("example:"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


#: one command line per command, shown at the end of its --help
EXAMPLES = {
    "validate": "hil validate --only coulomb_hold screw_modes --out validate-out",
    "bench": "hil bench tick --json",
    "sim": "hil sim configs/arrow500_x.toml --program programs/demo_moves.nc --out out/sim",
    "measure": "hil measure configs/arrow500_x.toml bode speed --amplitude 300 --offset 600 "
               "--at 250 --out out/meas",
    "report": "hil report out/run --controller out/ctl --cyclictest",
    "replay": "hil replay out/run --json",
    "export": "hil export out/run --to mdf4",
    "scope": "hil scope out/run --port 5006",
    "soak": "hil soak --minutes 30 --rate 4000 --out soak-out",
    "run": "hil run configs/arrow500_x.toml --adapter udp://127.0.0.1:5005 --record out/run",
    "controller": "hil controller configs/arrow500_x.toml --adapter udp://127.0.0.1:5005 "
                  "--program programs/seed000_moves.nc --out out/ctl",
    "eds": "hil eds configs/machines/arrow500_xy_2khz.toml --out eds --adapter "
           "'can://udp_multicast/239.74.163.2?node=5&rated_current_ma=28000'",
    "demo": "hil demo",
    "linuxcnc": "hil linuxcnc configs/linuxcnc/arrow500_xyz.ini --program "
                "programs/linuxcnc_square.ngc --out out/linuxcnc",
    "identify": "hil identify ../shared/data/EMPS/DATA_EMPS.mat --config configs/emps.toml "
                "--out out/identify --validate ../shared/data/EMPS/DATA_EMPS_PULSES.mat",
    "study": "hil study configs/studies/ci_small.toml --out out/study",
    "config-keys": "hil config-keys --markdown",
}
BENCH_EXAMPLES = {
    "plant": "hil bench plant --config configs/arrow500_x.toml --json",
    "loop": "hil bench loop --with-plant --adapter udp --config "
            "configs/machines/geiss_5axis.toml --seconds 60",
    "adapters": "hil bench adapters --n 5000",
    "fuzz": "hil bench fuzz --json",
    "tick": "hil bench tick --json",
    "can": "hil bench can --json",
    "identify": "hil bench identify --ci",
    "study": "hil bench study --json",
    "controller": "hil bench controller --json",
    "linuxcnc": "hil bench linuxcnc --json",
    "scope": "hil bench scope --seconds 30 --segments 4",
}


#: exit status when standard output's reader went away (``hil config-keys | head``): that
#: of a tool ended by SIGPIPE, as the shell reports it
EXIT_CLOSED_PIPE = 128 + int(signal.SIGPIPE)


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else argv
    try:
        args = build_parser(argv).parse_args(argv)
        status = args.func(args)
        sys.stdout.flush()  # a reader gone shows here, not in the interpreter's exit
        return status
    except BrokenPipeError:
        if not _stdout_closed():
            raise
        # what is still buffered goes nowhere, so that the flush at exit cannot fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_CLOSED_PIPE
    except ModuleNotFoundError as exc:
        # a command module is imported when chosen and its optional packages when it
        # needs them, so an extra that is not installed shows up here and nowhere else
        command, what = _chosen(words)
        named = f"hil {command} {what}" if command == "bench" else f"hil {command}"
        message = missing_extra(exc, named)
        if message is None:
            raise
        _eprint(message)
        return 2
    except Exception as exc:
        if not isinstance(exc, _bad_input()):
            raise
        _eprint(f"hil: {exc}")
        return 2


def _stdout_closed() -> bool:
    """Whether standard output is a pipe whose reader has gone (it polls as an error), as
    opposed to a socket or pipe of the command itself breaking, which stays an error."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by a stream without a file
        return False
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(events & select.POLLERR for _, events in poller.poll(0))


def _bad_input() -> tuple[type[Exception], ...]:
    """The errors :func:`main` reports as bad input (exit 2).  Imported only once one was
    raised: their modules load the plant (numba, scipy: 0.4 s), which ``hil --help`` and
    the commands that do not simulate never need."""
    from hil.controller.program import ProgramError
    from hil.report.latency import ReportError
    from plant.errors import ConfigError
    return ConfigError, KeyError, ProgramError, ReportError, FileNotFoundError


if __name__ == "__main__":
    sys.exit(main())
