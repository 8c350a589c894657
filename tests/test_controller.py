"""The simulated controller (hil.controller) in lock-step with the plant (hil.sim).

Independent references:

* following error: the Sinumerik definition of K_v (MD32200: 1 (m/min)/mm gives 1 mm of
  following error at 1 m/min), so e = v / K_v without feed-forward; with feed-forward the
  only error left is the lag of the symmetrising filter, a discrete first-order lag with
  T_eq at the position period T, whose steady lag behind a ramp of slope v is
  v T a / (1 - a), a = exp(-T / T_eq) (hand-derived from y_k = u_k + a (y_{k-1} - u_k));
* speed and position steps: the exact discrete closed loop built here with
  scipy.signal from the machine file's values alone (ZOH of the continuous plant, the PI
  and the encoder-difference speed measurement written out by hand), simulated with
  ``scipy.signal.dlsim``;
* filter blocks: the analogue prototypes evaluated at the prewarped frequency against
  ``scipy.signal.freqz`` of the biquad coefficients, closed-form -3 dB points; PI and PT1
  sequences computed by hand;
* drive: the CiA 402 state table (statusword patterns from hil.cia402, cross-checked with
  canopen in test_cia402.py) and the plant's enable input.
"""

import math
from typing import NamedTuple

import numpy as np
import pytest
import scipy.optimize
import scipy.signal

from hil.cia402 import SW_FAULT, State, statusword_state
from hil.controller.blocks import PI, PT1, lowpass2, notch
from hil.controller.config import ControllerSection, axis_limits, load_controller
from hil.controller.interpolator import plan
from hil.controller.program import parse_program
from hil.measure.runs import position_step, speed_step
from hil.sim import LockStep, SimResult
from plant import layout as L
from plant.config import MachineConfig, load_machine
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"

# ---------------------------------------------------------------- following error


class Cruise(NamedTuple):
    """Following error over the settled part of a constant-velocity move."""
    velocity: float      # m/s
    error: float         # mean following error, m
    samples: int         # position cycles averaged
    sec: ControllerSection
    position_period_s: float


def cruise_following_error(feed_mm_min: float, speed_ff: bool) -> Cruise:
    """A G1 move of about 1 s cruise at ``feed_mm_min`` on the Arrow 500 X (friction and
    cogging on); the controller's following error at its position cycles, averaged over
    the cruise from 0.5 s after it starts (the loop has settled; the average spans many
    cogging periods)."""
    cfg = load_machine(ARROW, overrides={"controller": {"speed_ff": speed_ff}})
    sec = load_controller(cfg)
    v = feed_mm_min / 60000.0
    x0 = 0.1
    target_mm = (x0 + v * 1.0 + 0.02) * 1e3
    profile = plan(parse_program(f"G1 X{target_mm:.3f} F{feed_mm_min:g}", start=x0),
                   axis_limits(cfg, sec))
    ls = LockStep(cfg, x0)
    ls.enable()
    ls.ctrl.run_profile(profile)
    res = ls.run(profile.duration_s)
    cycle = res["tick"] % sec.position_cycle_ratio == 0
    cruise = cycle & np.isclose(res["v_set"], v, rtol=1e-9, atol=0.0) & (res["a_set"] == 0.0)
    t = res["t_s"]
    settled = cruise & (t >= t[cruise][0] + 0.5)
    return Cruise(v, float(np.mean(res["following_error"][settled])), int(settled.sum()), sec,
                  ls.plant.pwm_period * sec.position_cycle_ratio)


@pytest.mark.parametrize("feed_mm_min", [1000.0, 6000.0])
def test_following_error_without_feedforward_is_v_over_kv(feed_mm_min):
    """Without feed-forward the steady following error is v / K_v: 0.5 mm at 1 m/min and
    3 mm at 6 m/min with K_v = 2 (m/min)/mm, within 1 %."""
    c = cruise_following_error(feed_mm_min, speed_ff=False)
    expected_mm = (feed_mm_min / 1000.0) / c.sec.kv_m_min_per_mm
    assert c.samples > 100
    assert c.error * 1e3 == pytest.approx(expected_mm, rel=0.01)


@pytest.mark.parametrize("feed_mm_min", [1000.0, 6000.0])
def test_following_error_with_feedforward_is_the_symmetrising_lag(feed_mm_min):
    """With speed feed-forward the P path sees the setpoint delayed by the symmetrising
    filter (PT1, T_eq = 2.5 ms at the 2 ms position cycle), so the following error is that
    filter's ramp lag v T a / (1 - a) (within 2 %), far below v / K_v."""
    c = cruise_following_error(feed_mm_min, speed_ff=True)
    a = math.exp(-c.position_period_s / c.sec.speedctrl_equiv_time_s)
    lag = c.velocity * c.position_period_s * a / (1.0 - a)
    without_ff = (feed_mm_min / 1000.0) / c.sec.kv_m_min_per_mm * 1e-3
    assert c.samples > 100
    assert c.error < 0.1 * without_ff
    assert c.error == pytest.approx(lag, rel=0.02)


# ---------------------------------------------------------------- linear variant

#: The Arrow 500 X drive made linear: rigid mechanics (rotor, screw and coupling as one
#: inertia, table through the lead), the current loop as a first-order lag, no friction,
#: cogging, current noise or quantization, a 30-bit encoder and a 1 us sub-step.
LINEAR_MACHINE = """
[machine]
name = "Arrow 500 X, linearised"
source = "test_controller.py"
kind = "screw"

[motor]
model = "first_order"
pole_pairs = 3
torque_constant_nm_per_a = 1.35
inertia_kgm2 = 0.0015
viscous_nms_per_rad = 0.0005
current_max_a = 28.0
pwm_frequency_hz = 8000.0

[current_loop]
time_constant_s = 0.0004

[mechanics]
model = "rigid"
lead_m = 0.010
load_inertia_kgm2 = 0.0004

[table]
mass_kg = 350.0
travel_m = 0.51
limit_switch_overtravel_m = 0.035
end_stop_overtravel_m = 0.07

[sensors]
encoder_counts_per_rev = 1073741824
scale_resolution_m = 0.0

[simulation]
substep_s = 1.0e-6

[controller]
speed_cycle_ratio = 1
position_cycle_ratio = 1
ipo_cycle_ratio = 32
feedback = "motor"
kv_m_min_per_mm = 12.0
speed_ff = false
speed_kp_nms_per_rad = 1.2
speed_tn_s = 0.010
max_velocity_mm_min = 30000.0
max_acceleration_m_s2 = 2.0
"""


@pytest.fixture(scope="module")
def linear_cfg(tmp_path_factory) -> MachineConfig:
    path = tmp_path_factory.mktemp("linear") / "linear.toml"
    path.write_text(LINEAR_MACHINE)
    return load_machine(path)


class Loop(NamedTuple):
    """A discrete state-space system x' = A x + B r, y = C x + D r at period ``dt``.

    State (iq, w, theta, theta_prev, I); outputs (w_act in rad/s, iq_set in A, x_act in m).
    """
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    dt: float


def plant_zoh(cfg: MachineConfig, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """ZOH discretisation of iq' = (u - iq)/T_cl, J w' = K_t iq - c w, theta' = w, with J
    the motor, load and table inertia (table through the lead) from the machine file."""
    mo = cfg.motor
    ratio = cfg.mechanics.lead_m / (2.0 * math.pi)
    J = mo.inertia_kgm2 + cfg.mechanics.load_inertia_kgm2 + cfg.table.mass_kg * ratio ** 2
    c, kt, tcl = mo.viscous_nms_per_rad, mo.torque_constant_nm_per_a, \
        cfg.current_loop.time_constant_s
    A = np.array([[-1.0 / tcl, 0.0, 0.0], [kt / J, -c / J, 0.0], [0.0, 1.0, 0.0]])
    B = np.array([[1.0 / tcl], [0.0], [0.0]])
    Ad, Bd, *_ = scipy.signal.cont2discrete((A, B, np.eye(3), np.zeros((3, 1))), dt, "zoh")
    return Ad, Bd[:, 0]


def closed_loop(cfg: MachineConfig, dt: float, position: bool) -> Loop:
    """The lock-step cascade as one linear discrete system; the input is the speed setpoint
    (rad/s) or, with ``position``, the position setpoint (m).

    Per tick k the controller reads the encoder angle theta_k that ends the previous PWM
    period, w_act = (theta_k - theta_{k-1}) / T, w_set = r (or K_v (r - l theta_k) / l with
    l = lead / 2 pi), e = w_set - w_act, torque = kp e + I, I += kp T / tn e (after the
    output), and iq_set = torque / K_t is held by the plant over period k.
    """
    sec = load_controller(cfg)
    kt = cfg.motor.torque_constant_nm_per_a
    ratio = cfg.mechanics.lead_m / (2.0 * math.pi)
    kv = sec.kv_m_min_per_mm * 1000.0 / 60.0
    kp, ki = sec.speed_kp_nms_per_rad, sec.speed_kp_nms_per_rad * dt / sec.speed_tn_s
    w_act = np.array([0.0, 0.0, 1.0 / dt, -1.0 / dt, 0.0])
    if position:
        e_x, e_r = np.array([0.0, 0.0, -kv, 0.0, 0.0]) - w_act, kv / ratio
    else:
        e_x, e_r = -w_act, 1.0
    integ = np.eye(5)[4]
    u_x, u_r = (kp * e_x + integ) / kt, kp * e_r / kt
    Ad, Bd = plant_zoh(cfg, dt)
    A = np.zeros((5, 5))
    A[:3, :3] = Ad
    A[:3] += np.outer(Bd, u_x)
    A[3, 2] = 1.0
    A[4] = integ + ki * e_x
    B = np.concatenate([Bd * u_r, [0.0, ki * e_r]])[:, None]
    C = np.vstack([w_act, u_x, [0.0, 0.0, ratio, 0.0, 0.0]])
    D = np.array([[0.0], [u_r], [0.0]])
    return Loop(A, B, C, D, dt)


def simulate(loop: Loop, r: np.ndarray) -> np.ndarray:
    """Outputs (n, 3) of ``loop`` from rest for the input sequence ``r``."""
    _, y, _ = scipy.signal.dlsim((loop.A, loop.B, loop.C, loop.D, loop.dt), r)
    return y


def figures(t: np.ndarray, y: np.ndarray, step: float) -> tuple[float, float]:
    """(10-90 % rise time in s, overshoot in % of the step) of a response from 0; the
    overshoot counts from the record's final value, its mean over the last tenth."""
    rel = y / step
    final = np.mean(rel[-max(1, rel.size // 10):])
    return float(t[np.argmax(rel >= 0.9)] - t[np.argmax(rel >= 0.1)]), 100.0 * (rel.max() - final)


def assert_matches(sim: SimResult, signal: str, reference: np.ndarray, scale: float,
                   tol: float) -> None:
    """``sim[signal]`` equals ``reference`` sample by sample within ``tol * scale``."""
    err = np.abs(sim[signal] - reference)
    k = int(np.argmax(err))
    assert err[k] <= tol * scale, (f"{signal} tick {k}: {sim[signal][k]:.9g} vs linear "
                                   f"{reference[k]:.9g} (error {err[k] / scale:.2e} of {scale:g})")


def test_speed_step_matches_the_exact_discrete_loop(linear_cfg):
    """A 0.6 m/min speed step on the linear variant against the discrete closed loop:
    w_act and iq_set agree sample by sample within 1e-3 of their step sizes; rise time
    within one PWM period, overshoot (~16 %) within 0.1 percentage point.

    The residual (~3e-4) is the plant's semi-implicit Euler against the reference's exact
    ZOH: the torque takes the current at the end of each sub-step and the angle the speed
    at its end, so the plant runs about one sub-step (1 us) ahead; the sample error is
    about that time shift times the response's steepest slope (w_c ~ 500 rad/s), and it
    halves each time the sub-step does.
    """
    step = 0.01  # m/s at the table
    res = speed_step(linear_cfg, step, duration_s=0.05)
    sim = res.sim
    y = simulate(closed_loop(linear_cfg, sim.period_s, position=False), sim["w_set"])
    w_step = step / sim.ratio
    assert_matches(sim, "w_act", y[:, 0], w_step, 1e-3)
    assert_matches(sim, "iq_set", y[:, 1], np.abs(y[:, 1]).max(), 1e-3)
    post = res.t_s >= 0.0
    rise, overshoot = figures(res.t_s[post], y[post, 0] * sim.ratio, step)
    assert overshoot > 5.0  # the comparison sees the loop's dynamics, not a flat line
    assert res.rise_time_s == pytest.approx(rise, abs=sim.period_s)
    assert res.overshoot_pct == pytest.approx(overshoot, abs=0.1)


def test_position_step_matches_the_exact_discrete_loop(linear_cfg):
    """A 0.05 mm position step on the single-rate linear variant (K_v = 12 (m/min)/mm
    around the speed loop) against the discrete closed loop: x_act within 1e-3 of the
    step sample by sample, rise time within one period, overshoot (~5.5 %) within 0.1
    percentage point.  Residual as in the speed step (sub-step timing of the plant)."""
    step = 5e-5
    res = position_step(linear_cfg, 0.0, step, duration_s=0.1)
    sim = res.sim
    y = simulate(closed_loop(linear_cfg, sim.period_s, position=True), sim["x_set"])
    assert_matches(sim, "x_act", y[:, 2], step, 1e-3)
    rise, overshoot = figures(res.t_s, y[:, 2], step)
    assert overshoot > 2.0
    assert res.rise_time_s == pytest.approx(rise, abs=sim.period_s)
    assert res.overshoot_pct == pytest.approx(overshoot, abs=0.1)


def test_speed_comparison_resolves_one_tick(linear_cfg):
    """The comparison can fail: the reference moved by one tick (a timing convention off by
    one PWM period) misses the simulation by more than ten times the 1e-3 tolerance."""
    step = 0.01
    sim = speed_step(linear_cfg, step, duration_s=0.02).sim
    y = simulate(closed_loop(linear_cfg, sim.period_s, position=False), sim["w_set"])
    late = np.concatenate([[0.0], y[:-1, 0]])
    assert np.abs(sim["w_act"] - late).max() > 1e-2 * step / sim.ratio


# ---------------------------------------------------------------- blocks

T_BLOCK = 125e-6


def biquad_response(f: np.ndarray, bq) -> np.ndarray:
    """freqz of a Biquad's coefficients at the frequencies ``f`` (Hz)."""
    _, h = scipy.signal.freqz([bq.b0, bq.b1, bq.b2], [1.0, bq.a1, bq.a2], worN=f,
                              fs=1.0 / T_BLOCK)
    return h


def prewarped(f: np.ndarray, f0: float) -> np.ndarray:
    """The analogue frequency, in units of w0, that the bilinear transform prewarped at f0
    maps the digital frequency f to: tan(pi f T) / tan(pi f0 T)."""
    return np.tan(np.pi * f * T_BLOCK) / math.tan(math.pi * f0 * T_BLOCK)


def crossing(h_of_f, f_lo: float, f_hi: float, level: float) -> float:
    """The frequency in (f_lo, f_hi) where |h| crosses ``level``."""
    return scipy.optimize.brentq(lambda f: abs(h_of_f(np.array([f]))[0]) - level, f_lo, f_hi,
                                 xtol=1e-9)


def test_lowpass2_is_the_prewarped_pt2():
    """PT2 at 300 Hz, D = 0.7: freqz equals 1 / (x^2 (j)^2 + 2 D j x + 1) at the prewarped
    x to 1e-9 everywhere; |H(f0)| = 1/(2D) at -90 deg; the -3 dB point is the analogue one,
    x3 = sqrt(1 - 2D^2 + sqrt((1 - 2D^2)^2 + 1)), mapped back through the prewarping."""
    f0, d = 300.0, 0.7
    bq = lowpass2(f0, d, T_BLOCK)
    f = np.linspace(1.0, 0.45 / T_BLOCK, 2000)
    jx = 1j * prewarped(f, f0)
    np.testing.assert_allclose(biquad_response(f, bq), 1.0 / (jx * jx + 2 * d * jx + 1.0),
                               atol=1e-9)
    h0 = biquad_response(np.array([f0]), bq)[0]
    assert abs(h0) == pytest.approx(1.0 / (2 * d), rel=1e-9)
    assert np.angle(h0, deg=True) == pytest.approx(-90.0, abs=1e-6)
    x3 = math.sqrt(1 - 2 * d * d + math.sqrt((1 - 2 * d * d) ** 2 + 1))
    f3 = math.atan(x3 * math.tan(math.pi * f0 * T_BLOCK)) / (math.pi * T_BLOCK)
    measured = crossing(lambda fr: biquad_response(fr, bq), 10.0, 3000.0, 2 ** -0.5)
    assert measured == pytest.approx(f3, rel=1e-6)


def test_notch_depth_and_width():
    """Notch at 400 Hz, 80 Hz wide, -20 dB: freqz equals the prewarped analogue section to
    1e-9; the depth at f0 is -20 dB; the -3 dB edges are the analogue ones,
    x = sqrt(c^2 + 1) -+ c with c = D_p sqrt(1 - 2 g^2) (g the depth as a gain), mapped
    through the prewarping, and the width is the bandwidth within 3 % (the analogue
    sqrt(1 - 2 g^2) = 0.99 and the warping of the edges)."""
    f0, bw, depth = 400.0, 80.0, -20.0
    bq = notch(f0, bw, depth, T_BLOCK)
    dp = bw / (2 * f0)
    g = 10 ** (depth / 20)
    f = np.linspace(1.0, 0.45 / T_BLOCK, 2000)
    jx = 1j * prewarped(f, f0)
    analogue = (jx * jx + 2 * dp * g * jx + 1.0) / (jx * jx + 2 * dp * jx + 1.0)
    np.testing.assert_allclose(biquad_response(f, bq), analogue, atol=1e-9)
    h0 = biquad_response(np.array([f0]), bq)[0]
    assert 20 * math.log10(abs(h0)) == pytest.approx(depth, abs=1e-9)
    lo = crossing(lambda fr: biquad_response(fr, bq), 100.0, f0, 2 ** -0.5)
    hi = crossing(lambda fr: biquad_response(fr, bq), f0, 1000.0, 2 ** -0.5)
    c = dp * math.sqrt(1 - 2 * g * g)
    edges = np.array([math.sqrt(c * c + 1) - c, math.sqrt(c * c + 1) + c])
    np.testing.assert_allclose(prewarped(np.array([lo, hi]), f0), edges, rtol=1e-6)
    assert hi - lo == pytest.approx(bw, rel=0.03)


def test_zero_frequency_filters_pass_the_signal():
    """f = 0 disables the PT2 and the notch: the section is the identity."""
    for bq in (lowpass2(0.0, 0.7, T_BLOCK), notch(0.0, 50.0, -40.0, T_BLOCK)):
        assert [bq.step(x) for x in (1.0, -2.5, 3.0)] == [1.0, -2.5, 3.0]


def test_pi_output_and_anti_windup():
    """kp = 2, tn = 10 ms, T = 1 ms (ki T = 0.2), limit 1, by hand: in range u = kp e + I
    with I updated after the output; saturated, the integrator freezes while the error
    pushes further and moves as soon as the error pulls back."""
    pi = PI(2.0, 0.01, 0.001, 1.0)
    assert pi.step(0.1) == pytest.approx(0.2)
    assert pi.step(0.1) == pytest.approx(0.22)
    assert pi.integ == pytest.approx(0.04)
    for _ in range(100):
        assert pi.step(5.0) == 1.0
    assert pi.integ == pytest.approx(0.04)
    assert pi.step(-0.1) == pytest.approx(-0.16)
    assert pi.integ == pytest.approx(0.02)
    pi.integ = 3.0
    assert pi.step(-0.5) == 1.0   # 3 - 1 = 2 is above the limit ...
    assert pi.integ == pytest.approx(2.9)  # ... but the error pulls back: integrate
    for _ in range(10):
        assert pi.step(-5.0) == -1.0  # -10 + 2.9: negative limit, error pushing further
    assert pi.integ == pytest.approx(2.9)


def test_pt1_step_is_exact():
    """PT1 with tau = 10 ms at T = 1 ms: y_k = 1 - exp(-k T / tau) for a unit step, to
    1e-12; tau = 0 passes the input."""
    pt1 = PT1(0.01, 0.001)
    y = [pt1.step(1.0) for _ in range(50)]
    np.testing.assert_allclose(y, 1.0 - np.exp(-np.arange(1, 51) * 0.1), atol=1e-12)
    assert PT1(0.0, 0.001).step(0.7) == 0.7


# ---------------------------------------------------------------- drive and enable


def drive_state(ls: LockStep) -> State:
    """The state the drive's last statusword reports."""
    return statusword_state(ls.fb.statusword)


def assert_torque_off(ls: LockStep) -> None:
    """The drive passes no enable, no current setpoint and no voltage to the plant."""
    inp = ls.plant.inp
    assert inp[L.I_ENABLE] == 0.0 and inp[L.I_IQ_REF] == 0.0 and inp[L.I_ID_REF] == 0.0
    assert ls.plant.output("ud_v") == 0.0 and ls.plant.output("uq_v") == 0.0


def test_enable_sequence_reaches_operation_enabled_with_torque_off_before():
    """The controller's enable sequence takes the drive through SWITCH ON DISABLED, READY
    TO SWITCH ON and SWITCHED ON to OPERATION ENABLED (CiA 402 transitions 1, 2, 3, 4);
    before OPERATION ENABLED the plant's power stage is off."""
    ls = LockStep(load_machine(ARROW), 0.25)
    seen = []
    for _ in range(20):
        ls.tick()
        state = drive_state(ls)
        if not seen or seen[-1] != state:
            seen.append(state)
        if state != State.OPERATION_ENABLED:
            assert_torque_off(ls)
        if ls.ctrl.enabled:
            break
    assert seen == [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                    State.OPERATION_ENABLED]
    assert ls.ctrl.enabled and ls.plant.inp[L.I_ENABLE] == 1.0


def test_plant_fault_faults_the_drive_the_nc_disables_it_and_its_reset_re_enables():
    """A NaN in the plant's state: the drive reports FAULT (statusword bit 3, its error
    code FF01h on the wire) with the power stage off, and the NC raises alarm 25201 and
    disables it.  The NC's RESET then takes it through the fault-reset edge (transition
    15) and 2, 3, 4 to OPERATION ENABLED again, and the axis holds its position."""
    x0 = 0.25
    ls = LockStep(load_machine(ARROW), x0)
    ls.enable()
    ls.run(0.01)
    ls.plant.state[int(ls.plant.params[L.P_SOFF_ROT])] = math.nan  # the rotor angle
    for _ in range(5):
        ls.tick()
    assert drive_state(ls) == State.FAULT
    assert ls.fb.statusword & SW_FAULT
    assert ls.fb.fault == 0xFF01
    assert_torque_off(ls)
    assert [a.number for a in ls.ctrl.alarms.alarms] == [25201] and not ls.ctrl.enabled
    ls.ctrl.reset_alarms()
    seen = []
    for _ in range(20):
        ls.tick()
        if not seen or seen[-1] != drive_state(ls):
            seen.append(drive_state(ls))
    assert ls.ctrl.enabled
    assert seen == [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                    State.OPERATION_ENABLED]
    hold = ls.run(0.05)
    assert ls.fb.fault == 0
    assert np.abs(hold["x_act"] - x0).max() < 1e-6
