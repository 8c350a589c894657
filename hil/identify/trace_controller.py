"""The simulated NC fed with a record's setpoints, for the replay of records taken on other
controllers.

The NC (:class:`hil.controller.nc.Controller`) honours every convention of ``[controller]``
itself (``speed_actual_filter_s``, ``speed_antiwindup``, ``current_delay_cycles``); what the
replay adds is the speed feed-forward as ``docs/trace-format.md`` (shared docs) defines it:
the record's ``vel_set`` per record row, not per position cycle.  At every speed cycle the
speed command is the P part of the last position cycle plus the feed-forward factor times
the feed-forward of that instant: with ``feedforward_interpolation = "linear"`` the linear
interpolation between the two record rows that bracket it, with ``"hold"`` the last row at
or before it -- whatever the position cycle, so a feed-forward step on a row between two
position cycles reaches the speed loop when the row says.
"""

import numpy as np

from hil.controller.config import ControllerSection
from hil.controller.nc import Controller
from plant.config import MachineConfig


class TraceController(Controller):
    """:class:`~hil.controller.nc.Controller` whose speed feed-forward at each speed cycle
    comes from the record's rows (:meth:`follow_feed_forward`).

    Args:
        cfg, period_s, x0, section: as for the base class (``section`` from
            :func:`~hil.controller.config.load_controller`, possibly with the record's
            conventions applied).
        compiled: as for the base class.
    """

    def __init__(self, cfg: MachineConfig, period_s: float, x0: float,
                 section: ControllerSection, compiled: bool = True):
        self._feed_forward: np.ndarray | None = None
        super().__init__(cfg, period_s, x0, section=section, compiled=compiled)

    def follow_feed_forward(self, v_rows: np.ndarray, ticks_per_row: int) -> None:
        """The feed-forward (m/s or rad/s) of the record rows of the points followed next
        (:meth:`run_points`), shape (n,): row r stands ``r * ticks_per_row`` PWM periods
        after the points' first position cycle.  Every speed cycle from there takes the
        rows' value at its instant (module docstring); past the last row, the last one."""
        if ticks_per_row < 1:
            raise ValueError(f"ticks_per_row {ticks_per_row} must be >= 1")
        v = np.asarray(v_rows, dtype=np.float64)
        if v.ndim != 1 or v.size == 0:
            raise ValueError(f"v_rows has shape {v.shape}, needs (n,) with n >= 1")
        self.settle()
        n_speed = self.sec.speed_cycle_ratio
        ticks = np.arange(-(-v.size * ticks_per_row // n_speed) + 1) * n_speed
        row, within = np.divmod(ticks, ticks_per_row)
        last = v.size - 1
        here = v[np.minimum(row, last)]
        if self.sec.feedforward_interpolation == "linear":
            ahead = v[np.minimum(row + 1, last)]
            here = here + (ahead - here) * (within / ticks_per_row)
        self._feed_forward = np.ascontiguousarray(here)

    def trace_feed_forward(self) -> np.ndarray | None:
        return self._feed_forward
