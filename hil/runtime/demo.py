"""``hil demo``: the emulator and the simulated controller as two processes over UDP
loopback, the run replayed and set beside the lock-step simulation, and a verdict.

1. ``hil run`` (``python -m hil.runtime.emulator``) on the machine file, ``udp://127.0.0.1:0``
   (a free port, read back from its ``ready:`` line), on the last CPU;
2. ``hil controller`` (``python -m hil.runtime.controller_proc``) on the same file and URL
   with the part program, on the first CPU when there are two or more;
3. when the controller is done, SIGTERM to the emulator (its clean stop: safe state,
   recording and report written);
4. the three traces (:mod:`hil.replay.timing`): ``hil sim`` of the same program
   (:func:`hil.commands.run_sim`, the lock-step), the **replay** of the emulator's run on
   the setpoints it applied (:func:`hil.replay.replay_run`, checked against the
   **recording** to 1e-9), and the **timing cost** lock-step - replay, with the late and
   missed setpoints counted and the following-error difference each run of them caused;
5. the latency report of the emulator's run with its round trips paired with the
   controller's rows (``hil report emulator --controller controller``; wake-up latency
   and lateness each beside a cyclictest of the same period when rt-tests is installed;
   :mod:`hil.report.latency`);
6. the verdict, the last line printed: ``PASS`` or ``FAIL: <reasons>``
   (:mod:`hil.runtime.demo_verdict`).

Every child gets a timeout and is killed if still running when the demo leaves; each phase
longer than two seconds shows its progress on stderr (:mod:`hil.progress`).  Files go to
``--out``: ``emulator/`` (recording.arrows, events.arrows, report.json and the latency
report: report.md, report_latency.json, latency_hist.png, latency_time.png),
``controller/`` (trace.csv, controller.npz, summary.json), ``lockstep/`` (trace.csv,
sim.png), the two logs and ``demo.json`` (the replay, the timing cost, the verdict).  Exit
status 0 on PASS, 1 on FAIL, 2 when the machine file or the program is refused (before
anything starts).
"""

import argparse
import os
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

from hil.controller.config import clamp_codes, load_controller
from hil.controller.program import ProgramError, read_program
from hil.progress import COLD_START, Progress
from hil.replay import ReplayResult
from hil.replay.timing import LOOP_PEAK, SHOWN_RUNS, TimingCost
from hil.report.baseline import CyclictestBaseline, run_cyclictest_baseline
from hil.report.latency import build_report, load_run, write_report
from hil.report.run_verdict import (
    judge_lockstep_timing,
    judge_timing_counts,
    read_json,
    replay_or_reason,
)
from hil.report.wakeup import wakeup_rows
from hil.rt.cyclictest import CyclictestError
from hil.rt.scheduling import last_cpu
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, eprint, reap, write_json
from hil.runtime.demo_verdict import (
    Verdict,
    check_processes,
    check_replay,
    timing_budget,
)
from plant.config import load_machine
from plant.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_CONFIG = ROOT / "configs" / "arrow500_x.toml"
DEFAULT_PROGRAM = ROOT / "programs" / "demo_moves.nc"
#: longest wait for the emulator's ready line (a cold numba cache compiles for
#: :data:`~hil.progress.COLD_START_S` on an idle machine) ...
READY_TIMEOUT_S = 120.0
#: ... and beyond it, while the emulator keeps working (compiling beside other busy
#: processes took over 120 s on the 2-vCPU VM), up to this long in all
READY_BUSY_MAX_S = 600.0
#: the emulator keeps working when it used at least this share of a CPU over the last
#: BUSY_WINDOW_S seconds
BUSY_SHARE = 0.2
BUSY_WINDOW_S = 10.0
#: what a wait for the emulator's ready line shows
EMULATOR_STARTING = f"emulator compiling and warming up ({COLD_START})"
#: longest wait for the controller beyond its program, and for the emulator's stop
CHILD_TIMEOUT_S = 120.0
#: how often a wait for a child looks again (and updates its progress line), s
POLL_S = 0.25
#: the cyclictest baseline run after the loopback run, s
DEFAULT_CYCLICTEST_S = 5.0


class DemoError(RuntimeError):
    """A child process did not start or finish as expected; the message says which."""


def process_cpu_s(pid: int) -> float:
    """User and system CPU time of process ``pid`` so far, s (0 once it has gone, or off
    Linux)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_ready(proc: subprocess.Popen, timeout_s: float,
               progress: Progress | None = None,
               busy_max_s: float = READY_BUSY_MAX_S) -> str:
    """The URL of the emulator's ``ready: URL`` line on its stdout (``progress`` updated
    while it compiles and warms up).  Past ``timeout_s`` it waits on while the emulator
    keeps working (:data:`BUSY_SHARE` of a CPU over the last :data:`BUSY_WINDOW_S`: a
    compile slowed by other processes), up to ``busy_max_s`` in all; DemoError otherwise."""
    start = time.monotonic()
    samples = [(start, process_cpu_s(proc.pid))]
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while True:
            now = time.monotonic()
            samples.append((now, process_cpu_s(proc.pid)))
            while samples[0][0] < now - BUSY_WINDOW_S and len(samples) > 2:
                samples.pop(0)
            if now - start > timeout_s:
                (t_a, cpu_a), (t_b, cpu_b) = samples[0], samples[-1]
                share = (cpu_b - cpu_a) / max(t_b - t_a, 1e-9)
                if now - start > busy_max_s or share < BUSY_SHARE:
                    raise DemoError(
                        f"the emulator was not ready within {now - start:.0f} s (it used "
                        f"{100 * share:.0f} % of a CPU over the last {t_b - t_a:.0f} s; it "
                        f"is waited for beyond {timeout_s:g} s only while it works, up to "
                        f"{busy_max_s:g} s)")
            if progress is not None:
                progress.update()
            if sel.select(POLL_S):
                line = proc.stdout.readline()
                if line.startswith("ready: "):
                    return line[len("ready: "):].strip()
                if not line:
                    raise DemoError(f"the emulator exited with {proc.wait()} before it was "
                                    "ready")


def wait_exit(proc: subprocess.Popen, timeout_s: float, progress: Progress) -> int:
    """``proc``'s exit status (``progress`` updated meanwhile); TimeoutExpired after
    ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while (status := proc.poll()) is None:
        if time.monotonic() > deadline:
            raise subprocess.TimeoutExpired(proc.args, timeout_s)
        progress.update()
        time.sleep(POLL_S)
    return status


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
                                           "--force",  # the demo's own folder: run again
                                           "--cpu", cpus[-1], *rt),
                                   stdout=subprocess.PIPE, stderr=emu_log, text=True, env=env)
            children.append(emu)
            with Progress(f"hil demo: {EMULATOR_STARTING}") as shown:
                url = wait_ready(emu, READY_TIMEOUT_S, shown)
            eprint(f"hil demo: emulator ready on {url}; controller running {program.name}")
            pin = ["--cpu", cpus[0]] if len(cpus) > 1 else []
            ctl = subprocess.Popen(_python("hil.runtime.controller_proc", config, "--adapter", url,
                                           "--program", program, "--out", out / "controller",
                                           *pin, *rt),
                                   stdout=ctl_log, stderr=subprocess.STDOUT, env=env)
            children.append(ctl)
            with Progress("hil demo: controller and emulator running") as shown:
                ctl_status = wait_exit(ctl, CHILD_TIMEOUT_S, shown)
            emu.send_signal(signal.SIGTERM)
            emu_status = emu.wait(timeout=CHILD_TIMEOUT_S)
            emu_log.write(emu.stdout.read())
        finally:
            reap(children)
    return emu_status, ctl_status


def _timing_rows(emulator: dict, controller: dict) -> list[str]:
    rows = ["loop lateness, µs      p50      p99    p99.9      max   overruns   ticks"]
    for name, loop in (("emulator", emulator["loop"]), ("controller", controller["loop"])):
        lat = loop["lateness_us"]
        rows.append(f"  {name:<12} {lat['p50']:9.2f} {lat['p99']:8.2f} {lat['p999']:8.1f} "
                    f"{lat['max']:8.1f} {loop['overruns']:10d} {loop['ticks']:7d}")
    return rows


def _round_trip_rows(rt: dict) -> list[str]:
    """The round trip's parts (p50, p99) from the latency report's ``round_trip``."""
    rows = [(f"round trip setpoint → feedback, µs    p50      p99   ({rt['samples']} setpoints, "
            f"{rt['pairing']['matched']} paired with the controller's rows)")]
    for label, key in (("transport", "transport_us"), ("wait for tick", "wait_us"),
                       ("compute", "compute_us"), ("total", "total_us")):
        q = rt[key]
        rows.append(f"  {label:<32}" + ("       —        —" if q is None else
                                          f"{q['p50']:7.1f}  {q['p99']:7.1f}"))
    return rows


def _one_way(controller: dict) -> str:
    one_way = controller["alignment"]["one_way_us"]
    return "unknown (no shared clock)" if one_way is None else f"{one_way:.1f}"


def _cost_rows(cost: TimingCost | str, k: float, unit: str) -> list[str]:
    """The three traces and the timing cost (positions times ``k`` in ``unit``)."""
    if isinstance(cost, str):
        return [f"timing cost: not computed ({cost})"]
    t = cost.tolerance
    rows = [f"following error, {unit}                       max",
            f"  lock-step (hil sim)                 {cost.fe_max_lockstep * k:9.2f}",
            f"  replay of the real timing           {cost.fe_max_replay * k:9.2f}",
            (f"timing cost (replay - lock-step FE), {unit}: max {cost.diff_max * k:.2f} at t = "
            f"{cost.diff_max_t_s:.4f} s, rms {cost.diff_rms * k:.2f} over {cost.rows} rows; "
            f"{cost.clean_diff * k:.2f} before the first late setpoint"),
            (f"  tolerance {t.value * k:.2f} {unit}: {LOOP_PEAK:g} x (v_max x m T + a_max x "
             f"(m T)²/2) + 2 counts, m = {t.late_ticks} tick(s) from {timing_budget(t)}"),
            (f"  setpoints due {cost.setpoints}: on time {cost.on_time}, late {cost.late}, "
            f"early {cost.early}, missed {cost.missed}; ticks without a new setpoint "
            f"{cost.held_ticks}; {len(cost.runs)} run(s) of late/missed setpoints")]
    for run in sorted(cost.runs, key=lambda r: -r.fe_diff)[:SHOWN_RUNS]:
        rows.append(f"    at drive tick {run.first_tick}: {run.setpoints} setpoint(s) (late "
                    f"{run.late}, early {run.early}, missed {run.missed}, worst "
                    f"+{run.worst_ticks} ticks) -> FE difference up to {run.fe_diff * k:.2f} "
                    f"{unit}")
    return rows


def summary_lines(replay: ReplayResult | str, cost: TimingCost | str,
                  scale: tuple[float, str], emulator: dict, controller: dict,
                  latency: dict, baseline_note: str) -> list[str]:
    """The demo's printed summary: the replay against the recording, the three traces and
    the timing cost (``scale``: factor and unit of positions), the loops' timing and the
    round trip (``latency``: the latency report), how the cyclictest baseline was made."""
    recording = (f"recording = replay: {replay.line()}" if not isinstance(replay, str)
                 else f"recording = replay: not checked ({replay})")
    return [
        recording, *_cost_rows(cost, *scale),
        *_timing_rows(emulator, controller),
        *wakeup_rows(latency, baseline_note),
        *_round_trip_rows(latency["round_trip"]),
        f"transport one way (measured while aligning), µs   {_one_way(controller)}",
    ]


def _baseline(period_ns: int, seconds: float) -> tuple[CyclictestBaseline | None, str]:
    """cyclictest at the run's period on the loop's CPU, and a note on what was run."""
    interval_us = max(1, round(period_ns / 1e3))
    try:
        with Progress(f"hil demo: cyclictest, {interval_us} µs for {seconds:g} s",
                      ticking=True):
            baseline = run_cyclictest_baseline(interval_us, seconds, cpu=last_cpu())
    except CyclictestError as e:
        return None, f"cyclictest failed: {e}"
    if baseline is None:
        return None, "cyclictest is not installed (apt-get install rt-tests)"
    return baseline, f"cyclictest {interval_us} µs for {seconds:g} s after the run"


def run_demo(config: Path, program: Path, out: Path, realtime: bool,
             cyclictest_s: float = DEFAULT_CYCLICTEST_S) -> int:
    """The whole demo; returns the exit status (0 PASS, 1 FAIL, 2 refused input)."""
    try:  # refuse bad input before any process starts
        cfg = load_machine(config)
        read_program(program, axis="C" if cfg.machine.kind == "rotary" else "X",
                     clamp=clamp_codes(load_controller(cfg)))
    except (ConfigError, ProgramError, OSError) as e:
        eprint(f"hil demo: {e}")
        return EXIT_BAD_INPUT
    out.mkdir(parents=True, exist_ok=True)
    for stale in (out / "controller" / "summary.json", out / "emulator" / "report.json"):
        stale.unlink(missing_ok=True)  # an earlier run's files are not this run's
    verdict = Verdict()
    try:
        emu_status, ctl_status = run_pair(config, program, out, realtime)
    except (DemoError, subprocess.TimeoutExpired) as e:
        verdict.fail(f"{e}; logs in {out}")
        print(verdict.line())
        return EXIT_FAILED
    controller = read_json(out / "controller" / "summary.json") or {}
    emulator = read_json(out / "emulator" / "report.json")
    replay = replay_or_reason(out / "emulator")
    check_replay(verdict, replay)
    check_processes(verdict, emu_status, ctl_status, controller, emulator)
    if emulator is None or not controller:
        print(verdict.line())
        return EXIT_FAILED
    cost, (k, shown) = judge_lockstep_timing(verdict, config, program, 0.0, out / "emulator",
                                             out / "controller", out / "lockstep")
    judge_timing_counts(verdict, emulator, controller, priced=not isinstance(cost, str))
    baseline, note = (_baseline(controller["period_ns"], cyclictest_s) if cyclictest_s > 0
                      else (None, "no cyclictest (--cyclictest-seconds 0)"))
    run = load_run(out / "emulator", controller=out / "controller")
    latency = build_report(run, baseline)
    write_report(out / "emulator", latency, run)
    print(f"hil demo: {emulator['machine']}, {program.name}, "
          f"{1e9 / controller['period_ns']:g} Hz over {emulator['adapter']['name']}")
    print("\n".join(summary_lines(replay, cost, (k, shown), emulator, controller, latency,
                                  note)))
    print(f"files in {out}/")
    write_json(out / "demo.json", {
        "replay": replay if isinstance(replay, str) else replay.as_dict(),
        "timing_cost": cost if isinstance(cost, str) else cost.as_dict(),
        "emulator_exit": emu_status, "controller_exit": ctl_status,
        "verdict": verdict.line(), "reasons": verdict.reasons})
    print(verdict.line())
    return EXIT_OK if verdict.passed else EXIT_FAILED


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil demo``."""
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="machine file (default: "
                   "configs/arrow500_x.toml, the Arrow 500 X)")
    p.add_argument("--program", default=str(DEFAULT_PROGRAM),
                   help="part program (default: programs/demo_moves.nc)")
    p.add_argument("--out", default="demo-out", help="folder for every file (default "
                   "%(default)s)")
    p.add_argument("--no-rt", action="store_true", help="both processes without SCHED_FIFO")
    p.add_argument("--cyclictest-seconds", type=float, default=DEFAULT_CYCLICTEST_S,
                   metavar="S", help="cyclictest at the run's period after it, for the "
                   "timing report (default %(default)g s; 0: none)")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil demo``: returns the exit status."""
    return run_demo(Path(args.config).resolve(), Path(args.program).resolve(),
                    Path(args.out).resolve(), not args.no_rt, args.cyclictest_seconds)


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.runtime.demo``: the same as ``hil demo``."""
    parser = argparse.ArgumentParser(prog="hil demo", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
