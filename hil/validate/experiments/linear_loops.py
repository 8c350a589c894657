"""Linear references for the closed loops, written from the machine file's values and
:func:`plant.assemble.mechanics_matrices`, never from the kernel's params arrays:

- :func:`current_loop_tf`: the drive's q-current loop as an exact discrete transfer
  function (ZOH R-L plant at the PWM period, discrete PI, one period of computation
  delay), locked rotor;
- :func:`closed_speed_loop`: the frequency response of the NC's closed speed loop, w_act
  per w_set, around that current loop and the linearised mechanics.
"""

import math

import numpy as np
import scipy.signal

from hil.controller.config import load_controller
from plant.assemble import mechanics_matrices, transmission_ratio
from plant.config import MachineConfig


def current_loop_tf(cfg: MachineConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """(numerator, denominator, period in s) in z of the sampled q current per q-current
    setpoint, locked rotor, no saturation.

    Plant: L di/dt = u - R i with the voltage held over the PWM period T (ZOH).
    Controller: u[k] = Kp e[k] + Ki T sum_{j<k} e[j] with Ki = Kp/Ti (forward-Euler
    integrator), e[k] the error of the current sampled at kT, u[k] applied over
    [(k+1)T, (k+2)T) (one period of computation delay), so the loop is C(z) z^-1 P(z).
    """
    mo, cl = cfg.motor, cfg.current_loop
    period = 1.0 / mo.pwm_frequency_hz
    r, ind = mo.resistance_ohm, mo.inductance_q_h
    num_p, den_p = scipy.signal.ss2tf(*scipy.signal.cont2discrete(
        (np.array([[-r / ind]]), np.array([[1.0 / ind]]), np.eye(1), np.zeros((1, 1))),
        period, method="zoh")[:4])
    kp, ki = cl.kp_v_per_a, cl.kp_v_per_a / cl.ti_s
    num_c, den_c = [kp, ki * period - kp], [1.0, -1.0]
    num = np.polymul(num_c, np.trim_zeros(num_p[0], "f"))
    den = np.polymul(np.polymul(den_c, [1.0, 0.0]), den_p)
    return num, np.polyadd(den, num), period


def current_loop_response(cfg: MachineConfig, freq_hz: np.ndarray) -> np.ndarray:
    """Complex response of :func:`current_loop_tf` at ``freq_hz`` (Hz), shape as given."""
    num, den, period = current_loop_tf(cfg)
    z = np.exp(2j * math.pi * np.asarray(freq_hz) * period)
    return np.polyval(num, z) / np.polyval(den, z)


def motor_angle_per_torque(cfg: MachineConfig, table_pos: float,
                           freq_hz: np.ndarray) -> np.ndarray:
    """Complex response (rad/(N·m)) of the motor angle to a motor torque, from the
    linearised mechanics at ``table_pos`` (m) with the table's viscous friction added
    (at steady sliding the Coulomb part is constant and the Stribeck part gone)."""
    m_mat, c_mat, k_mat = mechanics_matrices(cfg, table_pos)
    c_mat = c_mat.copy()
    table = cfg.friction.viscous_ns_per_m if cfg.friction is not None else 0.0
    if m_mat.shape[0] == 1:
        table *= transmission_ratio(cfg) ** 2  # the table sits on the one node
    c_mat[-1, -1] += table
    unit = np.zeros(m_mat.shape[0])
    unit[0] = 1.0
    s_all = 2j * math.pi * np.asarray(freq_hz, dtype=float)
    return np.array([np.linalg.solve(m_mat * s * s + c_mat * s + k_mat, unit)[0]
                     for s in s_all])


def closed_speed_loop(cfg: MachineConfig, table_pos: float,
                      freq_hz: np.ndarray) -> np.ndarray:
    """Complex response w_act / w_set of the NC's closed speed loop at ``freq_hz`` (Hz).

    L = C(z) G_i(z) G_theta(s) (1 - z^-1)/T_s, T = L / (1 + L), with the speed PI
    C(z) = K_p + K_p T_s / T_n / (z - 1) (integrator updated after the output) at the
    speed cycle T_s, the current loop G_i of :func:`current_loop_response` (the speed
    loop's current setpoint is a torque over K_t, the plant's torque K_t i: K_t cancels),
    the motor angle per torque G_theta of :func:`motor_angle_per_torque`, and the speed
    measured as the encoder's difference over the speed cycle.  Sampling is taken into
    account through z = exp(s T); aliasing and the encoder's quantisation are not.
    Refuses a controller with setpoint or current filters, a notch or a D term, which
    this reference leaves out.
    """
    sec = load_controller(cfg)
    extras = {"speed_setpoint_lowpass_hz": sec.speed_setpoint_lowpass_hz,
              "current_setpoint_lowpass_hz": sec.current_setpoint_lowpass_hz,
              "notch_hz": sec.notch_hz, "speed_kd_nms2_per_rad": sec.speed_kd_nms2_per_rad}
    used = {k: v for k, v in extras.items() if v}
    if used or cfg.machine.kind == "linear" or sec.plant_input != "current":
        raise ValueError(f"{cfg.path}: closed_speed_loop covers a rotary-motor PI speed loop "
                         f"on a plant taking current only, not {used or sec.plant_input}")
    period = sec.speed_cycle_ratio / cfg.motor.pwm_frequency_hz
    f = np.asarray(freq_hz, dtype=float)
    z = np.exp(2j * math.pi * f * period)
    kp = sec.speed_kp_nms_per_rad
    pi = kp + (kp * period / sec.speed_tn_s / (z - 1.0) if sec.speed_tn_s > 0.0 else 0.0)
    loop = (pi * current_loop_response(cfg, f) * motor_angle_per_torque(cfg, table_pos, f)
            * (1.0 - 1.0 / z) / period)
    return loop / (1.0 + loop)
