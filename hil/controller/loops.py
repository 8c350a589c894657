"""The cascade's loops: position (P with K_v and feed-forward), speed (PI + D, filters),
current (PI on d and q, for plants that take voltage).

Each loop is an object with a ``step`` per cycle; SI units throughout: motor
speeds in rad/s (m/s for linear motors), table positions in m (rad for
rotary tables), currents in A.
"""

import math

from hil.controller.blocks import PI, PT1, ClampPI, WindupPI, lowpass2, notch
from hil.controller.config import ControllerSection, kv_si

#: damping of the PT2 setpoint low-passes (the drives' default)
PT2_DAMPING = 0.7
#: the speed PI of the ``speed_antiwindup`` modes that are no conditional integration
_PI_CLASSES = {"clamp": ClampPI, "none": WindupPI}


class PositionLoop:
    """P position controller with K_v, speed feed-forward and the symmetrising delay.

    v_cmd = K_v (x_set' - x_act) + w_ff v_set, where x_set' is the setpoint
    delayed by the closed speed loop's equivalent time (MD32810) when
    feed-forward is on, so that the P path and the feed-forward path agree.
    """

    def __init__(self, sec: ControllerSection, period_s: float, v_max: float):
        self.kv = kv_si(sec)
        self.ff = sec.speed_ff_weight if sec.speed_ff else 0.0
        self.sym = PT1(sec.speedctrl_equiv_time_s if sec.speed_ff else 0.0, period_s)
        self.v_lim = v_max  # the speed command is limited to the maximum axis velocity
        self.error = 0.0

    def reset(self, x: float) -> None:
        """Start at rest at table position ``x``."""
        self.sym.reset(x)
        self.error = 0.0

    def finite(self) -> bool:
        """Every state is finite."""
        return self.error * 0.0 == 0.0 and self.sym.finite()

    def step(self, x_set: float, v_set: float, x_act: float) -> float:
        """Velocity command (table units per s) for this position cycle."""
        self.error = self.sym.step(x_set) - x_act
        return self.command(v_set)

    def command(self, v_ff: float) -> float:
        """Velocity command (table units per s) of the last cycle's P part with the speed
        feed-forward ``v_ff`` (table units per s): between position cycles, a finely
        interpolated feed-forward (``feedforward_interpolation = 'linear'``)."""
        v = self.kv * self.error + self.ff * v_ff
        return max(-self.v_lim, min(self.v_lim, v))


class SpeedLoop:
    """Speed controller: PT2 setpoint filter, PI (+ D, seed 003 eq. 7), torque / K_t,
    current feed-forward, PT2 and notch current-setpoint filters, current limit.

    The integrator's anti-windup (``speed_antiwindup``): 'torque_setpoint' stops it while
    the whole torque setpoint, PI + D + current feed-forward, is at the limit K_t I_max and
    the error pushes further (SINAMICS: I component frozen when the torque limit is
    reached); 'conditional' tests the PI's own output only, so D and feed-forward can hold
    the current at its limit while the integrator keeps integrating; 'clamp' holds the
    integrator within the limit (:class:`~hil.controller.blocks.ClampPI`), 'none' lets it
    wind up (:class:`~hil.controller.blocks.WindupPI`)."""

    def __init__(self, sec: ControllerSection, period_s: float, kind: str, kt: float,
                 i_max: float):
        linear = kind == "linear"
        kp = sec.speed_kp_ns_per_m if linear else sec.speed_kp_nms_per_rad
        self.kd_t = (sec.speed_kd_ns2_per_m if linear else sec.speed_kd_nms2_per_rad) / period_s
        self.antiwindup = sec.speed_antiwindup
        pi_class = _PI_CLASSES.get(sec.speed_antiwindup, PI)
        self.pi = pi_class(kp, sec.speed_tn_s, period_s, kt * i_max)
        self.set_filter = lowpass2(sec.speed_setpoint_lowpass_hz, PT2_DAMPING, period_s)
        self.cur_filter = lowpass2(sec.current_setpoint_lowpass_hz, PT2_DAMPING, period_s)
        self.notch = notch(sec.notch_hz, sec.notch_bandwidth_hz, sec.notch_depth_db, period_s)
        self.inv_kt = 1.0 / kt
        self.i_max = i_max
        self.kt = kt
        self.stop_on_total = sec.speed_antiwindup == "torque_setpoint"
        self.e_prev = 0.0

    def reset(self) -> None:
        """Clear every state (integrator, filters, D memory)."""
        self.pi.reset()
        for f in (self.set_filter, self.cur_filter, self.notch):
            f.reset()
        self.e_prev = 0.0

    def finite(self) -> bool:
        """Every state is finite."""
        return (self.e_prev * 0.0 == 0.0 and self.pi.finite() and self.set_filter.finite()
                and self.cur_filter.finite() and self.notch.finite())

    def step(self, w_set: float, w_act: float, i_ff: float) -> float:
        """q-current setpoint (A) for this speed cycle."""
        e = self.set_filter.step(w_set) - w_act
        d_part = self.kd_t * (e - self.e_prev)
        if self.stop_on_total:
            torque = self.pi.step_within(e, d_part + i_ff * self.kt) + d_part
        else:
            torque = self.pi.step(e) + d_part
        self.e_prev = e
        i = self.notch.step(self.cur_filter.step(torque * self.inv_kt + i_ff))
        return max(-self.i_max, min(self.i_max, i))


class CurrentLoop:
    """d and q current PI loops with EMF and cross-coupling precontrol from the measured
    speed (as a drive's own loop has) and the voltage vector limited to the converter's
    limit (U_dc/sqrt(3) or U_dc/2: plant.assemble.voltage_limit; d first).

    Args:
        motor: (pole pairs or pi / pole pitch, psi in V·s, L_d in H, L_q in H) of the motor.
    """

    def __init__(self, sec: ControllerSection, period_s: float, u_max: float,
                 motor: tuple[float, float, float, float]):
        self.d = PI(sec.current_kp_v_per_a, sec.current_ti_s, period_s, u_max)
        self.q = PI(sec.current_kp_v_per_a, sec.current_ti_s, period_s, u_max)
        self.u_max = u_max
        self.poles, self.psi, self.ld, self.lq = motor

    def reset(self) -> None:
        """Clear both integrators."""
        self.d.reset()
        self.q.reset()

    def finite(self) -> bool:
        """Both integrators are finite."""
        return self.d.finite() and self.q.finite()

    def step(self, id_set: float, iq_set: float, id_act: float, iq_act: float,
             w_motor: float):
        """(u_d, u_q) in V for this PWM period at motor speed ``w_motor`` (rad/s, or m/s)."""
        we = self.poles * w_motor
        ud = max(-self.u_max, min(self.u_max, self.d.step(id_set - id_act)
                                  - we * self.lq * iq_act))
        uq_max = math.sqrt(max(self.u_max * self.u_max - ud * ud, 0.0))
        uq = self.q.step(iq_set - iq_act) + we * (self.psi + self.ld * id_act)
        return ud, max(-uq_max, min(uq_max, uq))
