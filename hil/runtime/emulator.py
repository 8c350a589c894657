"""``hil run``: the emulator daemon -- one plant behind an adapter, in real time.

::

    hil run configs/arrow500_x.toml --adapter udp://127.0.0.1:5005 --record runs/r1

Life cycle, in this order (uvicorn's: one config, one server owning the life cycle,
signal handlers that only set a flag, a fixed shutdown order):

1. **Configure**: the runtime settings come from the command line into a frozen
   :class:`~hil.runtime.emulator_config.RuntimeConfig` (machine files have no ``[runtime]``
   section); the machine file
   is loaded and checked, the rate checked against its PWM frequency, and each axis's
   sub-steps per PWM period against what a real-time tick allows
   (:func:`plant.substeps.realtime_limit`).  A bad file, key or value is refused here
   (exit 2), before any adapter is opened.
2. **Build**: the plant's kernels compiled (or loaded from numba's cache) with SIGTERM and
   SIGINT left to end the process at once (a cold compile takes seconds inside numba,
   where a Python handler would not run; this phase, the next and the opening each show
   their progress on stderr when longer than two seconds, :mod:`hil.progress`); then the plant and the CiA 402 drive
   (:class:`hil.drive.EmulatedDrive`, its steady state compiled), the kernels warmed by
   :data:`WARMUP_CYCLES` cycles on the same arrays, enabled and holding in CSP (then reset;
   a signal ends the warm-up at the next cycle and the daemon exits before opening
   anything), the recording's ring
   (:class:`~hil.runtime.recording.Recorder`) and the
   :class:`~hil.runtime.streaming_loop.StreamingLoop` allocated and touched.
3. **Open** the run folder (:class:`~hil.runtime.run_folder.RunFolder`: made if missing,
   writable, no previous run unless ``--force``, room for the recording of ``--duration``
   or :data:`MIN_RECORD_S` at the rate, the figure in the message), the adapter (device
   role, draining: each tick uses the newest setpoint), the recording's streams (schema
   and metadata on disk by the writer process, warmed), and print ``ready: URL`` on
   stdout (the port actually bound for ``udp://HOST:0``).  With ``--inject-port N`` a
   bench's injection port too (:mod:`io_adapters.inject_port`: INJECT messages on a
   loopback UDP socket of its own, from ``hil scope``'s page or a script; its receive
   thread queues them), its address in the recording's metadata (``inject_port``); the
   loop takes one of its requests a tick and hands it to the axis's injector (source
   ``bench``), as it hands the adapter's.  IPC, the writer process and its threads (the
   injection port's too) here are set up before any priority change (see
   ``docs/platform-notes``: a SCHED_FIFO process must not start helpers later).
4. **Run** under :func:`hil.rt.scheduling.realtime_scheduling` (SCHED_FIFO, pinned, memory
   locked; ``--no-rt`` leaves the process as it is).  Each tick (:meth:`Emulator.step`):
   poll the newest setpoint (timeout 0), the :class:`~hil.runtime.watchdog.Watchdog`,
   ``cycles_per_tick`` drive cycles (one PWM period each), send the feedback, record.
   Nothing raises there: adapter errors are counted and logged once.  A ``udp://``
   adapter reads at most ``--rx-share`` of a period's worth of datagrams a tick and
   leaves the rest queued (:func:`io_adapters.udp.rx_budget_for`; a flood of strangers'
   datagrams is then held off by the kernel, :mod:`io_adapters.udp_flood`); what the
   adapter notices (:attr:`~io_adapters.base.Endpoint.notices`) becomes a ``link`` event
   of the tick.  A stall of the process of the watchdog's length or more (SIGSTOP, a
   paused VM) is not replayed: the loop resumes at the present deadline, whatever
   ``--overrun`` says, and records a ``stall`` event (:mod:`hil.rt.loop`), so the
   watchdog never counts the emulator's own missed ticks as the controller's silence.
   On an adapter whose cycle follows the master's SYNC (``can://``: the endpoint has
   ``last_sync_ns``) the loop's ticks are moved to a fixed phase after SYNC
   (:class:`hil.runtime.sync.SyncLock`), as a CiA 402 drive locks its cycle to SYNC,
   and a tick whose SYNC is late waits a little for it; lateness is then measured
   against the moved deadlines, and the compute time includes that wait.  An adapter's
   own threads (canopen's receive thread on ``can://``) run at SCHED_FIFO one below the
   loop, on its CPU (:func:`hil.rt.scheduling.helper_threads_realtime`), and so do the
   recording's threads and the injection port's here; the writer process stays at normal
   priority off the loop's CPU.
5. **Stop** on ``--duration``, on SIGTERM/SIGINT (the handlers only set the loop's stop
   flag), by the ``stop`` overrun policy, or when the recording cannot be written (a
   full disk: the writer's message sets the same flag); then: the safe state (one cycle with
   controlword 0, disable voltage: the drive leaves OPERATION ENABLED, torque off; a
   faulted drive stays in FAULT), real-time scheduling undone, the adapter closed, the
   recording's last rows and events (the safe state with its drive cycle, why the run
   stopped) written and the streams closed, ``report.json`` written last (its presence
   means the run folder is complete).

**The compiled tick**: in a steady state (every drive in OPERATION ENABLED in CSP, CSV or
CST, the same controlword and mode as the cycle before, no fault cause, no link cause) a
drive cycle is one numba call (:mod:`hil.drive.compiled`): the speed actual value, the
mode's command and its interpolation, the software limits, the monitor's checks and the
statusword, the position and speed loops, the current limit, the plant's sub-steps, the
feedback's values and the axis's row of the recording's ring.  Anything else -- a fault
cause, a changed controlword or mode, a refused setpoint, a plant status not OK -- hands
that cycle to the Python drive, before anything changed, which stays the one owner of the
state machine, the faults and their reactions (:mod:`hil.drive.compiled_path`; both give
the same bits, ``tests/test_tick_equivalence.py``); so does a drive with its power stage
off under a held controlword.  Over UDP the loop itself is compiled: one call runs up to
:data:`hil.runtime.steady_tick.BURST_S` of ticks, each from the deadline's wait to the
answer's send and the row's end (:mod:`hil.runtime.steady_tick`, the loop's ``burst``:
silent ticks, setpoints queued behind a late tick and an absent controller's ticks
included); on the other links Python decodes the setpoint, runs the watchdog, encodes and
sends the feedback and writes the row's common columns.

The recording streams to disk while the loop runs (:mod:`hil.runtime.record_writer`: a
separate process reads the ring in shared memory, about a second of it, whatever the
duration), so ``--duration`` is bounded by
the disk, not the memory.  The run folder (``--record DIR``) is what ``hil report RUN``,
``hil identify`` and ``hil export`` read: ``recording.arrows``, ``events.arrows``
(:mod:`hil.runtime.record_reader`) and ``report.json``
(:func:`~hil.runtime.emulator_report.run_report`).

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
import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

from hil.cia402 import DISABLE_VOLTAGE
from hil.controller.config import load_controller
from hil.drive import DriveSet, EmulatedDrive, load_drive
from hil.drive.compiled_path import WARM_CYCLES, warm
from hil.drive.objects import DriveObjects
from hil.inject.schedule import InjectEvent, injectors_for
from hil.progress import COLD_START, Progress
from hil.rt.clock import MonotonicClock
from hil.rt.loop import OverrunPolicy
from hil.rt.scheduling import helper_threads_realtime, last_cpu
from hil.runtime.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_OK,
    RuntimeInputError,
    StopFlag,
    check_link,
    eprint,
    scheduling,
    served_url,
    shared_cpu,
    start_positions,
    stop_on_signals,
)
from hil.runtime.emulator_config import (
    RuntimeConfig,
    Timing,
    add_arguments,
    resolve_timing,
)
from hil.runtime.emulator_report import final_events, metadata, run_report
from hil.runtime.record_writer import ESTIMATED_SHARE, RING_S, RecordingWriter
from hil.runtime.recording import Recorder, row_bytes
from hil.runtime.run_events import EventCollector, RunEvent
from hil.runtime.run_folder import REPORT, RESERVE_BYTES, RunFolder, human_bytes
from hil.runtime.steady_tick import SteadyTick
from hil.runtime.streaming_loop import StreamingLoop
from hil.runtime.sync import ShiftableClock, SyncLock
from hil.runtime.timing_quality import TimingQuality
from hil.runtime.watchdog import Watchdog
from io_adapters import AdapterError, Endpoint, open_endpoint
from io_adapters.can_url import IN_PROCESS_ONLY, in_process_only
from io_adapters.inject_port import InjectPort
from io_adapters.messages import (
    Feedback,
    FeedbackGroup,
    Setpoint,
    SetpointGroup,
    axis_records,
    message_pair,
)
from io_adapters.udp import rx_budget_for
from plant import Plant
from plant import layout as L
from plant.assemble import check_substep_count
from plant.config import MachineConfig
from plant.errors import ConfigError
from plant.machines import MachineSet, load_machine_set, single_axis
from plant.substeps import realtime_limit, realtime_limit_text

__all__ = ["Emulator", "RuntimeConfig", "Timing", "add_arguments",
           "main", "resolve_timing", "run_from_args", "short_gil_switch",
           "signals_end_process"]

#: drive cycles run on the plant before the clock starts (compiled code and caches warm)
WARMUP_CYCLES = WARM_CYCLES
#: the longest a fault reaction may still brake in the safe state at shutdown, s of drive
#: time; after it the drives inhibit their pulses (FF04h) ...
SAFE_STATE_MAX_S = 5.0
#: ... which takes the torque off within this many cycles (the state machine's transitions)
FORCED_OFF_CYCLES = 3
#: without --duration, the run folder must have room for at least this long a recording, s
MIN_RECORD_S = 60.0
#: the interpreter's thread switch interval while the loop runs, s: a loop waking up while
#: another thread of the process (an adapter's receive thread, the recording's event
#: thread) holds the GIL waits for it at most this long (Python's default, 5 ms, would be
#: 40 ticks at 8 kHz)
GIL_SWITCH_S = 1e-4


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
        self.stop = stop or StopFlag()
        self.x0 = start_positions(m, rc.start_cnc)
        self.plants = tuple(Plant(c, table_pos=x) for c, x in zip(m.configs, self.x0))
        self.plant = self.plants[0]
        self._warm_up()
        self.injectors = injectors_for(self.plants, m.configs, m.names, rc.inject)
        self.period_s = t.period_ns * 1e-9
        self._sp, self._fb = message_pair(len(m.axes))
        self.steady: SteadyTick | None = None  # the compiled tick (open() builds it)
        self.watchdog = Watchdog(t.watchdog_cycles, t.period_ns * 1e-9, self._log)
        self.recorder = Recorder(max(2, math.ceil(RING_S * t.rate_hz)),
                                 tuple(c.machine.kind for c in m.configs),
                                 m.names if m.multi_axis else None)
        self.recorder.attach(self.drives)
        self.loop = StreamingLoop(t.period_ns, self.step, self.recorder, n_ticks=t.n_ticks,
                                  policy=OverrunPolicy(rc.overrun, rc.stop_after,
                                                       t.grace_ticks, t.watchdog_cycles))
        self.stop.attach(self.loop)
        self.events = EventCollector(m.names, self.drives, self.watchdog, self.recorder,
                                     self.injectors, self.loop.stall_log)
        self.endpoint: Endpoint | None = None
        #: the bench's injection port (``--inject-port``; :meth:`open_inject_port`)
        self.inject_port: InjectPort | None = None
        self.sync_lock: SyncLock | None = None
        self.helper_threads: dict[str, str] = {}
        #: other processes' real-time threads pinned to the loop's CPU at its start
        self.cpu_shared_with: list[str] = []
        self.url = rc.adapter_url
        self.errors = AdapterErrors()
        self.setpoints_heard = 0
        self._notices: list[tuple[str, str]] = []  # the adapter's (open() takes them)
        self.folder: RunFolder | None = None
        self.writer: RecordingWriter | None = None
        self.recording_failure: str | None = None

    def _log(self, message: str) -> None:
        self.log(f"hil run: {message}")

    @property
    def sp(self) -> Setpoint | SetpointGroup:
        """The last setpoint applied (axis records in a group on several axes)."""
        if self.steady is not None:
            self.steady.settle()
        return self._sp

    @property
    def fb(self) -> Feedback | FeedbackGroup:
        """The last feedback, as the drives answered it."""
        if self.steady is not None:
            self.steady.settle()
        return self._fb

    def _warm_up(self) -> None:
        """Warm the drives' paths on the real arrays (the kernels are compiled, or loaded
        from numba's cache, by their first call): enabled as a controller enables them,
        then holding their position in CSP (the compiled steady-state path,
        :mod:`hil.drive.compiled_path`; CST on a drive without loops); then start
        afresh.  A stop request ends it at the next cycle (``warmup_cycles``: how many
        ran).  ``drives`` cycles every axis (:class:`DriveSet`); ``drive`` is axis 0's."""
        # the drives check [controller] for the CSP/CSV loops
        self.drives = DriveSet([EmulatedDrive(p, compiled=True) for p in self.plants])
        self.warmup_cycles = warm(self.drives, WARMUP_CYCLES, lambda: self.stop.requested)
        for p, x in zip(self.plants, self.x0):
            p.reset(x)
        self.drives = DriveSet([EmulatedDrive(p, compiled=True) for p in self.plants])
        self.drive = self.drives[0]

    def open_folder(self) -> RunFolder:
        """Open and check the run folder (see the module docstring, 3.); raises
        :class:`~hil.runtime.run_folder.RunFolderError`."""
        rc, t = self.rc, self.timing
        folder = RunFolder.open(rc.run_dir, rc.force)
        seconds = rc.duration_s if rc.duration_s is not None else MIN_RECORD_S
        per_s = self.bytes_per_s()
        try:
            folder.check_space(per_s * seconds + RESERVE_BYTES,
                               f"{seconds:g} s at {t.rate_hz:g} Hz, {len(self.machine.axes)} "
                               f"axis(es): {human_bytes(per_s)}/s, and "
                               f"{human_bytes(RESERVE_BYTES)} held back for its end")
            folder.hold_reserve()
        except BaseException:
            folder.close()
            raise
        self._log(f"run folder {rc.run_dir}: {human_bytes(folder.free_bytes())} free, room "
                  f"for about {folder.free_bytes() / per_s / 3600:.3g} h of recording")
        self.folder = folder
        return folder

    def bytes_per_s(self) -> float:
        """The recording's expected growth on disk, bytes/s (compressed rows)."""
        return row_bytes(len(self.machine.axes)) * ESTIMATED_SHARE * self.timing.rate_hz

    def open_recording(self) -> None:
        """Create the recording's streams in the open run folder (schema and metadata on
        disk, the writer warmed); call after :meth:`open` (the metadata has the URL
        served)."""
        self.writer = RecordingWriter(self.folder, self.recorder, self.events,
                                      metadata(self), self.timing.period_ns,
                                      self._recording_failed,
                                      status_grace_ticks=(self.timing.grace_ticks
                                                          if self.rc.status_line else None))

    def _recording_failed(self, message: str) -> None:
        """From the recording's answer thread: stop the loop (flags only); the safe state
        follows."""
        self.recording_failure = message
        self.loop.request_stop()

    def open(self, endpoint: Endpoint | None = None) -> str:
        """Open the adapter (device role, draining), or take ``endpoint``; returns the URL
        served (with the bound port for ``udp://HOST:0``)."""
        url = (self.rc.adapter_url if endpoint is not None
               else check_link(self.rc.adapter_url, len(self.machine.axes)))
        self.endpoint = endpoint or open_endpoint(url, "device")
        self.endpoint.drain = True
        if hasattr(self.endpoint, "rx_budget"):  # udp://: the share of a period to read
            self.endpoint.rx_budget = rx_budget_for(self.rc.rx_share, self.timing.period_ns)
        self._notices = self.endpoint.notices
        self.endpoint.setpoint_bounds = tuple(d.setpoint_bounds() for d in self.drives.drives)
        if hasattr(self.endpoint, "objects"):  # a CANopen node: its parameter objects
            self.endpoint.objects = DriveObjects(self.drives.drives,
                                                 self.endpoint.rated_current_a, self.injectors)
        if getattr(self.endpoint, "exposed", False):
            self._log(f"WARNING: {url} is reachable from the network; this bench tool has no "
                      "authentication (docs/drive.md: who may talk to it)")
        if hasattr(self.endpoint, "last_sync_ns"):  # the cycle follows SYNC
            clock = ShiftableClock(self.loop.clock)
            self.loop.clock = clock
            self.sync_lock = SyncLock(clock, self.timing.period_ns)
        self.url = served_url(url, getattr(self.endpoint, "address", None))
        self.steady = SteadyTick.for_emulator(self) if self.rc.steady_tick else None
        if self.steady is not None and type(self.loop.clock) is MonotonicClock:
            self.loop.burst = self.steady.burst
        return self.url

    def open_inject_port(self) -> None:
        """Open the bench's injection port of ``--inject-port`` (none without it) and
        start its receive thread; raises :class:`~io_adapters.base.AdapterError` (the port
        is taken).  Call before :meth:`open_recording` (the metadata has its address) and
        before :meth:`run` (its thread is made real-time with the other helpers)."""
        if self.rc.inject_port is None:
            return
        self.inject_port = InjectPort(self.rc.inject_port)
        self.inject_port.start()
        self._log(f"injection port {self.inject_port.url} (INJECT messages from this "
                  f"machine: hil scope's page)")

    def close_links(self) -> None:
        """Close the adapter and the injection port (each idempotent)."""
        if self.endpoint is not None:
            self.endpoint.close()
        if self.inject_port is not None:
            self.inject_port.close()

    def step(self, k: int) -> None:
        """Tick ``k``: newest setpoint, watchdog, drive cycles, feedback, record."""
        t_ns = time.monotonic_ns()
        steady = self.steady
        if steady is not None:
            if steady.tick(k, t_ns) is not None:  # it counted setpoints_heard
                if self._notices:
                    self._link_notices(k)
                return
            steady.settle()
        sp, fb, drives = self._sp, self._fb, self.drives
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
        requests = self.endpoint.injections
        if requests:
            self._injections(requests, "adapter", k)
            requests.clear()
        port = self.inject_port
        if port is not None and port.requests:  # one a tick: a flood cannot hold the loop
            self._injections((port.requests.popleft(),), "bench", k)
        for inj in self.injectors:
            if inj.busy:
                inj.update(k * self.period_s)
        self.recorder.begin_tick()
        for _ in range(self.timing.cycles_per_tick):
            drives.cycle(sp, fb)
        fb.tick_ns = t_ns
        if self.watchdog.answering or self.sync_lock is not None:  # SYNC asks for it
            try:
                self.endpoint.send_feedback(fb)
            except AdapterError as e:
                self._adapter_error("send", e)
        self.setpoints_heard += heard
        self.recorder.record(k, heard, t_ns, sp, fb, drives, refused)
        if self._notices:
            self._link_notices(k)

    def _link_notices(self, k: int) -> None:
        """The adapter's notices of tick ``k`` (a flood held off, frame numbers
        resynchronised) into the run's events and the log."""
        for kind, text in self._notices:
            self.events.note(RunEvent(k, "", "link", kind, text))
            self._log(f"link: {kind}: {text}")
        self._notices.clear()

    def _injections(self, requests, source: str, k: int) -> None:
        """Hand injection requests (:class:`~io_adapters.messages.InjectRequest`) of
        ``source`` ("adapter": the controller's link; "bench": the injection port) to
        their axes' injectors; one naming no axis of this machine is refused there and
        then, an event of tick ``k`` (on the first axis)."""
        for r in requests:
            if 0 <= r.axis < len(self.injectors):
                self.injectors[r.axis].request(r.fault, r.settings, source)
            else:
                self.injectors[0].events.append(InjectEvent(
                    k * self.period_s, "refused", f"{source}: axis {r.axis} of an injection "
                    f"request: this machine has {len(self.injectors)} axis(es)"))

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
        :data:`SAFE_STATE_MAX_S` of drive time, run back to back as the loop has stopped,
        then the pulses inhibited: every power stage ends off); the last feedback sent to
        a controller still listening; returns the state reached
        (per axis letter on a machine of several axes), with the drive cycle it was
        reached in."""
        sp, fb = self.sp, self.fb
        sp.controlword = DISABLE_VOLTAGE.value
        cycles = max(1, round(SAFE_STATE_MAX_S / self.plant.pwm_period))
        for k in range(cycles + FORCED_OFF_CYCLES):
            if k == cycles:  # a reaction still braking: the pulses go off all the same
                for d in self.drives.drives:
                    if d.plant.inp[L.I_ENABLE] != 0.0:
                        d.inhibit_pulses()
            self.drives.cycle(sp, fb)
            if all(d.plant.inp[L.I_ENABLE] == 0.0 for d in self.drives.drives):
                break
        if self.watchdog.answering:
            try:
                self.endpoint.send_feedback(fb)
            except AdapterError as e:
                self._adapter_error("send", e)
        states = {name: {"state": d.sm.state.name, "statusword": f"0x{fb.statusword:04X}",
                         "plant_enable": float(d.plant.inp[L.I_ENABLE]),
                         "error_code": f"0x{d.fault:04X}", "cycle": d.tick - 1}
                  for name, d, fb in zip(self.machine.names, self.drives.drives,
                                         axis_records(fb))}
        return states if self.machine.multi_axis else states[self.machine.names[0]]

    def run(self) -> dict:
        """Run the loop, then shut down in the fixed order; returns the report (also written
        to the run folder).  The adapter, the run folder and the recording must be open."""
        rc = self.rc
        cpu = rc.cpu if rc.cpu is not None else last_cpu()
        neighbours, warning = shared_cpu(rc.realtime, cpu, rc.priority)
        self.cpu_shared_with = [n.describe() for n in neighbours]
        if warning:
            self._log(warning)
        self.writer.start(cpu)
        with short_gil_switch(), scheduling(rc.realtime, cpu, rc.priority) as granted:
            if granted is not None and granted.fifo.granted:
                self.helper_threads = helper_threads_realtime(cpu, max(1, rc.priority - 1))
            try:
                stats = self.loop.run()
            finally:  # an exception leaves the axes in their safe state too
                safe = self.safe_state()
        self.close_links()
        self.writer.stop(final_events(self, stats, safe))
        lateness, compute = self.writer.loop_percentiles()
        stats = replace(stats, lateness_us=lateness, compute_us=compute)
        failed = stats.stopped_by == "overruns" or self.writer.failed is not None
        report = run_report(self, stats, granted, safe, EXIT_FAILED if failed else EXIT_OK)
        try:
            self.folder.write_json(REPORT, report)
        except OSError as e:
            self._log(f"cannot write {self.folder.path / REPORT}: {e.strerror or e}")
            report["exit_status"] = EXIT_FAILED
        finally:
            self.folder.close()
        return report


@contextmanager
def short_gil_switch() -> Iterator[None]:
    """The interpreter's thread switch interval at :data:`GIL_SWITCH_S` for the ``with``
    block (a loop's run), the previous one after it."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(GIL_SWITCH_S)
    try:
        yield
    finally:
        sys.setswitchinterval(previous)


@contextmanager
def signals_end_process() -> Iterator[None]:
    """SIGTERM and SIGINT end the process at once for the ``with`` block (the default
    action, taken by the kernel): a Python handler would wait for numba's compiler to
    return, seconds on a cold cache.  The previous handlers come back after it."""
    previous = {s: signal.signal(s, signal.SIG_DFL) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def run_from_args(args: argparse.Namespace) -> int:
    """``hil run``: configure, build, open, run; returns the exit status."""
    try:
        rc = RuntimeConfig.from_args(args)
        if in_process_only(rc.adapter_url):
            raise RuntimeInputError(f"--adapter {rc.adapter_url}: {IN_PROCESS_ONLY}")
        machine = load_machine_set(rc.machine_file)
        for cfg in machine.configs:
            check_substep_count(cfg, realtime_limit(cfg.motor.pwm_frequency_hz),
                                realtime_limit_text(cfg))
            # the [controller] and [drive] sections (the braking room among them) are
            # refused here, before the kernels compile, not when the drives are built
            load_drive(cfg, load_controller(cfg) if cfg.section("controller") else None)
        with signals_end_process(), Progress(
                f"hil run: loading the plant's compiled kernels ({COLD_START})", ticking=True):
            Plant(machine.configs[0])  # numba compiles here (or loads its cache)
    except (ConfigError, RuntimeInputError) as e:
        eprint(f"hil run: {e}")
        return EXIT_BAD_INPUT
    stop = StopFlag()
    with stop_on_signals(stop.request):
        try:
            with Progress("hil run: warming up the drives (a cold cache compiles their "
                          "kernels first)", ticking=True):
                emulator = Emulator(rc, machine, stop)
            if stop.requested:
                eprint("hil run: stopped by a signal while starting; nothing written")
                return EXIT_OK
            emulator.open_folder()
        except (ConfigError, RuntimeInputError, OSError) as e:
            eprint(f"hil run: {e.strerror if type(e) is OSError else e}")
            return EXIT_BAD_INPUT
        try:
            with Progress("hil run: opening the adapter and the recording (a cold cache "
                          "compiles the tick first)", ticking=True):
                url = emulator.open()
                emulator.open_inject_port()
                emulator.open_recording()
        except (AdapterError, OSError) as e:
            emulator.close_links()
            emulator.folder.close()
            eprint(f"hil run: {e}")
            return EXIT_BAD_INPUT
        print(f"ready: {url}", flush=True)
        report = emulator.run()
    loop, lat = report["loop"], report["loop"]["lateness_us"]
    print(f"hil run: {loop['ticks']} ticks at {emulator.timing.rate_hz:g} Hz, stopped: "
          f"{report['stopped']}; lateness p50 {lat['p50']:.1f} p99 {lat['p99']:.1f} p99.9 "
          f"{lat['p999']:.1f} max {lat['max']:.1f} µs; overruns {loop['overruns']}; "
          f"watchdog events {report['watchdog']['events_total']}; run folder {rc.run_dir}",
          flush=True)
    quality = TimingQuality.of_emulator(report)
    print(f"hil run: {quality.line()}", flush=True)
    if quality.worst_overrun:
        print(f"hil run: {quality.worst_text()}", flush=True)
    if emulator.recording_failure is not None:
        eprint(f"hil run: {emulator.recording_failure}; the axes were brought to their safe "
               "state")
    return report["exit_status"]


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.runtime.emulator ...``: the same as ``hil run ...``."""
    parser = argparse.ArgumentParser(prog="hil run", description="the emulator daemon")
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
