"""``hil run``: the emulator daemon -- one plant behind an adapter, in real time.

::

    hil run configs/arrow500_x.toml --adapter udp://127.0.0.1:5005 --record runs/r1

Life cycle, in this order (uvicorn's: one config, one server owning the life cycle,
signal handlers that only set a flag, a fixed shutdown order):

1. **Configure**: the runtime settings come from the command line into a frozen
   :class:`RuntimeConfig` (machine files have no ``[runtime]`` section); the machine file
   is loaded and checked, the rate checked against its PWM frequency.  A bad file, key or
   value is refused here (exit 2), before any adapter is opened.
2. **Build**: the plant and the CiA 402 drive (:class:`hil.drive.EmulatedDrive`), the
   kernel warmed by :data:`WARMUP_CYCLES` cycles on the same arrays (then reset), the
   recording buffers and the :class:`~hil.rt.loop.RealTimeLoop` allocated and touched.
3. **Open** the adapter, device role, draining (each tick uses the newest setpoint), and
   print ``ready: URL`` on stdout (the port actually bound for ``udp://HOST:0``).  IPC is
   set up before any priority change (see ``docs/platform-notes``: a SCHED_FIFO process
   must not start helpers later).
4. **Run** under :func:`hil.rt.scheduling.realtime_scheduling` (SCHED_FIFO, pinned, memory
   locked; ``--no-rt`` leaves the process as it is).  Each tick (:meth:`Emulator.step`):
   poll the newest setpoint (timeout 0), the :class:`~hil.runtime.watchdog.Watchdog`,
   ``cycles_per_tick`` drive cycles (one PWM period each), send the feedback, record.
   Nothing raises there: adapter errors are counted and logged once.  On an adapter
   whose cycle follows the master's SYNC (``can://``: the endpoint has
   ``last_sync_ns``) the loop's ticks are moved to a fixed phase after SYNC
   (:class:`hil.runtime.sync.SyncLock`), as a CiA 402 drive locks its cycle to SYNC,
   and a tick whose SYNC is late waits a little for it; lateness is then measured
   against the moved deadlines, and the compute time includes that wait.  An adapter's
   own threads (canopen's receive thread on ``can://``) run at SCHED_FIFO one below the
   loop, on its CPU (:func:`helper_threads_realtime`).
5. **Stop** on ``--duration``, on SIGTERM/SIGINT (the handlers only set the loop's stop
   flag), at ``--max-duration`` (the recording's capacity), or by the ``stop`` overrun
   policy; then: the safe state (one cycle with controlword 0, disable voltage: the drive
   leaves OPERATION ENABLED, torque off; a faulted drive stays in FAULT), real-time
   scheduling undone, the adapter closed, ``run.npz`` written, ``report.json`` written
   last (its presence means the run folder is complete).

The run folder (``--record DIR``) is what ``hil report RUN`` reads: ``run.npz``
(:mod:`hil.runtime.recording`) and ``report.json`` (:meth:`Emulator.report`).

**Several axes**: the machine file may be a manifest (:mod:`plant.machines`,
``configs/machines/``).  Then one plant and one CiA 402 drive per axis
(:class:`hil.drive.DriveSet`), every tick cycles them all on one message carrying every
axis's setpoint (:class:`~io_adapters.messages.SetpointGroup`, wire version 2 on
``udp://`` and ``serial://``, three axes at most on ``serial://``; on ``can://`` one
CiA 402 node per axis, node-IDs consecutive from ``node``, the URL's ``axes`` taken from
the machine), one watchdog faults every enabled drive, the
recording has per-axis columns (:mod:`hil.runtime.recording`) and ``report.json`` an
``axes`` list and a safe state per
axis.  A plain machine file runs exactly as before.

The rate defaults to the plant's PWM frequency (one PWM period per tick); a lower rate must
divide it, and each tick then runs that many PWM periods on the same setpoint, so the
plant stays in real time for a controller with a longer cycle.
"""

import argparse
import math
import os
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from hil.cia402 import DISABLE_VOLTAGE
from hil.drive import DriveSet, EmulatedDrive
from hil.drive.objects import DriveObjects
from hil.report.host import host_fingerprint
from hil.rt.loop import OverrunPolicy, RealTimeLoop
from hil.rt.scheduling import last_cpu
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
    scheduling_dict,
    served_url,
    start_arg,
    start_positions,
    stop_on_signals,
    write_json,
)
from hil.runtime.recording import RUN_NPZ, Recorder, units, write_npz
from hil.runtime.sync import ShiftableClock, SyncLock
from hil.runtime.watchdog import Watchdog
from io_adapters import AdapterError, Endpoint, open_endpoint
from io_adapters.messages import axis_records, message_pair
from plant import Plant
from plant import layout as L
from plant.config import MachineConfig
from plant.errors import ConfigError
from plant.machines import MachineSet, load_machine_set, single_axis

#: drive cycles run on the plant before the clock starts (compiled code and caches warm)
WARMUP_CYCLES = 2000
#: default watchdog: this long without a setpoint (an EtherCAT sync-manager watchdog's
#: usual 100 ms; shorter trips on the multi-millisecond pauses of a VM)
DEFAULT_WATCHDOG_S = 0.1
#: overruns in the first this-many seconds (start-up) never stop the loop
GRACE_S = 0.1
DEFAULT_MAX_DURATION_S = 120.0
#: the longest a fault reaction may still brake in the safe state at shutdown, s of drive time
SAFE_STATE_MAX_S = 5.0
DEFAULT_RUN_DIR = "hil-run"
RUN_JSON = "report.json"


@dataclass(frozen=True)
class RuntimeConfig:
    """The daemon's settings, from the command line (SI unless named).

    Attributes:
        machine_file: the TOML machine file, or a manifest of several axes.
        adapter_url: where the controller talks to the drive (``udp://``, ``serial://``).
        run_dir: the run folder for ``run.npz`` and ``report.json``.
        duration_s: run this long, or None: until SIGTERM/SIGINT (at most ``max_duration_s``).
        max_duration_s: the recording's capacity without ``duration_s``, s.
        rate_hz: loop rate, Hz; None: the plant's PWM frequency.
        watchdog_cycles: ticks without a setpoint that fault the drive; None: 0.1 s worth.
        overrun: "count", "skip" or "stop" (:class:`~hil.rt.loop.OverrunPolicy`).
        stop_after: with "stop", the overrun (after the first 0.1 s) that stops the run.
        realtime: request SCHED_FIFO, affinity, locked memory (else run as started).
        cpu: the CPU to pin the loop to; None: the last CPU.
        priority: SCHED_FIFO priority, 1-99.
        start_cnc: the table's position at start in the CNC's unit (mm; deg on rotary
            tables), for every axis, or per axis letter (:func:`~hil.runtime.common.start_arg`).
    """
    machine_file: Path
    adapter_url: str
    run_dir: Path = Path(DEFAULT_RUN_DIR)
    duration_s: float | None = None
    max_duration_s: float = DEFAULT_MAX_DURATION_S
    rate_hz: float | None = None
    watchdog_cycles: int | None = None
    overrun: str = "count"
    stop_after: int = 10
    realtime: bool = True
    cpu: int | None = None
    priority: int = 80
    start_cnc: float | dict = 0.0

    def __post_init__(self):
        positive = {"--duration (s)": self.duration_s, "--max-duration (s)": self.max_duration_s,
                    "--rate (Hz)": self.rate_hz}
        for option, value in positive.items():
            if value is not None and not 0.0 < value < math.inf:
                raise RuntimeInputError(f"{option} must be > 0 and finite, got {value}")
        if self.watchdog_cycles is not None and self.watchdog_cycles < 1:
            raise RuntimeInputError(f"--watchdog-cycles must be >= 1 cycle, got "
                                    f"{self.watchdog_cycles}")
        if not 1 <= self.priority <= 99:
            raise RuntimeInputError(f"--priority must be 1..99 (SCHED_FIFO), got {self.priority}")
        try:
            OverrunPolicy(self.overrun, self.stop_after)
        except ValueError as e:
            raise RuntimeInputError(f"--overrun/--stop-after: {e}") from e
        check_cpu(self.cpu)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> "RuntimeConfig":
        """From the options :func:`add_arguments` declares."""
        return cls(machine_file=Path(args.config), adapter_url=args.adapter,
                   run_dir=Path(args.record), duration_s=args.duration,
                   max_duration_s=args.max_duration, rate_hz=args.rate,
                   watchdog_cycles=args.watchdog_cycles, overrun=args.overrun,
                   stop_after=args.stop_after, realtime=not args.no_rt, cpu=args.cpu,
                   priority=args.priority, start_cnc=args.start)


@dataclass(frozen=True)
class Timing:
    """The loop's timing, resolved against the machine file."""
    rate_hz: float
    period_ns: int
    cycles_per_tick: int
    n_ticks: int
    watchdog_cycles: int
    grace_ticks: int


def resolve_timing(rc: RuntimeConfig, cfg: MachineConfig) -> Timing:
    """Rate, period and tick counts; refuses a rate that does not divide the PWM frequency."""
    f_pwm = cfg.motor.pwm_frequency_hz
    rate = rc.rate_hz or f_pwm
    cycles = round(f_pwm / rate)
    if cycles < 1 or abs(cycles * rate - f_pwm) > 1e-9 * f_pwm:
        raise RuntimeInputError(f"--rate {rate:g} Hz: must be the PWM frequency {f_pwm:g} Hz "
                                f"({cfg.path} [motor] pwm_frequency_hz) divided by a whole "
                                f"number")
    period_ns = period_ns_of(rate)
    seconds = rc.duration_s if rc.duration_s is not None else rc.max_duration_s
    return Timing(rate_hz=rate, period_ns=period_ns, cycles_per_tick=cycles,
                  n_ticks=max(1, round(seconds * 1e9 / period_ns)),
                  watchdog_cycles=rc.watchdog_cycles or max(1, round(DEFAULT_WATCHDOG_S * rate)),
                  grace_ticks=round(GRACE_S * rate))


def helper_threads_realtime(cpu: int, priority: int) -> dict[str, str]:
    """Give every thread of this process but the loop's and the main one (an adapter's
    receive thread: canopen's on ``can://``) SCHED_FIFO ``priority`` on ``cpu``; returns
    thread name -> what was done.  At normal priority such a thread, preempted while it
    holds the GIL, stalls the loop waiting behind it for milliseconds (priority
    inversion; measured on ``can://udp_multicast`` at 2 kHz: the emulator's lateness
    p99.9 2.4-3.4 ms, 50-100 µs with this).  One below the loop on the loop's CPU, it
    runs while the loop sleeps; it never spins (it blocks in its receive), so it cannot
    starve the loop."""
    done = {}
    for t in threading.enumerate():
        if t in (threading.main_thread(), threading.current_thread()) or t.native_id is None:
            continue
        try:
            os.sched_setaffinity(t.native_id, {cpu})
            os.sched_setscheduler(t.native_id, os.SCHED_FIFO, os.sched_param(priority))
            done[t.name] = f"SCHED_FIFO {priority} on CPU {cpu}"
        except OSError as e:
            done[t.name] = f"left as it was: {e}"
    return done


@dataclass
class AdapterErrors:
    """Transport errors met in the loop (counted, never raised there)."""
    receive: int = 0
    send: int = 0
    first: dict = field(default_factory=dict)


class Emulator:
    """The daemon: owns the plant, the drive, the adapter, the loop and the recording.

    Args:
        rc: the runtime settings.
        cfg: the machine file (one axis) or the machine of several axes, loaded and checked.
        stop: the flag the signal handlers set (a fresh one if not given).
        log: receives the log lines (stderr by default).
    """

    def __init__(self, rc: RuntimeConfig, cfg: MachineConfig | MachineSet,
                 stop: StopFlag | None = None, log=eprint):
        self.machine = m = cfg if isinstance(cfg, MachineSet) else single_axis(cfg)
        self.rc, self.cfg, self.log = rc, m.configs[0], log
        self.timing = t = resolve_timing(rc, self.cfg)  # one PWM period for all (manifest)
        self.x0 = start_positions(m, rc.start_cnc)
        self.plants = tuple(Plant(c, table_pos=x) for c, x in zip(m.configs, self.x0))
        self.plant = self.plants[0]
        self._warm_up()
        self.sp, self.fb = message_pair(len(m.axes))
        self.watchdog = Watchdog(t.watchdog_cycles, t.period_ns * 1e-9, self._log)
        self.recorder = Recorder(t.n_ticks, m.names if m.multi_axis else None)
        self.loop = RealTimeLoop(t.period_ns, self.step, n_ticks=t.n_ticks,
                                 policy=OverrunPolicy(rc.overrun, rc.stop_after, t.grace_ticks))
        self.stop = stop or StopFlag()
        self.stop.attach(self.loop)
        self.endpoint: Endpoint | None = None
        self.sync_lock: SyncLock | None = None
        self.helper_threads: dict[str, str] = {}
        self.url = rc.adapter_url
        self.errors = AdapterErrors()

    def _log(self, message: str) -> None:
        self.log(f"hil run: {message}")

    def _warm_up(self) -> None:
        """Compile and warm the drives' path on the real arrays, then start afresh.
        ``drives`` cycles every axis (:class:`DriveSet`); ``drive`` is axis 0's."""
        # the drives check [controller] for the CSP/CSV loops
        self.drives = DriveSet([EmulatedDrive(p) for p in self.plants])
        sp, fb = message_pair(len(self.plants))
        for _ in range(WARMUP_CYCLES):
            self.drives.cycle(sp, fb)
        for p, x in zip(self.plants, self.x0):
            p.reset(x)
        self.drives = DriveSet([EmulatedDrive(p) for p in self.plants])
        self.drive = self.drives[0]

    def open(self, endpoint: Endpoint | None = None) -> str:
        """Open the adapter (device role, draining), or take ``endpoint``; returns the URL
        served (with the bound port for ``udp://HOST:0``)."""
        url = (self.rc.adapter_url if endpoint is not None
               else check_link(self.rc.adapter_url, len(self.machine.axes)))
        self.endpoint = endpoint or open_endpoint(url, "device")
        self.endpoint.drain = True
        self.endpoint.setpoint_bounds = tuple(d.setpoint_bounds() for d in self.drives.drives)
        if hasattr(self.endpoint, "objects"):  # a CANopen node: its parameter objects
            self.endpoint.objects = DriveObjects(self.drives.drives,
                                                 self.endpoint.rated_current_a)
        if getattr(self.endpoint, "exposed", False):
            self._log(f"WARNING: {url} is reachable from the network; this bench tool has no "
                      "authentication (README: who may talk to the drive)")
        if hasattr(self.endpoint, "last_sync_ns"):  # the cycle follows SYNC
            clock = ShiftableClock(self.loop.clock)
            self.loop.clock = clock
            self.sync_lock = SyncLock(clock, self.timing.period_ns)
        self.url = served_url(url, getattr(self.endpoint, "address", None))
        return self.url

    def step(self, k: int) -> None:
        """Tick ``k``: newest setpoint, watchdog, drive cycles, feedback, record."""
        t_ns = time.monotonic_ns()
        sp, fb, drives = self.sp, self.fb, self.drives
        try:
            heard = self.endpoint.recv_setpoint(
                sp, 0.0 if self.sync_lock is None else self.sync_lock.wait_s)
        except AdapterError as e:
            heard = False
            self._adapter_error("receive", e)
        refused = self.endpoint.refused_axes
        if refused:
            for a, d in enumerate(drives.drives):
                if refused >> a & 1:
                    d.refuse_setpoint()
        if self.sync_lock is not None:
            self.sync_lock.update(self.endpoint.last_sync_ns)
        self.watchdog.update(heard, k, sp.seq, drives, self.endpoint)
        for _ in range(self.timing.cycles_per_tick):
            drives.cycle(sp, fb)
        fb.tick_ns = t_ns
        if self.watchdog.answering or self.sync_lock is not None:  # SYNC asks for it
            try:
                self.endpoint.send_feedback(fb)
            except AdapterError as e:
                self._adapter_error("send", e)
        self.recorder.record(k, heard, t_ns, sp, fb, drives)

    def _adapter_error(self, kind: str, err: AdapterError) -> None:
        count = getattr(self.errors, kind) + 1
        setattr(self.errors, kind, count)
        if count == 1:
            self.errors.first[kind] = str(err)
            self._log(f"adapter {kind} error (counted, logged once): {err}")

    def safe_state(self) -> dict:
        """Drive cycles with controlword 0 (disable voltage: transitions 7, 9, 10, 12 to
        SWITCH ON DISABLED; a drive in FAULT stays there) until every power stage is off:
        one cycle, or as many as a fault reaction still braking needs (at most
        :data:`SAFE_STATE_MAX_S` of drive time, run back to back as the loop has stopped);
        the last feedback sent to a controller still listening; returns the state reached
        (per axis letter on a machine of several axes)."""
        self.sp.controlword = DISABLE_VOLTAGE.value
        for _ in range(max(1, round(SAFE_STATE_MAX_S / self.plant.pwm_period))):
            self.drives.cycle(self.sp, self.fb)
            if all(d.plant.inp[L.I_ENABLE] == 0.0 for d in self.drives.drives):
                break
        if self.watchdog.answering:
            try:
                self.endpoint.send_feedback(self.fb)
            except AdapterError as e:
                self._adapter_error("send", e)
        states = {name: {"state": d.sm.state.name, "statusword": f"0x{fb.statusword:04X}",
                         "plant_enable": float(d.plant.inp[L.I_ENABLE]),
                         "error_code": f"0x{d.fault:04X}"}
                  for name, d, fb in zip(self.machine.names, self.drives.drives,
                                         axis_records(self.fb))}
        return states if self.machine.multi_axis else states[self.machine.names[0]]

    def run(self) -> dict:
        """Run the loop, then shut down in the fixed order; returns the report (also written
        to the run folder).  The adapter must be open."""
        rc = self.rc
        rc.run_dir.mkdir(parents=True, exist_ok=True)
        cpu = rc.cpu if rc.cpu is not None else last_cpu()
        with scheduling(rc.realtime, cpu, rc.priority) as granted:
            if granted is not None and granted.fifo.granted:
                self.helper_threads = helper_threads_realtime(cpu, max(1, rc.priority - 1))
            stats = self.loop.run()
            safe = self.safe_state()
        self.endpoint.close()
        columns = self.recorder.columns(stats.lateness_ns, stats.compute_ns)
        write_npz(rc.run_dir / RUN_NPZ, columns)
        status = EXIT_FAILED if stats.stopped_by == "overruns" else EXIT_OK
        report = self.report(stats, granted, safe, columns, status)
        write_json(rc.run_dir / RUN_JSON, report)
        return report

    def report(self, stats, granted, safe: dict, columns: dict, status: int) -> dict:
        """``report.json``: the keys ``hil report`` reads (loop, scheduling, adapter, host)
        and the daemon's own."""
        rc, t = self.rc, self.timing
        heard = columns["sp_new"] == 1
        return {
            "command": "hil run", "machine_file": str(rc.machine_file),
            "machine": self.machine.name, "exit_status": status,
            "axes": [{"name": a.name, "machine_file": a.config.path,
                      "machine": a.config.machine.name} for a in self.machine.axes],
            "runtime": {**{k: str(v) if isinstance(v, Path) else v
                           for k, v in asdict(rc).items()},
                        **asdict(t), "cpu_used": rc.cpu if rc.cpu is not None else last_cpu(),
                        "pwm_frequency_hz": self.cfg.motor.pwm_frequency_hz},
            "loop": stats.as_dict(), "scheduling": scheduling_dict(granted),
            "adapter": {"name": self.url, "stats": asdict(self.endpoint.stats)},
            "adapter_errors": asdict(self.errors),
            "sync_lock": None if self.sync_lock is None else self.sync_lock.as_dict(),
            "helper_threads": self.helper_threads,
            "setpoints": {"ticks_with_new_setpoint": int(heard.sum()),
                          "last_seq": int(self.sp.seq)},
            "watchdog": self.watchdog.as_dict(), "safe_state": safe,
            "faults": {name: d.faults.as_dict()
                       for name, d in zip(self.machine.names, self.drives.drives)},
            "recording": {"file": RUN_NPZ, "slots": len(stats.lateness_ns),
                          "ticks": stats.ticks,
                          "columns": units(self.machine.names if self.machine.multi_axis
                                           else None)},
            "host": host_fingerprint(),
        }


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil run``."""
    p.add_argument("config", help="machine file (TOML), or a manifest of several axes "
                   "(configs/machines/)")
    p.add_argument("--adapter", required=True, metavar="URL",
                   help="udp://HOST:PORT (port 0: any free one, printed) or serial://PATH")
    p.add_argument("--duration", type=float, metavar="S",
                   help="run S seconds (default: until SIGTERM/SIGINT)")
    p.add_argument("--max-duration", type=float, default=DEFAULT_MAX_DURATION_S, metavar="S",
                   help="without --duration: stop after S seconds; the recording is held in "
                        "memory, about 300 bytes per tick (default %(default)s)")
    p.add_argument("--record", default=DEFAULT_RUN_DIR, metavar="DIR",
                   help="run folder for run.npz and report.json (default %(default)s)")
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="loop rate (default: the plant's PWM frequency; must divide it)")
    p.add_argument("--watchdog-cycles", type=int, metavar="N",
                   help="ticks without a setpoint that fault the drive (default: 0.1 s)")
    p.add_argument("--overrun", choices=("count", "skip", "stop"), default="count",
                   help="what a late tick does (default %(default)s)")
    p.add_argument("--stop-after", type=int, default=10, metavar="N",
                   help="with --overrun stop: stop at the Nth overrun (default %(default)s)")
    p.add_argument("--no-rt", action="store_true",
                   help="no SCHED_FIFO, pinning or memory locking")
    p.add_argument("--cpu", type=int, help="CPU to run the loop on (default: the last)")
    p.add_argument("--priority", type=int, default=80, help="SCHED_FIFO priority (default 80)")
    p.add_argument("--start", type=start_arg, default=0.0,
                   help="table position at start, mm (deg on rotary tables), or per axis: "
                        "X=10,Y=-5")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil run``: configure, build, open, run; returns the exit status."""
    stop = StopFlag()
    with stop_on_signals(stop.request):
        try:
            rc = RuntimeConfig.from_args(args)
            emulator = Emulator(rc, load_machine_set(rc.machine_file), stop)
            url = emulator.open()
        except (ConfigError, RuntimeInputError, AdapterError) as e:
            eprint(f"hil run: {e}")
            return EXIT_BAD_INPUT
        print(f"ready: {url}", flush=True)
        report = emulator.run()
    loop, lat = report["loop"], report["loop"]["lateness_us"]
    print(f"hil run: {loop['ticks']} ticks at {emulator.timing.rate_hz:g} Hz, stopped by "
          f"{loop['stopped_by']}; lateness p50 {lat['p50']:.1f} p99 {lat['p99']:.1f} p99.9 "
          f"{lat['p999']:.1f} max {lat['max']:.1f} µs; overruns {loop['overruns']}; "
          f"watchdog events {report['watchdog']['events_total']}; run folder {rc.run_dir}",
          flush=True)
    return report["exit_status"]


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.runtime.emulator ...``: the same as ``hil run ...``."""
    parser = argparse.ArgumentParser(prog="hil run", description="the emulator daemon")
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
