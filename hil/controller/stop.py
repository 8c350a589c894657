"""An alarm's stop reaction, as a SINUMERIK axis does it: rapid stop, then the drive
disabled.

The NC brakes with the position loop open and the speed setpoint zero, so the speed
controller brakes at its current limit, and disables the drive (controlword disable
voltage) once the axis stands still -- its speed within MD36060 for a whole
position-control cycle, so that a speed crossing zero while the drive train swings back
is no standstill --, after MD36620 at the latest, or at once when the speed actual value
cannot be trusted (a feedback value was not finite).
"""

from enum import Enum

from hil.controller.config import MonitoringLimits


class Phase(Enum):
    """Where an axis is in the stop reaction."""
    RUN = "run"        # no stop: enabling, or running a program or test mode
    BRAKE = "brake"    # speed setpoint zero, position loop open
    HALT = "halt"      # drive disabled (or being disabled), follow-up


class Braking:
    """When the braking of one axis ends (see the module docstring).

    Args:
        limits: the axis's monitoring machine data (MD36060, MD36620).
        period_s: the basic clock, s.
        speed_ratio, position_ratio: the speed and position-control cycles in basic-clock
            ticks.
    """

    def __init__(self, limits: MonitoringLimits, period_s: float, speed_ratio: int,
                 position_ratio: int):
        self.standstill_velocity = limits.standstill_velocity
        self.limit_ticks = max(1, round(limits.disable_delay_s / period_s))
        self.speed_ratio = speed_ratio
        self.position_ratio = position_ratio
        self.start()

    def start(self) -> None:
        """The braking begins."""
        self.ticks = 0
        self.still_ticks = 0

    def over(self, speed_cycle: bool, v_act: float, feedback_ok: bool) -> bool:
        """One tick of braking: True when the drive is to be disabled now.

        Args:
            speed_cycle: the speed was measured this tick.
            v_act: the axis speed measured, m/s or rad/s.
            feedback_ok: this tick's feedback values were finite.
        """
        self.ticks += 1
        if not feedback_ok or self.ticks > self.limit_ticks:
            return True
        if speed_cycle:
            still = abs(v_act) <= self.standstill_velocity
            self.still_ticks = self.still_ticks + self.speed_ratio if still else 0
        return self.still_ticks >= self.position_ratio
