"""The drive's monitoring, once per drive cycle: which fault causes are present, and the
statusword bits that report the drive's limits.

All positions and speeds are in the motor coordinate (rad, rad/s; m, m/s on linear
motors), from the drive's own measurements (encoder position, the speed actual value from
the encoder difference, the sampled currents) as a real drive has them.  The checks that
judge the commanded motion (following error, software limits, limit switches) run only in
OPERATION ENABLED; the overspeed and I²t checks run always, so a fault they latched cannot
be reset while the axis is still too fast or the motor still too hot.

* **Following error** (CSP): |target - actual| beyond 6065h for longer than 6066h.
* **Software position limits** 607Dh: the position actual beyond a limit while moving
  further out, in the modes without a position target (CSV, CST, voltage).  In CSP the
  limits act on the target (:class:`~hil.drive.core.EmulatedDrive` holds it inside them,
  as it stops a CSV speed toward the outside at them), and the position actual is judged
  by the following error against that target and by the limit switches.  A drive that
  was reset beyond a limit may move back in.
* **Limit switches** (60FDh bits 0 and 1, the plant's switch outputs): a switch active
  while moving further out, or reached.
* **Overspeed**: |speed| above 6080h times :data:`~hil.drive.faults.OVERSPEED_FACTOR`.
* **Peak current in voltage mode**: the sampled current's magnitude above 6072h for longer
  than :data:`PEAK_TIME_S`, or above :data:`PEAK_TRIP_FACTOR` times it at once.  In the
  other modes the drive's current setpoint is held inside 6072h and the current loop
  follows it; in voltage mode the master's voltages drive the winding directly, so the
  drive trips as an inverter's over-current protection does (torque off).  The time lets
  a master's own current loop overshoot a step to the limit, as a loop does.
* **I²t**: the integral of (i_q² + i_d² - continuous²) dt, never below 0, trips at
  (peak² - continuous²) times the overload time (the power stage's peak current from cold
  for ``overload_time_s``); the cause stays present until it has cooled to
  :data:`I2T_COOLED` of that; above :data:`I2T_WARNING` the statusword's warning bit is set.

"Moving out" means faster than the standstill speed (:meth:`Monitor.standstill`).
"""

import math

from hil.cia402 import (
    SW_FOLLOWING_ERROR,
    SW_INTERNAL_LIMIT_ACTIVE,
    SW_TARGET_REACHED,
    SW_WARNING,
)
from hil.drive.config import DriveParameters
from hil.drive.faults import OVERSPEED_FACTOR, Cause

#: the I²t cause ends when the integral has fallen to this fraction of its trip level
I2T_COOLED = 0.9
#: above this fraction of the trip level the statusword's warning bit (7) is set
I2T_WARNING = 0.8
#: the standstill speed: this fraction of 6080h ...
STANDSTILL_FRACTION = 0.005
#: ... or this many encoder increments per speed cycle, whichever is larger
STANDSTILL_COUNTS = 4
#: voltage mode: the current may stay above 6072h this long, s ...
PEAK_TIME_S = 0.001
#: ... and never above this many times 6072h
PEAK_TRIP_FACTOR = 1.5


class Monitor:
    """The checks of one drive (see the module docstring).

    Args:
        params: the drive's parameters (read every cycle: SDO writes take effect at once).
        period_s: the drive cycle (one PWM period), s.
        speed_quantum: one encoder increment per speed cycle, motor units/s.

    Attributes:
        flags: statusword bits of the last :meth:`check` (7, 10, 11, 13).
        i2t_a2s: the I²t integral, A²·s.
        following_error: the last CSP following error, motor units (0 outside CSP).
    """

    def __init__(self, params: DriveParameters, period_s: float, speed_quantum: float):
        self.params = params
        self.period_s = period_s
        self.speed_quantum = speed_quantum
        self.flags = 0
        self.i2t_a2s = 0.0
        self._hot = False
        self._fe_time_s = 0.0
        self._in_window_s = 0.0
        self._switches = (0.0, 0.0)
        self._peak_s = 0.0
        self.following_error = 0.0

    def standstill(self) -> float:
        """The speed below which the axis counts as standing still, motor units/s."""
        p = self.params
        limit = STANDSTILL_FRACTION * p.max_speed if math.isfinite(p.max_speed) else 0.0
        return max(limit, STANDSTILL_COUNTS * self.speed_quantum)

    def reset(self) -> None:
        """Clear the timers (the I²t integral keeps its heat)."""
        self._fe_time_s = self._in_window_s = self._peak_s = 0.0
        self.following_error = 0.0

    def check(self, operating: bool, target: float, theta: float, w: float, currents_a2: float,
              switches: tuple[float, float], voltage: bool = False) -> int:
        """The causes present this cycle (a :class:`~hil.drive.faults.Cause` mask).

        Args:
            operating: the drive is in OPERATION ENABLED.
            target: the CSP position target (held inside 607Dh), or NaN in other modes.
            theta: the position actual.
            w: the speed actual.
            currents_a2: i_q² + i_d² of the sampled currents, A².
            switches: the plant's (negative, positive) limit-switch outputs, 1.0 = active.
            voltage: the drive runs in voltage mode (the peak-current trip).
        """
        p = self.params
        present = self._i2t(currents_a2)
        flags = SW_WARNING if self.i2t_a2s >= I2T_WARNING * p.i2t_trip_a2s else 0
        if abs(w) > OVERSPEED_FACTOR * p.max_speed:
            present |= Cause.OVERSPEED
        reached_neg = switches[0] > 0.0 and self._switches[0] <= 0.0
        reached_pos = switches[1] > 0.0 and self._switches[1] <= 0.0
        self._switches = switches
        if switches[0] > 0.0 or switches[1] > 0.0:
            flags |= SW_INTERNAL_LIMIT_ACTIVE
        if not operating:
            self.reset()
            self.flags = flags
            return present
        if voltage:
            present |= self._peak(currents_a2)
        out = self.standstill()
        if (switches[0] > 0.0 and (reached_neg or w < -out)) or (
                switches[1] > 0.0 and (reached_pos or w > out)):
            present |= Cause.LIMIT_SWITCH
        csp = target == target
        if not csp and ((theta < p.limit_min and w < -out) or (theta > p.limit_max and w > out)):
            present |= Cause.SOFTWARE_LIMIT
        if csp:
            present |= self._following_error(target - theta)
            flags |= self._target_reached()
        self.flags = flags | (SW_FOLLOWING_ERROR if abs(self.following_error) > p.fe_window
                              else 0)
        return present

    def _peak(self, currents_a2: float) -> int:
        p = self.params
        if currents_a2 > p.max_current_a ** 2:
            self._peak_s += self.period_s
            if (self._peak_s > PEAK_TIME_S
                    or currents_a2 > (PEAK_TRIP_FACTOR * p.max_current_a) ** 2):
                return Cause.PEAK_CURRENT
        else:
            self._peak_s = 0.0
        return 0

    def _following_error(self, error: float) -> int:
        p = self.params
        self.following_error = error
        if abs(error) > p.fe_window:
            self._fe_time_s += self.period_s
            if self._fe_time_s > p.fe_time_s:
                return Cause.FOLLOWING_ERROR
        else:
            self._fe_time_s = 0.0
        return 0

    def _target_reached(self) -> int:
        p = self.params
        if abs(self.following_error) <= p.position_window:
            self._in_window_s += self.period_s
        else:
            self._in_window_s = 0.0
        return SW_TARGET_REACHED if self._in_window_s >= p.position_window_time_s else 0

    def _i2t(self, currents_a2: float) -> int:
        p = self.params
        trip = p.i2t_trip_a2s
        heat = self.i2t_a2s + (currents_a2 - p.continuous_current_a ** 2) * self.period_s
        self.i2t_a2s = heat if heat > 0.0 else 0.0  # a NaN current (never sent) counts as cold
        if self.i2t_a2s >= trip:
            self._hot = True
        elif self.i2t_a2s <= I2T_COOLED * trip:
            self._hot = False
        return Cause.OVERCURRENT if self._hot else 0
