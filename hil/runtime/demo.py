"""``hil demo``: the emulator and the simulated controller as two processes over UDP
loopback, then the following error beside the lock-step simulation and the timing.

1. ``hil run`` (``python -m hil.runtime.emulator``) on the machine file, ``udp://127.0.0.1:0``
   (a free port, read back from its ``ready:`` line), on the last CPU;
2. ``hil controller`` (``python -m hil.runtime.controller_proc``) on the same file and URL
   with the part program, on the first CPU when there are two or more;
3. when the controller is done, SIGTERM to the emulator (its clean stop: safe state,
   recording and report written);
4. ``hil sim`` of the same program (:func:`hil.commands.run_sim`), and the comparison;
5. the latency report of the emulator's run with its round trips paired with the
   controller's rows (``hil report emulator --controller controller``, no cyclictest
   baseline; :mod:`hil.report.latency`), its round-trip split printed.

Every child gets a timeout and is killed if still running when the demo leaves.  Files go
to ``--out``: ``emulator/`` (the run folder), ``controller/`` (trace.csv,
controller.npz, summary.json), ``lockstep/`` (trace.csv, sim.png), the latency report
(report.md, report_latency.json, latency_hist.png), the two logs and ``demo.json``.
Exit status 0 when both processes finished cleanly and neither the controller nor the
lock-step simulation raised an alarm, 1 otherwise (the reason printed: the alarms, from the
controller's ``summary.json``, one line each), 2 when the machine file or the program is
refused (before anything starts).
"""

import argparse
import json
import math
import os
import selectors
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from hil.commands import run_sim
from hil.controller.config import clamp_codes, load_controller
from hil.controller.program import ProgramError, read_program
from hil.report.latency import build_report, load_run, write_report
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, eprint, write_json
from hil.runtime.sync import settled_rows
from hil.trace_file import read_trace
from plant.config import load_machine
from plant.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CONFIG = ROOT / "configs" / "arrow500_x.toml"
DEFAULT_PROGRAM = ROOT / "programs" / "demo_moves.nc"
#: longest wait for the emulator's ready line (a cold numba cache compiles ~10 s)
READY_TIMEOUT_S = 120.0
#: longest wait for the controller beyond its program, and for the emulator's stop
CHILD_TIMEOUT_S = 120.0


class DemoError(RuntimeError):
    """A child process did not start or finish as expected; the message says which."""


@dataclass(frozen=True)
class FollowingErrorComparison:
    """Following error (pos_set - pos) of two servo traces, row by row (position-control
    cycles from the program's start), in the traces' unit (mm or deg).

    Attributes:
        rows: rows compared (of the shorter trace, where the mask allows).
        max_a, rms_a: the first trace's (the loopback's) following error on those rows.
        max_b, rms_b: the second's (the lock-step simulation's) on those rows.
        diff_max, diff_rms: of the row-by-row difference.
        final_a, final_b: the last row's actual position.
    """
    rows: int
    max_a: float
    rms_a: float
    max_b: float
    rms_b: float
    diff_max: float
    diff_rms: float
    final_a: float
    final_b: float


def _max_rms(x: np.ndarray) -> tuple[float, float]:
    if x.size == 0:
        return math.nan, math.nan
    return float(np.abs(x).max()), float(np.sqrt(np.mean(x ** 2)))


def compare_following_error(trace_a: Path, trace_b: Path,
                            mask: np.ndarray | None = None) -> FollowingErrorComparison:
    """Compare the following error of two servo-trace files on the rows ``mask`` (of
    ``trace_a``'s rows) selects, all by default (see the class)."""
    a, b = read_trace(trace_a), read_trace(trace_b)
    set_name, pos_name = a.resolve("pos_set_mm"), a.resolve("pos_mm")
    fe_a = a.column(set_name) - a.column(pos_name)
    fe_b = b.column(set_name) - b.column(pos_name)
    n = min(fe_a.size, fe_b.size)
    keep = np.ones(n, bool) if mask is None else mask[:n]
    fe_a, fe_b = fe_a[:n][keep], fe_b[:n][keep]
    return FollowingErrorComparison(int(keep.sum()), *_max_rms(fe_a), *_max_rms(fe_b),
                                    *_max_rms(fe_a - fe_b), float(a.column(pos_name)[-1]),
                                    float(b.column(pos_name)[-1]))


def settled_mask(controller_dir: Path, summary: dict) -> np.ndarray:
    """The controller's trace rows clear of any timing fault (:func:`settled_rows`)."""
    with np.load(controller_dir / "controller.npz") as npz:
        cols = {k: npz[k] for k in ("lag_ticks", "fb_time_s", "tick")}
    return settled_rows(cols, summary["trace_every_ticks"], summary["period_ns"] * 1e-9)


def wait_ready(proc: subprocess.Popen, timeout_s: float) -> str:
    """The URL of the emulator's ``ready: URL`` line on its stdout."""
    deadline = time.monotonic() + timeout_s
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while (left := deadline - time.monotonic()) > 0:
            if sel.select(left):
                line = proc.stdout.readline()
                if line.startswith("ready: "):
                    return line[len("ready: "):].strip()
                if not line:
                    raise DemoError(f"the emulator exited with {proc.wait()} before it was "
                                    "ready")
    raise DemoError(f"the emulator was not ready within {timeout_s:g} s")


def _python(module: str, *args) -> list[str]:
    return [sys.executable, "-m", module, *map(str, args)]


def run_pair(config: Path, program: Path, out: Path, realtime: bool) -> tuple[int, int]:
    """Emulator and controller as child processes; returns their exit statuses."""
    cpus = sorted(os.sched_getaffinity(0))
    rt = [] if realtime else ["--no-rt"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (
        str(ROOT), os.environ.get("PYTHONPATH"))))}
    children = []
    with open(out / "emulator.log", "w") as emu_log, open(out / "controller.log", "w") as ctl_log:
        try:
            emu = subprocess.Popen(_python("hil.runtime.emulator", config, "--adapter",
                                           "udp://127.0.0.1:0", "--record", out / "emulator",
                                           "--cpu", cpus[-1], *rt),
                                   stdout=subprocess.PIPE, stderr=emu_log, text=True, env=env)
            children.append(emu)
            url = wait_ready(emu, READY_TIMEOUT_S)
            eprint(f"hil demo: emulator ready on {url}; controller running {program.name}")
            pin = ["--cpu", cpus[0]] if len(cpus) > 1 else []
            ctl = subprocess.Popen(_python("hil.runtime.controller_proc", config, "--adapter", url,
                                           "--program", program, "--out", out / "controller",
                                           *pin, *rt),
                                   stdout=ctl_log, stderr=subprocess.STDOUT, env=env)
            children.append(ctl)
            ctl_status = ctl.wait(timeout=CHILD_TIMEOUT_S)
            emu.send_signal(signal.SIGTERM)
            emu_status = emu.wait(timeout=CHILD_TIMEOUT_S)
            emu_log.write(emu.stdout.read())
        finally:
            for child in children:
                if child.poll() is None:
                    child.kill()
                    child.wait()
            if children:
                children[0].stdout.close()
    return emu_status, ctl_status


def _timing_rows(emulator: dict, controller: dict) -> list[str]:
    rows = ["loop lateness, µs      p50      p99    p99.9      max   overruns   ticks"]
    for name, loop in (("emulator", emulator["loop"]), ("controller", controller["loop"])):
        lat = loop["lateness_us"]
        rows.append(f"  {name:<12} {lat['p50']:9.2f} {lat['p99']:8.2f} {lat['p999']:8.1f} "
                    f"{lat['max']:8.1f} {loop['overruns']:10d} {loop['ticks']:7d}")
    return rows


def _fe_rows(label: str, cmp: FollowingErrorComparison, k: float, rows: int) -> list[str]:
    if not cmp.rows:
        return [f"  {label}: none of {rows} rows"]
    share = f"{100 * cmp.diff_max / cmp.max_b:.2f} %"
    return [f"  {label}: {cmp.rows} of {rows} rows",
            f"    loopback    {cmp.max_a * k:9.2f} {cmp.rms_a * k:8.2f}",
            f"    lock-step   {cmp.max_b * k:9.2f} {cmp.rms_b * k:8.2f}",
            f"    difference  {cmp.diff_max * k:9.2f} {cmp.diff_rms * k:8.2f}   "
            + f"({share} of the lock-step maximum)"]


def _round_trip_rows(rt: dict) -> list[str]:
    """The round trip's parts (p50, p99) from the latency report's ``round_trip``."""
    rows = [f"round trip setpoint → feedback, µs    p50      p99   ({rt['samples']} setpoints, "
            f"{rt['pairing']['matched']} paired with the controller's rows)"]
    for label, key in (("transport", "transport_us"), ("wait for tick", "wait_us"),
                       ("compute", "compute_us"), ("total", "total_us")):
        q = rt[key]
        rows.append(f"  {label:<32}" + ("       —        —" if q is None else
                                          f"{q['p50']:7.1f}  {q['p99']:7.1f}"))
    return rows


def _one_way(controller: dict) -> str:
    one_way = controller["alignment"]["one_way_us"]
    return "unknown (no shared clock)" if one_way is None else f"{one_way:.1f}"


def summary_lines(every: FollowingErrorComparison, settled: FollowingErrorComparison,
                  emulator: dict, controller: dict, unit: str,
                  round_trip: dict) -> list[str]:
    """The demo's printed summary (micrometres for the following error on mm axes);
    ``round_trip`` is the latency report's."""
    k, shown = (1e3, "µm") if unit == "mm" else (1.0, unit)
    fb = controller["feedback"]
    n = max(1, controller["ticks_recorded"])
    return [
        f"following error, {shown}         max      rms",
        *_fe_rows("every row", every, k, every.rows),
        *_fe_rows("rows clear of timing faults", settled, k, every.rows),
        f"  final position: loopback {every.final_a:.4f} {unit}, lock-step "
        + f"{every.final_b:.4f} {unit}",
        *_timing_rows(emulator, controller),
        *_round_trip_rows(round_trip),
        f"transport one way (measured while aligning), µs   {_one_way(controller)}",
        f"controller ticks at lock-step timing: {100 * fb['ticks_in_step'] / n:.2f} %",
    ]


def run_demo(config: Path, program: Path, out: Path, realtime: bool) -> int:
    """The whole demo; returns the exit status."""
    try:  # refuse bad input before any process starts
        cfg = load_machine(config)
        read_program(program, axis="C" if cfg.machine.kind == "rotary" else "X",
                     clamp=clamp_codes(load_controller(cfg)))
    except (ConfigError, ProgramError, OSError) as e:
        eprint(f"hil demo: {e}")
        return EXIT_BAD_INPUT
    out.mkdir(parents=True, exist_ok=True)
    summary_file = out / "controller" / "summary.json"
    summary_file.unlink(missing_ok=True)  # an earlier run's alarms are not this run's
    try:
        emu_status, ctl_status = run_pair(config, program, out, realtime)
    except (DemoError, subprocess.TimeoutExpired) as e:
        eprint(f"hil demo: {e}; logs in {out}")
        return EXIT_FAILED
    controller = json.loads(summary_file.read_text()) if summary_file.exists() else {}
    alarms = controller.get("alarms", [])
    if (emu_status, ctl_status) != (EXIT_OK, EXIT_OK) or alarms:
        eprint(f"hil demo: emulator exited with {emu_status}, controller with {ctl_status}; "
               f"logs in {out}")
        for alarm in alarms:
            eprint(f"hil demo: the controller raised {alarm['message']}")
        return EXIT_FAILED
    sim = run_sim(config, program, out / "lockstep", 0.0, None, None)
    if sim["alarms"]:
        for alarm in sim["alarms"]:
            eprint(f"hil demo: the lock-step simulation raised {alarm['message']}")
        return EXIT_FAILED
    emulator = json.loads((out / "emulator" / "report.json").read_text())
    loopback = out / "controller" / "trace.csv"
    every = compare_following_error(loopback, Path(sim["trace"]))
    settled = compare_following_error(loopback, Path(sim["trace"]),
                                      settled_mask(out / "controller", controller))
    unit = "deg" if "following_error_max_deg" in controller else "mm"
    latency = build_report(load_run(out / "emulator", controller=out / "controller"))
    write_report(out, latency)
    print(f"hil demo: {emulator['machine']}, {program.name}, "
          f"{1e9 / controller['period_ns']:g} Hz over {emulator['adapter']['name']}")
    print("\n".join(summary_lines(every, settled, emulator, controller, unit,
                                  latency["round_trip"])))
    print(f"files in {out}/")
    write_json(out / "demo.json", {"following_error": asdict(every),
                                   "following_error_settled": asdict(settled), "unit": unit,
                                   "emulator_exit": emu_status, "controller_exit": ctl_status})
    return EXIT_OK


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil demo``."""
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="machine file (default: "
                   "the Arrow 500 X)")
    p.add_argument("--program", default=str(DEFAULT_PROGRAM),
                   help="part program (default: programs/demo_moves.nc)")
    p.add_argument("--out", default="demo-out", help="folder for every file (default "
                   "%(default)s)")
    p.add_argument("--no-rt", action="store_true", help="both processes without SCHED_FIFO")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil demo``: returns the exit status."""
    return run_demo(Path(args.config).resolve(), Path(args.program).resolve(),
                    Path(args.out).resolve(), not args.no_rt)


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.runtime.demo``: the same as ``hil demo``."""
    parser = argparse.ArgumentParser(prog="hil demo", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
