"""``hil bench can``: a CSP program over CAN at a 1 kHz SYNC, against the same program over
UDP and the lock-step simulation -- following error and overruns side by side (JSON).

::

    hil bench can [--config configs/machines/arrow500_x_2khz.toml]
                  [--program programs/demo_moves.nc]
                  [--sync-hz 1000] [--group 239.74.163.2] [--port 43113] [--json]

The program is planned by the NC's interpolator (:func:`hil.controller.interpolator.plan`)
and sampled once per communication cycle: one 607Ah target (motor-encoder increments) per
SYNC, as a CiA 402 master in CSP sends it, without feed-forward, and again with the
velocity offset 60B1h a master sends as its speed feed-forward: the target's step over the
cycle the drive interpolates it in, per second.  Five runs of those targets:

* **lock-step**: the drive and plant of the machine file in this process, the targets
  taken every ``PWM / sync-hz`` drive cycles exactly, interpolated over 60C2h = the SYNC
  period as the CAN node sets it (:func:`lockstep`);
* **can**: ``hil run`` on ``can://udp_multicast/GROUP?node=5`` in a process of its own, and
  this process the master (:class:`io_adapters.can_master.CanMasterEndpoint`): each cycle
  the RPDOs and SYNC, at ``sync-hz`` (the drive interpolates between SYNCs; its loop keeps
  the PWM rate);
* **udp**: ``hil run`` on ``udp://127.0.0.1:0``, the same targets sent at ``sync-hz``
  (the drive takes each as it comes: UDP has no interpolation time period);
* **lockstep_ff** and **can_ff**: the lock-step and the CAN run with the feed-forward, the
  CAN run compared with the lock-step with it.

The following error here is the drive's target less its position, per drive cycle, in µm
of table travel: each link run's from its recording (``sp_target_position_counts``,
``plant_encoder_counts``), from the first cycle whose target left the start on, for the
program's duration and :data:`SETTLE_S`, placed by tick (a tick the loop skipped, late,
is left out); the lock-step's the same way.  Reported per run: its maximum and RMS, the
largest difference from the lock-step's, cycle by cycle, and the cycles that ran; the
loop's overruns and ticks (``report.json``); over CAN the bus load per cycle.  The
group must be routed over the loopback interface (``ip route add GROUP/32 dev lo``).
"""

import argparse
import json
import math
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.cia402 import EnableSequencer, State
from hil.controller.config import axis_limits, cnc_unit, load_controller
from hil.controller.interpolator import plan
from hil.controller.program import read_program
from hil.drive import EmulatedDrive
from hil.rt.clock import MonotonicClock
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, eprint
from hil.runtime.demo import DemoError, wait_ready
from hil.runtime.record_reader import Recording
from io_adapters import AdapterError, Endpoint, Feedback, Setpoint, open_endpoint
from io_adapters.can_dictionary import interpolation_period
from io_adapters.messages import MODE_CSP
from plant import Plant
from plant import layout as L
from plant.config import MachineConfig
from plant.errors import ConfigError
from plant.machines import load_machine_set

ROOT = Path(__file__).resolve().parents[2]
#: how long the axis is watched after the program's end, s
SETTLE_S = 0.3
#: bound on the emulator's start (a cold numba cache compiles for
#: :data:`~hil.progress.COLD_START_S`)
READY_S = 120.0
#: bound on enabling the drive and on the emulator's exit, s
ENABLE_S = 5.0
EXIT_S = 60.0
RATED_MA = 28000


@dataclass(frozen=True)
class Program:
    """The targets of one run.

    Attributes:
        start_mm: where the axis starts (``hil run --start``), mm (deg on rotary tables).
        deltas: the target of each SYNC less the start, increments, shape (n,).
        sync_s: the communication cycle, s.
        ticks_per_sync: drive cycles per SYNC.
    """
    start_mm: float
    deltas: np.ndarray
    sync_s: float
    ticks_per_sync: int

    def feedforward(self) -> np.ndarray:
        """60B1h with each target, increments/s, shape (n,): the step from the target
        before it over the cycle the drive interpolates it in."""
        return np.diff(self.deltas, prepend=0.0) / self.sync_s


def load_axis(config: Path) -> MachineConfig:
    """The machine file of one axis (or a manifest of one axis, with its overrides);
    ConfigError for a machine of several."""
    machine = load_machine_set(config)
    if machine.multi_axis:
        raise ConfigError(f"{config}: {len(machine.axes)} axes; hil bench can runs one")
    return machine.configs[0]


def program_targets(config: Path, program: Path, sync_hz: float) -> Program:
    """The program sampled once per SYNC, in increments from where it starts."""
    cfg = load_axis(config)
    profile = plan(read_program(program), axis_limits(cfg, load_controller(cfg)))
    plant = Plant(cfg)
    sync_s = 1.0 / sync_hz
    ticks = cfg.motor.pwm_frequency_hz / sync_hz
    if abs(ticks - round(ticks)) > 1e-9:
        raise ConfigError(f"{config}: {sync_hz:g} Hz SYNC is no whole number of PWM periods "
                          f"({cfg.motor.pwm_frequency_hz:g} Hz)")
    n = math.ceil((profile.duration_s + SETTLE_S) / sync_s)
    pos = profile.sample_array(np.arange(1, n + 1) * sync_s).pos
    start = profile.sample(0.0).pos
    counts = (pos - start) / plant.built.ratio * plant.params[L.P_ENC_COUNTS_PER_RAD]
    return Program(start * cnc_unit(cfg)[0], np.round(counts), sync_s, round(ticks))


def lockstep(config: Path, prog: Program, feedforward: bool = False
             ) -> tuple[np.ndarray, np.ndarray]:
    """(targets, positions) per drive cycle of the lock-step run, increments, from the
    first target on (with ``feedforward``: each target with its 60B1h)."""
    cfg = load_axis(config)
    plant = Plant(cfg, table_pos=prog.start_mm / cnc_unit(cfg)[0])
    drive = EmulatedDrive(plant)
    drive.params.interpolation_value, drive.params.interpolation_index = \
        interpolation_period(round(prog.sync_s * 1e6))  # as the CAN node sets 60C2h
    sp, fb = Setpoint(mode=MODE_CSP), Feedback()
    drive.cycle(sp, fb)
    start = sp.target_position_counts = fb.encoder_counts
    seq = EnableSequencer(timeout_cycles=100)
    seq.enable()
    while not seq.done:
        sp.controlword = seq.next_controlword(fb.statusword)
        drive.cycle(sp, fb)
        if seq.failed:
            raise RuntimeError(f"lock-step: {seq.reason}")
    n = len(prog.deltas) * prog.ticks_per_sync
    targets, positions = np.empty(n), np.empty(n)
    velocities = prog.feedforward() if feedforward else np.zeros(len(prog.deltas))
    for k, delta in enumerate(prog.deltas):
        sp.seq, sp.target_position_counts = k + 1, start + delta
        sp.velocity_offset_counts_s = velocities[k]
        for j in range(prog.ticks_per_sync):
            drive.cycle(sp, fb)
            targets[k * prog.ticks_per_sync + j] = sp.target_position_counts
            positions[k * prog.ticks_per_sync + j] = fb.encoder_counts
    return targets - start, positions - start


def master(ep: Endpoint, prog: Program, feedforward: bool = False) -> None:
    """Enable the drive in CSP where it stands, send the targets one per SYNC period (RPDOs
    and SYNC over CAN; with ``feedforward`` each with its 60B1h), hold the last, disable.
    Raises AdapterError if it will not enable."""
    period_ns = round(prog.sync_s * 1e9)
    clock = MonotonicClock.for_period(period_ns)
    sp, fb = Setpoint(mode=MODE_CSP), Feedback()
    seq = EnableSequencer(timeout_cycles=round(ENABLE_S / prog.sync_s))
    velocities = prog.feedforward() if feedforward else np.zeros(len(prog.deltas))
    start = None
    deadline = clock.now_ns()
    silent_until = deadline + round(ENABLE_S * 1e9)
    k = -1
    while k < len(prog.deltas):
        deadline += period_ns
        clock.sleep_until(deadline)
        while ep.recv_feedback(fb, 0.0):
            pass
        if start is None:
            if fb.statusword:
                start = fb.encoder_counts
                seq.enable()
            elif deadline > silent_until:
                raise AdapterError(f"no feedback from {ep!r} within {ENABLE_S:g} s")
            sp.target_position_counts = fb.encoder_counts
        elif not seq.done:
            sp.controlword = seq.next_controlword(fb.statusword)
            if seq.failed:
                raise AdapterError(f"the drive did not enable: {seq.reason}")
        else:
            k += 1
            if k < len(prog.deltas):
                sp.target_position_counts = start + prog.deltas[k]
                sp.velocity_offset_counts_s = velocities[k]
            else:
                sp.velocity_offset_counts_s = 0.0
        sp.seq += 1
        ep.send_setpoint(sp)
    seq.disable()
    for _ in range(round(ENABLE_S / prog.sync_s)):
        deadline += period_ns
        clock.sleep_until(deadline)
        while ep.recv_feedback(fb, 0.0):
            pass
        sp.controlword = seq.next_controlword(fb.statusword)
        sp.seq += 1
        ep.send_setpoint(sp)
        if seq.done:
            break


def link_run(config: Path, url: str, prog: Program, folder: Path,
             feedforward: bool = False) -> tuple[dict, dict]:
    """``hil run`` on ``url`` in a child process and :func:`master` here: (report.json,
    the recording's target and encoder columns)."""
    run_dir = folder / "run"
    with open(folder / "emulator.log", "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "hil.runtime.emulator", str(config),
                                 "--adapter", url, "--record", str(run_dir), "--start",
                                 str(prog.start_mm), "--overrun", "skip"],
                                cwd=ROOT, stdout=subprocess.PIPE, stderr=log, text=True)
    try:
        served = wait_ready(proc, READY_S)
        with open_endpoint(served, "controller") as ep:
            ep.drain = True
            master(ep, prog, feedforward)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=EXIT_S)
        proc.stdout.close()
    report = json.loads((run_dir / "report.json").read_text())
    cols = Recording(run_dir).read(["tick", "sp_target_position_counts",
                                    "plant_encoder_counts", "drive_state"])
    return report, cols


def following_error(ticks: np.ndarray, targets: np.ndarray, positions: np.ndarray,
                    enabled: np.ndarray, n: int) -> np.ndarray:
    """Target less position on the ``n`` drive cycles from the program's first target on
    -- the first that left the target held when the drive was ``enabled`` (OPERATION
    ENABLED) -- placed by tick (``ticks``: each row's; NaN where a tick did not run)."""
    on = np.flatnonzero(enabled)
    held = targets[on[0]] if on.size else targets[0]
    moved = np.flatnonzero((np.abs(targets - held) > 0.5) & enabled)
    first = moved[0] if moved.size else 0
    fe = np.full(n, np.nan)
    at = ticks[first:] - ticks[first]
    keep = at < n
    fe[at[keep]] = (targets - positions)[first:][keep]
    return fe


def summary(fe_um: np.ndarray, reference_um: np.ndarray) -> dict:
    """Maximum and RMS of the cycles that ran, and the largest difference from the
    lock-step's on the cycles both ran."""
    ran = ~np.isnan(fe_um)
    both = ran & ~np.isnan(reference_um)
    return {"fe_max_um": float(np.abs(fe_um[ran]).max()),
            "fe_rms_um": float(np.sqrt(np.mean(fe_um[ran] ** 2))),
            "difference_to_lockstep_max_um": float(np.abs(fe_um - reference_um)[both].max()),
            "cycles_run": int(ran.sum())}


def run(config: Path, program: Path, sync_hz: float, group: str, port: int) -> dict:
    """The five runs; the JSON ``hil bench can`` prints."""
    prog = program_targets(config, program, sync_hz)
    cfg = load_axis(config)
    plant = Plant(cfg)
    um = plant.built.ratio / plant.params[L.P_ENC_COUNTS_PER_RAD] * 1e6  # µm per increment
    n = len(prog.deltas) * prog.ticks_per_sync
    rows, references = {}, {}
    for name, ff in (("lockstep", False), ("lockstep_ff", True)):
        targets, positions = lockstep(config, prog, ff)
        references[ff] = reference = following_error(np.arange(n), targets, positions,
                                                     np.ones(n, bool), n) * um
        rows[name] = {**summary(reference, reference), "overruns": 0, "ticks": n}
    can_url = f"can://udp_multicast/{group}?node=5&rated_current_ma={RATED_MA}&port={port}"
    links = {"can": (can_url, False), "udp": ("udp://127.0.0.1:0", False),
             "can_ff": (can_url, True)}
    for name, (url, ff) in links.items():
        with tempfile.TemporaryDirectory(prefix=f"hil-bench-can-{name}-") as tmp:
            report, cols = link_run(config, url, prog, Path(tmp), ff)
        enabled = cols["drive_state"] == State.OPERATION_ENABLED
        fe = following_error(cols["tick"], cols["sp_target_position_counts"],
                             cols["plant_encoder_counts"], enabled, n) * um
        loop = report["loop"]
        rows[name] = {**summary(fe, references[ff]), "overruns": loop["overruns"],
                      "ticks": loop["ticks"], "lateness_p99_us": loop["lateness_us"]["p99"]}
        if url == can_url:
            stats = report["adapter"]["stats"]
            rows[name].update({k: stats[k] for k in ("bus_load_max", "bus_load_mean",
                                                     "bus_plan_load", "bus_bits_per_cycle_max",
                                                     "sync_cycles")})
    return {"config": str(config), "program": str(program), "sync_hz": sync_hz,
            "pwm_hz": cfg.motor.pwm_frequency_hz, "syncs": len(prog.deltas), "runs": rows}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil bench can``."""
    p.add_argument("--config", default=str(ROOT / "configs" / "machines" /
                                           "arrow500_x_2khz.toml"),
                   help="machine file of one axis, or a manifest of one (default %(default)s: "
                   "the Arrow 500 X at 2 kHz; at its 8 kHz the loop and the CAN receive "
                   "thread overrun a 2-vCPU VM)")
    p.add_argument("--program", default=str(ROOT / "programs" / "demo_moves.nc"),
                   help="part program (default %(default)s)")
    p.add_argument("--sync-hz", type=float, default=1000.0,
                   help="SYNC rate, Hz: one CSP target per SYNC (default %(default)s)")
    p.add_argument("--group", default="239.74.163.2", help="udp_multicast group, routed "
                   "over lo (default %(default)s)")
    p.add_argument("--port", type=int, default=43113, help="udp_multicast port (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the JSON only")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil bench can``: print the comparison; 2 on bad input, 1 if a run failed."""
    try:
        result = run(Path(args.config), Path(args.program), args.sync_hz, args.group,
                     args.port)
    except (ConfigError, OSError) as e:
        eprint(f"hil bench can: {e}")
        return EXIT_BAD_INPUT
    except (AdapterError, DemoError, RuntimeError) as e:
        eprint(f"hil bench can: {e}")
        return EXIT_FAILED
    if not args.json:
        eprint(f"hil bench can: {result['syncs']} SYNCs at {result['sync_hz']:g} Hz, drive "
               f"at {result['pwm_hz']:g} Hz")
        for name, row in result["runs"].items():
            eprint(f"  {name:11s} following error max {row['fe_max_um']:9.1f} µm, RMS "
                   f"{row['fe_rms_um']:8.1f} µm, max difference to lock-step "
                   f"{row['difference_to_lockstep_max_um']:7.1f} µm, overruns "
                   f"{row['overruns']} of {row['ticks']} ticks ({row['cycles_run']} of the "
                   "program's cycles ran)")
    print(json.dumps(result, indent=1))
    return EXIT_OK
