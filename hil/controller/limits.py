"""The NC's software limit switches (SINUMERIK MD36100 POS_LIMIT_MINUS, MD36110
POS_LIMIT_PLUS) and how the NC keeps an axis inside them.

**Where they lie.**  One derivation owns an axis's software limits: the drive's 607Dh
(:func:`hil.drive.config.load_drive`: the ``[drive]`` keys, or what it derives from the
travel).  The NC's limits lie inside 607Dh by the standstill tolerance MD36030: an axis
stopped at the NC's limit stands no further out than that without the NC's alarm 25040,
so the overshoot of a move that ends on the limit (micrometres: the position loop, and
the screw's twist between the scale the NC reads and the motor encoder 607Dh watches)
never reaches the drive's software-limit fault 8612h.  An axis whose 607Dh is off (a
rotary table by default) has no software limits and is never limited.

**Block preparation (alarm 10720).**  Before a program moves, the NC checks every move
block's end point against the limits.  A block moves on a straight line (this NC has no
circles: the parsers refuse G2/G3), so its extent is its two end points, and its start is
the end of the block before it (or the program's start, which may lie beyond a limit: the
axis may move back in); absolute and incremental (G91) end points alike are the block's
position after it.  The first block with an end point beyond a limit raises alarm 10720,
naming its line, the axis, the limit and the programmed value; the blocks before it run,
and the program ends at rest where that block would have begun: no motion of it, as
SINUMERIK's interpreter stop does.  Every axis of a multi-axis program stops before the
same block.  The alarm does not stop the axes (they stand at a block end, in position
control), but NC start is refused until the NC's RESET.

**Setpoints no interpolator planned** (a measuring function's position step, a replayed
trace) are checked the same way before they move: one beyond a limit raises 10720 and
none of them runs.

**Motion no end point bounds** (the speed and current test modes of the measuring
functions) is limited in speed near the limits: toward a limit at distance d the
velocity is at most sqrt(2 a d), a the axis's maximum acceleration MD32300, so the axis
can stop on the limit at that deceleration and stands there.  In speed mode the speed
setpoint is held within that bound; in current mode, which has no speed loop, the NC
takes the axis over with its speed loop the moment the axis is faster than the bound, on
the same bound.  Either raises alarm 10620 (the axis reaches the software limit switch),
which leaves the axis enabled: no alarm stop reaction, the bound does the braking.
"""

import math
from dataclasses import dataclass

import numpy as np

from hil.controller.config import ControllerSection, cnc_unit, monitoring_limits
from hil.controller.interpolator import Profile, ProfileSamples
from hil.controller.program import _number
from hil.drive.config import load_drive
from plant.assemble import transmission_ratio
from plant.config import MachineConfig
from plant.errors import ConfigError

#: a position is beyond a limit only by more than this many CNC units (1e-6 mm = 1 nm,
#: 1e-6 deg): the resolution a program is written to (``format_program``), so that a
#: limit and a programmed value that differ in their last floating-point bit agree
RESOLUTION = 1e-6


@dataclass(frozen=True)
class LimitViolation:
    """What block preparation found beyond the software limits: where the program stops
    (the start of the block in its profile, s) and alarm 10720's detail."""
    t_s: float
    detail: str


@dataclass(frozen=True)
class SoftwareLimits:
    """An axis's software limit switches.

    Attributes:
        minus, plus: MD36100 and MD36110 in SI table units (m or rad); -inf and inf: none.
        per_si: CNC units (mm or deg) per SI unit, for messages.
        unit: the CNC unit, "mm" or "deg".
    """
    minus: float
    plus: float
    per_si: float
    unit: str

    def side(self, x: float) -> str:
        """"+" when ``x`` (m or rad) lies beyond the plus limit, "-" beyond the minus limit,
        "" otherwise (NaN included: a non-finite setpoint is the monitoring's business)."""
        tol = RESOLUTION / self.per_si
        if x > self.plus + tol:
            return "+"
        if x < self.minus - tol:
            return "-"
        return ""

    def speed_range(self, x: float, acceleration: float) -> tuple[float, float]:
        """The lowest and highest velocity (m/s or rad/s) from which the axis at ``x`` can
        stop on the limits at ``acceleration`` (/s²): -sqrt(2 a d_minus), sqrt(2 a d_plus),
        0 toward a limit the axis stands at or beyond."""
        hi = math.sqrt(2.0 * acceleration * max(self.plus - x, 0.0))
        lo = -math.sqrt(2.0 * acceleration * max(x - self.minus, 0.0))
        return lo, hi

    def limit(self, side: str) -> str:
        """The limit ``side`` ("+" or "-") in CNC units, for an alarm's detail."""
        x = self.plus if side == "+" else self.minus
        return f"{side} limit {_number(x * self.per_si)} {self.unit}"

    def beyond(self, x: float, side: str) -> str:
        """``x`` (m or rad) beyond the limit ``side``, in CNC units, for an alarm's detail."""
        return f"{_number(x * self.per_si)} {self.unit} beyond the {self.limit(side)}"

    def first_violation(self, profile: Profile, axis: str) -> LimitViolation | None:
        """Block preparation: the first move block of ``profile`` whose end point lies
        beyond the limits (its line, the axis ``axis`` and the end point named), or None."""
        for move in profile.moves:
            side = self.side(move.target)
            if side:
                return LimitViolation(move.t_s,
                                      f"line {move.line}: {axis}{self.beyond(move.target, side)}")
        return None

    def first_setpoint_beyond(self, points: ProfileSamples, axis: str) -> str | None:
        """Alarm 10720's detail for the first of ``points`` beyond the limits, or None."""
        tol = RESOLUTION / self.per_si
        out = np.flatnonzero((points.pos > self.plus + tol) | (points.pos < self.minus - tol))
        if not out.size:
            return None
        x = float(points.pos[out[0]])
        return (f"setpoint {axis}{self.beyond(x, self.side(x))} at t = "
                f"{float(points.t[out[0]]):.3f} s")


def software_limits(cfg: MachineConfig, section: ControllerSection) -> SoftwareLimits:
    """The NC's software limits of the axis of ``cfg`` with machine data ``section``: the
    drive's 607Dh, each MD36030 inside it (module docstring); ConfigError when 607Dh
    leaves no room between them."""
    drive = load_drive(cfg, section)
    ratio = transmission_ratio(cfg)  # table SI units per motor unit
    lo, hi = drive.limit_min * ratio, drive.limit_max * ratio
    margin = monitoring_limits(cfg, section).standstill_tol
    per_si, unit = cnc_unit(cfg)
    if lo + margin > hi - margin:
        raise ConfigError(f"{cfg.path}: [drive] software limits (607Dh) {_number(lo * per_si)} "
                          f"to {_number(hi * per_si)} {unit} leave no travel to the NC's "
                          f"software limits, [controller] standstill_pos_tol_{unit} = "
                          f"{_number(margin * per_si)} {unit} inside each")
    return SoftwareLimits(lo + margin, hi - margin, per_si, unit)
