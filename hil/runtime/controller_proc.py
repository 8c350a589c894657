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
   duration plus :data:`hil.controller.interpolator.SETTLE_S`.  An alarm of the NC
   (:mod:`hil.controller.alarms`: contour, standstill or clamping monitoring, a bad
   feedback value, a drive fault) ends the run once the NC has stopped every axis
   (braked, drives disabled); the ticks until then are recorded.  A tick without new
   feedback (a late drive
   cycle, a lost frame) extrapolates the last one with the drive's speed actual value
   (606Ch) over one period, as a controller bridges a missing bus telegram, instead of
   reading a frozen encoder as standstill; on a link whose feedback says how old it is
   (``lag_is_age``: ``can://``, where an answer that came after this loop's tick is read
   a tick late) a late answer is extrapolated the same way over the ticks it is late;
   Over UDP, while the program runs in steady state, the loop's ticks are compiled
   (:mod:`hil.runtime.controller_steady`, the loop's ``burst``; the same setpoints,
   rows and counters as this Python tick);
5. send disable voltage, close, write ``trace.csv`` (servo-trace format, one row per
   position-control cycle, :func:`hil.sim.servo_trace_columns`), ``controller.npz`` (every
   recorded tick: :data:`FLOAT_COLUMNS`, :data:`INT_COLUMNS`, and the loop's
   ``lateness_ns``/``compute_ns`` per deadline; ``seq_minus_k``, the sequence number of
   tick k's setpoint less k, mod 2**32) and ``summary.json``
   (:mod:`hil.runtime.controller_files`).

**Several axes**: the machine file may be a manifest (:mod:`plant.machines`); then one
Controller per axis (:class:`hil.controller.machine.MachineController`), a multi-axis
program (:mod:`hil.controller.path`: ``G1 X10 Y5 F1000`` moves both on one line), one
message carrying every axis per tick, one servo trace per axis (``trace_X.csv``).

The run fails (exit 1, the reason in the summary and on stderr) when no drive answers
within ``--connect-timeout``, the enable sequence fails, the NC raised an alarm (the drive
leaving OPERATION ENABLED, after a fault or the emulator's watchdog, is alarm 25201 with
the drive's error code; ``summary.json`` lists every alarm with its number, axis, text,
tick and time, and stderr prints one line each), no feedback comes for
``--feedback-timeout`` cycles, or the axis is not where the program starts (``--start``).
The last line on stderr of a failed run is ``hil controller: FAIL: <reasons>``: each
alarm, and the drive's error code 603Fh in words when a drive reported a fault (8250h: the
emulator's watchdog found no valid setpoint in time).
"""

import argparse
import math
import sys
import time
from dataclasses import dataclass
from operator import attrgetter
from pathlib import Path

import numpy as np

from hil.cia402 import DISABLE_VOLTAGE
from hil.controller.compiled_path import warm
from hil.controller.config import clamp_codes, cnc_unit
from hil.controller.interpolator import SETTLE_S, plan
from hil.controller.machine import MachineController
from hil.controller.path import read_path_program
from hil.controller.program import ProgramError, read_program
from hil.drive.faults import fault_text
from hil.inject import INJECT_HELP
from hil.inject.sender import InjectionSender
from hil.progress import COLD_START, COMPILING, Progress
from hil.rt.loop import OverrunPolicy, RealTimeLoop
from hil.runtime.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    RuntimeInputError,
    StopFlag,
    check_cpu,
    check_link,
    eprint,
    period_ns_of,
    scheduling,
    shared_cpu,
    start_arg,
    start_positions,
    stop_on_signals,
)
from hil.runtime.controller_files import (
    CTRL_SIGNALS,
    FLOAT_COLUMNS,
    INT_COLUMNS,
    write_outputs,
)
from hil.runtime.controller_steady import ControllerSteady
from hil.runtime.sync import START_MARGIN_NS, U32, DriveNotAnswering, align
from hil.runtime.timing_quality import TimingQuality
from io_adapters import AdapterError, Endpoint, open_endpoint
from io_adapters.messages import axis_records, message_pair
from plant.errors import ConfigError
from plant.machines import load_machine_set

#: the axis must be this close to the program's start when enabled: SINUMERIK exact stop
#: coarse (MD36000), mm or deg
START_WINDOW_CNC = 0.04
DEFAULT_FEEDBACK_TIMEOUT_S = 0.1
#: FLOAT_COLUMNS and INT_COLUMNS of controller.npz: :mod:`hil.runtime.controller_files`.
#: The integer columns: the loop's deadline index, 1 when new feedback came, the lag
#: (ticks between the setpoint the feedback answers and the one sent last tick: 0 =
#: lock-step timing), the feedback's round trip (ns), and its stamps that pair it with
#: the emulator's recording (``hil report RUN --controller DIR``): its sp_t_ns and t_ns (the
#: setpoint it answers, its send on the drive's clock) and its rx_ns (this clock); the
#: last four 0 without new feedback
__all__ = [
    "FLOAT_COLUMNS",
    "INT_COLUMNS",
    "ControllerProcess",
    "ControllerRunConfig",
    "add_arguments",
    "failure_reasons",
    "fault_text",
    "main",
    "run_from_args",
]


@dataclass(frozen=True)
class ControllerRunConfig:
    """``hil controller``'s settings (SI unless named; see :func:`add_arguments`)."""
    machine_file: Path
    adapter_url: str
    program_file: Path
    out_dir: Path = Path("hil-controller")
    start_cnc: float | dict = 0.0
    axis: str | None = None
    realtime: bool = True
    cpu: int | None = None
    priority: int = 70
    overrun: str = "count"
    connect_timeout_s: float = 10.0
    feedback_timeout_cycles: int | None = None
    inject: tuple[str, ...] = ()

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
    """The controller's life cycle: program, adapter, alignment, loop, files.

    On a machine of several axes (a manifest) every axis has its own
    :class:`~hil.controller.nc.Controller` (:class:`~hil.controller.machine.MachineController`),
    the program moves them on straight lines (:mod:`hil.controller.path`) and one message
    pair per tick carries every axis (:class:`~io_adapters.messages.SetpointGroup`).
    """

    def __init__(self, rc: ControllerRunConfig, stop: StopFlag):
        self.rc = rc
        self.machine = m = load_machine_set(rc.machine_file, rc.axis)
        if m.manifest and rc.axis is not None:
            raise RuntimeInputError(f"--axis {rc.axis}: {rc.machine_file} names its axes "
                                    f"({', '.join(m.names)}); --axis is for a single machine file")
        self.url = check_link(rc.adapter_url, len(m.axes))  # can://: axes=N added
        self.cfg = m.configs[0]
        self.units = tuple(cnc_unit(c) for c in m.configs)
        self.k_cnc, self.unit = self.units[0]
        self.x0 = start_positions(m, rc.start_cnc)
        self.period_ns = period_ns_of(m.pwm_frequency_hz)
        self.period_s = self.period_ns * 1e-9
        self.mctrl = MachineController(m, self.period_s, self.x0)
        self.ctrl = self.mctrl.ctrls[0]
        with Progress(COMPILING, ticking=True):
            warm()  # the NC's compiled tick, now rather than at the loop's first steady tick
        if m.multi_axis:
            self.program = read_path_program(rc.program_file, m.names, self.x0,
                                             clamp=self.mctrl.clamp_codes)
            self.profiles = self.mctrl.plan(self.program)
            self.program_end = self.program.end
        else:
            self.program = read_program(rc.program_file, axis=m.names[0], start=self.x0[0],
                                        clamp=clamp_codes(self.ctrl.sec))
            self.profiles = (plan(self.program, self.mctrl.limits[0]),)
            self.program_end = (self.program.end,)
        self.profile = self.profiles[0]
        self.injections = InjectionSender(rc.inject, m)
        #: linear-scale counts per motor-encoder count per axis, to extrapolate the scale too
        self.scale_per_count = tuple(c.rad_per_count * c.ratio / c.scale_res
                                     if c.scale_res else 0.0 for c in self.mctrl.ctrls)
        self.n_run = math.ceil((self.profile.duration_s + SETTLE_S) / self.period_s)
        self.feedback_timeout = rc.feedback_timeout_cycles or max(
            1, round(DEFAULT_FEEDBACK_TIMEOUT_S / self.period_s))
        self.sp, self.fb = message_pair(len(m.axes))
        self.fbs = axis_records(self.fb)
        self.delay_ticks = 0        # the link's, set when it is opened (run)
        self.lag_is_age = False
        self.floats = np.full((self.n_run, len(m.axes), len(FLOAT_COLUMNS)), np.nan)
        self.ints = np.zeros((self.n_run, len(INT_COLUMNS)), dtype=np.int64)
        #: each recorded tick's NC part (every axis's Controller.tick), ns
        self.nc_ns = np.zeros(self.n_run, dtype=np.int64)
        self._get = attrgetter(*CTRL_SIGNALS)
        timeout = self.mctrl.enable_timeout_ticks
        self.loop = RealTimeLoop(self.period_ns, self.step, n_ticks=timeout + 2 + self.n_run,
                                 policy=OverrunPolicy(rc.overrun, grace_ticks=timeout))
        stop.attach(self.loop)
        self.stop = stop
        self.ep: Endpoint | None = None
        #: the compiled steady loop (run() builds it once the link is open)
        self.steady: ControllerSteady | None = None
        self.rows = 0
        self.running = False
        self.profile_start_s = 0.0
        self.seq_minus_k = 0
        self.silent = 0
        self.adapter_errors = 0
        #: other processes' real-time threads pinned to the loop's CPU at its start
        self.cpu_shared_with: list[str] = []
        self.result = "completed"

    def step(self, k: int) -> None:
        """Newest feedback, one controller tick, the setpoint out; enable, then the program
        (in compiled code where :class:`~hil.runtime.controller_steady.ControllerSteady`
        takes the tick)."""
        if self.steady is not None and self.steady.tick(k):
            return
        mctrl, sp, fb = self.mctrl, self.sp, self.fb
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
        t0 = time.perf_counter_ns()
        mctrl.tick(fb, sp)
        nc_ns = time.perf_counter_ns() - t0
        try:
            self.ep.send_setpoint(sp)
        except AdapterError:
            self.adapter_errors += 1
        if self.silent >= self.feedback_timeout:
            self._fail(f"no feedback for {self.silent} cycles at tick {k}")
            return
        if self.running:
            self.nc_ns[self.rows] = nc_ns
            self._record(k, new)
            if self.injections.planned:
                self._inject()
        elif not mctrl.alarmed:
            self._start(k)
        if mctrl.alarmed:
            if self.result == "completed":
                self.result = mctrl.alarms[0].message()
            if mctrl.stopped:
                self.loop.request_stop()

    def _record(self, k: int, new: bool) -> None:
        """Row ``self.rows`` of the recording; the run ends when the last is taken."""
        mctrl, sp, fb = self.mctrl, self.sp, self.fb
        i = self.rows
        row = self.floats[i]
        for a, (ctrl, f) in enumerate(zip(mctrl.ctrls, self.fbs)):
            row[a] = self._get(ctrl) + (f.iq_a, f.encoder_counts * ctrl.rad_per_count,
                                        ctrl.tick_count - 1, fb.time_s)
        lag = (sp.seq - 1 - fb.seq) & U32
        self.ints[i] = ((k, 1, lag, fb.round_trip_ns(), fb.sp_t_ns, fb.t_ns, fb.rx_ns)
                        if new else (k, 0, lag, 0, 0, 0, 0))
        self.rows = i + 1
        if self.rows == self.n_run:
            self.loop.request_stop()

    def _inject(self) -> None:
        """Send the ``--inject`` requests due at this program time."""
        for request in self.injections.due(self.ctrl.t - self.profile_start_s):
            try:
                self.ep.send_injection(request)
            except AdapterError:
                self.adapter_errors += 1

    def _extrapolate(self, ticks: int) -> None:
        """The feedback moved on by ``ticks`` periods at each drive's speed actual value."""
        dt = ticks * self.period_s
        for f, scale in zip(self.fbs, self.scale_per_count):
            f.encoder_counts += f.velocity_counts_s * dt
            f.scale_counts += f.velocity_counts_s * scale * dt
        self.fb.time_s += dt

    def _enable_reason(self) -> str:
        return (self.mctrl.enable_reason() if self.machine.multi_axis
                else self.ctrl.enable.reason)

    def _start(self, k: int) -> None:
        mctrl = self.mctrl
        if mctrl.enable_failed:
            self._fail(f"enable failed: {self._enable_reason()}")
        elif mctrl.enabled:
            for name, ctrl, x0, (k_cnc, unit) in zip(self.machine.names, mctrl.ctrls,
                                                     self.x0, self.units):
                if abs(ctrl.x_act - x0) * k_cnc > START_WINDOW_CNC:
                    axis = f"axis {name}" if self.machine.multi_axis else "the axis"
                    self._fail(f"{axis} is at {ctrl.x_act * k_cnc:.4f} {unit}, the program "
                               f"starts at {x0 * k_cnc:.4f} {unit} (--start)")
                    return
            mctrl.run_profiles(self.profiles)
            self.profile_start_s = self.ctrl.t
            # every tick sends one setpoint, the compiled ones too: the sequence number
            # of tick k's is k plus this (hil export --controller finds a row by it)
            self.seq_minus_k = (self.sp.seq - k) & U32
            self.running = True

    def drive_faults(self) -> list[str]:
        """The error code 603Fh of each axis whose last feedback reported one, in words."""
        names = self.machine.names
        return [f"axis {name}: the drive reported 603Fh = {f.fault:04X}h "
                f"({fault_text(f.fault)})" for name, f in zip(names, self.fbs) if f.fault]

    def _fail(self, reason: str) -> None:
        self.result = reason
        self.loop.request_stop()

    def run(self) -> dict:
        """Open, align, run, disable, write; returns the summary."""
        rc = self.rc
        self.ep = open_endpoint(self.url, "controller")
        self.ep.drain = True
        self.delay_ticks = getattr(self.ep, "feedback_delay_ticks", 0)
        self.lag_is_age = getattr(self.ep, "lag_is_age", False)
        self.steady = ControllerSteady.for_process(self)
        if self.steady is not None:
            with Progress(f"loading the compiled loop ({COLD_START})", ticking=True):
                self.steady.warm()
            self.loop.burst = self.steady.burst
        neighbours, warning = shared_cpu(rc.realtime, rc.cpu, rc.priority)
        self.cpu_shared_with = [n.describe() for n in neighbours]
        if warning:
            eprint(f"hil controller: {warning}")
        try:
            with scheduling(rc.realtime, rc.cpu, rc.priority) as granted:
                with Progress(f"waiting for the drive at {self.url} (up to "
                              f"{rc.connect_timeout_s:g} s)", ticking=True):
                    alignment = align(self.ep, self.sp, self.fb, self.period_ns,
                                      rc.connect_timeout_s)
                self.loop.start_ns = alignment.first_deadline(
                    self.period_ns, self.loop.clock.now_ns() + START_MARGIN_NS)
                stats = self.loop.run()
                self._disable()
        finally:
            self.ep.close()
        if stats.stopped_by == "overruns":
            self.result = "stopped by overruns"
        elif self.result == "completed" and self.rows < self.n_run:
            self.result = ("stopped by SIGTERM/SIGINT" if self.stop.requested
                           else f"the program did not finish in {stats.ticks} ticks")
        return write_outputs(self, stats, granted, alignment)

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


def failure_reasons(summary: dict, drive_faults: list[str]) -> list[str]:
    """Why a run failed, one phrase each: every alarm, else the result; then the drives'
    faults (``drive_faults``, :meth:`ControllerProcess.drive_faults`)."""
    reasons = [a["message"] for a in summary["alarms"]] or [summary["result"]]
    return reasons + drive_faults


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil controller``."""
    p.add_argument("config", help="machine file (TOML) with a [controller] section, or a "
                   "manifest of several axes (configs/machines/)")
    p.add_argument("--adapter", required=True, metavar="URL", help="the drive's adapter URL")
    p.add_argument("--program", required=True, help="part program (G-code subset)")
    p.add_argument("--out", default="hil-controller", help="folder for trace.csv, "
                   "controller.npz and summary.json (default %(default)s)")
    p.add_argument("--start", type=start_arg, default=0.0,
                   help="table position at start, mm (deg on rotary tables), or per axis: "
                        "X=10,Y=-5")
    p.add_argument("--axis", help="axis letter in the program of a single machine file "
                   "(default X, or C if rotary)")
    p.add_argument("--no-rt", action="store_true", help="no SCHED_FIFO, pinning or locking")
    p.add_argument("--cpu", type=int, help="CPU to run the loop on (default: not pinned)")
    p.add_argument("--priority", type=int, default=70,
                   help="SCHED_FIFO priority (default 70, below the emulator's 80)")
    p.add_argument("--overrun", choices=("count", "skip"), default="count",
                   help="what a late tick does (default %(default)s)")
    p.add_argument("--inject", action="append", metavar="[AXIS/]FAULT:KEY=VALUE,...",
                   help=INJECT_HELP.replace("inject a fault", "send the drive a fault", 1)
                   + "; at_s is the time into the program to send it at (the INJECT message)")
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
                feedback_timeout_cycles=args.feedback_timeout, inject=tuple(args.inject or ()))
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
    quality = TimingQuality.of_controller(summary)
    print(f"hil controller: {quality.line()}", flush=True)
    if quality.worst_overrun:
        print(f"hil controller: {quality.worst_text()}", flush=True)
    if summary["exit_status"] != EXIT_OK:
        reasons = failure_reasons(summary, proc.drive_faults())
        if quality.worst_overrun:  # a failure under load: name the stall with it
            reasons.append(quality.worst_text())
        eprint(f"hil controller: FAIL: {'; '.join(reasons)}")
    return summary["exit_status"]


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.runtime.controller_proc ...``: the same as ``hil controller ...``."""
    parser = argparse.ArgumentParser(prog="hil controller",
                                     description="the simulated NC as a process")
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
