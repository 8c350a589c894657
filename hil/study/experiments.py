"""What a study does to every machine: a step, a frequency response, a part program (and,
in :mod:`hil.study.circularity`, a circle on two axes; in :mod:`hil.study.analytic`, the
test functions of the pipeline checks).

An experiment is declared in the study file's ``[experiment]`` table (several as
``[[experiment]]``), its keys checked by the machine-file loader's own rules
(:func:`plant.config.build_section`: unknown key, type, range, each named with its unit).
It runs the simulated controller and the plant in lock-step (:mod:`hil.sim`, the
controller's measuring functions of :mod:`hil.measure.runs`) and returns its outputs
(:mod:`hil.study.outputs`) and, for the report's percentile bands, one curve on a grid
that is the same for every sample.  Positions at this edge are in mm and mm/min (screw
and linear axes); inside, SI.
"""

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.commands import SETTLE_S
from hil.controller.blocks import lowpass2
from hil.controller.config import load_controller
from hil.controller.loops import PT2_DAMPING
from hil.controller.path import parse_path_program
from hil.controller.program import ProgramError, read_program_text
from hil.measure.runs import bode, position_step, speed_step
from hil.sim import MachineLockStep
from hil.study.keys import StudySpecError, checked_section
from hil.study.machine import MachineSource
from hil.study.outputs import following_error_um, response_figures, step_metrics
from plant.assemble import transmission_ratio
from plant.config import MachineConfig, shown_name
from plant.errors import ConfigError
from plant.files import checked_name, shown_path
from plant.machines import MachineSet
from plant.schema import key

MM = 1e-3  # m per mm
MM_MIN = 1e-3 / 60.0  # m/s per mm/min
CURVE_POINTS = 200  # samples of a time curve
BODE_POINTS = 150  # samples of a magnitude curve, log-spaced


@dataclass(frozen=True)
class Curve:
    """The one curve an experiment keeps per sample: values (shape (n,), in ``unit``) on
    ``grid`` (shape (n,), the quantity ``grid_name`` in ``grid_unit``), the same grid for
    every sample."""
    name: str
    unit: str
    grid: np.ndarray
    grid_name: str
    grid_unit: str
    log_grid: bool = False


@dataclass(frozen=True)
class Measurement:
    """One experiment on one machine: output name -> value, and the curve's values
    (shape of the curve's grid; None when the experiment keeps none)."""
    values: dict
    curve: np.ndarray | None


class Experiment(ABC):
    """An experiment of a study.  Subclasses declare ``kind``, ``options`` (a dataclass of
    :func:`plant.schema.key` fields), ``outputs`` (names it can give) and ``needs_machine``,
    and implement :meth:`run`."""
    kind: str = ""
    options: type
    outputs: tuple[str, ...] = ()
    needs_machine = True

    def __init__(self, opts, selected: tuple[str, ...], study_dir: Path,
                 machine: MachineSource | None, where: str):
        self.opts = opts
        self.selected = selected
        self.where = where
        self.check(study_dir, machine)

    @classmethod
    def default_outputs(cls, opts) -> tuple[str, ...]:
        """The outputs when the table names none: all the kind gives."""
        return cls.outputs

    def check(self, study_dir: Path, machine: MachineSource | None) -> None:
        """Refuse options this machine cannot run (StudySpecError naming the key)."""

    def check_machine(self, machine: MachineSet) -> None:
        """Refuse options that leave every sample of this built machine empty (a table
        position beyond its travel: StudySpecError naming the key, the value and the
        travel); run on the nominal machine and on every corner of the parameters'
        ranges before the study starts."""

    @property
    def curve(self) -> Curve | None:
        """The curve kept per sample (None: none)."""
        return None

    @abstractmethod
    def run(self, machine: MachineSet | None, values: dict) -> Measurement:
        """Run on ``machine`` (``values``: the sample's parameters by name, for experiments
        without a machine)."""


def parse_experiment(cls: type, table: dict, where: str, study_dir: Path,
                     machine: MachineSource | None) -> Experiment:
    """One ``[experiment]`` table of kind ``cls.kind``: its options checked like a
    machine-file section, its ``outputs`` (default: all the kind gives) checked by name."""
    values = dict(table)
    selected = values.pop("outputs", None)
    opts = checked_section(cls.options, values, where, "experiment")
    if selected is None:
        selected = list(cls.default_outputs(opts))
    if (not isinstance(selected, list) or not selected
            or any(not isinstance(s, str) for s in selected)):
        raise StudySpecError(f"{where}: [experiment] outputs = {selected!r} must be a "
                             "non-empty list of output names")
    for name in selected:
        if name not in cls.outputs:
            raise StudySpecError(f"{where}: [experiment] kind = '{cls.kind}' has no output "
                                 f"'{shown_name(name)}' (its outputs: "
                                 f"{', '.join(cls.outputs)})")
    if cls.needs_machine and machine is None:
        raise StudySpecError(f"{where}: [experiment] kind = '{cls.kind}' needs [study] "
                             "machine (a machine file or manifest)")
    return cls(opts, tuple(selected), study_dir, machine, where)


def axis_config(machine: MachineSet, letter: str) -> MachineConfig:
    """The machine file of axis ``letter`` ("" : the first axis)."""
    for axis in machine.axes:
        if axis.name == letter or not letter:
            return axis.config
    raise KeyError(letter)


def check_axis(exp: Experiment, machine: MachineSource, letter: str) -> None:
    """Refuse an axis the machine has not, or a rotary one (the options are in mm)."""
    if letter and letter not in machine.letters:
        raise StudySpecError(f"{exp.where}: [experiment] axis = '{letter}': the machine has "
                             f"the axes {', '.join(machine.letters)}")
    configs = machine.configs()
    cfg = configs.get(letter) or next(iter(configs.values()))
    if cfg.machine.kind == "rotary":
        raise StudySpecError(f"{exp.where}: [experiment] kind = '{exp.kind}' runs on screw "
                             "and linear axes (its options are in mm); "
                             f"{cfg.path} is a rotary table")


def check_travel(exp: Experiment, cfg: MachineConfig, key: str, position_mm: float) -> None:
    """Refuse a table position (mm, named ``key`` in the study file) outside the axis's
    usable travel 0 .. [table] travel_m: the limit switches and the end stops sit just
    beyond it, so the drive would fault on every sample.  A rotary table has no travel."""
    if cfg.table is None:
        return
    travel_mm = cfg.table.travel_m / MM
    if not 0.0 <= position_mm <= travel_mm:
        raise StudySpecError(f"{exp.where}: [experiment] {key} = {position_mm:g} mm lies "
                             f"outside the travel of {cfg.path}, 0 .. {travel_mm:g} mm "
                             f"([table] travel_m = {cfg.table.travel_m:g} m): the axis would "
                             "stand on its limit switches and every sample fail")


def on_grid(t: np.ndarray, y: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``y(t)`` resampled on ``grid`` (linear; held beyond the ends)."""
    return np.interp(grid, t, y)


@dataclass(frozen=True, kw_only=True)
class StepOptions:
    """``[experiment] kind = "step"``: the controller's step measurement."""
    kind: str = key("-", "The experiment.", choices=("step",))
    loop: str = key("-", "position: a position setpoint step past the interpolator; "
                    "speed: a speed setpoint step with the position loop open.", "position",
                    choices=("position", "speed"))
    axis: str = key("-", "Axis letter on a manifest (default: the first axis).", "")
    amplitude_mm: float = key("mm", "Position step.", 0.5, gt=0.0)
    amplitude_mm_min: float = key("mm/min", "Speed step.", 500.0, gt=0.0)
    at_mm: float = key("mm", "Table position where the step starts.", 0.0)
    duration_s: float = key("s", "Simulated time from the start.", 0.3, gt=0.0, le=60.0)
    settling_band_pct: float = key("%", "Settling band around the target, % of the step.",
                                   2.0, gt=0.0, le=50.0)


class StepExperiment(Experiment):
    """A position or speed step; the curve is the response from its start value."""
    kind = "step"
    options = StepOptions
    outputs = ("rise_time_s", "lag_50pct_s", "overshoot_pct", "settling_time_s")

    def check(self, study_dir: Path, machine: MachineSource | None) -> None:
        check_axis(self, machine, self.opts.axis)
        self.check_machine(machine.build())

    def check_machine(self, machine: MachineSet) -> None:
        o = self.opts
        cfg = axis_config(machine, o.axis)
        check_travel(self, cfg, "at_mm", o.at_mm)
        if o.loop == "position":
            check_travel(self, cfg, "at_mm + amplitude_mm", o.at_mm + o.amplitude_mm)

    @property
    def curve(self) -> Curve:
        grid = np.linspace(0.0, self.opts.duration_s, CURVE_POINTS)
        if self.opts.loop == "position":
            return Curve("position from the start", "mm", grid, "time", "s")
        return Curve("table velocity", "mm/min", grid, "time", "s")

    def run(self, machine: MachineSet | None, values: dict) -> Measurement:
        o = self.opts
        cfg = axis_config(machine, o.axis)
        x0 = o.at_mm * MM
        if o.loop == "position":
            res = position_step(cfg, x0, o.amplitude_mm * MM, o.duration_s)
            y0, step, scale = x0, o.amplitude_mm * MM, 1.0 / MM
        else:
            res = speed_step(cfg, o.amplitude_mm_min * MM_MIN, o.duration_s, x0)
            y0, step, scale = 0.0, o.amplitude_mm_min * MM_MIN, 1.0 / MM_MIN
        post = res.t_s >= 0.0
        m = step_metrics(res.t_s[post], res.response[post], y0, step, o.settling_band_pct)
        curve = on_grid(res.t_s, (res.response - y0) * scale, self.curve.grid)
        return Measurement({name: getattr(m, name) for name in self.selected}, curve)


@dataclass(frozen=True, kw_only=True)
class FrequencyResponseOptions:
    """``[experiment] kind = "frequency_response"``: the controller's PRBS measurement."""
    kind: str = key("-", "The experiment.", choices=("frequency_response",))
    loop: str = key("-", "speed: speed setpoint to speed actual value; current: q-current "
                    "setpoint to measured q-current.", "speed", choices=("speed", "current"))
    axis: str = key("-", "Axis letter on a manifest (default: the first axis).", "")
    amplitude_mm_min: float = key("mm/min", "Speed loop: PRBS amplitude at the table.", 250.0,
                                  gt=0.0)
    offset_mm_min: float = key("mm/min", "Speed loop: offset that keeps the axis moving one "
                               "way.", 1000.0)
    amplitude_a: float = key("A", "Current loop: PRBS amplitude.", 1.0, gt=0.0)
    at_mm: float = key("mm", "Table position at the start.", 0.0)
    order: int = key("1", "PRBS register length (period 2^order - 1 cycles).", 10, ge=6,
                     le=16)
    periods: int = key("1", "PRBS periods averaged (one more runs first and is dropped).", 4,
                       ge=1, le=32)


class FrequencyResponseExperiment(Experiment):
    """A closed-loop frequency response; the curve is its magnitude on a log grid."""
    kind = "frequency_response"
    options = FrequencyResponseOptions
    outputs = ("bandwidth_hz", "peaking_db", "resonance_freq_hz", "resonance_peak_db",
               "phase_margin_deg", "gain_margin_db")

    def check(self, study_dir: Path, machine: MachineSource | None) -> None:
        check_axis(self, machine, self.opts.axis)
        cfg = machine.configs().get(self.opts.axis) or next(iter(machine.configs().values()))
        self._dt = (1.0 / cfg.motor.pwm_frequency_hz) * load_controller(cfg).speed_cycle_ratio
        self.check_machine(machine.build())

    def check_machine(self, machine: MachineSet) -> None:
        check_travel(self, axis_config(machine, self.opts.axis), "at_mm", self.opts.at_mm)

    @property
    def curve(self) -> Curve:
        f_low = 1.0 / ((2 ** self.opts.order - 1) * self._dt)
        grid = np.geomspace(f_low, 0.5 / self._dt, BODE_POINTS)
        return Curve("closed-loop magnitude", "dB", grid, "frequency", "Hz", log_grid=True)

    def run(self, machine: MachineSet | None, values: dict) -> Measurement:
        o = self.opts
        cfg = axis_config(machine, o.axis)
        prefilter = None
        if o.loop == "speed":
            per_rad = MM_MIN / transmission_ratio(cfg)  # motor rad/s per mm/min
            amplitude, offset = o.amplitude_mm_min * per_rad, o.offset_mm_min * per_rad
        else:
            amplitude, offset = o.amplitude_a, 0.0
        m = bode(cfg, o.loop, amplitude, offset, order=o.order, periods=o.periods,
                 x0=o.at_mm * MM)
        fr = m.response
        if o.loop == "speed":
            prefilter = setpoint_filter_response(cfg, m.dt_s, fr.freq_hz)
        figures = response_figures(fr, prefilter)
        grid = self.curve.grid
        curve = np.interp(np.log(grid), np.log(fr.freq_hz), fr.magnitude_db)
        return Measurement({name: figures[name] for name in self.selected}, curve)


def setpoint_filter_response(cfg: MachineConfig, dt_s: float, freq_hz: np.ndarray):
    """The speed loop's setpoint PT2 (``[controller] speed_setpoint_lowpass_hz``) at
    ``freq_hz``: complex, shape of ``freq_hz``; None when it is off."""
    sec = load_controller(cfg)
    if sec.speed_setpoint_lowpass_hz <= 0.0:
        return None
    f = lowpass2(sec.speed_setpoint_lowpass_hz, PT2_DAMPING, dt_s)
    z1 = np.exp(-2j * math.pi * freq_hz * dt_s)
    return (f.b0 + f.b1 * z1 + f.b2 * z1 * z1) / (1.0 + f.a1 * z1 + f.a2 * z1 * z1)


@dataclass(frozen=True, kw_only=True)
class ProgramOptions:
    """``[experiment] kind = "program"``: a part program on every axis of the machine."""
    kind: str = key("-", "The experiment.", choices=("program",))
    program: str = key("-", "Part program (G-code subset), relative to the study file.")
    start_mm: tuple = key("mm", "Each axis's table position at the start, in axis order "
                          "(default: all 0).", ())
    settle_s: float = key("s", "Simulated after the program's end.", SETTLE_S, ge=0.0)


class ProgramExperiment(Experiment):
    """A part program; the curve is the first axis's following error."""
    kind = "program"
    options = ProgramOptions
    outputs = ("following_error_max_um", "following_error_rms_um", "contour_error_max_um",
               "alarms")

    def check(self, study_dir: Path, machine: MachineSource | None) -> None:
        for letter in machine.letters:
            check_axis(self, machine, letter if machine.manifest else "")
        try:
            path = checked_name(study_dir / self.opts.program, "part program").resolve()
            self.text = read_program_text(path)
        except (ConfigError, ProgramError) as exc:
            raise StudySpecError(f"{self.where}: [experiment] program = "
                                 f"'{shown_path(self.opts.program)}': {exc}") from exc
        self.source = str(path)
        n = len(machine.letters)
        if self.opts.start_mm and len(self.opts.start_mm) != n:
            raise StudySpecError(f"{self.where}: [experiment] start_mm = "
                                 f"{list(self.opts.start_mm)}: one position (mm) per axis, "
                                 f"{n} axes")
        self.start = tuple(x * MM for x in self.opts.start_mm) or (0.0,) * n
        built = machine.build()
        self.check_machine(built)
        ctrl = MachineLockStep(built, self.start).ctrl
        try:
            program = parse_path_program(self.text, ctrl.names, self.start, self.source,
                                         ctrl.clamp_codes)
            self.profile_s = max(p.duration_s for p in ctrl.plan(program))
        except ValueError as exc:  # ProgramError is a ValueError
            raise StudySpecError(f"{self.where}: [experiment] program: {exc}") from exc

    def check_machine(self, machine: MachineSet) -> None:
        for axis, x in zip(machine.axes, self.start):
            check_travel(self, axis.config, f"start_mm of axis {axis.name}", x / MM)

    @property
    def curve(self) -> Curve:
        grid = np.linspace(0.0, self.profile_s + self.opts.settle_s, CURVE_POINTS)
        return Curve("following error, first axis", "um", grid, "time", "s")

    def run(self, machine: MachineSet | None, values: dict) -> Measurement:
        ls = MachineLockStep(machine, self.start)
        ls.enable()
        program = parse_path_program(self.text, machine.names, self.start, self.source,
                                     ls.ctrl.clamp_codes)
        profiles = ls.ctrl.plan(program)
        ls.ctrl.run_profiles(profiles)
        runs = ls.run(max(p.duration_s for p in profiles) + self.opts.settle_s)
        sims = list(runs.values())
        figures = following_error_um([s["following_error"] for s in sims])
        figures["contour_error_max_um"] = float(max(np.max(np.abs(s["contour_deviation"]))
                                                    for s in sims) * 1e6)
        figures["alarms"] = float(len(ls.ctrl.alarms))
        first = sims[0]
        t = first["t_s"] - first["t_s"][0]
        curve = on_grid(t, first["following_error"] * 1e6, self.curve.grid)
        return Measurement({name: figures[name] for name in self.selected}, curve)

