"""The simulated NC fed with a record's setpoints, for the replay of records taken on other
controllers.

The NC (:class:`hil.controller.nc.Controller`) honours every convention of ``[controller]``
itself (``feedforward_interpolation``, ``speed_actual_filter_s``, ``speed_antiwindup``,
``current_delay_cycles``); what the replay adds is where a linear fine interpolation of the
speed feed-forward runs to: the record's feed-forward at the next position cycle rather than
the fine interpolator's.
"""

from hil.controller.config import ControllerSection
from hil.controller.nc import Controller
from plant.config import MachineConfig


class TraceController(Controller):
    """:class:`~hil.controller.nc.Controller` whose next position cycle's feed-forward is
    set by the replay (:meth:`set_next_feed_forward`).

    Args:
        cfg, period_s, x0, section: as for the base class (``section`` from
            :func:`~hil.controller.config.load_controller`, possibly with the record's
            conventions applied).
    """

    def __init__(self, cfg: MachineConfig, period_s: float, x0: float,
                 section: ControllerSection):
        super().__init__(cfg, period_s, x0, section=section)
        self.ff_next = 0.0

    def set_next_feed_forward(self, v_next: float) -> None:
        """The feed-forward of the next position cycle (m/s or rad/s), towards which a
        linear fine interpolation runs during this one."""
        self.ff_next = v_next

    def _next_feed_forward(self) -> float:
        return self.ff_next
