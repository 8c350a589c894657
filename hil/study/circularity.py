"""A circularity test on two axes (ISO 230-4, the ballbar test), as a study experiment.

The two axes follow a circle of radius R about a centre at a constant feed: the path
length s(t) is planned by the controller's own interpolator as one rest-to-rest move
(the axes' smaller velocity, acceleration and jerk limits) over a full turn plus the
ramps, and both axes get their IPO points

    x = cx + R cos(s/R),  y = cy ± R sin(s/R)

with the matching velocities and accelerations for the feed-forward.  The actual
positions (linear scale or motor encoder, as the machine file says) of the full turn
run at the constant feed give the radial deviation r - R; the circular deviation G is
max r - min r.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.controller.config import AxisLimits
from hil.controller.interpolator import Profile, ProfileSamples, plan
from hil.controller.program import Block, BlockKind, Program, ProgramError
from hil.sim import MachineLockStep
from hil.study.experiments import (
    MM,
    MM_MIN,
    Curve,
    Experiment,
    Measurement,
    axis_config,
    check_axis,
    check_travel,
)
from hil.study.keys import StudySpecError
from hil.study.machine import MachineSource
from hil.study.outputs import circle_figures, following_error_um
from plant.machines import MachineSet
from plant.schema import key

ANGLE_BINS = 360  # the curve: mean radial deviation per degree
CONSTANT_FEED = 0.999  # share of the feed that counts as the constant-feed phase


@dataclass(frozen=True, kw_only=True)
class CircularityOptions:
    """``[experiment] kind = "circularity"``."""
    kind: str = key("-", "The experiment.", choices=("circularity",))
    axes: str = key("-", "The two axis letters of the plane, first the one along angle 0 "
                    "(e.g. \"XY\").", "XY")
    radius_mm: float = key("mm", "Circle radius.", 10.0, gt=0.0)
    feed_mm_min: float = key("mm/min", "Path feed.", 1000.0, gt=0.0)
    center_mm: tuple = key("mm", "Circle centre, one position per axis of the plane.",
                           (250.0, 250.0))
    direction: str = key("-", "ccw: counter-clockwise (G3); cw: clockwise (G2).", "ccw",
                         choices=("ccw", "cw"))
    settle_s: float = key("s", "Simulated after the move's end.", 0.1, ge=0.0)


class CircularityExperiment(Experiment):
    """A full circle at constant feed on two axes of a manifest."""
    kind = "circularity"
    options = CircularityOptions
    outputs = ("circularity_um", "contour_error_max_um", "following_error_max_um",
               "following_error_rms_um")

    def check(self, study_dir: Path, machine: MachineSource | None) -> None:
        o = self.opts
        label = f"{self.where}: [experiment] kind = 'circularity'"
        if not machine.manifest or len(o.axes) != 2 or any(a not in machine.letters
                                                            for a in o.axes):
            raise StudySpecError(f"{label}: axes = '{o.axes}' must name two axes of a "
                                 f"manifest (this machine: {', '.join(machine.letters)})")
        for letter in o.axes:
            check_axis(self, machine, letter)
        if len(o.center_mm) != 2:
            raise StudySpecError(f"{label}: center_mm = {list(o.center_mm)} needs two "
                                 "positions (mm)")
        built = machine.build()
        self.check_machine(built)
        ctrl = MachineLockStep(built).ctrl
        limits = [ctrl.limits[ctrl.names.index(a)] for a in o.axes]
        self.limits = AxisLimits(min(lim.velocity for lim in limits),
                                 min(lim.acceleration for lim in limits),
                                 min(lim.jerk for lim in limits))
        v, r = o.feed_mm_min * MM_MIN, o.radius_mm * MM
        if v > self.limits.velocity or v * v / r > self.limits.acceleration:
            raise StudySpecError(
                f"{label}: feed_mm_min = {o.feed_mm_min:g} on radius_mm = {o.radius_mm:g} "
                f"needs {v * v / r:g} m/s^2 centripetal; the axes allow "
                f"{self.limits.velocity / MM_MIN:g} mm/min and "
                f"{self.limits.acceleration:g} m/s^2")
        try:
            self._plan()
        except ProgramError as exc:
            raise StudySpecError(f"{label}: feed_mm_min = {o.feed_mm_min:g}: "
                                 f"{exc.reason}") from exc

    def check_machine(self, machine: MachineSet) -> None:
        o = self.opts
        for letter, centre in zip(o.axes, o.center_mm):
            cfg = axis_config(machine, letter)
            for sign, side in ((-1.0, "-"), (1.0, "+")):
                check_travel(self, cfg, f"center_mm {side} radius_mm on axis {letter}",
                             centre + sign * o.radius_mm)

    def _plan(self) -> Profile:
        """The path length s(t) over a full turn and the ramps (SI), one rest-to-rest
        move; ProgramError when it would run longer than a program may."""
        o = self.opts
        r, v = o.radius_mm * MM, o.feed_mm_min * MM_MIN
        lim = self.limits
        ramp = v * v / lim.acceleration + (v * lim.acceleration / lim.jerk if lim.jerk else 0.0)
        length = 2.0 * math.pi * r + 2.0 * ramp
        return plan(Program("X", False, 0.0, (Block(BlockKind.MOVE, 1, 0.0, length, feed=v),)),
                    lim)

    @property
    def curve(self) -> Curve:
        grid = (np.arange(ANGLE_BINS) + 0.5) * 360.0 / ANGLE_BINS
        return Curve("radial deviation r - R", "um", grid, "angle", "deg")

    def _path(self, ipo_period_s: float) -> tuple[ProfileSamples, ProfileSamples]:
        """The two axes' IPO points (SI)."""
        o = self.opts
        r = o.radius_mm * MM
        s = self._plan().ipo_points(ipo_period_s)
        sign = 1.0 if o.direction == "ccw" else -1.0
        phi = s.pos / r
        c, sn = np.cos(phi), np.sin(phi)
        cx, cy = (x * MM for x in o.center_mm)
        centripetal = s.vel * s.vel / r
        x = ProfileSamples(s.t, cx + r * c, -sn * s.vel, -c * centripetal - sn * s.acc)
        y = ProfileSamples(s.t, cy + sign * r * sn, sign * c * s.vel,
                           sign * (c * s.acc - sn * centripetal))
        return x, y

    def run(self, machine: MachineSet | None, values: dict) -> Measurement:
        o = self.opts
        ix, iy = (machine.names.index(a) for a in o.axes)
        start = [0.0] * len(machine.axes)
        r = o.radius_mm * MM
        start[ix], start[iy] = o.center_mm[0] * MM + r, o.center_mm[1] * MM
        ls = MachineLockStep(machine, start)
        ls.enable()
        ctrl_x, ctrl_y = ls.ctrl.ctrls[ix], ls.ctrl.ctrls[iy]
        px, py = self._path(ctrl_x.ipo_period_s)
        ctrl_x.run_points(px, monitored=True)
        ctrl_y.run_points(py, monitored=True)
        runs = ls.run(px.t[-1] + o.settle_s)
        sx, sy = runs[o.axes[0]], runs[o.axes[1]]
        # the constant-feed turn: setpoint speed at the feed, one turn of setpoint angle
        speed = np.hypot(sx["v_set"], sy["v_set"])
        cx, cy = o.center_mm[0] * MM, o.center_mm[1] * MM
        angle = np.unwrap(np.arctan2(sy["x_set"] - cy, sx["x_set"] - cx))
        angle = np.abs(angle - angle[0])
        steady = np.flatnonzero(speed >= CONSTANT_FEED * o.feed_mm_min * MM_MIN)
        turn = steady[angle[steady] <= angle[steady[0]] + 2.0 * math.pi]
        figures = circle_figures(sx["x_act"][turn], sy["x_act"][turn], (cx, cy), r)
        figures.update(following_error_um([sx["following_error"][turn],
                                           sy["following_error"][turn]]))
        phi = np.degrees(np.arctan2(sy["x_act"][turn] - cy, sx["x_act"][turn] - cx)) % 360.0
        dev = (np.hypot(sx["x_act"][turn] - cx, sy["x_act"][turn] - cy) - r) * 1e6
        bins = np.minimum((phi * ANGLE_BINS / 360.0).astype(int), ANGLE_BINS - 1)
        count = np.bincount(bins, minlength=ANGLE_BINS)
        total = np.bincount(bins, weights=dev, minlength=ANGLE_BINS)
        curve = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        return Measurement({name: figures[name] for name in self.selected}, curve)
