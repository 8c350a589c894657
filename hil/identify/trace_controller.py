"""The simulated NC fed with a record's setpoints, for the replay of records taken on other
controllers.

The NC (:class:`hil.controller.nc.Controller`) honours every convention of ``[controller]``
itself (``feedforward_interpolation``, ``speed_actual_filter_s``, ``speed_antiwindup``,
``current_delay_cycles``); what the replay adds is where a linear fine interpolation of the
speed feed-forward runs to: the record's feed-forward at the next position cycle rather than
the fine interpolator's.
"""

import numpy as np

from hil.controller.config import ControllerSection
from hil.controller.nc import Controller
from plant.config import MachineConfig


class TraceController(Controller):
    """:class:`~hil.controller.nc.Controller` whose feed-forward at each position cycle is
    given by the replay (:meth:`follow_feed_forward`).

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

    def follow_feed_forward(self, v_pos: np.ndarray) -> None:
        """The feed-forward (m/s or rad/s) of the position cycles of the points followed
        next (:meth:`run_points`), shape (n,): ``v_pos[j]`` is that of position cycle j,
        towards which a linear fine interpolation runs during cycle j - 1."""
        self.settle()
        self._feed_forward = np.ascontiguousarray(v_pos, dtype=np.float64)

    def trace_feed_forward(self) -> np.ndarray | None:
        return self._feed_forward

    def _next_feed_forward(self) -> float:
        if self._feed_forward is None:
            return super()._next_feed_forward()
        return float(self._feed_forward[self._fine_cycles])
