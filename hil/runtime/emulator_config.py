"""``hil run``'s settings: the command line into a frozen :class:`RuntimeConfig`, and the
loop's :class:`Timing` resolved against the machine file (machine files have no
``[runtime]`` section).  A value out of range is a
:class:`~hil.runtime.common.RuntimeInputError` naming the option, the value and the range.
"""

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

from hil.inject import INJECT_HELP
from hil.rt.loop import OverrunPolicy
from hil.runtime.common import RuntimeInputError, check_cpu, period_ns_of, start_arg
from plant.config import MachineConfig

#: default watchdog: this long without a setpoint (an EtherCAT sync-manager watchdog's
#: usual 100 ms; shorter trips on the multi-millisecond pauses of a VM)
DEFAULT_WATCHDOG_S = 0.1
#: overruns in the first this-many seconds (start-up) never stop the loop
GRACE_S = 0.1
#: the share of a period a tick may spend reading datagrams (--rx-share; the adapter's
#: receive budget, io_adapters.udp.rx_budget_for)
DEFAULT_RX_SHARE = 0.25
DEFAULT_RUN_DIR = "hil-run"


@dataclass(frozen=True)
class RuntimeConfig:
    """The daemon's settings, from the command line (SI unless named).

    Attributes:
        machine_file: the TOML machine file, or a manifest of several axes.
        adapter_url: where the controller talks to the drive (``udp://``, ``serial://``).
        run_dir: the run folder (recording, events, ``report.json``).
        duration_s: run this long, or None: until SIGTERM/SIGINT.
        force: replace a run already in ``run_dir``.
        rate_hz: loop rate, Hz; None: the plant's PWM frequency.
        watchdog_cycles: ticks without a setpoint that fault the drive; None: 0.1 s worth.
        overrun: "count", "skip" or "stop" (:class:`~hil.rt.loop.OverrunPolicy`).
        stop_after: with "stop", the overrun (after the first 0.1 s) that stops the run.
        realtime: request SCHED_FIFO, affinity, locked memory (else run as started).
        cpu: the CPU to pin the loop to; None: the last CPU.
        priority: SCHED_FIFO priority, 1-99.
        start_cnc: the table's position at start in the CNC's unit (mm; deg on rotary
            tables), for every axis, or per axis letter (:func:`~hil.runtime.common.start_arg`).
        inject: ``--inject`` flags, ``[AXIS/]FAULT:KEY=VALUE,...`` (:mod:`hil.inject`).
        steady_tick: run steady ticks in one compiled call where that applies
            (:mod:`hil.runtime.steady_tick`); False: every tick in Python (the reference
            the compiled tick is tested against).
        rx_share: the share of a period a tick may spend reading datagrams, (0, 1]: a
            ``udp://`` adapter reads at most that many datagrams' worth a tick and leaves
            the rest queued (:func:`io_adapters.udp.rx_budget_for`).
        status_line: show the run's status on stderr while it goes on
            (:mod:`hil.runtime.run_status`; ``hil run`` does unless ``--no-status``).
        inject_port: the UDP port on 127.0.0.1 of a bench's injection port
            (:mod:`io_adapters.inject_port`: INJECT messages from ``hil scope``'s page or
            a script on this machine; 0: any free one); None: none.
    """
    machine_file: Path
    adapter_url: str
    run_dir: Path = Path(DEFAULT_RUN_DIR)
    duration_s: float | None = None
    force: bool = False
    rate_hz: float | None = None
    watchdog_cycles: int | None = None
    overrun: str = "count"
    stop_after: int = 10
    realtime: bool = True
    cpu: int | None = None
    priority: int = 80
    start_cnc: float | dict = 0.0
    inject: tuple[str, ...] = ()
    steady_tick: bool = True
    rx_share: float = DEFAULT_RX_SHARE
    status_line: bool = False
    inject_port: int | None = None

    def __post_init__(self):
        positive = {"--duration (s)": self.duration_s, "--rate (Hz)": self.rate_hz}
        for option, value in positive.items():
            if value is not None and not 0.0 < value < math.inf:
                raise RuntimeInputError(f"{option} must be > 0 and finite, got {value}")
        if self.watchdog_cycles is not None and self.watchdog_cycles < 1:
            raise RuntimeInputError(f"--watchdog-cycles must be >= 1 cycle, got "
                                    f"{self.watchdog_cycles}")
        if not 0.0 < self.rx_share <= 1.0:
            raise RuntimeInputError(f"--rx-share must be > 0 and <= 1 (a share of the "
                                    f"period), got {self.rx_share}")
        if not 1 <= self.priority <= 99:
            raise RuntimeInputError(f"--priority must be 1..99 (SCHED_FIFO), got {self.priority}")
        try:
            OverrunPolicy(self.overrun, self.stop_after)
        except ValueError as e:
            raise RuntimeInputError(f"--overrun/--stop-after: {e}") from e
        if self.inject_port is not None and not 0 <= self.inject_port <= 65535:
            raise RuntimeInputError(f"--inject-port must be 0..65535 (0: any free port), got "
                                    f"{self.inject_port}")
        check_cpu(self.cpu)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> "RuntimeConfig":
        """From the options :func:`add_arguments` declares."""
        return cls(machine_file=Path(args.config), adapter_url=args.adapter,
                   run_dir=Path(args.record), duration_s=args.duration,
                   force=args.force, rate_hz=args.rate,
                   watchdog_cycles=args.watchdog_cycles, overrun=args.overrun,
                   stop_after=args.stop_after, realtime=not args.no_rt, cpu=args.cpu,
                   priority=args.priority, start_cnc=args.start,
                   inject=tuple(args.inject or ()), rx_share=args.rx_share,
                   status_line=not args.no_status, inject_port=args.inject_port)


@dataclass(frozen=True)
class Timing:
    """The loop's timing, resolved against the machine file (``n_ticks`` None: until
    stopped)."""
    rate_hz: float
    period_ns: int
    cycles_per_tick: int
    n_ticks: int | None
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
    n_ticks = None if rc.duration_s is None else max(1, round(rc.duration_s * 1e9 / period_ns))
    return Timing(rate_hz=rate, period_ns=period_ns, cycles_per_tick=cycles, n_ticks=n_ticks,
                  watchdog_cycles=rc.watchdog_cycles or max(1, round(DEFAULT_WATCHDOG_S * rate)),
                  grace_ticks=round(GRACE_S * rate))


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil run``."""
    p.add_argument("config", help="machine file (TOML), or a manifest of several axes "
                   "(configs/machines/)")
    p.add_argument("--adapter", required=True, metavar="URL",
                   help="udp://HOST:PORT[?wire=msgpack|fixed] (port 0: any free one, "
                   "printed); serial://PATH or serial://fd/N [?baud=N&wire=msgpack|fixed]; "
                   "can://INTERFACE/CHANNEL?node=N&rated_current_ma=MA (python-can, e.g. "
                   "udp_multicast or socketcan; a CiA 402 node per axis); each scheme's "
                   "options: docs/realtime.md")
    p.add_argument("--duration", type=float, metavar="S",
                   help="run S seconds (default: until SIGTERM/SIGINT); bounded by the disk "
                        "(the recording streams to it), checked before the start")
    p.add_argument("--record", default=DEFAULT_RUN_DIR, metavar="DIR",
                   help="run folder for recording.arrows, events.arrows and report.json "
                        "(default %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="replace a run already in the run folder")
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="loop rate (default: the plant's PWM frequency; must divide it)")
    p.add_argument("--watchdog-cycles", type=int, metavar="N",
                   help="ticks without a setpoint that fault the drive (default: 0.1 s)")
    p.add_argument("--overrun", choices=("count", "skip", "stop"), default="count",
                   help="what a late tick does (default %(default)s); after a stall of "
                        "the watchdog's length or more the loop resumes at the present "
                        "deadline whatever this says")
    p.add_argument("--rx-share", type=float, default=DEFAULT_RX_SHARE, metavar="F",
                   help="share of a period a tick may spend reading datagrams (udp://): "
                        "the rest waits in the socket (default %(default)s)")
    p.add_argument("--stop-after", type=int, default=10, metavar="N",
                   help="with --overrun stop: stop at the Nth overrun (default %(default)s)")
    p.add_argument("--no-rt", action="store_true",
                   help="no SCHED_FIFO, pinning or memory locking")
    p.add_argument("--no-status", action="store_true",
                   help="no status line on stderr while the run goes on (by default: "
                        "time, the controller's link, each axis's state, mode, fault and "
                        "position, overruns; rewritten in place on a terminal, a line every "
                        "10 s when stderr is a pipe or a file)")
    p.add_argument("--cpu", type=int, help="CPU to run the loop on (default: the last)")
    p.add_argument("--priority", type=int, default=80, help="SCHED_FIFO priority (default 80)")
    p.add_argument("--start", type=start_arg, default=0.0,
                   help="table position at start, mm (deg on rotary tables), or per axis: "
                        "X=10,Y=-5")
    p.add_argument("--inject", action="append", metavar="[AXIS/]FAULT:KEY=VALUE,...",
                   help=INJECT_HELP)
    p.add_argument("--inject-port", type=int, metavar="N",
                   help="take fault injections (INJECT messages) from this machine on UDP "
                        "127.0.0.1:N besides the adapter: hil scope's injection panel; 0: any "
                        "free port, written into the recording's metadata (default: none)")
