"""``hil bench linuxcnc``: LinuxCNC's servo thread and the fixed wire's frames, beside
cyclictest at the same period in the same run.

One ``hil linuxcnc`` session (:func:`hil.linuxcnc.command.run_linuxcnc`; by default
configs/linuxcnc/arrow500_xyz.ini on programs/linuxcnc_square.ngc, the emulator's loop on
the first CPU so that LinuxCNC's real-time threads, pinned by LinuxCNC to the last, have
theirs to themselves), then ``cyclictest`` at the servo period, at the SCHED_FIFO priority
the session gives LinuxCNC's threads (SCHED_OTHER with ``--no-rt``, as they then run), on
the CPU they ran on, for as long as the machine was on (at least :data:`MIN_CYCLICTEST_S`).
JSON::

    {"ini", "program", "verdict", "realtime",
     "servo_thread": {"nominal_us", "periods", "span_s", "period_us": {p50, p99, p999, max},
                      "jitter_us": {...}, "stale_periods", "feedback_frames",
                      "setpoints_per_s", "feedback_per_s"},
     "emulator": {"received", "sent", "lost", "out_of_order", "duplicates", "malformed",
                  "wall_s", "received_per_s", "sent_per_s", "overruns", "ticks"},
     "cyclictest": {"interval_us", "seconds", "cpu", "priority", "latency_us": {...}},
     "jitter_over_cyclictest": {"p99", "p999", "max"},
     "load_avg_before", "load_avg_after"}

``servo_thread`` is what the feeddrive HAL component measured in LinuxCNC's servo thread
while the machine was on (:class:`hil.linuxcnc.session.ServoTiming`): each period as it
ran (``feeddrive.period-ns``), its distance from the nominal period (the jitter, which
for a thread woken late on an absolute deadline peaks at its largest wake-up latency,
cyclictest's figure), the periods that found no new feedback, and the datagrams each way
per second.  ``emulator`` is ``hil run``'s side over its whole run (its report's adapter
statistics and loop).  ``jitter_over_cyclictest`` divides the servo thread's jitter by
cyclictest's latency in the tails (p99, p99.9, max; a steady latency cancels in a period,
so the medians do not compare): near 1, LinuxCNC's thread wakes as well as the machine
allows; far above, LinuxCNC or the emulator beside it costs the rest.

Exit status 0 when the session passed and cyclictest ran, 1 when the session failed or
cyclictest could not run (the figures are printed all the same), 2 on bad input or where
LinuxCNC cannot be run.
"""

import argparse
import contextlib
import json
import math
import os
import sys
import tempfile
from pathlib import Path

from hil.linuxcnc import session
from hil.linuxcnc.command import DEFAULT_TIMEOUT_S, run_linuxcnc
from hil.rt.cyclictest import CyclictestError, run_cyclictest
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK

ROOT = Path(__file__).resolve().parents[2]
INI = ROOT / "configs" / "linuxcnc" / "arrow500_xyz.ini"
PROGRAM = ROOT / "programs" / "linuxcnc_square.ngc"
#: the shortest cyclictest run, s (cyclictest counts whole seconds)
MIN_CYCLICTEST_S = 5.0
#: the emulator's loop CPU: the first, away from LinuxCNC's real-time threads on the last
EMULATOR_CPU = 0


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) else math.nan


def emulator_side(report: dict | None) -> dict | None:
    """hil run's frames and loop from its report.json (None: no report)."""
    if report is None:
        return None
    stats, loop = report["adapter"]["stats"], report["loop"]
    wall = loop["wall_s"]
    return {**{k: stats[k] for k in ("received", "sent", "lost", "out_of_order",
                                     "duplicates", "malformed")},
            "wall_s": wall, "received_per_s": _ratio(stats["received"], wall),
            "sent_per_s": _ratio(stats["sent"], wall), "overruns": loop["overruns"],
            "ticks": loop["ticks"]}


def figures(ini: Path, out: Path, realtime: bool, cyclictest_s: float | None = None
            ) -> dict:
    """The JSON of the module docstring from a session's files in ``out`` (``realtime``:
    it ran with SCHED_FIFO), with cyclictest run now for ``cyclictest_s`` s (None: as long
    as the machine was on, at least :data:`MIN_CYCLICTEST_S`)."""
    summary = json.loads((out / "linuxcnc.json").read_text())
    report_path = out / "emulator" / "report.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else None
    timing = summary["servo_thread"]
    interval_us = session.read_config(ini).servo_period_ns // 1000
    cpus = summary.get("rt_cpus") or []
    cpu = cpus[-1] if cpus else None
    priority = session.SERVO_PRIORITY if realtime else 0
    if cyclictest_s is None:
        cyclictest_s = max(MIN_CYCLICTEST_S, timing["span_s"] if timing else 0.0)
    cyclictest: dict | str
    try:
        latency = run_cyclictest(interval_us, cyclictest_s, priority=priority, cpu=cpu)
        cyclictest = ("cyclictest is not installed (apt-get install rt-tests)"
                      if latency is None else
                      {"interval_us": interval_us, "seconds": math.ceil(cyclictest_s),
                       "cpu": cpu, "priority": priority, "latency_us": latency.as_dict()})
    except CyclictestError as e:
        cyclictest = str(e)
    ratio = None
    if timing and isinstance(cyclictest, dict):
        # a steady wake-up latency cancels in a period, so only the tails compare
        ratio = {k: _ratio(timing["jitter_us"][k], cyclictest["latency_us"][k])
                 for k in ("p99", "p999", "max")}
    return {"ini": str(ini), "program": summary.get("program"), "verdict": summary["verdict"],
            "realtime": realtime, "servo_thread": timing, "emulator": emulator_side(report),
            "cyclictest": cyclictest, "jitter_over_cyclictest": ratio}


def measure(ini: Path, program: Path, out: Path, realtime: bool, timeout_s: float
            ) -> tuple[int, dict]:
    """The session and :func:`figures`; (exit status of the module docstring, the JSON)."""
    load_before = os.getloadavg()
    with contextlib.redirect_stdout(sys.stderr):  # the session's lines; stdout: the bench's
        status = run_linuxcnc(ini, program, out, [], realtime, timeout_s, EMULATOR_CPU)
    if status == EXIT_BAD_INPUT:
        return status, {}
    result = {**figures(ini, out, realtime), "load_avg_before": list(load_before), "load_avg_after": list(os.getloadavg())}
    passed = (status == EXIT_OK and isinstance(result["cyclictest"], dict)
              and result["servo_thread"] is not None)
    return (EXIT_OK if passed else EXIT_FAILED), result


def _row(name: str, p: dict) -> str:
    return f"    {name:<22}{p['p50']:9.1f}{p['p99']:9.1f}{p['p999']:9.1f}{p['max']:9.1f}"


def text(r: dict) -> str:
    """The report in lines."""
    program = Path(r["program"]).name if r["program"] else "no program"
    lines = [f"hil bench linuxcnc: {Path(r['ini']).name} on {program}: {r['verdict']}"]
    t, c = r["servo_thread"], r["cyclictest"]
    if t is not None:
        lines += [(f"  LinuxCNC's servo thread, {t['nominal_us']:g} µs, {t['periods']} "
                   f"periods while the machine was on ({t['span_s']:.1f} s)"),
                  "    µs                         p50      p99    p99.9      max",
                  _row("period as it ran", t["period_us"]),
                  _row("jitter |period - nom.|", t["jitter_us"])]
    if isinstance(c, dict):
        lines.append(_row("cyclictest latency", c["latency_us"]))
        lines.append(f"    (cyclictest {c['interval_us']} µs for {c['seconds']} s on CPU "
                     f"{c['cpu']}, priority {c['priority']}, after the session)")
    else:
        lines.append(f"  cyclictest: {c}")
    if r["jitter_over_cyclictest"]:
        q = r["jitter_over_cyclictest"]
        lines.append(f"    jitter / cyclictest    {'':>9}{q['p99']:9.2f}{q['p999']:9.2f}"
                     f"{q['max']:9.2f}")
    if t is not None:
        lines.append(f"  frames: {t['setpoints_per_s']:.1f} setpoints/s sent and "
                     f"{t['feedback_per_s']:.1f} feedbacks/s taken by LinuxCNC; "
                     f"{t['stale_periods']} periods without a new feedback")
    e = r["emulator"]
    if e is not None:
        lines.append(f"  hil run: {e['received']} setpoints received ({e['lost']} lost, "
                     f"{e['out_of_order']} out of order, {e['malformed']} malformed), "
                     f"{e['sent']} feedbacks sent in {e['wall_s']:.1f} s; "
                     f"{e['overruns']} overruns in {e['ticks']} ticks")
    load = " ".join(f"{x:.2f}" for x in r["load_avg_before"])
    lines.append(f"  load average before: {load}")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil bench linuxcnc``."""
    p.add_argument("--ini", type=Path, default=INI, help="LinuxCNC INI (default: the Arrow "
                   "500 XYZ, configs/linuxcnc/arrow500_xyz.ini)")
    p.add_argument("--program", type=Path, default=PROGRAM, help="G-code program (default "
                   "programs/linuxcnc_square.ngc)")
    p.add_argument("--out", type=Path, help="keep the session's files here (default: a "
                   "temporary folder)")
    p.add_argument("--no-rt", action="store_true", help="hil run and LinuxCNC's threads "
                   "without SCHED_FIFO; cyclictest then runs at SCHED_OTHER too")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil bench linuxcnc``: print the report; the exit status of the module docstring."""
    with contextlib.ExitStack() as stack:
        out = args.out or Path(stack.enter_context(
            tempfile.TemporaryDirectory(prefix="hil-bench-linuxcnc-")))
        status, result = measure(args.ini.resolve(), args.program.resolve(), out.resolve(),
                                 not args.no_rt, DEFAULT_TIMEOUT_S)
    if status == EXIT_BAD_INPUT:
        return status
    print(json.dumps(result, indent=1) if args.json else text(result))
    return status


def main(argv: list[str] | None = None) -> int:
    """``python3 -m hil.bench.linuxcnc ...``: the same as ``hil bench linuxcnc ...``."""
    parser = argparse.ArgumentParser(prog="hil bench linuxcnc",
                                     description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
