"""The simulated NC with the controller conventions of ``[controller]`` that the emulator's
own controller (:class:`hil.controller.nc.Controller`) does not model yet, for the replay of
records taken on other controllers:

* ``feedforward_interpolation = "linear"``: the speed feed-forward interpolated at every
  speed cycle between this position cycle's value and the next one's (a fine
  interpolation), instead of held over the position cycle;
* ``speed_actual_filter_s``: a first-order filter on the measured motor speed;
* ``speed_antiwindup = "clamp"`` or ``"none"``: the speed integrator held within the
  current limit, or not limited at all (``"conditional"`` is the emulator's own PI);
* ``current_delay_cycles``: the current setpoint applied that many PWM periods late.

With every key at its default the class behaves exactly as its base.
"""

import collections

from hil.controller.blocks import PI, PT1
from hil.controller.config import ControllerSection
from hil.controller.nc import Controller
from io_adapters.messages import MODE_CST, Feedback, Setpoint
from plant.config import MachineConfig


class ClampPI(PI):
    """PI whose integrator is held within ±limit (it always integrates)."""

    def step(self, err: float) -> float:
        u = self.kp * err + self.integ
        self.integ = max(-self.limit, min(self.limit, self.integ + self.ki_t * err))
        return max(-self.limit, min(self.limit, u))


class WindupPI(PI):
    """PI without anti-windup: the integrator integrates whatever the output's limit."""

    def step(self, err: float) -> float:
        u = self.kp * err + self.integ
        self.integ += self.ki_t * err
        return max(-self.limit, min(self.limit, u))


_PI_CLASSES = {"clamp": ClampPI, "none": WindupPI}


class TraceController(Controller):
    """:class:`~hil.controller.nc.Controller` with the conventions of the module docstring.

    Args:
        cfg, period_s, x0, section: as for the base class (``section`` from
            :func:`~hil.controller.config.load_controller`, possibly with the record's
            conventions applied).
    """

    def __init__(self, cfg: MachineConfig, period_s: float, x0: float,
                 section: ControllerSection):
        super().__init__(cfg, period_s, x0, section=section)
        sec = self.sec
        pi_class = _PI_CLASSES.get(sec.speed_antiwindup)
        if pi_class is not None:
            old = self.speed_loop.pi
            new = pi_class(old.kp, 0.0, period_s, old.limit)
            new.ki_t = old.ki_t  # the gains as the speed loop computed them
            self.speed_loop.pi = new
        self.speed_filter = PT1(sec.speed_actual_filter_s, period_s * sec.speed_cycle_ratio)
        self.ff_linear = sec.feedforward_interpolation == "linear" and sec.speed_ff
        self.ff_next = 0.0
        self._delay = collections.deque([0.0] * sec.current_delay_cycles)

    def set_next_feed_forward(self, v_next: float) -> None:
        """The feed-forward of the next position cycle (m/s or rad/s), towards which a
        linear fine interpolation runs during this one."""
        self.ff_next = v_next

    def _measure(self, fb: Feedback, k: int) -> None:
        super()._measure(fb, k)
        if self.sec.speed_actual_filter_s > 0.0 and k % self.sec.speed_cycle_ratio == 0:
            self.w_act = self.speed_filter.step(self.w_act)
            self.v_act = self.w_act * self.ratio

    def _clear_loops(self) -> None:
        super()._clear_loops()
        self.speed_filter.reset()

    def _run(self, k: int) -> None:
        sec = self.sec
        n_pos = sec.position_cycle_ratio
        if (self.ff_linear and self.mode == "position" and k % n_pos
                and k % sec.speed_cycle_ratio == 0):
            # between position cycles: the P part held, the feed-forward interpolated
            frac = (k % n_pos) / n_pos
            loop = self.pos_loop
            v_ff = self.v_set + (self.ff_next - self.v_set) * frac
            v = loop.kv * loop.error + loop.ff * v_ff
            self.v_cmd = max(-loop.v_lim, min(loop.v_lim, v))
            self.w_set = self.v_cmd / self.ratio
        super()._run(k)

    def tick(self, fb: Feedback, sp: Setpoint) -> None:
        super().tick(fb, sp)
        if self._delay and sp.mode == MODE_CST:
            self._delay.append(sp.iq_ref_a)
            sp.iq_ref_a = self._delay.popleft()
