"""Lock-step simulation: controller and emulated drive alternate, no real time.

Each basic-clock tick the controller reads the last feedback and writes a
setpoint, then the drive applies it and advances the plant one PWM period.
The same Controller and EmulatedDrive objects run in real time over an
adapter; here they are only called back to back, faster than real time.  The NC and the
drives take their compiled steady-state paths (:mod:`hil.controller.compiled_path`,
:mod:`hil.drive.compiled_path`: the same results bit for bit), and the ticks on which
both do run in blocks of one compiled call (:mod:`hil.sim_block`).
:class:`MachineLockStep` does the same for every axis of a machine at once.  An alarm of
the NC (:mod:`hil.controller.alarms`) does not end a run: the axes brake and are disabled
as the NC does it, the run goes on to its end, and the alarms are in the result.

``feedback_delay_ticks`` models a link whose feedback comes back later than the next
tick: with d, controller tick k reads the feedback of drive cycle k-1-d (0: cycle k-1).
CANopen CiA 402 with synchronous PDOs has d = 1: the drive's TPDOs at SYNC k carry
the cycle SYNC k-1 started, and the master reads them before its next SYNC.
"""

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hil.controller.alarms import Alarm
from hil.controller.compiled_path import warm as warm_nc
from hil.controller.machine import MachineController
from hil.controller.nc import Controller
from hil.decimal_grid import decimal_step, on_grid
from hil.drive import DriveSet, EmulatedDrive
from hil.drive.compiled_path import warm as warm_drives
from hil.inject.schedule import Injector, injectors_for
from hil.sim_block import COLUMNS, DRIVE_DECLINED, RAN, Blocks
from hil.trace_file import si_factor
from io_adapters.messages import Feedback, Setpoint, axis_records, message_pair
from plant import Plant
from plant.config import MachineConfig
from plant.layout import S_TIME
from plant.machines import MachineSet

_UNITS = {
    "t_s": "s", "x_set": "m", "v_set": "m/s", "a_set": "m/s^2", "x_act": "m",
    "v_act": "m/s", "v_cmd": "m/s", "w_set": "rad/s", "w_act": "rad/s", "iq_set": "A",
    "iq_meas": "A", "iq_true": "A", "table_pos": "m", "motor_pos": "rad", "motor_pos_meas": "rad",
    "following_error": "m", "contour_deviation": "m", "tick": "1", "table_vel": "m/s",
}
#: recorded signals: name -> unit (SI, table units; w_* are motor-side), in the order of
#: the compiled blocks' recording (:data:`hil.sim_block.COLUMNS`)
SIGNALS = {name: _UNITS[name] for name in COLUMNS}


@dataclass(frozen=True)
class SimResult:
    """Recorded signals of a lock-step run, one sample per basic-clock tick.

    Attributes:
        signals: name -> array, shape (n,), units in ``SIGNALS`` (rad and rad/s replace m
            and m/s on rotary tables).
        kind: the machine's kind ("screw", "linear", "rotary").
        ratio: table travel per motor rad (1 when direct).
        period_s: tick period.
        meta: text metadata (machine file, program, ...).
        alarms: the axis's alarms (:class:`~hil.controller.alarms.Alarm`) when the run
            ended.
        position_cycle_ticks: ticks per position-control cycle, the period of the ripple
            the position cycle leaves on the currents (:func:`position_cycle_mean`);
            None where unknown (a recording rebuilt from files).
        scale_resolution_m: the count of the linear scale the NC read its position
            from, m; 0 where it read the motor encoder.  The servo trace puts the actual
            position back on its grid (:func:`servo_trace_columns`).
    """
    signals: dict
    kind: str
    ratio: float
    period_s: float
    meta: dict = field(default_factory=dict)
    alarms: tuple[Alarm, ...] = ()
    position_cycle_ticks: int | None = None
    scale_resolution_m: float = 0.0

    def __getitem__(self, name: str) -> np.ndarray:
        return self.signals[name]


class _Stepper(ABC):
    """What both lock-step runners share: the feedback in flight, one tick, the wait for
    enable, the run in compiled blocks.  Subclasses set ``ctrl``, ``sp``, ``_cycle`` (the
    drive side's step), ``ctrls``, ``drive_list`` and ``plants`` (per axis), ``compiled``
    and ``feedback_delay_ticks``, and call :meth:`_line_of`."""

    def _line_of(self, feedbacks: list) -> None:
        #: the feedback in flight: the controller reads slot i, the drive then rewrites it
        self._line = feedbacks
        self._slot = 0
        self.fb = self._line[0]
        #: each axis's setpoint and (with no feedback delay) feedback record
        self.sps = tuple(axis_records(self.sp))
        self.fbs = tuple(axis_records(self._line[0]))

    @abstractmethod
    def _enable_reason(self) -> str:
        """Why the drives are not enabled yet."""

    def enable(self, max_ticks: int = 1000) -> None:
        """Run the CiA 402 enable sequence(s) until OPERATION ENABLED."""
        for _ in range(max_ticks):
            if self.ctrl.enabled:
                return
            self.tick()
        raise RuntimeError(f"not enabled after {max_ticks} ticks: {self._enable_reason()}")

    def _inject(self, plants, configs, names, flags) -> None:
        """The fault injectors of the plants (their machine files' ``[inject]`` tables and
        the ``--inject`` flags, :mod:`hil.inject`; ``flags`` None: none at all);
        ConfigError before anything runs."""
        self.injectors = (tuple(Injector(p.params, c) for p, c in zip(plants, configs))
                          if flags is None else injectors_for(plants, configs, names, flags))
        self._injected = tuple(zip(self.injectors, (p.state for p in plants)))

    def tick(self) -> None:
        """One controller cycle and one PWM period of the plant(s)."""
        fb = self._line[self._slot]
        self.ctrl.tick(fb, self.sp)
        for inj, state in self._injected:
            if inj.busy:
                inj.update(state[S_TIME])
        self._cycle(self.sp, fb)
        self.fb = fb
        self._slot = (self._slot + 1) % len(self._line)

    def finish_tick(self, axis: int) -> None:
        """The rest of a tick whose NC and drives before ``axis`` ran in a block (the
        drive of ``axis`` declined its compiled cycle)."""
        if axis == 0:
            self._cycle(self.sp, self.fb)
            return
        for drive, s, f in zip(self.drive_list[axis:], self.sps[axis:], self.fbs[axis:]):
            drive.cycle(s, f)
        self.fb.seq = self.sp.seq
        self.fb.time_s = self.fbs[0].time_s

    def record(self, recs: list, rows: int, first: int | None = None, every: int = 1,
               progress=None, stop=None) -> int:
        """Run until each axis's recording in ``recs`` (:class:`AxisRecording`) has ``rows``
        rows: row r is taken after the tick whose number (the controller's
        ``tick_count`` before it) is ``first + r * every`` (default ``first``: the next
        tick).  In compiled blocks where every axis's NC and drive are on their compiled
        paths, else tick by tick; ``progress(fraction of the rows)`` about 20 times;
        ``stop()``, asked after each tick the Python path runs (no compiled tick needs
        it: they decline whatever would), ends the run before that tick's row.  Returns
        the rows taken.  :attr:`blocks` is then the run's :class:`~hil.sim_block.Blocks`
        (None when not compiled)."""
        ctrl = self.ctrls[0]
        first = ctrl.tick_count if first is None else first
        blocks = self.blocks = (Blocks(self, [r.array for r in recs], first, every)
                                if self.compiled else None)
        step = max(1, rows // 20)
        report = row = 0
        while row < rows:
            if progress is not None and row >= report:
                progress(report / rows)
                report += step
            declined = -1
            if blocks is not None and blocks.ready():
                blocks.run(2 ** 62, row, min(rows, report) if progress is not None else rows)
                row = blocks.row
                if blocks.stop == RAN:
                    continue
                declined = blocks.axis if blocks.stop == DRIVE_DECLINED else -1
            k = ctrl.tick_count
            if declined >= 0:
                k -= 1  # the NC's part of the tick ran in the block
                self.finish_tick(declined)
            else:
                self.tick()
            if stop is not None and stop():
                return row
            if k >= first and (k - first) % every == 0:
                for rec, fb in zip(recs, axis_records(self.fb)):
                    rec.take(row, fb)
                row += 1
        return row

    def run_ticks(self, n: int) -> None:
        """``n`` ticks, nothing recorded (compiled blocks where they can run)."""
        blocks = (Blocks(self, [np.empty((len(SIGNALS), 1)) for _ in self.ctrls], 2 ** 62, 1)
                  if self.compiled else None)
        end = self.ctrls[0].tick_count + n
        while self.ctrls[0].tick_count < end:
            if blocks is not None and blocks.ready():
                blocks.run(end - self.ctrls[0].tick_count, 0, 1)
                if blocks.stop == RAN:
                    continue
                if blocks.stop == DRIVE_DECLINED:
                    self.finish_tick(blocks.axis)
                    continue
            self.tick()


def _check_delay(feedback_delay_ticks: int) -> None:
    if feedback_delay_ticks < 0:
        raise ValueError(f"feedback_delay_ticks must be >= 0, got {feedback_delay_ticks}")


class LockStep(_Stepper):
    """A controller and an emulated drive of one machine file, stepped together.

    Args:
        cfg: the machine file.
        x0: the table's position at start.
        feedback_delay_ticks: extra ticks the feedback takes to reach the controller
            (see the module docstring); ``fb`` is always the drive's newest feedback.
        axis: the axis name in the NC's alarms (default X, or C on a rotary table).
        inject: ``--inject`` flags (:mod:`hil.inject`), besides the machine file's
            ``[inject]`` tables; None: no fault injected, those tables' neither.
        compiled: the NC's and the drive's compiled steady-state paths and the compiled
            blocks (False: every tick in Python, the reference they equal).
        plant, ctrl: the axis's plant and controller, when the caller builds them (``hil
            identify``'s replay: its trace-fed controller); by default built here from
            ``cfg``, ``x0`` and ``axis``.
    """

    def __init__(self, cfg: MachineConfig, x0: float = 0.0, feedback_delay_ticks: int = 0,
                 axis: str | None = None, inject: Sequence[str] | None = (),
                 compiled: bool = True, plant: Plant | None = None,
                 ctrl: Controller | None = None):
        _check_delay(feedback_delay_ticks)
        self.cfg = cfg
        self.plant = plant or Plant(cfg, table_pos=x0)
        self._inject((self.plant,), (cfg,), ("",), inject)
        self.drive = EmulatedDrive(self.plant, compiled=compiled)
        self._cycle = self.drive.cycle
        self.ctrl = ctrl or Controller(cfg, self.plant.pwm_period, x0, axis=axis,
                                       compiled=compiled)
        self.sp = Setpoint()
        self.feedback_delay_ticks = feedback_delay_ticks
        self.compiled = compiled
        self.ctrls, self.drive_list, self.plants = (self.ctrl,), (self.drive,), (self.plant,)
        self._line_of([Feedback() for _ in range(feedback_delay_ticks + 1)])

    def _enable_reason(self) -> str:
        return self.ctrl.enable.reason

    def run(self, duration_s: float, progress=None) -> SimResult:
        """Run ``duration_s`` of simulated time, recording every tick."""
        n = math.ceil(duration_s / self.plant.pwm_period)
        rec = AxisRecording(n, self.ctrl, self.plant)
        self.record([rec], n, progress=progress)
        return rec.result(self.cfg)


class AxisRecording:
    """The :data:`SIGNALS` of one axis, one row per tick."""

    def __init__(self, n: int, ctrl: Controller, plant: Plant):
        #: one row per signal, in :data:`SIGNALS` order (NaN until taken)
        self.array = np.full((len(SIGNALS), n), math.nan)
        self.rec = dict(zip(SIGNALS, self.array))
        self.ctrl, self.plant = ctrl, plant

    def take(self, k: int, fb: Feedback) -> None:
        rec, ctrl, out = self.rec, self.ctrl, self.plant
        rec["t_s"][k] = ctrl.t
        rec["x_set"][k] = ctrl.x_set
        rec["v_set"][k] = ctrl.v_set
        rec["a_set"][k] = ctrl.a_set
        rec["x_act"][k] = ctrl.x_act
        rec["v_act"][k] = ctrl.v_act
        rec["v_cmd"][k] = ctrl.v_cmd
        rec["w_set"][k] = ctrl.w_set
        rec["w_act"][k] = ctrl.w_act
        rec["iq_set"][k] = ctrl.iq_set
        rec["iq_meas"][k] = fb.iq_a
        rec["iq_true"][k] = out.output("iq_a")
        rec["table_pos"][k] = out.output("table_pos")
        rec["motor_pos"][k] = out.output("motor_pos")
        rec["motor_pos_meas"][k] = ctrl.theta_act
        rec["following_error"][k] = ctrl.following_error
        rec["contour_deviation"][k] = ctrl.contour_deviation
        rec["tick"][k] = ctrl.tick_count - 1
        rec["table_vel"][k] = out.output("table_vel")

    def result(self, cfg: MachineConfig) -> SimResult:
        return SimResult(self.rec, cfg.machine.kind, self.ctrl.ratio, self.plant.pwm_period,
                         {"machine": cfg.path}, tuple(self.ctrl.alarms.alarms),
                         self.ctrl.sec.position_cycle_ratio, self.ctrl.scale_res)


class MachineLockStep(_Stepper):
    """Every axis of a machine: its controllers (:class:`MachineController`) and drives
    (:class:`DriveSet`) stepped together through one message pair, as :class:`LockStep`
    steps one axis (same ``feedback_delay_ticks``).  On one axis it is :class:`LockStep`
    exactly.

    Args:
        machine: the machine.
        x0: each axis's table position at start (SI; default all 0).
        feedback_delay_ticks: as for :class:`LockStep`.
        inject: as for :class:`LockStep` (``AXIS/FAULT:...`` on several axes).
        compiled: as for :class:`LockStep`.
    """

    def __init__(self, machine: MachineSet, x0: Sequence[float] | None = None,
                 feedback_delay_ticks: int = 0, inject: Sequence[str] = (),
                 compiled: bool = True):
        _check_delay(feedback_delay_ticks)
        self.machine = machine
        x0 = tuple(x0) if x0 is not None else (0.0,) * len(machine.axes)
        self.plants = tuple(Plant(a.config, table_pos=x) for a, x in zip(machine.axes, x0))
        self._inject(self.plants, machine.configs, machine.names, inject)
        self.drives = DriveSet([EmulatedDrive(p, compiled=compiled) for p in self.plants])
        self.period = self.plants[0].pwm_period
        self.ctrl = MachineController(machine, self.period, x0, compiled=compiled)
        n = len(machine.axes)
        self.sp = message_pair(n)[0]
        self._cycle = self.drives.cycle
        self.feedback_delay_ticks = feedback_delay_ticks
        self.compiled = compiled
        self.ctrls, self.drive_list = self.ctrl.ctrls, tuple(self.drives.drives)
        self._line_of([message_pair(n)[1] for _ in range(feedback_delay_ticks + 1)])

    def _enable_reason(self) -> str:
        return self.ctrl.enable_reason()

    def run(self, duration_s: float) -> dict[str, SimResult]:
        """Run ``duration_s`` of simulated time; axis letter -> its recording."""
        n = math.ceil(duration_s / self.period)
        recs = [AxisRecording(n, c, p) for c, p in zip(self.ctrl.ctrls, self.plants)]
        self.record(recs, n)
        return {a.name: rec.result(a.config) for a, rec in zip(self.machine.axes, recs)}


#: simulated time of :func:`warm`'s lock-step, s
WARM_S = 0.02


def warm(machine: MachineSet) -> None:
    """Compile, or load from numba's cache, every kernel a lock-step of ``machine`` runs,
    before the first run that is timed: the drives' paths
    (:func:`hil.drive.compiled_path.warm`), the NC's compiled tick
    (:func:`hil.controller.compiled_path.warm`) and the compiled blocks for its number
    of axes and for one (a study's experiment may step one of its axes): short
    lock-steps holding at rest, on machines built afresh."""
    warm_drives(DriveSet([EmulatedDrive(Plant(a.config), compiled=True)
                          for a in machine.axes]))
    warm_nc()
    steppers = [MachineLockStep(machine)]
    if len(machine.axes) > 1:
        steppers.append(LockStep(machine.configs[0]))
    for ls in steppers:
        ls.enable()
        ls.run(WARM_S)


def position_cycle_mean(x: np.ndarray, ticks: int) -> np.ndarray:
    """The mean of ``x`` (shape (n,), one sample per tick) over ``ticks`` consecutive
    samples centred on each one (``ticks // 2`` before it, the rest after), shape (n,).
    With ``ticks`` the position cycle, the ripple the position cycle leaves on the
    currents averages out exactly: the speed command changes once per position cycle (the
    position loop's output, and the feed-forward with ``feedforward_interpolation =
    "hold"``), so while the axis accelerates i_q saw-tooths at the position-cycle
    frequency (500 Hz on a 2 ms cycle) and one sample per cycle sees the same phase of it.
    Within half a window of either end the mean is over the samples there are; a NaN
    spoils only the windows that hold it."""
    if ticks < 1:
        raise ValueError(f"position_cycle_mean: ticks must be >= 1, got {ticks}")
    x = np.asarray(x, dtype=float)
    window = np.ones(ticks)
    # "full" convolution: entry e sums x[e - ticks + 1 .. e]; sample i's window ends at
    # e = i - ticks // 2 + ticks - 1, and the same convolution of ones counts its samples
    ends = np.arange(x.size) - ticks // 2 + ticks - 1
    sums = np.convolve(x, window)[ends]
    counts = np.convolve(np.ones(x.size), window)[ends]
    return sums / counts


def ripple_hz(res: SimResult) -> float:
    """The frequency of the position cycle's ripple on the currents: one over the
    position-control cycle, Hz."""
    if res.position_cycle_ticks is None:
        raise ValueError("the recording does not know its position-control cycle")
    return 1.0 / (res.position_cycle_ticks * res.period_s)


#: servo-trace column (trace-format.md, linear-axis names) -> SimResult signal
TRACE_COLUMNS = {
    "pos_set_mm": "x_set", "pos_mm": "x_act", "vel_set_mm_min": "v_set",
    "vel_mm_min": "v_act", "iq_set_a": "iq_set", "iq_a": "iq_meas",
    "motor_pos_mm": "motor_pos_meas",
}
#: servo-trace column of a current's mean over the position cycle -> SimResult signal
MEAN_COLUMNS = {"iq_set_mean_a": "iq_set", "iq_mean_a": "iq_meas"}
#: what this module's servo traces carry in their header besides the caller's keys
TRACE_METADATA = {"vel_set_column": "feedforward"}
#: the same columns on a rotary table
ROTARY_NAMES = {"pos_set_mm": "pos_set_deg", "pos_mm": "pos_deg", "vel_set_mm_min":
                "vel_set_deg_min", "vel_mm_min": "vel_deg_min", "motor_pos_mm": "motor_pos_deg"}


def servo_trace_columns(res: SimResult, every: int) -> dict[str, np.ndarray]:
    """The recording as servo-trace columns in the file's units (mm, mm/min, A, or deg on
    rotary tables), on the ticks that are multiples of ``every`` (the position-control
    cycle: there setpoint and actual position are taken at the same instant, as the
    NC's servo trace does), time starting at 0.  The velocity setpoint is the speed
    feed-forward, the interpolator's velocity (trace-format.md; the speed command is the
    position controller's output plus the feed-forward factor times it): the header's
    ``vel_set_column`` (:data:`TRACE_METADATA`) says so; the motor position is converted
    to table travel through the lead.  Where the recording knows its position cycle, the
    columns :data:`MEAN_COLUMNS` follow, last: the currents' :func:`position_cycle_mean`
    at each row (rows one position cycle apart all see the same phase of the currents'
    position-cycle ripple, so ``iq_set_a`` and ``iq_a`` alone can look far apart while the
    axis accelerates; :func:`mean_columns_note` says so in words)."""
    rows = np.flatnonzero(res["tick"] % every == 0)
    ticks = res["tick"][rows] - res["tick"][rows[0]]
    cols = {"t_s": on_grid(ticks, decimal_step(res.period_s))}
    for name, sig in TRACE_COLUMNS.items():
        values = res[sig][rows] * (res.ratio if sig == "motor_pos_meas" else 1.0)
        if res.kind == "rotary":
            name = ROTARY_NAMES.get(name, name)
        factor, _ = si_factor(name)
        cols[name] = values / factor
    if res.scale_resolution_m and res.kind != "rotary":
        cols["pos_mm"] = _on_scale_grid(res["x_act"][rows], res.scale_resolution_m)
    if res.position_cycle_ticks is not None:
        for name, sig in MEAN_COLUMNS.items():
            cols[name] = position_cycle_mean(res[sig], res.position_cycle_ticks)[rows]
    return cols


def _on_scale_grid(x_m: np.ndarray, resolution_m: float) -> np.ndarray:
    """Positions ``x_m`` (m) in mm, those that are whole counts of the scale (the NC's
    counts times its resolution, within float rounding) as the float nearest their exact
    value (:mod:`hil.decimal_grid`): 1234567 counts of 0.1 µm print as 123.4567; the rest
    (the start position before the first feedback) as they are."""
    counts = np.round(x_m / resolution_m)
    on_grid_mm = on_grid(counts, decimal_step(resolution_m) * 1000)
    whole = np.isclose(counts * resolution_m, x_m, rtol=1e-12, atol=0.0)
    return np.where(whole, on_grid_mm, x_m * 1e3)


def mean_columns_note(res: SimResult) -> str:
    """A comment line for a servo trace with :data:`MEAN_COLUMNS`: what they are and why."""
    cycle_ms = res.position_cycle_ticks * res.period_s * 1e3
    return (f"iq_set_mean_a and iq_mean_a are iq_set_a and iq_a averaged over the "
            f"{cycle_ms:g} ms position cycle centred on the row; while the axis "
            f"accelerates the currents ripple at {ripple_hz(res):g} Hz (the speed command "
            f"changes once per position cycle), and rows a whole number of cycles apart "
            f"all see the same phase of it")
