"""``hil bench tick``: the emulator's whole tick, its socket calls, its compiled work and
the glue between them, against the plant step alone (issues 12 part 6 and 29).

The loop is ``hil run``'s: the emulator (:class:`~hil.runtime.emulator.Emulator`) on
the UDP adapter on 127.0.0.1 runs its own :class:`~hil.runtime.streaming_loop.
StreamingLoop` for ``seconds`` at the machine's rate (8 kHz on the Arrow 500 X), the
steady ticks in the compiled loop (:mod:`hil.runtime.steady_tick`), the others in
Python, without real-time scheduling (the figures are the code's, not the scheduler's).
A controller in a child process (spawn) enables the drives with the CiA 402 sequence and
then moves them in CSP (a cosine of :data:`AMPLITUDE_COUNTS` at :data:`MOTION_HZ`, with
its speed feed-forward), one setpoint per period of its own clock, reading the newest
feedback without waiting on the socket (as ``hil controller`` does).  A thread of this
process takes the recording's rows as the writer process would, so every tick writes
its row.  After the run, one plant step alone (``Plant.step(sub_per_pwm)`` on a twin of
axis 0's plant, fed the inputs the run ended with) is timed :data:`PLANT_SAMPLES` times.
JSON, per machine file::

    {"config", "axes", "rate_hz", "drive", "seconds", "ticks",
     "tick_compute_us": {"p50", "p99", "p999", "max"}, "lateness_us": {...},
     "plant_step_us": {"p50", "p999"}, "ratio_p50", "overruns", "grace_overruns",
     "setpoints_heard",
     "ticks_lost_to_the_ring", "load_avg_1min", "exits", "compiled_share",
     "compiled_loop": {...} or null, "compiled_tick_us": {...}, "socket_calls_us": {...},
     "compiled_work_us": {...}, "glue_us": {...}, "python_per_call_us",
     "ratio_compiled_work_p50"}

``tick_compute_us`` is every tick's compute time as the loop measured it (from its
wake-up to its end), ``lateness_us`` its wake-up after the deadline; ``ratio_p50`` the
tick's p50 over the plant step's; an overrun is a tick that ended after the next
deadline (``grace_overruns``: those of the loop's grace period, counted apart).  Of the ticks the compiled loop ran (``compiled_share`` of all;
``compiled_loop``: its counts, :meth:`~hil.runtime.steady_tick.SteadyTick.as_dict`),
each stamped in the loop (:data:`~hil.runtime.steady_tick.T_WAKE` ...):
``compiled_tick_us`` the whole tick, ``socket_calls_us`` its ``recvmsg`` calls (the
datagrams and the empty read after them) and its ``sendto``, ``compiled_work_us`` the
setpoints decoded, every axis's drive cycles with the plant's sub-steps, the answer
encoded and the recording row written, ``glue_us`` the rest: the books kept between the
work and the send, plus Python's time around the compiled calls
(``python_per_call_us`` a call) shared by the ticks each call ran;
``ratio_compiled_work_p50`` the work's p50 over the plant step's.  ``exits``: how often
a drive handed a cycle back to Python, by reason.  ``--python-drive`` times the same
loop with every drive cycle in Python (``"drive": "python"``), the reference.  The goals
(issue 29, on a quiet 2-vCPU VM): glue p50 <= 1 µs on every machine; the five-axis
``configs/machines/geiss_5axis.toml`` at 8 kHz with tick p50 <= 25 µs and p99.9 <= 60 µs.
"""

import argparse
import json
import math
import multiprocessing
import os
import threading
import time
from pathlib import Path

import numpy as np

from hil.cia402 import EnableSequencer
from hil.drive import compiled as C
from hil.progress import COLD_START, Progress
from hil.rt.loop import Percentiles
from hil.runtime import steady_tick as S
from hil.runtime.emulator import Emulator, RuntimeConfig, short_gil_switch
from io_adapters import open_endpoint
from io_adapters.messages import MODE_CSP, axis_records, message_pair
from plant import Plant
from plant.machines import load_machine_set

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
#: the machine files timed by default: one axis, and two axes of the same drive
DEFAULT_CONFIGS = (CONFIGS / "arrow500_x.toml", CONFIGS / "machines" / "arrow500_xy.toml")
#: the controller's motion: a cosine of this amplitude, increments, at this frequency, Hz
AMPLITUDE_COUNTS = 50_000.0
MOTION_HZ = 1.0
#: longest wait for the child to start (imports), s
START_S = 60.0
#: the controller's spin (rather than sleep) for the last this-many ns before a deadline
#: (it need not be punctual, and shares the machine)
CONTROLLER_SPIN_NS = 20_000
#: how often the bench's drain takes the ring's rows, s (the ring holds about a second)
DRAIN_S = 0.05
#: plant steps timed alone after the run
PLANT_SAMPLES = 20_000


def controller(port: int, n_axes: int, period_ns: int, conn) -> None:
    """The child: enable, then CSP motion, one setpoint per period of its own clock (as
    ``hil controller`` and a CNC pace themselves: it never waits on the socket, so the
    emulator's answer wakes nobody); ends when ``conn`` has a message."""
    with open_endpoint(f"udp://127.0.0.1:{port}", "controller") as ep:
        ep.drain = True
        sp, fb = message_pair(n_axes)
        enable = EnableSequencer(timeout_cycles=10_000)
        enable.enable()
        start = None
        conn.send("ready")
        seq = 0
        deadline = time.monotonic_ns()
        while not conn.poll():
            ep.recv_feedback(fb, 0.0)
            seq += 1
            sp.seq = seq
            fbs = axis_records(fb)
            sp.controlword = enable.next_controlword(fbs[0].statusword)
            if start is None and enable.done:
                start = [f.encoder_counts for f in fbs], fbs[0].time_s
            for s, f, i in zip(axis_records(sp), fbs, range(n_axes)):
                s.mode = MODE_CSP
                if start is None:
                    s.target_position_counts = f.encoder_counts
                    continue
                phase = 2.0 * math.pi * MOTION_HZ * (f.time_s - start[1])
                s.target_position_counts = start[0][i] + AMPLITUDE_COUNTS * (
                    1.0 - math.cos(phase))
                s.velocity_offset_counts_s = (AMPLITUDE_COUNTS * 2.0 * math.pi * MOTION_HZ
                                              * math.sin(phase))
            ep.send_setpoint(sp)
            deadline += period_ns
            _wait_until(deadline, CONTROLLER_SPIN_NS)


def _wait_until(deadline_ns: int, spin_ns: int) -> int:
    """Sleep, then spin for the last ``spin_ns``, until ``deadline_ns`` (monotonic);
    returns the time woken."""
    now = time.monotonic_ns()
    if deadline_ns - now > spin_ns:
        time.sleep((deadline_ns - now - spin_ns) * 1e-9)
    while (now := time.monotonic_ns()) < deadline_ns:
        pass
    return now


def bench(config: Path, seconds: float, compiled: bool = True) -> dict:
    """Time ``seconds`` of ticks of ``config`` (see the module docstring); ``compiled``
    False: every drive cycle in Python (the reference: the tick before issue 12's part
    6)."""
    machine = load_machine_set(config)
    rc = RuntimeConfig(config, "udp://127.0.0.1:0", realtime=False, steady_tick=compiled,
                       duration_s=seconds)
    name = config.name
    with Progress(f"hil bench tick: {name}: the emulator loading its compiled kernels and "
                  f"warming up ({COLD_START})", ticking=True):
        emulator = Emulator(rc, machine, log=lambda message: None)
        if not compiled:
            for d in emulator.drives.drives:
                d.compiled = None
        emulator.open()  # the compiled tick is built here
    period_ns = emulator.timing.period_ns
    n_ticks = emulator.timing.n_ticks
    drives = emulator.drives.drives
    ctx = multiprocessing.get_context("spawn")
    parent, child_conn = ctx.Pipe()
    steady = emulator.steady
    trace = steady.keep_trace(n_ticks) if steady is not None else None
    child = ctx.Process(target=controller, args=(emulator.endpoint.address[1],
                                                  len(drives), period_ns, child_conn))
    child.start()
    drain = Drain(emulator.recorder, n_ticks)
    try:
        with Progress(f"hil bench tick: {name}: the controller process starting",
                      ticking=True):
            if not parent.poll(START_S):
                raise RuntimeError(f"the controller process did not start within {START_S} s")
            parent.recv()
        drain.start()
        # shown at the start and ended with the run, never updated meanwhile: a thread of
        # this process would take the GIL from the loop
        with short_gil_switch(), Progress(f"hil bench tick: {name}: the loop measured for "
                                          f"{seconds:g} s") as shown:
            shown.expect(seconds)
            stats = emulator.loop.run()
    finally:
        drain.stop()
        parent.send("stop")
        child.join(5.0)
        if child.is_alive():
            child.kill()
            child.join()
        emulator.endpoint.close()
    ran = drain.compute >= 0
    tick_p = Percentiles.of_ns_in_us(drain.compute[ran])
    plant_p = Percentiles.of_ns_in_us(_plant_steps(machine.configs[0], emulator))
    row = {"config": str(config), "axes": len(drives), "rate_hz": emulator.timing.rate_hz,
           "drive": "compiled" if compiled else "python",
           "seconds": n_ticks * period_ns * 1e-9, "ticks": stats.ticks,
           "tick_compute_us": tick_p.as_dict(),
           "lateness_us": Percentiles.of_ns_in_us(drain.lateness[ran]).as_dict(),
           "plant_step_us": {"p50": plant_p.p50, "p999": plant_p.p999},
           "ratio_p50": tick_p.p50 / plant_p.p50,
           "overruns": stats.overruns, "grace_overruns": stats.grace_overruns,
           "setpoints_heard": emulator.setpoints_heard,
           "ticks_lost_to_the_ring": emulator.recorder.lost,
           "load_avg_1min": os.getloadavg()[0]}
    exits = {name: sum(d.compiled.exits[code] for d in drives if d.compiled is not None)
             for code, name in C.EXIT_NAMES.items()}
    row["exits"] = exits
    if steady is None:
        return {**row, "compiled_share": 0.0, "compiled_loop": None}
    t = trace[trace[:, S.T_WAKE] != 0]
    socket_ns = t[:, S.T_RECEIVED] - t[:, S.T_WAKE] + t[:, S.T_SENT] - t[:, S.T_SENDING]
    work_ns = t[:, S.T_WORKED] - t[:, S.T_RECEIVED]
    # the books between the work and the send, and Python's time around the calls,
    # shared by their ticks
    glue_ns = (t[:, S.T_SENDING] - t[:, S.T_WORKED]
               + (steady.python_ns // max(1, steady.ticks)))
    work_p = Percentiles.of_ns_in_us(work_ns)
    return {**row, "compiled_share": steady.ticks / max(1, stats.ticks),
            "compiled_loop": steady.as_dict(),
            "compiled_tick_us": Percentiles.of_ns_in_us(
                t[:, S.T_SENT] - t[:, S.T_WAKE]).as_dict(),
            "socket_calls_us": Percentiles.of_ns_in_us(socket_ns).as_dict(),
            "compiled_work_us": work_p.as_dict(),
            "glue_us": Percentiles.of_ns_in_us(glue_ns).as_dict(),
            "python_per_call_us": steady.python_ns * 1e-3 / max(1, steady.calls),
            "ratio_compiled_work_p50": work_p.p50 / plant_p.p50}


class Drain:
    """The recording writer's part, in a thread of this process: takes the ring's rows
    as they are committed (every :data:`DRAIN_S`), keeping each tick's lateness and
    compute time (ns; -1: the tick did not run)."""

    def __init__(self, recorder, n_ticks: int):
        self.recorder = recorder
        self.lateness = np.full(n_ticks, -1, np.int64)
        self.compute = np.full(n_ticks, -1, np.int64)
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._done.set()
        if self._thread.is_alive():
            self._thread.join()
        self._take()

    def _run(self) -> None:
        while not self._done.wait(DRAIN_S):
            self._take()

    def _take(self) -> None:
        """The rows committed since the last call, in a few array operations (the GIL is
        held meanwhile, and the loop may want it back)."""
        recorder = self.recorder
        first, end = recorder.pending()
        j = np.arange(first, end) % recorder.slots
        common = recorder.common
        k = common[S.R_TICK, j]
        keep = (k >= 0) & (k < self.compute.size)
        self.lateness[k[keep]] = common[S.R_LATENESS, j[keep]]
        self.compute[k[keep]] = common[S.R_COMPUTE, j[keep]]
        recorder.release(end)


def _plant_steps(cfg, emulator: Emulator, n: int = PLANT_SAMPLES) -> np.ndarray:
    """``n`` steps of one PWM period of a twin of axis 0's plant, fed the inputs the run
    ended with, each timed alone (ns)."""
    twin = Plant(cfg, table_pos=emulator.x0[0])
    twin.inp[:] = emulator.plant.inp
    times = np.zeros(n, np.int64)
    for i in range(n):
        t0 = time.monotonic_ns()
        twin.step(twin.sub_per_pwm)
        times[i] = time.monotonic_ns() - t0
    return times


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", action="append", type=Path,
                        help="machine file or manifest (repeatable; default: the Arrow 500 X "
                        "and the two-axis Arrow 500 XY)")
    parser.add_argument("--seconds", type=float, default=2.0,
                        help="run per config, s (default %(default)s: 16 000 ticks at 8 kHz, "
                        "a quick look; docs/benchmarks.md's figures took 10)")
    parser.add_argument("--python-drive", action="store_true",
                        help="every drive cycle in Python (the reference)")
    parser.add_argument("--json", action="store_true",
                        help="print the rows as JSON instead of the summary lines")


def run_from_args(args: argparse.Namespace) -> int:
    rows = [bench(c, args.seconds, not args.python_drive)
            for c in (args.config or DEFAULT_CONFIGS)]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for r in rows:
        t, late = r["tick_compute_us"], r["lateness_us"]
        print(f"{Path(r['config']).name}: {r['axes']} axis(es) at {r['rate_hz']:g} Hz, "
              f"{r['ticks']} ticks: tick compute p50 {t['p50']:.1f} µs (p99 {t['p99']:.1f}, "
              f"p99.9 {t['p999']:.1f}, max {t['max']:.1f}); lateness p99.9 "
              f"{late['p999']:.1f} µs; plant step p50 {r['plant_step_us']['p50']:.1f} µs; "
              f"tick/plant {r['ratio_p50']:.2f}; compiled {100 * r['compiled_share']:.1f} % "
              f"of ticks; overruns {r['overruns']}; load {r['load_avg_1min']:.2f}")
        loop = r["compiled_loop"]
        if loop is not None:
            c, w, g = r["socket_calls_us"], r["compiled_work_us"], r["glue_us"]
            print(f"  compiled ticks: socket calls p50 {c['p50']:.1f} µs, compiled work p50 "
                  f"{w['p50']:.1f} µs ({r['ratio_compiled_work_p50']:.2f} x the plant step), "
                  f"glue p50 {g['p50']:.2f} µs; Python {r['python_per_call_us']:.1f} µs per "
                  f"call of {loop['ticks'] / max(1, loop['calls']):.0f} ticks")
    return 0
