"""``hil controller``: the simulated NC as a process, running a part program over an adapter.

::

    hil controller configs/arrow500_x.toml --adapter udp://127.0.0.1:5005 \\
        --program programs/demo_moves.nc --out runs/c1

The same :class:`~hil.controller.nc.Controller` as ``hil sim``, ticked once per PWM period
by a :class:`~hil.rt.loop.RealTimeLoop` instead of back to back with the drive:

1. load and check the machine file, read and plan the program (exit 2 on bad input);
2. open the adapter (controller role, draining: each tick uses the newest feedback);
3. **align** (:func:`hil.runtime.sync.align`): exchange disable-voltage setpoints for
   feedback for a moment and place this loop's ticks half a period from the drive's, so
   that a setpoint reaches the drive before its next cycle and the feedback comes back
   before this loop's next tick: the two loops then exchange data exactly as the lock-step
   simulation does (tick k reads drive cycle k-1, its setpoint drives cycle k).  Over a
   link whose master produces SYNC (``can://``) the drive locks its cycle to this loop's
   SYNC instead (:func:`hil.runtime.sync.align_by_sync`), and its answer comes one SYNC
   later: tick k reads drive cycle k-2 (the endpoint's ``feedback_delay_ticks``, 1;
   ``hil.sim.LockStep(feedback_delay_ticks=1)`` is the matching simulation);
4. run: each tick polls the newest feedback (timeout 0), ``ctrl.tick(fb, sp)``, sends the
   setpoint; the CiA 402 enable sequence first, then, on the tick the drive reports
   OPERATION ENABLED, the program (as ``hil sim`` does), recorded for the program's
   duration plus :data:`hil.commands.SETTLE_S`.  A tick without new feedback (a late drive
   cycle, a lost frame) extrapolates the last one with the drive's speed actual value
   (606Ch) over one period, as a controller bridges a missing bus telegram, instead of
   reading a frozen encoder as standstill; on a link whose feedback says how old it is
   (``lag_is_age``: ``can://``, where an answer that came after this loop's tick is read
   a tick late) a late answer is extrapolated the same way over the ticks it is late;
5. send disable voltage, close, write ``trace.csv`` (servo-trace format, one row per
   position-control cycle, :func:`hil.sim.servo_trace_columns`), ``controller.npz`` (every
   recorded tick: :data:`FLOAT_COLUMNS`, :data:`INT_COLUMNS`, and the loop's
   ``lateness_ns``/``compute_ns`` per deadline) and ``summary.json``.

The run fails (exit 1, the reason in the summary and on stderr) when no drive answers
within ``--connect-timeout``, the enable sequence fails, the drive leaves OPERATION
ENABLED (a fault, the emulator's watchdog), no feedback comes for ``--feedback-timeout``
cycles, or the axis is not where the program starts (``--start``).
"""

import argparse
import math
import sys
import time
from dataclasses import asdict, dataclass
from operator import attrgetter
from pathlib import Path

import numpy as np

from hil.cia402 import DISABLE_VOLTAGE
from hil.commands import SETTLE_S
from hil.controller.config import axis_limits, load_controller
from hil.controller.interpolator import plan
from hil.controller.nc import Controller
from hil.controller.program import ProgramError, read_program
from hil.report.host import host_fingerprint
from hil.rt.clock import MonotonicClock
from hil.rt.loop import OverrunPolicy, Percentiles, RealTimeLoop
from hil.runtime.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    RuntimeInputError,
    StopFlag,
    check_cpu,
    cnc_unit,
    eprint,
    period_ns_of,
    scheduling,
    scheduling_dict,
    stop_on_signals,
    write_json,
)
from hil.runtime.sync import U32, Alignment, DriveNotAnswering, align, in_step
from hil.sim import SimResult, servo_trace_columns
from hil.trace_file import write_trace
from io_adapters import AdapterError, Endpoint, Feedback, Setpoint, open_endpoint
from plant.config import load_machine
from plant.errors import ConfigError

#: the axis must be this close to the program's start when enabled: SINUMERIK exact stop
#: coarse (MD36000), mm or deg
START_WINDOW_CNC = 0.04
DEFAULT_FEEDBACK_TIMEOUT_S = 0.1
#: controller attributes recorded each tick (SI, hil.sim.SIGNALS names; ``t`` is t_s)
CTRL_SIGNALS = ("t", "x_set", "v_set", "a_set", "x_act", "v_act", "v_cmd", "w_set", "w_act",
                "iq_set", "following_error")
#: float columns of controller.npz: the signals, then the feedback's (motor_pos: the encoder
#: angle, rad; fb_time_s: the drive's time stamp of the cycle read)
FLOAT_COLUMNS = ("t_s", *CTRL_SIGNALS[1:], "iq_meas", "motor_pos", "tick", "fb_time_s")
#: integer columns: the loop's deadline index, 1 when new feedback came, the lag (ticks
#: between the setpoint the feedback answers and the one sent last tick: 0 = lock-step
#: timing), the feedback's round trip (ns), and its stamps that pair it with the
#: emulator's run.npz (``hil report RUN --controller DIR``): its sp_t_ns and t_ns (the
#: setpoint it answers, its send on the drive's clock) and its rx_ns (this clock); the
#: last four 0 without new feedback
INT_COLUMNS = ("k", "fb_new", "lag_ticks", "round_trip_ns", "fb_sp_t_ns", "fb_t_ns",
               "fb_rx_ns")


@dataclass(frozen=True)
class ControllerRunConfig:
    """``hil controller``'s settings (SI unless named; see :func:`add_arguments`)."""
    machine_file: Path
    adapter_url: str
    program_file: Path
    out_dir: Path = Path("hil-controller")
    start_cnc: float = 0.0
    axis: str | None = None
    realtime: bool = True
    cpu: int | None = None
    priority: int = 70
    overrun: str = "count"
    connect_timeout_s: float = 10.0
    feedback_timeout_cycles: int | None = None

    def __post_init__(self):
        if not self.connect_timeout_s > 0.0:
            raise RuntimeInputError(f"--connect-timeout must be > 0 s, got "
                                    f"{self.connect_timeout_s}")
        if self.feedback_timeout_cycles is not None and self.feedback_timeout_cycles < 1:
            raise RuntimeInputError(f"--feedback-timeout must be >= 1 cycle, got "
                                    f"{self.feedback_timeout_cycles}")
        if not 1 <= self.priority <= 99:
            raise RuntimeInputError(f"--priority must be 1..99 (SCHED_FIFO), got {self.priority}")
        check_cpu(self.cpu)


class ControllerProcess:
    """The controller's life cycle: program, adapter, alignment, loop, files."""

    def __init__(self, rc: ControllerRunConfig, stop: StopFlag):
        self.rc = rc
        self.cfg = cfg = load_machine(rc.machine_file)
        sec = load_controller(cfg)
        self.k_cnc, self.unit = cnc_unit(cfg)
        self.x0 = rc.start_cnc / self.k_cnc
        axis = rc.axis or ("C" if cfg.machine.kind == "rotary" else "X")
        self.program = read_program(rc.program_file, axis=axis, start=self.x0)
        self.profile = plan(self.program, axis_limits(cfg, sec))
        self.period_ns = period_ns_of(cfg.motor.pwm_frequency_hz)
        self.period_s = self.period_ns * 1e-9
        self.ctrl = ctrl = Controller(cfg, self.period_s, self.x0, sec)
        #: linear-scale counts per motor-encoder count, to extrapolate the scale too
        self.scale_per_count = (ctrl.rad_per_count * ctrl.ratio / ctrl.scale_res
                                if ctrl.scale_res else 0.0)
        self.n_run = math.ceil((self.profile.duration_s + SETTLE_S) / self.period_s)
        self.feedback_timeout = rc.feedback_timeout_cycles or max(
            1, round(DEFAULT_FEEDBACK_TIMEOUT_S / self.period_s))
        self.sp, self.fb = Setpoint(), Feedback()
        self.delay_ticks = 0        # the link's, set when it is opened (run)
        self.lag_is_age = False
        self.floats = np.full((self.n_run, len(FLOAT_COLUMNS)), np.nan)
        self.ints = np.zeros((self.n_run, len(INT_COLUMNS)), dtype=np.int64)
        self._get = attrgetter(*CTRL_SIGNALS)
        self.loop = RealTimeLoop(self.period_ns, self.step,
                                 n_ticks=ctrl.enable_timeout_ticks + 2 + self.n_run,
                                 policy=OverrunPolicy(rc.overrun,
                                                      grace_ticks=ctrl.enable_timeout_ticks))
        stop.attach(self.loop)
        self.stop = stop
        self.ep: Endpoint | None = None
        self.rows = 0
        self.running = False
        self.silent = 0
        self.adapter_errors = 0
        self.result = "completed"

    def step(self, k: int) -> None:
        """Newest feedback, one controller tick, the setpoint out; enable, then the program."""
        ctrl, sp, fb = self.ctrl, self.sp, self.fb
        try:
            new = self.ep.recv_feedback(fb, 0.0)
        except AdapterError:
            new = False
            self.adapter_errors += 1
        if new:
            self.silent = 0
            if self.lag_is_age:
                late = ((sp.seq - fb.seq) & U32) - self.delay_ticks
                if 0 < late < self.feedback_timeout:
                    self._extrapolate(late)
        else:
            self.silent += 1
            self._extrapolate(1)
        ctrl.tick(fb, sp)
        try:
            self.ep.send_setpoint(sp)
        except AdapterError:
            self.adapter_errors += 1
        if self.silent >= self.feedback_timeout:
            self._fail(f"no feedback for {self.silent} cycles at tick {k}")
        elif not self.running:
            self._start(k)
        elif not ctrl.enabled:
            self._fail(f"the drive left OPERATION ENABLED at tick {k}: {ctrl.enable.reason}")
        else:
            i = self.rows
            self.floats[i] = self._get(ctrl) + (fb.iq_a, fb.encoder_counts * ctrl.rad_per_count,
                                                ctrl.tick_count - 1, fb.time_s)
            lag = (sp.seq - 1 - fb.seq) & U32
            self.ints[i] = ((k, 1, lag, fb.round_trip_ns(), fb.sp_t_ns, fb.t_ns, fb.rx_ns)
                            if new else (k, 0, lag, 0, 0, 0, 0))
            self.rows = i + 1
            if self.rows == self.n_run:
                self.loop.request_stop()

    def _extrapolate(self, ticks: int) -> None:
        """The feedback moved on by ``ticks`` periods at the drive's speed actual value."""
        fb, dt = self.fb, ticks * self.period_s
        fb.encoder_counts += fb.velocity_counts_s * dt
        fb.scale_counts += fb.velocity_counts_s * self.scale_per_count * dt
        fb.time_s += dt

    def _start(self, k: int) -> None:
        ctrl = self.ctrl
        if ctrl.enable.failed:
            self._fail(f"enable failed: {ctrl.enable.reason}")
        elif ctrl.enabled:
            off = abs(ctrl.x_act - self.x0) * self.k_cnc
            if off > START_WINDOW_CNC:
                self._fail(f"the axis is at {ctrl.x_act * self.k_cnc:.4f} {self.unit}, the "
                           f"program starts at {self.x0 * self.k_cnc:.4f} {self.unit} (--start)")
            else:
                ctrl.run_profile(self.profile)
                self.running = True

    def _fail(self, reason: str) -> None:
        self.result = reason
        self.loop.request_stop()

    def run(self) -> dict:
        """Open, align, run, disable, write; returns the summary."""
        rc = self.rc
        self.ep = open_endpoint(rc.adapter_url, "controller")
        self.ep.drain = True
        self.delay_ticks = getattr(self.ep, "feedback_delay_ticks", 0)
        self.lag_is_age = getattr(self.ep, "lag_is_age", False)
        try:
            with scheduling(rc.realtime, rc.cpu, rc.priority) as granted:
                alignment = align(self.ep, self.sp, self.fb, self.period_ns,
                                  rc.connect_timeout_s)
                clock = MonotonicClock.for_period(self.period_ns)
                t0 = alignment.first_deadline(self.period_ns, clock.now_ns() + self.period_ns)
                clock.sleep_until(t0 - self.period_ns)  # run() places tick 0 one period on
                stats = self.loop.run()
                self._disable()
        finally:
            self.ep.close()
        if stats.stopped_by == "overruns":
            self.result = "stopped by overruns"
        elif self.result == "completed" and self.rows < self.n_run:
            self.result = ("stopped by SIGTERM/SIGINT" if self.stop.requested
                           else f"the program did not finish in {stats.ticks} ticks")
        return self._finish(stats, granted, alignment)

    def _disable(self) -> None:
        """Disable voltage, three times a period apart (the drive leaves torque on
        otherwise until its watchdog faults it)."""
        self.sp.controlword = DISABLE_VOLTAGE.value
        for _ in range(3):
            self.sp.seq = (self.sp.seq + 1) & U32
            try:
                self.ep.send_setpoint(self.sp)
            except AdapterError:
                self.adapter_errors += 1
            time.sleep(self.period_s)

    def _finish(self, stats, granted, alignment: Alignment) -> dict:
        rc, n = self.rc, self.rows
        rc.out_dir.mkdir(parents=True, exist_ok=True)
        cols = {name: self.floats[:n, i].copy() for i, name in enumerate(FLOAT_COLUMNS)}
        cols.update({name: self.ints[:n, i].copy() for i, name in enumerate(INT_COLUMNS)})
        np.savez(rc.out_dir / "controller.npz", **cols, lateness_ns=stats.lateness_ns,
                 compute_ns=stats.compute_ns)
        res = SimResult(cols, self.cfg.machine.kind, self.ctrl.ratio, self.period_s)
        every = self.ctrl.sec.position_cycle_ratio
        trace = None
        if np.any(cols["tick"] % every == 0):
            trace = write_trace(rc.out_dir / "trace.csv", servo_trace_columns(res, every), {
                "machine": str(rc.machine_file), "program": str(rc.program_file),
                "axis": self.program.axis, "source": f"hil controller over {rc.adapter_url}"})
        fe = cols["following_error"] * self.k_cnc
        new = cols["fb_new"] == 1
        lag = cols["lag_ticks"]
        delay = self.delay_ticks
        drive_clock = getattr(self.ep, "drive_clock", True)
        u = self.unit
        summary = {
            "command": "hil controller", "result": self.result,
            "exit_status": EXIT_OK if self.result in ("completed", "stopped by SIGTERM/SIGINT")
            else EXIT_FAILED,
            "machine_file": str(rc.machine_file), "program": str(rc.program_file),
            "period_ns": self.period_ns, "trace_every_ticks": every, "ticks_recorded": n,
            "ticks_planned": self.n_run,
            f"following_error_max_{u}": float(np.abs(fe).max()) if n else None,
            f"following_error_rms_{u}": float(np.sqrt(np.mean(fe ** 2))) if n else None,
            f"final_position_{u}": float(cols["x_act"][-1] * self.k_cnc) if n else None,
            f"program_end_{u}": self.program.end * self.k_cnc,
            "round_trip_us": Percentiles.of_ns_in_us(cols["round_trip_ns"][new]).as_dict(),
            "feedback": {"ticks_without_new": int(n - new.sum()),
                         "ticks_in_step": int(in_step(cols, self.period_s, delay,
                                                      drive_clock).sum()),
                         "delay_ticks": delay, "drive_clock": drive_clock,
                         "lag_ticks": {"0": int((lag == 0).sum()), "1": int((lag == 1).sum()),
                                       "2+": int((lag >= 2).sum())}},
            "alignment": alignment.as_dict(),
            "loop": stats.as_dict(), "scheduling": scheduling_dict(granted),
            "adapter": {"name": rc.adapter_url, "stats": asdict(self.ep.stats),
                        "errors": self.adapter_errors},
            "trace": None if trace is None else str(trace), "host": host_fingerprint(),
        }
        write_json(rc.out_dir / "summary.json", summary)
        return summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil controller``."""
    p.add_argument("config", help="machine file (TOML) with a [controller] section")
    p.add_argument("--adapter", required=True, metavar="URL", help="the drive's adapter URL")
    p.add_argument("--program", required=True, help="part program (G-code subset)")
    p.add_argument("--out", default="hil-controller", help="folder for trace.csv, "
                   "controller.npz and summary.json (default %(default)s)")
    p.add_argument("--start", type=float, default=0.0,
                   help="table position at start, mm (deg on rotary tables)")
    p.add_argument("--axis", help="axis letter in the program (default X, or C if rotary)")
    p.add_argument("--no-rt", action="store_true", help="no SCHED_FIFO, pinning or locking")
    p.add_argument("--cpu", type=int, help="CPU to run the loop on (default: not pinned)")
    p.add_argument("--priority", type=int, default=70,
                   help="SCHED_FIFO priority (default 70, below the emulator's 80)")
    p.add_argument("--overrun", choices=("count", "skip"), default="count",
                   help="what a late tick does (default %(default)s)")
    p.add_argument("--connect-timeout", type=float, default=10.0, metavar="S",
                   help="how long to wait for the drive's first answers (default 10 s)")
    p.add_argument("--feedback-timeout", type=int, metavar="N",
                   help="ticks without feedback that end the run (default: 0.1 s)")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil controller``: returns the exit status."""
    stop = StopFlag()
    with stop_on_signals(stop.request):
        try:
            rc = ControllerRunConfig(
                machine_file=Path(args.config), adapter_url=args.adapter,
                program_file=Path(args.program), out_dir=Path(args.out), start_cnc=args.start,
                axis=args.axis, realtime=not args.no_rt, cpu=args.cpu, priority=args.priority,
                overrun=args.overrun, connect_timeout_s=args.connect_timeout,
                feedback_timeout_cycles=args.feedback_timeout)
            proc = ControllerProcess(rc, stop)
        except (ConfigError, ProgramError, RuntimeInputError, ValueError, OSError) as e:
            eprint(f"hil controller: {e}")
            return EXIT_BAD_INPUT
        try:
            summary = proc.run()
        except AdapterError as e:
            eprint(f"hil controller: {e}")
            return EXIT_BAD_INPUT
        except DriveNotAnswering as e:
            eprint(f"hil controller: {e}")
            return EXIT_FAILED
    u = proc.unit
    fe_max = summary[f"following_error_max_{u}"]
    rt = summary["round_trip_us"]
    print(f"hil controller: {summary['result']}; following error max "
          f"{fe_max if fe_max is None else format(fe_max, '.4g')} {u}; round trip p50 "
          f"{rt['p50']:.1f} p99 {rt['p99']:.1f} µs; summary in {rc.out_dir / 'summary.json'}",
          flush=True)
    if summary["exit_status"] != EXIT_OK:
        eprint(f"hil controller: {summary['result']}")
    return summary["exit_status"]


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.runtime.controller_proc ...``: the same as ``hil controller ...``."""
    parser = argparse.ArgumentParser(prog="hil controller",
                                     description="the simulated NC as a process")
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
