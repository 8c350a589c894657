"""``hil soak``: the emulator and a controller as two processes for minutes or hours, their
memory and timing watched.

::

    hil soak --minutes 30 --rate 4000 [--config FILE] [--no-rt] [--out DIR]

1. ``hil run`` (``python -m hil.runtime.emulator``) on the machine file at ``--rate``,
   ``udp://127.0.0.1:0``, on the last CPU, recording into ``DIR/emulator``, the table
   mid-travel; its ``ready:`` line gives the URL (:func:`hil.runtime.demo.wait_ready`);
2. the soak master (:mod:`hil.runtime.soak_master`: CSP targets on a sine, at the same
   rate) on the first CPU when there are two, for ``--minutes``;
3. meanwhile each process's resident memory (``VmRSS``) every ``--rss-every`` seconds;
4. when the master is done, SIGTERM to the emulator (its clean stop), then the figures:
   per minute and process the lateness p50/p99/p99.9 and the overruns (the emulator's from
   its recording, the master's from its summary), the RSS growth (last sample minus the
   first after the warm-up, :func:`warmup_s`) and slope (least squares over the same
   samples), and the two goals: RSS growth under :data:`RSS_GOAL_MB` and the last
   window's p99.9 lateness within :data:`LATENESS_GOAL` of the first window's (windows of
   five minutes, a third of the run when shorter);
5. ``DIR/soak.json`` and ``DIR/soak.png`` (RSS, lateness, overruns against time).

Each of these phases that takes longer than two seconds shows its progress on stderr
(:mod:`hil.progress`): the emulator's start, the run (the share of ``--minutes`` done), the
emulator's stop, the figures; stdout has the summary alone.

Exit status 0 when both processes ended cleanly (whatever the goals say: they are
measurements, printed and in the JSON), 1 otherwise, 2 on bad input.
"""

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

from hil.progress import Progress
from hil.rt.loop import Percentiles
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, eprint, reap, write_json
from hil.runtime.demo import (
    DEFAULT_CONFIG,
    EMULATOR_STARTING,
    POLL_S,
    READY_TIMEOUT_S,
    ROOT,
    DemoError,
    wait_ready,
)
from hil.runtime.record_reader import Recording
from hil.runtime.soak_master import SUMMARY
from plant.config import load_machine
from plant.errors import ConfigError

#: RSS samples in the first this share of the run, and at least the first WARMUP_MIN_S
#: (but never more than half the run), are the warm-up, left out of the growth and slope:
#: the allocators' pools fill in the first half minute or so
WARMUP_SHARE = 0.1
WARMUP_MIN_S = 30.0
#: the goals of issue 11: RSS growth (MB) over the run, and the last window's p99.9
#: lateness over the first window's
RSS_GOAL_MB = 5.0
LATENESS_GOAL = 1.2
WINDOW_MIN = 5.0
#: how long the children get beyond the run, s
EXIT_S = 120.0


def rss_mb(pid: int) -> float | None:
    """Resident memory of process ``pid``, MB (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _python(module: str, *args) -> list[str]:
    return [sys.executable, "-m", module, *map(str, args)]


def warmup_s(run_s: float) -> float:
    """The warm-up of a run of ``run_s`` seconds, s (see :data:`WARMUP_SHARE`)."""
    return min(max(WARMUP_SHARE * run_s, WARMUP_MIN_S), 0.5 * run_s)


def memory_trend(samples: list[tuple[float, float]], run_s: float) -> dict:
    """RSS growth (MB) and slope (MB/min) over the samples after the warm-up."""
    kept = [(t, mb) for t, mb in samples if t >= warmup_s(run_s)]
    if len(kept) < 2:
        return {"growth_mb": None, "slope_mb_per_min": None, "samples": len(kept)}
    t, mb = np.array(kept).T
    slope = np.polyfit(t / 60.0, mb, 1)[0]
    return {"growth_mb": float(mb[-1] - mb[0]), "slope_mb_per_min": float(slope),
            "first_mb": float(mb[0]), "last_mb": float(mb[-1]), "samples": len(kept)}


def _minute(minute: int, lateness: list[np.ndarray], overruns: int) -> dict:
    values = np.concatenate(lateness) if lateness else np.empty(0, np.int64)
    return {"minute": minute, "ticks": int(values.size), "overruns": overruns,
            "lateness_us": Percentiles.of_ns_in_us(values).as_dict()}


def emulator_minutes(rec: Recording) -> list[dict]:
    """Per minute of the emulator's recording: ticks, overruns, lateness percentiles
    (read a flush at a time)."""
    period = rec.period_ns
    per_minute = round(60e9 / period)
    minutes, lateness, overruns, current = [], [], 0, 0
    for rows in rec.batches(["tick", "lateness_ns", "compute_ns"]):
        minute = rows["tick"] // per_minute
        late = rows["lateness_ns"] + rows["compute_ns"] > period
        for m in np.unique(minute).tolist():
            if m != current:
                minutes.append(_minute(current, lateness, overruns))
                lateness, overruns, current = [], 0, m
            here = minute == m
            lateness.append(rows["lateness_ns"][here])
            overruns += int(late[here].sum())
    minutes.append(_minute(current, lateness, overruns))
    return minutes


def window_ratio(rec: Recording, run_s: float) -> dict:
    """p99.9 lateness of the emulator's first and last window (module docstring): the
    recording's first and last ``window_s``."""
    window = min(WINDOW_MIN * 60.0, run_s / 3.0)
    width = window * 1e9 / rec.period_ns  # ticks
    first, tail = [], deque()
    for rows in rec.batches(["tick", "lateness_ns"]):
        tick = rows["tick"]
        first.append(rows["lateness_ns"][tick < width])
        tail.append((tick, rows["lateness_ns"]))
        while tail[0][0][-1] < tick[-1] - width:
            tail.popleft()
    end = tail[-1][0][-1] if tail else 0
    last = [lat[t > end - width] for t, lat in tail]
    p_first = Percentiles.of_ns_in_us(np.concatenate(first or [np.empty(0, np.int64)])).p999
    p_last = Percentiles.of_ns_in_us(np.concatenate(last or [np.empty(0, np.int64)])).p999
    return {"window_s": window, "first_p999_us": p_first, "last_p999_us": p_last,
            "ratio": p_last / p_first if p_first > 0 else None}


def plot(result: dict, path: Path) -> None:
    """RSS, lateness per minute and overruns per minute of both processes."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_rss, ax_lat, ax_ovr) = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    warmup_min = warmup_s(result["minutes"] * 60.0) / 60.0
    for name, proc in result["processes"].items():
        t, mb = np.array(proc["rss_mb"]).T if proc["rss_mb"] else np.empty((2, 0))
        after = t >= warmup_min * 60.0  # the growth the goal is about
        base = proc["memory"].get("first_mb") or 0.0
        ax_rss.plot(t[after] / 60.0, mb[after] - base,
                    label=f"{name} (RSS after the warm-up {base:.0f} MB)")
        minutes = proc["minutes"]
        x = [m["minute"] + 0.5 for m in minutes]
        for key, style in (("p50", ":"), ("p99", "--"), ("p999", "-")):
            ax_lat.plot(x, [m["lateness_us"][key] for m in minutes], style,
                        label=f"{name} {key.replace('p999', 'p99.9')}")
        ax_ovr.plot(x, [m["overruns"] for m in minutes], "o-", label=name)
    ax_rss.set_ylabel("RSS growth after\nthe warm-up, MB")
    ax_lat.set_ylabel("lateness, µs")
    ax_lat.set_yscale("log")
    ax_ovr.set_ylabel("overruns per minute")
    ax_ovr.set_xlabel("time, min")
    for ax in (ax_rss, ax_lat, ax_ovr):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    rt = "real time" if result["realtime"] else "--no-rt"
    fig.suptitle(f"hil soak: {result['minutes']:g} min at {result['rate_hz']:g} Hz, {rt}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _start_arg(config: Path) -> str:
    """The emulator's --start: mid-travel (mm) on a table with a stroke, 0 on a rotary one."""
    cfg = load_machine(config)
    return str(cfg.table.travel_m * 500.0) if cfg.table is not None else "0"


def sample_rss(emu: subprocess.Popen, master: subprocess.Popen, seconds: float,
               every_s: float, samples: dict, progress: Progress) -> None:
    """Until the master ends: both processes' RSS every ``every_s`` into ``samples``, and
    ``progress`` (ms of the run's ``seconds``) every :data:`POLL_S`."""
    t0 = time.monotonic()
    due = 0.0
    while master.poll() is None:
        t = time.monotonic() - t0
        if t >= due:
            for name, proc in (("emulator", emu), ("master", master)):
                mb = rss_mb(proc.pid)
                if mb is not None:
                    samples[name].append((t, mb))
            due += every_s
        if t > seconds + EXIT_S:
            raise DemoError(f"the master did not finish {EXIT_S:g} s after its "
                            f"{seconds:g} s")
        progress.update(min(round(t * 1e3), progress.total))
        time.sleep(min(POLL_S, every_s))


def run_children(args: argparse.Namespace, out: Path) -> tuple[int, int, dict]:
    """Emulator and master as child processes, RSS sampled; their exit statuses and the
    samples (process name -> [(t_s, MB), ...])."""
    cpus = sorted(os.sched_getaffinity(0))
    rt = ["--no-rt"] if args.no_rt else []
    seconds = args.minutes * 60.0
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (
        str(ROOT), os.environ.get("PYTHONPATH"))))}
    samples = {"emulator": [], "master": []}
    children = []
    with open(out / "emulator.log", "w") as emu_log, open(out / "master.log", "w") as m_log:
        try:
            emu = subprocess.Popen(_python(
                "hil.runtime.emulator", args.config, "--adapter", "udp://127.0.0.1:0",
                "--record", out / "emulator", "--force", "--rate", args.rate, "--cpu",
                cpus[-1], "--start", _start_arg(args.config), *rt),
                stdout=subprocess.PIPE, stderr=emu_log, text=True, env=env)
            children.append(emu)
            with Progress(f"hil soak: {EMULATOR_STARTING}") as shown:
                url = wait_ready(emu, READY_TIMEOUT_S, shown)
            pin = ["--cpu", cpus[0]] if len(cpus) > 1 else []
            master = subprocess.Popen(_python(
                "hil.runtime.soak_master", args.config, "--adapter", url, "--rate", args.rate,
                "--seconds", seconds, "--out", out / "master", *pin, *rt),
                stdout=m_log, stderr=subprocess.STDOUT, env=env)
            children.append(master)
            # the run's share done, in ms of its length (the line then says how far it is)
            with Progress(f"hil soak: the master drives the emulator for {seconds:g} s",
                          total=max(1, round(seconds * 1e3))) as shown:
                sample_rss(emu, master, seconds, args.rss_every, samples, shown)
            with Progress("hil soak: the emulator stopping (its recording and report "
                          "written)", ticking=True):
                emu.send_signal(signal.SIGTERM)
                emu_status = emu.wait(timeout=EXIT_S)
        finally:
            reap(children)
    return emu_status, master.returncode, samples


def run_soak(args: argparse.Namespace) -> int:
    """The whole soak; returns the exit status."""
    out = Path(args.out).resolve()
    try:
        load_machine(args.config)
        if not args.minutes > 0 or not args.rate > 0 or not args.rss_every > 0:
            raise ValueError("--minutes, --rate and --rss-every must be > 0")
    except (ConfigError, ValueError) as e:
        eprint(f"hil soak: {e}")
        return EXIT_BAD_INPUT
    out.mkdir(parents=True, exist_ok=True)
    try:
        emu_status, master_status, samples = run_children(args, out)
    except (DemoError, subprocess.TimeoutExpired) as e:
        eprint(f"hil soak: {e}; logs in {out}")
        return EXIT_FAILED
    with Progress("hil soak: the figures from the recording, and the plot", ticking=True):
        result = soak_result(args, out, emu_status, master_status, samples)
    print("\n".join(summary_lines(result)))
    print(f"files in {out}/")
    return EXIT_OK if (emu_status, master_status) == (EXIT_OK, EXIT_OK) else EXIT_FAILED


def soak_result(args: argparse.Namespace, out: Path, emu_status: int, master_status: int,
                samples: dict) -> dict:
    """The soak's figures (module docstring, 4.) from both processes' files and the RSS
    ``samples``; ``DIR/soak.json`` and ``DIR/soak.png`` written."""
    run_s = args.minutes * 60.0
    master = json.loads((out / "master" / SUMMARY).read_text())
    recording = Recording(out / "emulator")
    result = {
        "minutes": args.minutes, "rate_hz": args.rate, "realtime": not args.no_rt,
        "config": str(args.config), "exit": {"emulator": emu_status, "master": master_status},
        "processes": {
            "emulator": {"rss_mb": samples["emulator"], "minutes": emulator_minutes(recording),
                         "memory": memory_trend(samples["emulator"], run_s)},
            "master": {"rss_mb": samples["master"], "minutes": master["minutes"],
                       "memory": memory_trend(samples["master"], run_s)}},
        "emulator_lateness_windows": window_ratio(recording, run_s),
        "master_dropped_out": master["dropped_out"],
    }
    growth = [p["memory"]["growth_mb"] for p in result["processes"].values()]
    ratio = result["emulator_lateness_windows"]["ratio"]
    result["goals"] = {"rss_growth_under_mb": RSS_GOAL_MB,
                       "rss_met": all(g is not None and g < RSS_GOAL_MB for g in growth),
                       "lateness_ratio_within": LATENESS_GOAL,
                       "lateness_met": ratio is not None and ratio <= LATENESS_GOAL}
    write_json(out / "soak.json", result)
    plot(result, out / "soak.png")
    return result


def summary_lines(result: dict) -> list[str]:
    """The printed summary: per process RSS and lateness over the run, the goals."""
    rt = "real time" if result["realtime"] else "--no-rt"
    lines = [f"hil soak: {result['minutes']:g} min at {result['rate_hz']:g} Hz, {rt}",
             "process      RSS first → last MB  growth MB  slope MB/min   lateness p99.9 µs "
             "(first → last minute)   overruns"]
    for name, proc in result["processes"].items():
        m, minutes = proc["memory"], proc["minutes"]
        first = minutes[0]["lateness_us"]["p999"] if minutes else float("nan")
        last = minutes[-1]["lateness_us"]["p999"] if minutes else float("nan")
        overruns = sum(x["overruns"] for x in minutes)
        if m["growth_mb"] is None:
            lines.append(f"  {name:<10} (too few RSS samples)")
            continue
        lines.append(f"  {name:<10} {m['first_mb']:8.1f} → {m['last_mb']:6.1f}   "
                     f"{m['growth_mb']:8.2f}   {m['slope_mb_per_min']:10.3f}   "
                     f"{first:10.1f} → {last:8.1f}   {overruns:8d}")
    w = result["emulator_lateness_windows"]
    goals = result["goals"]
    lines.append(f"emulator p99.9 lateness, first {w['window_s']:g} s {w['first_p999_us']:.1f} "
                 f"µs, last {w['last_p999_us']:.1f} µs: ratio "
                 f"{w['ratio']:.2f} (goal <= {LATENESS_GOAL}: "
                 f"{'met' if goals['lateness_met'] else 'NOT met'}); RSS growth goal < "
                 f"{RSS_GOAL_MB:g} MB: {'met' if goals['rss_met'] else 'NOT met'}")
    return lines


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil soak``."""
    p.add_argument("--minutes", type=float, default=30.0, help="how long (default 30)")
    p.add_argument("--rate", type=float, default=4000.0,
                   help="loop rate of both processes, Hz; must divide the PWM frequency "
                        "(default 4000)")
    p.add_argument("--config", default=str(DEFAULT_CONFIG),
                   help="machine file (default: configs/arrow500_x.toml, the Arrow 500 X)")
    p.add_argument("--no-rt", action="store_true", help="both processes without SCHED_FIFO")
    p.add_argument("--rss-every", type=float, default=5.0, metavar="S",
                   help="RSS sample period, s (default 5)")
    p.add_argument("--out", default="soak-out", help="folder for everything "
                   "(default %(default)s)")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil soak``: returns the exit status."""
    return run_soak(args)
