"""Mechanical validation: the kernel's chains against analytic mechanics, the linearised
matrices of :mod:`plant.assemble`, a second ODE solver and the TLM solver.

The Arrow 500 X axis (seed 000) is the test machine.  Variants of its machine
file (rigid, two-mass, undamped, torque-free) are built in memory from the
parsed TOML, so every run goes through the same checks as a user's file.
"""

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.integrate
import scipy.linalg

from hil.validate import plots
from hil.validate.core import VERIFICATION, Result, experiment, within
from hil.validate.experiments.variants import (
    ARROW,
    HELD_MOTOR_KGM2,
    ScrewState,
    crossing_frequency,
    frictionless,
    lumped_variant,
    machine_raw,
    mean_acceleration,
    plant_of,
    rigid_inertia,
    screw_energy,
    torque_free,
    undamped,
    with_keys,
)
from plant import Plant
from plant import layout as L
from plant.assemble import build_chains, mechanics_matrices, natural_frequencies
from plant.config import load_machine


@experiment("rigid_acceleration", "000")
def rigid_acceleration(out_dir: Path | None) -> list[Result]:
    """Rigid Arrow axis, friction off: constant torque (first-order and d-q current loops)
    and a constant table force give the analytic acceleration T / J_total.

    The d-q case is compared with the mean electromagnetic torque the kernel reports: the
    drive's PI current loop has no back-EMF decoupling, so under the ramping back-EMF it
    settles about 0.8 A below the 2 A setpoint (steady error of a type-1 loop to a ramp).
    """
    base = frictionless(lumped_variant(machine_raw(), "rigid"))
    cases = (
        ("first-order current 2 A", torque_free(base), {"iq_ref_a": 2.0}),
        ("d-q FOC current 2 A (T: mean reported torque)", with_keys(base, {"cogging": None}),
         {"iq_ref_a": 2.0}),
        ("table force 500 N, no current", torque_free(base), {"load": 500.0}),
    )
    rows, traces = [], []
    for name, raw, inputs in cases:
        plant = plant_of(raw, f"{ARROW} (rigid variant)")
        j_total = rigid_inertia(plant)
        acc, torque, status, tr = mean_acceleration(plant, inputs, 0.02, 0.06)
        if plant.config.motor.model == "first_order":
            torque = plant.config.motor.torque_constant_nm_per_a * inputs.get("iq_ref_a", 0.0)
        ref = (torque + inputs.get("load", 0.0) * plant.built.ratio) / j_total
        rows.append(Result(f"rigid: acceleration, {name}", ref, acc, "rad/s^2",
                           status == 0 and within(acc, ref, rel=2e-3),
                           "analytic: T / (J_m + J_load + m (lead/2pi)^2)", "±0.2 %",
                           VERIFICATION))
        traces.append((name, tr))
    if out_dir is not None:
        fig, ax = plots.new_figure(1, 1, "Rigid Arrow axis: motor speed under constant drive")
        for name, tr in traces:
            ax[0, 0].plot(tr["time_s"] * 1e3, tr["motor_vel"], label=name)
        ax[0, 0].set(xlabel="time (ms)", ylabel="motor speed (rad/s)")
        ax[0, 0].legend()
        plots.save(fig, out_dir, "rigid_acceleration")
    return rows


# --- 2. two-mass resonance ---------------------------------------------------------------------

def free_vibration(plant: Plant, node: int, twist: float, periods: float, f_guess: float):
    """Twist torsional node ``node`` by ``twist`` (rad) from rest, let go, and return
    (time in s, velocity in rad/s of the node's far end: motor node 0, or the last node when
    ``node`` is 0), the worst status."""
    p, s = plant.params, plant.state
    ro, nr = int(p[L.P_SOFF_ROT]), int(p[L.P_N_ROT])
    s[ro + node] += twist
    watch = ro + nr + (nr - 1 if node == 0 else 0)
    n_calls = int(periods / (f_guess * plant.dt)) + 1
    t, v = np.empty(n_calls), np.empty(n_calls)
    status = 0
    for k in range(n_calls):
        status = max(status, plant.step(1))
        t[k], v[k] = s[L.S_TIME], s[watch]
    return t, v, status


@experiment("two_mass_resonance", "000")
def two_mass_resonance(out_dir: Path | None) -> list[Result]:
    """Two-mass Arrow axis, undamped and frictionless: free vibration of motor against load
    at w_r = sqrt(k (J1+J2)/(J1 J2)); with the rotor held (10^7 x inertia) the load swings
    at the anti-resonance w_a = sqrt(k/J2), the zero of the torque-to-motor-speed response."""
    # assumed: omega*dt <= 0.05 keeps the symplectic-Euler frequency error below 1e-4
    raw = with_keys(undamped(torque_free(lumped_variant(machine_raw(), "two_mass"))),
                    {"simulation": {"max_omega_dt": 0.05}})
    free = plant_of(raw, f"{ARROW} (two-mass variant)")
    held = plant_of(with_keys(raw, {"motor": {"inertia_kgm2": HELD_MOTOR_KGM2}}),
                    f"{ARROW} (two-mass variant, rotor held)")
    cfg = free.config
    half_hub = 0.5 * cfg.coupling.inertia_kgm2  # the coupling's hubs, one on each side
    j1 = cfg.motor.inertia_kgm2 + half_hub
    r = cfg.mechanics.lead_m / (2.0 * math.pi)
    j2 = half_hub + cfg.mechanics.load_inertia_kgm2 + cfg.table.mass_kg * r * r
    k = cfg.coupling.stiffness_nm_per_rad
    refs = {"resonance": math.sqrt(k * (j1 + j2) / (j1 * j2)),
            "anti-resonance": math.sqrt(k / j2)}
    rows, curves = [], []
    for (name, ref), plant, node in zip(refs.items(), (free, held), (1, 0)):
        t, v, status = free_vibration(plant, node, 1e-3, 20.0, ref / (2 * math.pi))
        f_model = crossing_frequency(t, v)
        f_ref = ref / (2.0 * math.pi)
        rows.append(Result(f"two-mass: {name} frequency", f_ref, f_model, "Hz",
                           status == 0 and within(f_model, f_ref, rel=1e-3),
                           "analytic: sqrt(k (J1+J2)/(J1 J2)), sqrt(k/J2)", "±0.1 %",
                           VERIFICATION))
        curves.append((name, t, v))
    if out_dir is not None:
        fig, ax = plots.new_figure(1, 1, "Two-mass Arrow axis: free vibration")
        for name, t, v in curves:
            ax[0, 0].plot(t * 1e3, v / np.abs(v).max(), label=name)
        ax[0, 0].set(xlabel="time (ms)", ylabel="speed (normalised)")
        ax[0, 0].legend()
        plots.save(fig, out_dir, "two_mass_resonance")
    return rows


# --- 3. screw modes ---------------------------------------------------------------------------

def clamped_first_frequency(m: np.ndarray, k_link: np.ndarray, first_free: int) -> float:
    """First natural frequency (Hz) of a chain with nodes before ``first_free`` clamped.

    Args:
        m: node inertias, shape (n,); k_link: link stiffnesses, shape (n-1,).
    Tridiagonal stiffness assembled here, independently of plant.assemble.
    """
    mm = m[first_free:]
    k_left = k_link[first_free - 1:]
    k_right = np.append(k_link[first_free:], 0.0)
    kk = np.diag(k_left + k_right) - np.diag(k_link[first_free:], 1) - np.diag(
        k_link[first_free:], -1)
    lam = scipy.linalg.eigh(kk, np.diag(mm), eigvals_only=True, subset_by_index=[0, 0])
    return math.sqrt(lam[0]) / (2.0 * math.pi)


def rod_convergence(segments: tuple) -> dict:
    """Relative errors of the lumped screw's first torsional and axial frequencies against
    the continuous fixed-free rod, f = sqrt(G/rho)/(4L) and sqrt(E/rho)/(4L).

    The torsional rod is clamped at its coupling-side node, the axial rod at the thrust
    bearing; the supported end is free in both.  Returns name -> (f_ref in Hz, errors).
    """
    sc = load_machine(ARROW).screw
    refs = {"torsional": math.sqrt(sc.shear_modulus_pa / sc.density_kg_m3) / (4 * sc.length_m),
            "axial": math.sqrt(sc.youngs_modulus_pa / sc.density_kg_m3) / (4 * sc.length_m)}
    errs = {name: [] for name in refs}
    for n in segments:
        rot, ax = build_chains(load_machine(ARROW, {"screw": {"segments": n}}))
        # rot node 0 is the motor, node 1 the screw's coupling end; ax node 0 the bearing end
        f = {"torsional": clamped_first_frequency(rot.m, rot.k_link, 2),
             "axial": clamped_first_frequency(ax.m, ax.k_link, 1)}
        for name, f_ref in refs.items():
            errs[name].append(f[name] / f_ref - 1.0)
    return {name: (refs[name], np.array(errs[name])) for name in refs}


@dataclass(frozen=True)
class ModeRun:
    """The kernel's free vibration started in one eigenvector of mechanics_matrices.

    Attributes:
        f_lin: linearised natural frequency (Hz).
        f_kernel: frequency of the kernel's modal coordinate (Hz).
        leak: largest amplitude any other elastic mode reaches, relative to this one.
        status: worst kernel status.
        t: s, shape (n,); eta: the modal coordinate, normalised, shape (n,).
    """
    f_lin: float
    f_kernel: float
    leak: float
    status: int
    t: np.ndarray
    eta: np.ndarray


def kernel_mode_frequency(plant: Plant, mode: int, periods: float = 20.0) -> ModeRun:
    """Start the (undamped) screw model in eigenvector ``mode`` of mechanics_matrices,
    1 µm at the table, and follow its modal coordinate for ``periods`` periods."""
    table_pos = plant.state[L.S_TABLE_X]
    m_mat, _, k_mat = mechanics_matrices(plant.config, table_pos)
    lam, phi = scipy.linalg.eigh(k_mat, m_mat)
    shape = phi[:, mode] * (1e-6 / abs(phi[-1, mode]))  # 1 µm at the table
    st = ScrewState(plant)
    st.displace(shape)
    f_lin = math.sqrt(lam[mode]) / (2.0 * math.pi)
    n_calls = int(periods / (f_lin * plant.dt * 4)) + 1
    t, q, status = st.record(n_calls, 4)
    eta = q @ (m_mat @ phi)  # modal coordinates, shape (n_calls, nq)
    eta /= np.abs(eta[:, mode]).max()
    others = np.delete(eta, [0, mode], axis=1)  # mode 0: rigid-body rotation
    return ModeRun(f_lin, crossing_frequency(t, eta[:, mode] - eta[:, mode].mean()),
                   float(np.abs(others).max()), status, t, eta[:, mode])


@experiment("screw_modes", "000")
def screw_modes(out_dir: Path | None) -> list[Result]:
    """Lumped N-segment screw vs the continuous fixed-free rod (error ~ 1/N^2), and the
    kernel's free vibration in two modes vs the eigenvalues of mechanics_matrices."""
    segments = (2, 4, 7, 14, 28)
    conv = rod_convergence(segments)
    rows = []
    for name, (f_ref, err) in conv.items():
        slope = np.polyfit(np.log(segments), np.log(np.abs(err)), 1)[0]
        rows.append(Result(f"screw {name} mode 1, N = {segments[-1]}", f_ref,
                           f_ref * (1 + err[-1]), "Hz", abs(err[-1]) < 1e-3,
                           "analytic: continuous rod, fixed-free, sqrt(M/rho)/(4L)", "±0.1 %",
                           VERIFICATION))
        rows.append(Result(f"screw {name} mode 1: convergence order", -2.0, float(slope), "1",
                           within(slope, -2.0, abs_=0.1),
                           "second-order lumping of a uniform rod", "±0.1", VERIFICATION))
    raw = undamped(torque_free(machine_raw()))
    traces = []
    for mode in (1, 2):
        plant = plant_of(raw, f"{ARROW} (undamped, torque-free)", table_pos=0.25)
        run = kernel_mode_frequency(plant, mode)
        ok = run.status == 0 and within(run.f_kernel, run.f_lin, rel=1e-3) and run.leak < 0.01
        rows.append(Result(f"Arrow screw model mode {mode}: kernel free vibration", run.f_lin,
                           run.f_kernel, "Hz", ok, "linearisation: eigh(K, M) of "
                           "mechanics_matrices at 250 mm", "±0.1 %, other modes < 1 %",
                           VERIFICATION))
        traces.append((mode, run.t, run.eta))
    if out_dir is not None:
        _plot_screw_modes(out_dir, segments, conv, traces)
    return rows


def _plot_screw_modes(out_dir, segments, conv, traces):
    fig, ax = plots.new_figure(1, 2, "Ball screw modes (Arrow 500 X)")
    for (name, (f_ref, err)), style in zip(conv.items(), ("o-", "x--")):
        ax[0, 0].loglog(segments, np.abs(err), style, label=f"{name} ({f_ref:.0f} Hz)")
    ax[0, 0].loglog(segments, 0.5 * np.abs(conv["axial"][1][0]) * (segments[0] / np.array(
        segments)) ** 2, "k--", label="1/N^2")
    ax[0, 0].set(xlabel="segments N", ylabel="|f_lumped / f_rod - 1|")
    ax[0, 0].legend()
    for mode, t, eta in traces:
        first = t < 0.02
        ax[0, 1].plot(t[first] * 1e3, eta[first], label=f"mode {mode}")
    ax[0, 1].set(xlabel="time (ms)", ylabel="modal coordinate (kernel, normalised)")
    ax[0, 1].legend()
    plots.save(fig, out_dir, "screw_modes")


# --- 4. moving nut ----------------------------------------------------------------------------

def series_compliance(cfg, s_eff: float) -> float:
    """Analytic axial compliance (m/N) at the table with the rotor held, fixed-supported:
    1/k_bearing + s/(E A) + 1/k_nut + r^2 (1/k_coupling + s/(G J_p)), r = lead/2pi, with
    ``s_eff`` (m) the nut's distance from the thrust bearing."""
    sc = cfg.screw
    d = sc.diameter(sc.stiffness_diameter)
    area = math.pi * d ** 2 / 4.0
    jp = math.pi * d ** 4 / 32.0
    r = cfg.mechanics.lead_m / (2.0 * math.pi)
    return (1.0 / sc.thrust_bearing_stiffness_n_per_m + s_eff / (sc.youngs_modulus_pa * area)
            + 1.0 / sc.nut_stiffness_n_per_m
            + r * r * (1.0 / cfg.coupling.stiffness_nm_per_rad
                       + s_eff / (sc.shear_modulus_pa * jp)))


def screw_geometry(cfg) -> str:
    """The diameters the screw's stiffness and inertia are computed with, in words."""
    sc = cfg.screw
    return (f"stiffness from the {sc.stiffness_diameter} diameter "
            f"{sc.diameter(sc.stiffness_diameter) * 1e3:g} mm, inertia from the "
            f"{sc.inertia_diameter} diameter {sc.diameter(sc.inertia_diameter) * 1e3:g} mm")


def lumped_nut_distance(cfg, table_pos: float) -> float:
    """Effective nut distance (m) of the lumped screw: the nut is interpolated linearly
    between nodes j and j+1 (weight w), so only the share w of the force crosses segment j
    and the nut sees (j + w^2) segments instead of (j + w)."""
    seg = cfg.screw.length_m / cfg.screw.segments
    pos = (cfg.screw.nut_offset_m + table_pos) / seg
    j = math.floor(pos)
    return (j + (pos - j) ** 2) * seg


def static_stiffness(raw: dict, table_pos: float, force: float, t_end: float):
    """Table stiffness (N/m) seen by a constant table force ``force`` (N) with the rotor held,
    after settling for ``t_end`` s; also the relative change over the last 10 % of the run
    (settling check) and the worst status."""
    plant = plant_of(raw, f"{ARROW} (rotor held)", table_pos)
    r = plant.built.ratio
    x0, th0 = plant.output("table_pos"), plant.output("motor_pos")
    plant.set_input(load=force)
    n = round(t_end / plant.pwm_period)
    tr = plant.run(n, plant.sub_per_pwm)
    defl = (tr["table_pos"] - x0) - r * (tr["motor_pos"] - th0)
    drift = abs(defl[-1] - defl[int(0.9 * n)]) / abs(defl[-1])
    return force / defl[-1], drift, int(tr["status"].max())


@experiment("moving_nut_stiffness", "003")
def moving_nut_stiffness(out_dir: Path | None) -> list[Result]:
    """Static axial stiffness at the table vs table position (seed 003's moving nut), against
    the analytic series formula; first natural frequency vs position (linearisation)."""
    # assumed: 2e5 N·s/m of table damping settles the table mode (zeta ~ 0.4) without
    # changing the static deflection
    raw = with_keys(torque_free(frictionless(machine_raw())),
                    {"motor": {"inertia_kgm2": HELD_MOTOR_KGM2},
                     "friction": {"viscous_ns_per_m": 2.0e5}})
    cfg = load_machine(ARROW)
    seg = cfg.screw.length_m / cfg.screw.segments
    at_nodes = [k * seg - cfg.screw.nut_offset_m for k in (2, 3, 4, 5)]
    between = [x + 0.5 * seg for x in at_nodes[:3]]
    rows, points = [], []
    for x in sorted(at_nodes + between):
        k_model, drift, status = static_stiffness(raw, x, 1000.0, 0.12)
        k_ref = 1.0 / series_compliance(cfg, lumped_nut_distance(cfg, x))
        where = "at a node" if x in at_nodes else "mid-segment, s_eff = (j + w^2) seg"
        rows.append(Result(f"nut stiffness at table {x * 1e3:.1f} mm ({where})", k_ref,
                           k_model, "N/m", status == 0 and drift < 1e-4
                           and within(k_model, k_ref, rel=2e-3),
                           "analytic series formula, fixed-supported, rotor held; screw "
                           f"{screw_geometry(cfg)}", "±0.2 %", VERIFICATION))
        points.append((x, k_model))
    if out_dir is not None:
        _plot_moving_nut(out_dir, cfg, points)
    return rows


def _plot_moving_nut(out_dir, cfg, points):
    xs = np.linspace(0.0, cfg.table.travel_m, 101)
    fig, ax = plots.new_figure(1, 2, "Moving nut (Arrow 500 X): stiffness and first mode")
    cont = [1e-6 / series_compliance(cfg, cfg.screw.nut_offset_m + x) for x in xs]
    lump = [1e-6 / series_compliance(cfg, lumped_nut_distance(cfg, x)) for x in xs]
    ax[0, 0].plot(xs * 1e3, cont, label="analytic, continuous screw")
    ax[0, 0].plot(xs * 1e3, lump, "--", label="analytic, 7 lumped segments")
    ax[0, 0].plot([p[0] * 1e3 for p in points], [p[1] * 1e-6 for p in points], "o",
                  label="kernel, static load 1 kN")
    ax[0, 0].set(xlabel="table position (mm)", ylabel="stiffness at the table (N/µm)")
    ax[0, 0].legend()
    f1 = [natural_frequencies(cfg, x)[1] / (2 * math.pi) for x in xs]
    ax[0, 1].plot(xs * 1e3, f1)
    ax[0, 1].set(xlabel="table position (mm)", ylabel="first natural frequency (Hz)")
    plots.save(fig, out_dir, "moving_nut_stiffness")


# --- 5. energy ---------------------------------------------------------------------------------

def conservative_arrow(max_omega_dt: float | None = None, table_pos: float = 0.25):
    """Undamped, frictionless, torque-free Arrow screw model with the coupling pre-twisted by
    1 mrad (motor node); returns (plant, its ScrewState, the initial displacement dq)."""
    raw = undamped(torque_free(machine_raw()))
    if max_omega_dt is not None:
        raw = with_keys(raw, {"simulation": {"max_omega_dt": max_omega_dt}})
    plant = plant_of(raw, f"{ARROW} (undamped, torque-free)", table_pos)
    st = ScrewState(plant)
    dq = np.zeros(st.q0.size)
    dq[0] = 1e-3
    st.displace(dq)
    return plant, st, dq


def energy_history(plant: Plant, n_calls: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(t in s, energy / initial energy, worst status) over ``n_calls`` PWM periods."""
    e0 = screw_energy(plant)
    t, e = np.empty(n_calls), np.empty(n_calls)
    status = 0
    for k in range(n_calls):
        status = max(status, plant.step(plant.sub_per_pwm))
        t[k], e[k] = plant.output("time_s"), screw_energy(plant) / e0
    return t, e, status


def linear_reference(cfg, table_pos: float, dq: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Free response q(t) - q_rest, shape (t.size, nq), of M q'' + C q' + K q = 0 from
    mechanics_matrices at ``table_pos`` (m), starting from ``dq`` at rest, by solve_ivp
    DOP853 (rtol 1e-10)."""
    m_mat, c_mat, k_mat = mechanics_matrices(cfg, table_pos)
    m_inv = np.linalg.inv(m_mat)
    nq = dq.size

    def rhs(_, y):
        return np.concatenate([y[nq:], -m_inv @ (k_mat @ y[:nq] + c_mat @ y[nq:])])

    sol = scipy.integrate.solve_ivp(rhs, (0.0, t[-1]), np.concatenate([dq, np.zeros(nq)]),
                                    method="DOP853", rtol=1e-10, atol=1e-16, t_eval=t)
    return sol.y[:nq].T


@dataclass(frozen=True)
class TrajectoryRun:
    """The kernel against the DOP853 reference from the same start.

    Attributes:
        dt: sub-step (s).
        errors: "motor" / "table" -> largest deviation relative to the reference amplitude.
        status: worst kernel status.
        t: s, shape (n,); q, ref: kernel and reference q - q_rest, shape (n, nq).
    """
    dt: float
    errors: dict
    status: int
    t: np.ndarray
    q: np.ndarray
    ref: np.ndarray


def trajectory_errors(max_omega_dt: float | None, horizon: float) -> TrajectoryRun:
    """Run the pre-twisted undamped Arrow for ``horizon`` s with the kernel and DOP853."""
    plant, st, dq = conservative_arrow(max_omega_dt)
    n = round(horizon / plant.pwm_period)
    t, q, status = st.record(n, plant.sub_per_pwm)
    ref = linear_reference(plant.config, st.q0[-1], dq, t)
    errs = {name: float(np.abs(q[:, i] - ref[:, i]).max() / np.abs(ref[:, i]).max())
            for name, i in (("motor", 0), ("table", -1))}
    return TrajectoryRun(plant.dt, errs, status, t, q, ref)


@experiment("energy_conservation", "000")
def energy_conservation(out_dir: Path | None) -> list[Result]:
    """Undamped Arrow screw model, coupling pre-twisted: the energy (both chains, table, nut)
    oscillates boundedly without drift over 4000 PWM periods, 104 000 sub-steps (symplectic
    Euler conserves a shadow energy within O(omega dt)); the trajectory matches solve_ivp on
    the linear M, C, K, with the first-order error of semi-implicit Euler (10x smaller dt,
    10x smaller error)."""
    plant, _, _ = conservative_arrow()
    omega_dt = plant.built.omega_max * plant.dt
    t_e, e, status = energy_history(plant, 4000)
    tenth = e.size // 10
    spread = float(np.abs(e - 1.0).max())
    drift = float(abs(e[-tenth:].mean() - e[:tenth].mean()))
    rows = [Result(f"energy: largest deviation over {4000 * plant.sub_per_pwm} sub-steps", 0.0,
                   spread, "E/E0 - 1", status == 0 and spread < 0.05,
                   f"conservation (bound omega_max dt / 2 = {omega_dt / 2:.2f})", "< 5 %",
                   VERIFICATION),
            Result("energy: drift, mean of last vs first tenth", 0.0, drift, "E/E0",
                   status == 0 and drift < 1e-4, "conservation (symplectic: no drift)",
                   "< 1e-4", VERIFICATION)]
    runs = {}
    for label, mod in (("config dt", None), ("dt / 10", 0.1 * omega_dt)):
        run = runs[label] = trajectory_errors(mod, 0.01)
        for name, err in run.errors.items():
            rows.append(Result(f"trajectory vs DOP853, {name}, {label} "
                               f"({run.dt * 1e6:.2f} µs)", 0.0, err, "max error / amplitude",
                               run.status == 0 and err < 0.01,
                               "second solver: solve_ivp DOP853 on mechanics_matrices",
                               "< 1 % over 10 ms", VERIFICATION))
    coarse, fine = runs["config dt"], runs["dt / 10"]
    order = math.log(coarse.errors["motor"] / fine.errors["motor"]) / math.log(
        coarse.dt / fine.dt)
    rows.append(Result("trajectory error order in dt (motor angle)", 1.0, order, "1",
                       within(order, 1.0, abs_=0.2), "semi-implicit Euler is first order",
                       "±0.2", VERIFICATION))
    if out_dir is not None:
        _plot_energy(out_dir, t_e, e, coarse)
    return rows


def _plot_energy(out_dir, t_e, e, run):
    t, q, ref = run.t, run.q, run.ref
    fig, ax = plots.new_figure(1, 2, "Undamped Arrow screw model")
    ax[0, 0].plot(t_e * 1e3, e - 1.0)
    ax[0, 0].set(xlabel="time (ms)", ylabel="E / E0 - 1")
    ax[0, 1].plot(t * 1e3, q[:, -1] * 1e6, label="kernel")
    ax[0, 1].plot(t * 1e3, ref[:, -1] * 1e6, "--", label="solve_ivp DOP853")
    ax[0, 1].set(xlabel="time (ms)", ylabel="table displacement (µm)")
    ax[0, 1].legend()
    plots.save(fig, out_dir, "energy_conservation")


# --- 6. lumped vs TLM ---------------------------------------------------------------------------

@experiment("lumped_vs_tlm", "003")
def lumped_vs_tlm(out_dir: Path | None) -> list[Result]:
    """The Arrow screw under both chain solvers (seed 003's TLM and semi-implicit Euler):
    the same first natural frequency (undamped free vibration in mode 1) and the same static
    stiffness at the table (rotor held, 1 kN), table at 250 mm."""
    free_raw = undamped(torque_free(machine_raw()))
    held_raw = with_keys(torque_free(frictionless(machine_raw())),
                         {"motor": {"inertia_kgm2": HELD_MOTOR_KGM2},
                          "friction": {"viscous_ns_per_m": 2.0e5}})  # assumed: as above
    res = {}
    for solver in ("lumped", "tlm"):
        change = {"mechanics": {"solver": solver}}
        plant = plant_of(with_keys(free_raw, change), f"{ARROW} ({solver}, undamped)", 0.25)
        run = kernel_mode_frequency(plant, 1)
        k, _, status = static_stiffness(with_keys(held_raw, change), 0.25, 1000.0, 0.12)
        res[solver] = (run.f_kernel, k, max(run.status, status), run.t, run.eta)
        f_lin = run.f_lin
    (f_l, k_l, st_l, *_), (f_t, k_t, st_t, *_) = res["lumped"], res["tlm"]
    ok = st_l == 0 and st_t == 0
    rows = [Result("TLM vs lumped: first natural frequency at 250 mm", f_l, f_t, "Hz",
                   ok and within(f_t, f_l, rel=1e-3), "second solver: lumped kernel "
                   f"(linearisation: {f_lin:.2f} Hz)", "±0.1 %", VERIFICATION),
            Result("TLM vs lumped: static stiffness at the table, 250 mm", k_l, k_t, "N/m",
                   ok and within(k_t, k_l, rel=1e-3), "second solver: lumped kernel",
                   "±0.1 %", VERIFICATION)]
    if out_dir is not None:
        fig, ax = plots.new_figure(1, 1, "Arrow screw, mode 1 free vibration: TLM vs lumped")
        for solver, (*_, t, eta) in res.items():
            ax[0, 0].plot(t * 1e3, eta, "--" if solver == "tlm" else "-", label=solver)
        ax[0, 0].set(xlabel="time (ms)", ylabel="modal coordinate (normalised)")
        ax[0, 0].legend()
        plots.save(fig, out_dir, "lumped_vs_tlm")
    return rows
