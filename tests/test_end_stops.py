"""Mechanical end stops and limit switches (plant.end_stops, plant.effects.end_stop).

References, each independent of the kernel:
* static: Hooke, a constant force F into a stop settles at the penetration F/k;
* impact: the unilateral Kelvin-Voigt contact in closed form.  While it pushes, the
  contact is the bilateral m x'' = -k x - c x'; the clamp ends it where the force
  k x + c x' (= -m x'') reaches zero, at omega_d t = 2 arccos(zeta), and the table leaves
  with e = exp(-2 zeta arccos(zeta) / sqrt(1 - zeta^2)) of its speed, more than the
  bilateral model's exp(-zeta pi / sqrt(1 - zeta^2)), whose damper pulls the table back
  while it leaves.  A scipy solve_ivp of the same clamped contact checks the closed form;
* runaway at the current limit: static equilibrium with the stall force K_t I_max / ratio,
  and the rigid-body energy bound of the impact, F x + 1/2 M v^2 >= 1/2 k x^2;
* the ringing of an axis held against a stop: the damped eigenvalues of the linearised
  mechanics with the stop as a spring and damper (mechanics_matrices);
* the sub-step: the stability bound of semi-implicit Euler on a damped oscillator,
  (sqrt(k/m) + c/m) dt < 2, and the chains' natural frequencies without the stops.
"""

import math
import re

import numpy as np
import pytest
import scipy.integrate
import tomllib
from hypothesis import given, settings
from hypothesis import strategies as st

from hil.validate.experiments.electrical import NO_COGGING, merged
from plant import ConfigError, Plant
from plant import layout as L
from plant.assemble import mechanics_matrices, natural_frequencies, reflected_inertia
from plant.config import load_machine, parse_machine, schema_rows
from plant.end_stops import AUTO_DAMPING_RATIO
from plant.machines import load_machine_set
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
LINEAR = CONFIGS / "ld386_linear.toml"
#: the linear motor without friction and cogging: a bare mass on the stops
BARE = {"friction": {"viscous_ns_per_m": 0.0, "coulomb_n": 0.0, "breakaway_n": 0.0,
                     "zero_velocity_band_m_s": 0.0},
        "cogging": {"orders": [], "amplitudes_n": [], "phases_deg": []}}


def _two_mass_arrow():
    """The Arrow 500 X as a two-mass model: the screw's inertia joins the load side."""
    raw = tomllib.loads(ARROW.read_text())
    sc = raw.pop("screw")
    j_screw = 7850.0 * math.pi * sc["diameter_m"] ** 4 / 32.0 * sc["length_m"]  # steel
    raw["mechanics"] = {"model": "two_mass", "lead_m": raw["mechanics"]["lead_m"],
                        "load_inertia_kgm2": j_screw}
    return parse_machine(raw, f"{ARROW} (two-mass variant)")


def _stall_force(plant: Plant) -> float:
    """N: the motor's force on the table at the current limit, K_t I_max / ratio."""
    mo = plant.config.motor
    kt = mo.force_constant_n_per_a if plant.config.machine.kind == "linear" \
        else mo.torque_constant_nm_per_a
    return kt * mo.current_max_a / plant.built.ratio


def _impact_bound(plant: Plant, v_impact: float) -> float:
    """m: the rigid-body energy bound on the penetration of a table driven by the stall
    force F into its stop at ``v_impact`` (m/s), F x + M v^2/2 >= k x^2/2, so x <= 2 F/k +
    v sqrt(M/k), M every inertia the motor moves (reflected to the table).  The kernel's
    symplectic Euler keeps a modified energy instead, whose amplitude on the contact
    spring is larger by 1/sqrt(1 - (omega dt)^2/4) (omega = sqrt(k/M), dt the sub-step;
    1.4 % at omega dt = 0.33): the bound carries that factor."""
    k = plant.built.end_stops.stiffness
    mass = reflected_inertia(plant.config) / plant.built.ratio ** 2
    omega_dt = math.sqrt(k / mass) * plant.dt
    discrete = 1.0 / math.sqrt(1.0 - omega_dt ** 2 / 4.0)
    return (2.0 * _stall_force(plant) / k + v_impact * math.sqrt(mass / k)) * discrete


# --- the contact law ----------------------------------------------------------------------

@pytest.mark.parametrize("path", [LINEAR, ARROW], ids=["linear", "screw"])
@pytest.mark.parametrize("side", [1.0, -1.0], ids=["pos", "neg"])
def test_constant_force_settles_at_penetration_f_over_k(path, side):
    """Hooke: a constant force F (the plant input load) pushing the table into a stop,
    motor off and no friction, settles at the penetration F/k; the stop's force is -F."""
    over = BARE if path == LINEAR else merged(NO_COGGING, {
        "friction": {"viscous_ns_per_m": 0.0, "coulomb_n": 0.0, "breakaway_n": 0.0}})
    probe = Plant.from_file(path, overrides=over)
    stops = probe.built.end_stops
    stop = stops.stop_pos if side > 0 else stops.stop_neg
    plant = Plant(probe.config, table_pos=stop)
    force = 2000.0
    plant.set_input(enable=0.0, load=side * force)
    trace = plant.run(int(0.5 / plant.pwm_period), plant.sub_per_pwm)
    assert np.all(trace["status"] == L.STATUS_OK)
    penetration = side * (trace["table_pos"][-1] - stop)
    assert penetration == pytest.approx(force / stops.stiffness, rel=1e-3)
    assert trace["end_stop_force_n"][-1] == pytest.approx(-side * force, rel=1e-3)


def test_explicit_stiffness_and_damping_are_the_contacts():
    """The file's stiffness and damping are the contact's, and a constant force settles at
    F/k with that k (Hooke)."""
    over = merged(BARE, {"table": {"end_stop_stiffness_n_per_m": 5.0e7,
                                   "end_stop_damping_ns_per_m": 2.0e4}})
    probe = Plant.from_file(LINEAR, overrides=over)
    stops = probe.built.end_stops
    assert (stops.stiffness, stops.damping) == (5.0e7, 2.0e4)
    plant = Plant(probe.config, table_pos=stops.stop_pos)
    plant.set_input(enable=0.0, load=300.0)
    plant.run(int(0.2 / plant.pwm_period), plant.sub_per_pwm)
    assert plant.output("table_pos") - stops.stop_pos == pytest.approx(300.0 / 5.0e7, rel=1e-6)


def _unilateral_restitution(zeta: float) -> float:
    """Closed form of the clamped Kelvin-Voigt contact (module docstring)."""
    return math.exp(-2.0 * zeta * math.acos(zeta) / math.sqrt(1.0 - zeta * zeta))


def _solve_ivp_restitution(zeta: float, omega: float = 400.0) -> float:
    """The same clamped contact, m x'' = max(0, k x + c x') pushing out, by solve_ivp
    (x the penetration, m = 1); the exit speed over the entry speed."""
    k, c = omega * omega, 2.0 * zeta * omega

    def rhs(_t, y):
        return [y[1], -max(0.0, k * y[0] + c * y[1]) if y[0] > 0.0 else 0.0]

    def leaves(_t, y):
        return y[0] + 1e-3  # 1 mm back outside the stop

    leaves.terminal = True
    leaves.direction = -1.0
    sol = scipy.integrate.solve_ivp(rhs, (0.0, 1.0), [0.0, 1.0], events=leaves, rtol=1e-11,
                                    atol=1e-14, max_step=1e-4)
    return -sol.y_events[0][0][1]


def _kernel_restitution(zeta: float, omega: float) -> float:
    """The rebound of the bare linear motor's table from a stop of contact frequency
    ``omega`` (rad/s) and damping ratio ``zeta``, entering half-way through a sub-step."""
    v0 = 0.2
    mass = Plant.from_file(LINEAR, overrides=BARE).built.end_stops.mass
    k = mass * omega * omega
    over = merged(BARE, {"table": {"end_stop_stiffness_n_per_m": k,
                                   "end_stop_damping_ns_per_m": 2 * zeta * math.sqrt(k * mass)}})
    probe = Plant.from_file(LINEAR, overrides=over)
    stop = probe.built.end_stops.stop_pos
    plant = Plant(probe.config, table_pos=stop - 1e-3 - 0.5 * v0 * probe.dt)
    plant.set_input(enable=0.0)
    plant.state[int(plant.params[L.P_SOFF_ROT]) + 1] = v0  # the one node's velocity
    trace = plant.run(int(0.1 / plant.pwm_period), plant.sub_per_pwm)
    assert trace["table_pos"].max() > stop
    return -trace["table_vel"][-1] / v0


@pytest.mark.parametrize("zeta", [0.05, 0.2, AUTO_DAMPING_RATIO, 0.9])
def test_impact_rebounds_with_the_unilateral_restitution(zeta):
    """A bare table hitting the stop leaves with e of its speed: e of the clamped
    Kelvin-Voigt contact in closed form and by solve_ivp, more than the bilateral model's.
    The damper's force c v switches on within a sub-step, so the kernel converges at first
    order in omega dt: at omega dt = 0.0125 within 1 %, four times closer than at 0.05."""
    e_closed = _unilateral_restitution(zeta)
    assert _solve_ivp_restitution(zeta) == pytest.approx(e_closed, rel=1e-6)
    coarse = _kernel_restitution(zeta, 400.0) / e_closed - 1.0  # omega dt = 0.05 at 125 us
    fine = _kernel_restitution(zeta, 100.0) / e_closed - 1.0
    assert abs(fine) < 0.01
    assert abs(fine) < abs(coarse) / 3.0
    assert e_closed * (1.0 + fine) > math.exp(-zeta * math.pi / math.sqrt(1.0 - zeta * zeta))


# --- runaway at the current limit ---------------------------------------------------------

def _runaway_configs():
    return [load_machine(ARROW), load_machine(LINEAR), load_machine(CONFIGS / "emps.toml"),
            load_machine(CONFIGS / "xy_table_004.toml"), load_machine(CONFIGS / "tlm_rig.toml"),
            _two_mass_arrow()]


@pytest.mark.parametrize("cfg", _runaway_configs(), ids=lambda c: c.path.split("/")[-1])
@pytest.mark.parametrize("side", [1.0, -1.0], ids=["pos", "neg"])
def test_runaway_at_the_current_limit_is_held_by_the_stop(cfg, side):
    """q-current held at the limit for 3 s from mid travel: the kernel never faults, the
    table stays within the stop plus the impact's rigid-body energy bound, comes to
    rest against the stop in static equilibrium (stop + motor + friction forces = 0, the
    motor's at the stall force K_t I_max / ratio) at the penetration F_stop/k, and its
    limit switch is on exactly while the table is beyond it."""
    plant = Plant(cfg, table_pos=0.5 * cfg.table.travel_m)
    stops = plant.built.end_stops
    stop, limit = (stops.stop_pos, stops.limit_pos) if side > 0 else (stops.stop_neg,
                                                                     stops.limit_neg)
    plant.set_input(iq_ref_a=side * cfg.motor.current_max_a)
    trace = plant.run(int(3.0 / plant.pwm_period), plant.sub_per_pwm)
    assert np.all(trace["status"] == L.STATUS_OK)
    for name in ("table_pos", "table_vel", "motor_vel", "end_stop_force_n", "nut_force_n"):
        assert np.all(np.isfinite(trace[name])), name
    x = trace["table_pos"]
    penetration = side * (x - stop)
    v_impact = np.abs(trace["table_vel"][penetration <= 0.0]).max()
    assert penetration.max() <= _impact_bound(plant, v_impact)
    held = slice(int(0.9 * x.size), None)
    assert np.abs(trace["table_vel"][held]).max() < 1e-3
    f_motor = trace["torque"][held].mean() / plant.built.ratio
    f_stop = trace["end_stop_force_n"][held].mean()
    f_friction = trace["friction"][held].mean()
    f_stall = _stall_force(plant)
    assert f_motor == pytest.approx(side * f_stall, rel=0.01)
    assert f_stop + f_motor + f_friction + cfg.table.external_force_n == pytest.approx(
        0.0, abs=5e-3 * f_stall)
    assert stops.stiffness * penetration[held].mean() == pytest.approx(-side * f_stop,
                                                                       rel=1e-2)
    assert np.all(side * trace["end_stop_force_n"] <= 0.0)
    on, off = ("limit_pos", "limit_neg") if side > 0 else ("limit_neg", "limit_pos")
    np.testing.assert_array_equal(trace[on], (side * (x - limit) > 0.0).astype(float))
    assert trace[on][-1] == 1.0
    assert not trace[off].any()


def test_an_axis_held_against_the_stop_rings_at_its_mode_in_contact():
    """The Arrow 500 X driven into the stop at the current limit rings afterwards at the
    lowest mode of the linearised mechanics with the stop as a spring and damper
    (motor, coupling and screw on the nut against the held table, ~61 Hz), and decays at
    that mode's rate (the current loop holds the current: no electrical damping)."""
    plant = Plant(load_machine(ARROW), table_pos=0.5)
    stops = plant.built.end_stops
    plant.set_input(iq_ref_a=plant.config.motor.current_max_a)
    trace = plant.run(int(3.0 / plant.pwm_period), plant.sub_per_pwm)
    m, c, k = mechanics_matrices(plant.config, stops.stop_pos, stops.stiffness)
    c[-1, -1] += stops.damping
    n = m.shape[0]
    a = np.block([[np.zeros((n, n)), np.eye(n)],
                  [-np.linalg.solve(m, k), -np.linalg.solve(m, c)]])
    lam = np.linalg.eigvals(a)
    lam = lam[lam.imag > 0.0]
    first = lam[np.argmin(lam.imag)]
    t, w = trace["time_s"], trace["motor_vel"]
    ring = t > 1.0
    y = w[ring] - w[ring].mean()
    freqs = np.fft.rfftfreq(y.size, t[1] - t[0])
    peak = freqs[np.argmax(np.abs(np.fft.rfft(y * np.hanning(y.size))))]
    assert peak == pytest.approx(first.imag / (2 * math.pi), rel=0.02)
    windows = [(t > a) & (t <= a + 0.25) for a in np.arange(1.0, 2.75, 0.25)]
    rms = [w[s].std() for s in windows]
    rate = -np.polyfit(np.arange(len(rms)) * 0.25, np.log(rms), 1)[0]
    assert rate == pytest.approx(-first.real, rel=0.15)


def test_a_rotary_table_has_no_stops_and_no_switches():
    """A direct-drive rotary table turns endlessly: no stroke, every stop output 0."""
    plant = Plant.from_file(CONFIGS / "geiss_c_axis.toml")
    assert plant.built.end_stops is None and plant.params[L.P_STROKE] == 0.0
    plant.set_input(iq_ref_a=plant.config.motor.current_max_a)
    trace = plant.run(int(1.0 / plant.pwm_period), plant.sub_per_pwm)
    assert np.abs(trace["table_pos"]).max() > 2 * math.pi
    for name in ("limit_neg", "limit_pos", "end_stop_force_n"):
        assert not trace[name].any(), name


# --- the sub-step -------------------------------------------------------------------------

#: every axis of every shipped machine file and manifest, by file:axis
SHIPPED = {f"{f.name}:{a.name}": a.config
           for f in sorted(CONFIGS.glob("*.toml")) + sorted((CONFIGS / "machines").glob("*.toml"))
           for a in load_machine_set(f).axes}


@pytest.mark.parametrize("cfg", list(SHIPPED.values()), ids=list(SHIPPED))
def test_automatic_stops_keep_every_shipped_configs_substeps(cfg):
    """The sub-step of the chains alone (highest natural frequency over the travel, the
    docs/model.md's rule n = ceil(T_pwm omega_max / max_omega_dt)) is the plant's: the automatic
    stops add no sub-step, and their contact stays within omega dt <= max_omega_dt."""
    period = 1.0 / cfg.motor.pwm_frequency_hz
    if cfg.mechanics.model == "screw":
        w = max(natural_frequencies(cfg, x)[-1] for x in np.linspace(0, cfg.table.travel_m, 5))
    else:
        w = natural_frequencies(cfg)[-1]
    plant = Plant(cfg)
    assert plant.sub_per_pwm == max(1, math.ceil(period * w / cfg.simulation.max_omega_dt))
    assert plant.built.omega_max * plant.dt <= cfg.simulation.max_omega_dt
    if plant.built.end_stops is not None:
        assert plant.built.end_stops.rate * plant.dt <= cfg.simulation.max_omega_dt


def _largest_in(message: str) -> float:
    return float(re.search(r"at most (\S+) N/m fits", message).group(1))


@pytest.mark.parametrize("damping", [0.0, 3000.0], ids=["auto-damping", "given-damping"])
def test_too_stiff_a_stop_for_the_pwm_period_is_refused_with_the_largest_that_fits(damping):
    """With the sub-step at the PWM period, a stop whose contact breaks semi-implicit
    Euler's bound (sqrt(k/m) + c/m) dt < 2 is refused naming the file, the key and the
    largest stiffness that fits: m ((2 - c dt/m) / dt)^2, or with the automatic damping
    c = 2 zeta sqrt(k m), m (2 / ((1 + 2 zeta) dt))^2; that value loads, 1 % more does not."""
    period = 1.0 / load_machine(LINEAR).motor.pwm_frequency_hz
    base = {"simulation": {"substep_s": period},
            "table": {"end_stop_damping_ns_per_m": damping}}
    mass = Plant.from_file(LINEAR, overrides=base).built.end_stops.mass
    if damping:
        k_max = mass * ((2.0 - damping * period / mass) / period) ** 2
    else:
        k_max = mass * (2.0 / ((1.0 + 2.0 * AUTO_DAMPING_RATIO) * period)) ** 2
    with pytest.raises(ConfigError) as err:
        Plant.from_file(LINEAR, overrides=merged(base, {"table": {
            "end_stop_stiffness_n_per_m": 1e10}}))
    message = str(err.value)
    assert "ld386_linear.toml" in message and "[table] end_stop_stiffness_n_per_m" in message
    assert _largest_in(message) == pytest.approx(k_max, rel=2e-3)
    fits = Plant.from_file(LINEAR, overrides=merged(base, {"table": {
        "end_stop_stiffness_n_per_m": 0.998 * k_max}}))
    assert fits.sub_per_pwm == 1
    with pytest.raises(ConfigError, match="too stiff"):
        Plant.from_file(LINEAR, overrides=merged(base, {"table": {
            "end_stop_stiffness_n_per_m": 1.01 * k_max}}))


def test_too_much_damping_for_the_pwm_period_is_refused_naming_its_bound():
    """A damper alone beyond c dt/m < 2 (explicit Euler on m v' = -c v) fits no stiffness:
    the refusal names the damping's bound 2 m / dt."""
    period = 1.0 / load_machine(LINEAR).motor.pwm_frequency_hz
    mass = Plant.from_file(LINEAR).built.end_stops.mass
    with pytest.raises(ConfigError) as err:
        Plant.from_file(LINEAR, overrides={"simulation": {"substep_s": period}, "table": {
            "end_stop_damping_ns_per_m": 2.5 * mass / period}})
    bound = re.search(r"end_stop_damping_ns_per_m must be < 2 m / dt = (\S+) N\*s/m",
                      str(err.value))
    assert float(bound.group(1)) == pytest.approx(2.0 * mass / period, rel=1e-3)


def test_too_stiff_a_stop_on_the_screw_is_refused_at_its_explicit_substep():
    """The screw model's explicit sub-step: the refusal names the largest stiffness that
    fits, and that value loads."""
    period = 1.0 / load_machine(ARROW).motor.pwm_frequency_hz
    base = {"simulation": {"substep_s": period / 8}}
    with pytest.raises(ConfigError) as err:
        Plant.from_file(ARROW, overrides=merged(base, {"table": {
            "end_stop_stiffness_n_per_m": 1e13}}))
    k_max = _largest_in(str(err.value))
    fits = Plant.from_file(ARROW, overrides=merged(base, {"table": {
        "end_stop_stiffness_n_per_m": 0.998 * k_max}}))
    assert fits.built.omega_max * fits.dt < 2.0


def test_a_stiff_explicit_stop_takes_more_substeps():
    """With the automatic sub-step, an explicit stiffness gets the sub-steps it needs:
    n = ceil(T_pwm (1 + 2 zeta) sqrt(k/m) / max_omega_dt) on the bare linear motor."""
    k = 1e10
    plant = Plant.from_file(LINEAR, overrides={"table": {"end_stop_stiffness_n_per_m": k}})
    cfg, mass = plant.config, plant.built.end_stops.mass
    rate = (1.0 + 2.0 * AUTO_DAMPING_RATIO) * math.sqrt(k / mass)
    assert plant.sub_per_pwm == math.ceil(rate / (cfg.motor.pwm_frequency_hz
                                                  * cfg.simulation.max_omega_dt))


# --- the machine file ---------------------------------------------------------------------

def test_limit_switches_beyond_the_stops_are_refused():
    """The switches must trip before the stops: refused naming the file, key and unit."""
    with pytest.raises(ConfigError, match=r"ld386_linear\.toml: \[table\] "
                                          r"limit_switch_overtravel_m = 0\.03 m must be < "
                                          r"end_stop_overtravel_m = 0\.03 m"):
        load_machine(LINEAR, {"table": {"limit_switch_overtravel_m": 0.03,
                                        "end_stop_overtravel_m": 0.03}})


def test_the_stop_keys_are_documented_with_their_units():
    """hil config-keys reads the schema: the four keys with their units."""
    rows = {r["key"]: r for r in schema_rows() if r["section"] == "table"}
    assert {k: rows[k]["unit"] for k in ("end_stop_overtravel_m", "limit_switch_overtravel_m",
                                         "end_stop_stiffness_n_per_m",
                                         "end_stop_damping_ns_per_m")} == {
        "end_stop_overtravel_m": "m", "limit_switch_overtravel_m": "m",
        "end_stop_stiffness_n_per_m": "N/m", "end_stop_damping_ns_per_m": "N*s/m"}


# --- property ---------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(path=st.sampled_from([LINEAR, CONFIGS / "xy_table_004.toml", ARROW]),
       stiffness=st.one_of(st.just(0.0), st.floats(3.0, 13.0).map(lambda e: 10.0 ** e)),
       damping=st.one_of(st.just(0.0), st.floats(0.0, 6.0).map(lambda e: 10.0 ** e)),
       overtravel=st.floats(1e-3, 0.1), switch_share=st.floats(0.0, 0.99),
       side=st.sampled_from([1.0, -1.0]))
def test_random_stops_keep_the_state_finite(path, stiffness, damping, overtravel,
                                            switch_share, side):
    """Any stiffness, damping and overtravel in their ranges: a runaway into the stop
    stays finite, never faults and stays within the impact's energy bound."""
    table = {"end_stop_stiffness_n_per_m": stiffness, "end_stop_damping_ns_per_m": damping,
             "end_stop_overtravel_m": overtravel,
             "limit_switch_overtravel_m": switch_share * overtravel}
    cfg = load_machine(path, {"table": table})
    start = cfg.table.travel_m if side > 0 else 0.0
    plant = Plant(cfg, table_pos=start)
    stops = plant.built.end_stops
    plant.set_input(iq_ref_a=side * cfg.motor.current_max_a)
    trace = plant.run(int(0.3 / plant.pwm_period), plant.sub_per_pwm)
    assert np.all(trace["status"] == L.STATUS_OK)
    assert np.all(np.isfinite(plant.state))
    stop = stops.stop_pos if side > 0 else stops.stop_neg
    bound = _impact_bound(plant, np.abs(trace["table_vel"]).max())
    assert (side * (trace["table_pos"] - stop)).max() <= bound
