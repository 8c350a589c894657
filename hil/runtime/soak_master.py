"""The controller side of ``hil soak``: a CiA 402 master that keeps an axis moving for as
long as asked, in bounded memory.

::

    python -m hil.runtime.soak_master CONFIG --adapter URL --rate 4000 --seconds 1800 \\
        --out DIR

It aligns its ticks between the drive's (:func:`hil.runtime.sync.align`), enables the
drive (:class:`hil.cia402.EnableSequencer`) and then sends, every tick, a cyclic
synchronous position (CSP) target on a sine about where the axis stood at enable
(:data:`AMPLITUDE_M`, :data:`FREQUENCY_HZ`) with its speed as the feed-forward 60B1h: the
drive's own position and speed loops follow it.  A drive that leaves OPERATION ENABLED
(a fault, its watchdog after a stall of this process) is counted and enabled again.

Each tick's lateness and compute time go into one minute's preallocated arrays; a
full minute is handed to a helper thread (normal priority, started before real-time
scheduling) that sorts it in a preallocated array and reduces it to p50/p99/p99.9/max
(nearest rank) and the overruns, so the loop never sorts and nothing grows but one small
row per minute.  ``DIR/soak_master.json`` holds
them with the adapter's counters and the faults.
"""

import argparse
import math
import os
import queue
import sys
import threading
from dataclasses import asdict
from pathlib import Path

import numpy as np

from hil.cia402 import DISABLE_VOLTAGE, EnableSequencer, State, statusword_state
from hil.rt.loop import OverrunPolicy, Percentiles, nearest_rank
from hil.runtime.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    RuntimeInputError,
    StopFlag,
    eprint,
    period_ns_of,
    scheduling,
    scheduling_dict,
    stop_on_signals,
    write_json,
)
from hil.runtime.streaming_loop import StreamingLoop
from hil.runtime.sync import START_MARGIN_NS, U32, DriveNotAnswering, align
from io_adapters import AdapterError, Feedback, Setpoint, open_endpoint
from io_adapters.messages import MODE_CSP
from plant.config import load_machine
from plant.errors import ConfigError

#: the sine's amplitude, m (rad on a rotary table), and frequency, Hz: 63 mm/s peak
AMPLITUDE_M = 0.02
FREQUENCY_HZ = 0.5
#: the CiA 402 enable sequence gets this many ticks
ENABLE_TIMEOUT_TICKS = 200
SUMMARY = "soak_master.json"


class MinuteStats:
    """The loop's sink: each tick's lateness into the current minute's array, overruns
    counted; a full minute goes to the helper thread (see the module docstring)."""

    def __init__(self, period_ns: int, ticks_per_minute: int, loop_cpu: int | None):
        self.period_ns = period_ns
        self.loop_cpu = loop_cpu
        self.buffers = np.full((2, ticks_per_minute), 0, dtype=np.int64)
        # sorted in place: a fresh array of a minute's ticks for every minute would grow the
        # helper's heap in steps (glibc raises its mmap threshold after the first one)
        self._sorted = np.full(ticks_per_minute, 0, dtype=np.int64)
        self.active = 0
        self.n = 0
        self.overruns = 0
        self.minutes: list[dict] = []
        self._full: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._reduce, name="soak-minutes", daemon=True)
        self._thread.start()

    def end_tick(self, k: int, lateness_ns: int, compute_ns: int) -> None:
        self.buffers[self.active, self.n] = lateness_ns
        self.n += 1
        if lateness_ns + compute_ns > self.period_ns:
            self.overruns += 1
        if self.n == self.buffers.shape[1]:
            self._hand_over()

    def _hand_over(self) -> None:
        self._full.put((self.active, self.n, self.overruns))
        self.active, self.n, self.overruns = 1 - self.active, 0, 0

    def _reduce(self) -> None:
        others = os.sched_getaffinity(0) - {self.loop_cpu}
        if others:  # off the loop's CPU: never preempted there holding the GIL
            os.sched_setaffinity(0, others)
        while (item := self._full.get()) is not None:
            buffer, n, overruns = item
            ordered = self._sorted[:n]
            np.copyto(ordered, self.buffers[buffer, :n])
            ordered.sort()
            p50, p99, p999 = (float(ordered[nearest_rank(q, n) - 1]) / 1e3
                              for q in (500, 990, 999))
            p = Percentiles(p50=p50, p99=p99, p999=p999, max=float(ordered[-1]) / 1e3)
            self.minutes.append({"minute": len(self.minutes), "ticks": n,
                                 "overruns": overruns, "lateness_us": p.as_dict()})

    def close(self) -> None:
        """Reduce the last, partial minute and stop the helper."""
        if self.n:
            self._hand_over()
        self._full.put(None)
        self._thread.join()


class SoakMaster:
    """Align, enable, then a CSP sine every tick (see the module docstring)."""

    def __init__(self, args: argparse.Namespace, stop: StopFlag):
        self.args = args
        cfg = load_machine(args.config)
        f_pwm = cfg.motor.pwm_frequency_hz
        if args.rate <= 0 or abs(f_pwm / args.rate - round(f_pwm / args.rate)) > 1e-9:
            raise RuntimeInputError(f"--rate {args.rate:g} Hz must divide the PWM frequency "
                                    f"{f_pwm:g} Hz of {args.config}")
        self.period_ns = period_ns_of(args.rate)
        self.period_s = self.period_ns * 1e-9
        n_ticks = max(1, round(args.seconds / self.period_s))
        self.stats = MinuteStats(self.period_ns, round(60.0 / self.period_s), args.cpu)
        self.loop = StreamingLoop(self.period_ns, self.step, self.stats, n_ticks=n_ticks,
                                  policy=OverrunPolicy("count"))
        stop.attach(self.loop)
        counts_per_m = 1.0 / (self._table_per_count(cfg))
        self.amplitude = AMPLITUDE_M * counts_per_m
        self.omega = 2.0 * math.pi * FREQUENCY_HZ
        self.sp, self.fb = Setpoint(mode=MODE_CSP), Feedback()
        self.seq = EnableSequencer(timeout_cycles=ENABLE_TIMEOUT_TICKS)
        self.centre = math.nan
        self.t_enabled = 0.0
        self.enables = 0
        self.dropped_out: list[dict] = []
        self.ep = None

    @staticmethod
    def _table_per_count(cfg) -> float:
        """Table units (m or rad) per motor-encoder count: a CSP target's unit."""
        if cfg.machine.kind == "linear":
            return cfg.sensors.encoder_resolution_m
        ratio = cfg.mechanics.lead_m / (2 * math.pi) if cfg.machine.kind == "screw" else 1.0
        return 2.0 * math.pi / cfg.sensors.encoder_counts_per_rev * ratio

    def step(self, k: int) -> None:
        """Newest feedback, the enable sequence or the sine, the setpoint out."""
        sp, fb = self.sp, self.fb
        try:
            self.ep.recv_feedback(fb, 0.0)
        except AdapterError:
            pass
        state = statusword_state(fb.statusword)
        if self.seq.done and state == State.OPERATION_ENABLED:
            t = k * self.period_s - self.t_enabled
            sp.target_position_counts = self.centre + self.amplitude * math.sin(self.omega * t)
            sp.velocity_offset_counts_s = self.amplitude * self.omega * math.cos(self.omega * t)
        else:
            if self.seq.done:  # it dropped out: count it, enable again
                self.dropped_out.append({"tick": k, "statusword": f"0x{fb.statusword:04X}",
                                         "error_code": f"0x{fb.fault:04X}"})
                self.seq.enable()
            sp.controlword = self.seq.next_controlword(fb.statusword)
            sp.target_position_counts = fb.encoder_counts
            sp.velocity_offset_counts_s = 0.0
            if self.seq.done:
                self.centre, self.t_enabled = fb.encoder_counts, (k + 1) * self.period_s
                self.enables += 1
            elif self.seq.failed:
                self.seq.enable()
        sp.seq = (sp.seq + 1) & U32
        try:
            self.ep.send_setpoint(sp)
        except AdapterError:
            pass

    def run(self) -> dict:
        """Open, align, run, disable; returns the summary (also written to --out)."""
        a = self.args
        self.ep = open_endpoint(a.adapter, "controller")
        self.ep.drain = True
        try:
            with scheduling(not a.no_rt, a.cpu, a.priority) as granted:
                alignment = align(self.ep, self.sp, self.fb, self.period_ns, 10.0)
                self.loop.start_ns = alignment.first_deadline(
                    self.period_ns, self.loop.clock.now_ns() + START_MARGIN_NS)
                self.seq.enable()
                loop = self.loop.run()
                self.sp.controlword = DISABLE_VOLTAGE.value
                self.ep.send_setpoint(self.sp)
        finally:
            self.ep.close()
            self.stats.close()
        summary = {"command": "hil soak master", "config": str(a.config), "rate_hz": a.rate,
                   "loop": {k: v for k, v in loop.as_dict().items()
                            if k not in ("lateness_us", "compute_us")},
                   "minutes": self.stats.minutes, "enables": self.enables,
                   "dropped_out": self.dropped_out, "alignment": alignment.as_dict(),
                   "adapter": {"name": a.adapter, "stats": asdict(self.ep.stats)},
                   "scheduling": scheduling_dict(granted)}
        Path(a.out).mkdir(parents=True, exist_ok=True)
        write_json(Path(a.out) / SUMMARY, summary)
        return summary


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.runtime.soak_master``: see the module docstring."""
    p = argparse.ArgumentParser(prog="hil soak master", description=__doc__.splitlines()[0])
    p.add_argument("config", help="machine file with a [controller] section (CSP)")
    p.add_argument("--adapter", required=True, help="the drive's adapter URL")
    p.add_argument("--rate", type=float, required=True, help="loop rate, Hz")
    p.add_argument("--seconds", type=float, required=True, help="how long to run, s")
    p.add_argument("--out", required=True, help="folder for soak_master.json")
    p.add_argument("--cpu", type=int, help="CPU to run the loop on")
    p.add_argument("--priority", type=int, default=70, help="SCHED_FIFO priority")
    p.add_argument("--no-rt", action="store_true", help="no SCHED_FIFO, pinning or locking")
    args = p.parse_args(argv)
    stop = StopFlag()
    with stop_on_signals(stop.request):
        try:
            master = SoakMaster(args, stop)
            summary = master.run()
        except (ConfigError, RuntimeInputError, AdapterError) as e:
            eprint(f"hil soak master: {e}")
            return EXIT_BAD_INPUT
        except DriveNotAnswering as e:
            eprint(f"hil soak master: {e}")
            return EXIT_FAILED
    return EXIT_OK if summary["enables"] else EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
