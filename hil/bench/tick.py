"""``hil bench tick``: the emulator's whole tick against the plant step alone, in the same
run (issue 12 part 6).

The tick is the real one: :meth:`hil.runtime.emulator.Emulator.step` (newest setpoint
from the UDP adapter on 127.0.0.1, watchdog, drive cycles, feedback sent, the row written
into the recording's shared-memory ring) and the ring's :meth:`end_tick`, paced at the
machine's rate (8 kHz on the Arrow 500 X) for ``seconds``.  A controller in a child
process (spawn) enables the drives with the CiA 402 sequence and then moves them in CSP
(a cosine of :data:`AMPLITUDE_COUNTS` at :data:`MOTION_HZ`, with its speed
feed-forward), one setpoint per period of its own clock, reading the newest feedback
without waiting on the socket (as ``hil controller`` does).  This process drains the
ring between ticks as the recording's writer would (outside the timed part), so every
tick writes its row.

After each tick, in its slack, one plant step alone (``Plant.step(sub_per_pwm)`` on a
twin plant of axis 0 fed the tick's plant inputs) is timed, so both figures share the
machine's state.  JSON, per machine file::

    {"config", "axes", "rate_hz", "drive", "seconds", "ticks",
     "tick_compute_us": {"p50", "p99", "p999", "max"}, "tick_cpu_us": {...},
     "plant_step_us": {"p50", "p999"},
     "ratio_p50", "compiled_call_us": {"p50", "p99", "p999", "max"},
     "ratio_compiled_call_p50", "steady_share", "steady_declined", "compiled_share",
     "enabled_ticks", "compiled_share_enabled",
     "exits", "overruns", "setpoints_heard", "load_avg_1min",
     "socket_calls_us": {"recvmsg", "poll", "sendto", "sum"}, "tick_without_socket_p50_us",
     "ratio_without_socket_p50"}

``tick_compute_us`` is from the start of the step to the end of ``end_tick`` (wall
time), ``tick_cpu_us`` the loop thread's CPU time in it (what the tick costs whatever
else the machine runs: on a loaded machine the wall time includes the other processes'
turns);
``ratio_p50`` the tick's p50 over the plant step's; ``compiled_call_us`` the compiled
tick's call alone, in the ticks it ran (from its start to the answer's stamp: the
setpoints decoded, the drive cycles with the plant's sub-steps and the recording rows;
without the call's dispatch, the answer's encoding and the socket calls; null with
``--python-drive``), ``ratio_compiled_call_p50`` its p50 over the plant step's;
``steady_share`` the share of ticks
run whole by the compiled tick (:mod:`hil.runtime.steady_tick`: from the datagram to the
answer), ``steady_declined`` the datagrams it handed to the Python path, by reason;
``compiled_share`` the share of ticks whose every drive cycle took the compiled path
(:mod:`hil.drive.compiled_path`; a compiled tick's included),
``compiled_share_enabled`` that share among the ticks that started with every drive in
OPERATION ENABLED; ``exits`` how often a drive handed a cycle back to Python, by reason;
an overrun is a tick that ended after the next deadline.  ``socket_calls_us``: the
tick's three socket calls timed alone in the same run (:func:`socket_calls_us`: the
kernel's part, which no compiled code removes), ``tick_without_socket_p50_us`` the tick's
p50 less their sum, and ``ratio_without_socket_p50`` that over the plant step's (an
estimate: a difference of medians).  ``--python-drive`` times the
same tick with every drive cycle in Python (``"drive": "python"``), the reference.  The
goal on the Arrow 500 X at 8 kHz: p50 <= 15 µs, p99.9 <= 40 µs, ``ratio_p50`` <= 1.5,
and two axes without overruns on a quiet machine.
"""

import argparse
import json
import math
import multiprocessing
import os
import select
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.cia402 import EnableSequencer, State
from hil.drive import compiled as C
from hil.rt.loop import Percentiles
from hil.runtime import steady_tick as S
from hil.runtime.emulator import Emulator, RuntimeConfig
from io_adapters import codec_compiled as K
from io_adapters import open_endpoint
from io_adapters.messages import MODE_CSP, axis_records, message_pair
from io_adapters.udp import MAX_DATAGRAM, SO_TIMESTAMPNS, TIMESPEC
from io_adapters.udp_steady import L_CALL_NS
from plant import Plant
from plant.machines import load_machine_set

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
#: the machine files timed by default: one axis, and two axes of the same drive
DEFAULT_CONFIGS = (CONFIGS / "arrow500_x.toml", CONFIGS / "machines" / "arrow500_xy.toml")
#: the controller's motion: a cosine of this amplitude, increments, at this frequency, Hz
AMPLITUDE_COUNTS = 50_000.0
MOTION_HZ = 1.0
#: calls timed by :func:`socket_calls_us`, and its datagrams' sizes (a version-1 setpoint,
#: a feedback), bytes
SOCKET_SAMPLES = 20_000
SETPOINT_BYTES, FEEDBACK_BYTES = 110, 120
#: longest wait for the child to start (imports), s
START_S = 60.0
#: spin (rather than sleep) for the last this-many ns before a deadline: the loop's, and
#: the controller's (it need not be punctual, and shares the machine)
SPIN_NS = 150_000
CONTROLLER_SPIN_NS = 20_000
_EXIT_NAMES = {C.EXIT_COMMAND: "command", C.EXIT_REFUSED: "refused", C.EXIT_CAUSE: "cause",
               C.EXIT_LOOP: "loop", C.EXIT_PLANT: "plant"}


_DECLINED_NAMES = {S.DECLINED_FRAME: "frame", S.DECLINED_SEQUENCE: "sequence",
                   S.DECLINED_CYCLE: "cycle"}


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


def _wait_until(deadline_ns: int, spin_ns: int = SPIN_NS) -> int:
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
    False: every drive cycle in Python (the reference: the tick before part 6)."""
    machine = load_machine_set(config)
    rc = RuntimeConfig(config, "udp://127.0.0.1:0", realtime=False, steady_tick=compiled)
    emulator = Emulator(rc, machine, log=lambda message: None)
    if not compiled:
        for d in emulator.drives.drives:
            d.compiled = None
    period_ns = emulator.timing.period_ns
    n_ticks = max(1, round(seconds * 1e9 / period_ns))
    twin = Plant(machine.configs[0], table_pos=emulator.x0[0])
    drives = emulator.drives.drives
    ctx = multiprocessing.get_context("spawn")
    parent, child_conn = ctx.Pipe()
    emulator.open()
    child = ctx.Process(target=controller, args=(emulator.endpoint.address[1],
                                                  len(drives), period_ns, child_conn))
    child.start()
    try:
        if not parent.poll(START_S):
            raise RuntimeError(f"the controller process did not start within {START_S} s")
        parent.recv()
        stats = _ticks(emulator, twin, n_ticks, period_ns)
    finally:
        parent.send("stop")
        child.join(5.0)
        if child.is_alive():
            child.kill()
            child.join()
        emulator.endpoint.close()
    tick_p = Percentiles.of_ns_in_us(stats.compute_ns)
    cpu_p = Percentiles.of_ns_in_us(stats.cpu_ns)
    plant_p = Percentiles.of_ns_in_us(stats.plant_ns)
    calls = stats.call_ns[stats.call_ns >= 0]
    call_p = Percentiles.of_ns_in_us(calls) if calls.size else None
    taken, enabled = stats.compiled, stats.enabled
    exits = {name: sum(d.compiled.exits[code] for d in drives if d.compiled is not None)
             for code, name in _EXIT_NAMES.items()}
    return {"config": str(config), "axes": len(drives), "rate_hz": emulator.timing.rate_hz,
            "drive": "compiled" if compiled else "python",
            "seconds": n_ticks * period_ns * 1e-9, "ticks": n_ticks,
            "tick_compute_us": tick_p.as_dict(), "tick_cpu_us": cpu_p.as_dict(),
            "plant_step_us": {"p50": plant_p.p50, "p999": plant_p.p999},
            "ratio_p50": tick_p.p50 / plant_p.p50,
            "compiled_call_us": call_p.as_dict() if call_p is not None else None,
            "ratio_compiled_call_p50": call_p.p50 / plant_p.p50 if call_p is not None
            else None,
            "compiled_share": float(taken.mean()),
            "enabled_ticks": int(enabled.sum()),
            "compiled_share_enabled": (float(taken[enabled].mean()) if enabled.any()
                                       else None),
            "exits": exits, "overruns": stats.overruns,
            "steady_share": (emulator.steady.ticks / n_ticks if emulator.steady is not None
                             else 0.0),
            "steady_declined": ({_DECLINED_NAMES[c]: v
                                 for c, v in emulator.steady.declined.items()}
                                if emulator.steady is not None else {}),
            "setpoints_heard": emulator.setpoints_heard, "load_avg_1min": os.getloadavg()[0]}


@dataclass(frozen=True)
class TickSamples:
    """What the paced loop measured, one element per tick.

    Attributes:
        compute_ns: wall time of the step and ``end_tick``, ns.
        cpu_ns: the loop thread's CPU time in them, ns (without the time other processes
            took the CPU: a loaded machine inflates ``compute_ns`` only).
        plant_ns: wall time of the twin plant's step alone, ns.
        call_ns: in a tick the compiled tick ran, its call's own time (from its start to
            the answer's stamp, :data:`~io_adapters.udp_steady.L_CALL_NS`), ns; else -1.
        compiled: every drive cycle of the tick took the compiled path.
        enabled: every drive was in OPERATION ENABLED at the start of the tick.
        overruns: ticks that ended after the next deadline.
    """
    compute_ns: np.ndarray
    cpu_ns: np.ndarray
    plant_ns: np.ndarray
    call_ns: np.ndarray
    compiled: np.ndarray
    enabled: np.ndarray
    overruns: int


def _ticks(emulator: Emulator, twin: Plant, n_ticks: int, period_ns: int) -> TickSamples:
    """The paced loop (see the module docstring)."""
    drives = emulator.drives.drives
    recorder, plant = emulator.recorder, emulator.plant
    per_tick = emulator.timing.cycles_per_tick
    compute = np.zeros(n_ticks, dtype=np.int64)
    cpu = np.zeros(n_ticks, dtype=np.int64)
    plant_ns = np.zeros(n_ticks, dtype=np.int64)
    call_ns = np.full(n_ticks, -1, dtype=np.int64)
    steady = emulator.steady
    compiled = np.zeros(n_ticks, dtype=bool)
    enabled = np.zeros(n_ticks, dtype=bool)
    overruns = 0
    deadline = time.monotonic_ns() + period_ns
    for k in range(n_ticks):
        enabled[k] = all(d.sm.state == State.OPERATION_ENABLED for d in drives)
        before = [_cycles(d) for d in drives]
        woke = _wait_until(deadline)
        cpu_start = time.thread_time_ns()
        ran = steady.ticks if steady is not None else 0
        emulator.step(k)
        recorder.end_tick(k, woke - deadline, time.monotonic_ns() - woke)
        done = time.monotonic_ns()
        cpu[k] = time.thread_time_ns() - cpu_start
        compute[k] = done - woke
        overruns += done > deadline + period_ns
        compiled[k] = all(_cycles(d) - b == per_tick for d, b in zip(drives, before))
        if steady is not None and steady.ticks > ran:
            call_ns[k] = steady.link.fb_ints[K.F_T_NS] - steady.link.link[L_CALL_NS]
        twin.inp[:] = plant.inp
        t0 = time.monotonic_ns()
        twin.step(twin.sub_per_pwm)
        plant_ns[k] = time.monotonic_ns() - t0
        recorder.release(recorder.committed)  # the writer's part, untimed
        deadline += period_ns
    return TickSamples(compute, cpu, plant_ns, call_ns, compiled, enabled, overruns)


def _cycles(drive) -> int:
    return drive.compiled.cycles if drive.compiled is not None else 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", action="append", type=Path,
                        help="machine file or manifest (repeatable; default: the Arrow 500 X "
                        "and the two-axis Arrow 500 XY)")
    parser.add_argument("--seconds", type=float, default=2.0,
                        help="run per config, s (default %(default)s: 16 000 ticks at 8 kHz, "
                        "a quick look; the README's figures took 10)")
    parser.add_argument("--python-drive", action="store_true",
                        help="every drive cycle in Python (the reference)")
    parser.add_argument("--json", action="store_true")


def socket_calls_us(n: int = SOCKET_SAMPLES) -> dict:
    """The kernel's part of a tick's socket calls, measured alone: on a pair of UDP
    sockets on 127.0.0.1 in this process, one receiving as the device does
    (``recvmsg_into`` with the kernel's receive stamp, then ``poll`` for anything queued
    behind) and answering with ``sendto``, datagrams of a setpoint's and a feedback's
    size; the peer reads without waiting (as the bench's controller does), so no send
    wakes it.  p50 of ``n`` calls each, µs."""
    device = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        device.bind(("127.0.0.1", 0))
        peer.bind(("127.0.0.1", 0))
        device.setblocking(False)
        peer.setblocking(False)
        if SO_TIMESTAMPNS is not None:
            device.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        poller = select.poll()
        poller.register(device, select.POLLIN)
        buf = (bytearray(MAX_DATAGRAM),)
        ancillary = socket.CMSG_SPACE(TIMESPEC.size)
        setpoint, feedback = bytes(SETPOINT_BYTES), bytes(FEEDBACK_BYTES)
        to_device, to_peer = device.getsockname(), peer.getsockname()
        times = np.zeros((3, n), dtype=np.int64)
        for k in range(n):
            peer.sendto(setpoint, to_device)
            t0 = time.perf_counter_ns()
            device.recvmsg_into(buf, ancillary)
            t1 = time.perf_counter_ns()
            poller.poll(0)
            t2 = time.perf_counter_ns()
            device.sendto(feedback, to_peer)
            t3 = time.perf_counter_ns()
            peer.recv(MAX_DATAGRAM)
            times[:, k] = t1 - t0, t2 - t1, t3 - t2
    finally:
        device.close()
        peer.close()
    p50 = np.median(times, axis=1) * 1e-3
    return {"recvmsg": float(p50[0]), "poll": float(p50[1]), "sendto": float(p50[2]),
            "sum": float(p50.sum())}


def run_from_args(args: argparse.Namespace) -> int:
    rows = [bench(c, args.seconds, not args.python_drive)
            for c in (args.config or DEFAULT_CONFIGS)]
    calls = socket_calls_us()
    for r in rows:
        r["socket_calls_us"] = calls
        r["tick_without_socket_p50_us"] = r["tick_compute_us"]["p50"] - calls["sum"]
        r["ratio_without_socket_p50"] = (r["tick_without_socket_p50_us"]
                                         / r["plant_step_us"]["p50"])
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for r in rows:
        t = r["tick_compute_us"]
        print(f"{Path(r['config']).name}: {r['axes']} axis(es) at {r['rate_hz']:g} Hz, "
              f"{r['ticks']} ticks: tick compute p50 {t['p50']:.1f} µs (p99 {t['p99']:.1f}, "
              f"p99.9 {t['p999']:.1f}, max {t['max']:.1f} µs); plant step p50 "
              f"{r['plant_step_us']['p50']:.1f} µs; tick/plant {r['ratio_p50']:.2f}; "
              f"compiled tick {100 * r['steady_share']:.1f} %, compiled drive cycles "
              f"{100 * r['compiled_share']:.1f} % of ticks; overruns "
              f"{r['overruns']}; load {r['load_avg_1min']:.2f}", file=sys.stdout)
        c = r["socket_calls_us"]
        print(f"  the socket calls alone: recvmsg {c['recvmsg']:.1f} poll {c['poll']:.1f} "
              f"sendto {c['sendto']:.1f} µs; the tick without them p50 "
              f"{r['tick_without_socket_p50_us']:.1f} µs, "
              f"{r['ratio_without_socket_p50']:.2f} x the plant step", file=sys.stdout)
        if r["compiled_call_us"] is not None:
            k = r["compiled_call_us"]
            print(f"  the compiled call alone: p50 {k['p50']:.1f} µs (p99.9 {k['p999']:.1f}), "
                  f"{r['ratio_compiled_call_p50']:.2f} x the plant step", file=sys.stdout)
    return 0
